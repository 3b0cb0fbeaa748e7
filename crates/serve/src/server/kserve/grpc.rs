//! The Open Inference Protocol over gRPC: `inference.GRPCInferenceService`
//! (proto/inference.proto). Inputs arrive as typed `contents` or as `raw_input_contents`;
//! outputs always go out as `raw_output_contents` (as Triton's clients expect). Errors are gRPC
//! statuses from the one mapping in `server::errors`.

use tonic::{Request, Response, Status};

use super::super::errors::{grpc_code, grpc_status};
use super::super::metrics::count_grpc as count;
use super::super::AppState;
use std::collections::HashMap;

use super::shared_memory::ShmRef;
use super::shared_tensors::SharedInput;
use super::tensors::{DataType, InputTensor, Placement, RequestedOutput, TensorData, TensorSpec, INPUTS, OUTPUTS};
use super::{InferRequest, InferResponse};
use posefuse_core::error::{Error, Result};

/// Generated messages, server and client of `proto/inference.proto`.
#[allow(clippy::all, missing_docs)]
pub mod proto {
    tonic::include_proto!("inference");
}

use proto::grpc_inference_service_server::{GrpcInferenceService, GrpcInferenceServiceServer};

/// The service, with the server's message size limit.
pub fn service(state: AppState) -> GrpcInferenceServiceServer<KserveService> {
    let limit = state.body_limit;
    GrpcInferenceServiceServer::new(KserveService { state }).max_decoding_message_size(limit)
}

/// Implements `inference.GRPCInferenceService`.
pub struct KserveService {
    state: AppState,
}

/// Counts the call and turns an error into its status.
fn answer<T>(method: &'static str, r: Result<T>) -> std::result::Result<Response<T>, Status> {
    count(method, r.as_ref().map_or_else(grpc_code, |_| tonic::Code::Ok));
    r.map(Response::new).map_err(|e| grpc_status(&e))
}

fn specs(s: &[TensorSpec]) -> Vec<proto::model_metadata_response::TensorMetadata> {
    s.iter()
        .map(|t| proto::model_metadata_response::TensorMetadata {
            name: t.name.into(),
            datatype: t.datatype.as_str().into(),
            shape: t.shape.to_vec(),
        })
        .collect()
}

/// Triton's `ModelConfig` message for the served model (see `kserve::config`).
fn model_config(name: String) -> proto::ModelConfig {
    use super::config::{optional, triton_type};
    proto::ModelConfig {
        name,
        platform: super::PLATFORM.into(),
        backend: super::PLATFORM.into(),
        version_policy: Some(proto::ModelVersionPolicy {
            latest: Some(proto::model_version_policy::Latest { num_versions: 1 }),
        }),
        max_batch_size: 0,
        input: INPUTS
            .iter()
            .map(|s| proto::ModelInput {
                name: s.name.into(),
                data_type: triton_type(s.datatype).1,
                dims: s.shape.to_vec(),
                optional: optional(s),
            })
            .collect(),
        output: OUTPUTS
            .iter()
            .map(|s| proto::ModelOutput {
                name: s.name.into(),
                data_type: triton_type(s.datatype).1,
                dims: s.shape.to_vec(),
            })
            .collect(),
    }
}

/// The methods of `inference.GRPCInferenceService` this server implements; any other is
/// answered UNIMPLEMENTED with a message (tonic's own answer has none).
pub const METHODS: [&str; 10] = [
    "ServerLive",
    "ServerReady",
    "ModelReady",
    "ServerMetadata",
    "ModelMetadata",
    "ModelInfer",
    "ModelConfig",
    "SystemSharedMemoryStatus",
    "SystemSharedMemoryRegister",
    "SystemSharedMemoryUnregister",
];

/// The path of `ModelInfer` (admitted before its message is read).
pub const INFER_PATH: &str = "/inference.GRPCInferenceService/ModelInfer";

/// The status for a call to a method of the service that is not among [`METHODS`]; `None` for
/// other paths.
pub fn unimplemented(path: &str) -> Option<Status> {
    let method = path.strip_prefix("/inference.GRPCInferenceService/")?;
    (!METHODS.contains(&method)).then(|| {
        Status::unimplemented(format!(
            "posefuse does not offer inference.GRPCInferenceService/{method} (served: {}; docs/KSERVE.md)",
            METHODS.join(", ")
        ))
    })
}

/// A tensor's elements from the typed `contents` field of its datatype.
fn from_contents(name: &str, dt: DataType, c: proto::InferTensorContents) -> Result<TensorData> {
    Ok(match dt {
        DataType::Bool => TensorData::Bool(c.bool_contents),
        DataType::I8 | DataType::I16 | DataType::I32 => {
            TensorData::Int(c.int_contents.into_iter().map(i64::from).collect())
        }
        DataType::I64 => TensorData::Int(c.int64_contents),
        DataType::U8 => TensorData::U8(
            c.uint_contents
                .into_iter()
                .map(|x| u8::try_from(x).map_err(|_| Error::field(name, format!("element {x} is not 0..=255"))))
                .collect::<Result<_>>()?,
        ),
        DataType::U16 | DataType::U32 => TensorData::UInt(c.uint_contents.into_iter().map(u64::from).collect()),
        DataType::U64 => TensorData::UInt(c.uint64_contents),
        DataType::F32 => TensorData::F32(c.fp32_contents),
        DataType::F64 => TensorData::F64(c.fp64_contents),
        DataType::Bytes => TensorData::Bytes(c.bytes_contents),
        DataType::F16 | DataType::Bf16 => {
            return Err(Error::field(name, format!("datatype {} is not supported by this model", dt.as_str())))
        }
    })
}

/// Where a tensor lies in shared memory, from its `shared_memory_region`,
/// `shared_memory_byte_size` and `shared_memory_offset` parameters (integers as `int64_param`,
/// as tritonclient sends them, or `uint64_param`); `None` without a region.
fn shm_param(params: &HashMap<String, proto::InferParameter>, tensor: &str) -> Result<Option<ShmRef>> {
    use proto::infer_parameter::ParameterChoice as P;
    let Some(region) = params.get("shared_memory_region") else { return Ok(None) };
    let Some(P::StringParam(region)) = &region.parameter_choice else {
        return Err(Error::field(tensor, "parameter `shared_memory_region` must be a string"));
    };
    let number = |key: &str| -> Result<Option<u64>> {
        match params.get(key).map(|p| &p.parameter_choice) {
            None => Ok(None),
            Some(Some(P::Int64Param(n))) if *n >= 0 => Ok(Some(*n as u64)),
            Some(Some(P::Uint64Param(n))) => Ok(Some(*n)),
            Some(_) => Err(Error::field(tensor, format!("parameter `{key}` must be a non-negative integer"))),
        }
    };
    let byte_size = number("shared_memory_byte_size")?.ok_or_else(|| {
        Error::field(tensor, "parameter `shared_memory_byte_size` is required with `shared_memory_region`")
    })?;
    Ok(Some(ShmRef { region: region.clone(), byte_size, offset: number("shared_memory_offset")?.unwrap_or(0) }))
}

/// A `ModelInferRequest` as an inference request (tensors checked against their shapes). With
/// `raw_input_contents`, inputs in shared memory have no entry there (as Triton's clients send).
pub fn request_from_proto(r: proto::ModelInferRequest) -> Result<InferRequest> {
    let raw = r.raw_input_contents;
    let mut shared = Vec::new();
    let mut in_message = Vec::with_capacity(r.inputs.len());
    for t in r.inputs {
        let dt = DataType::parse(&t.name, &t.datatype)?;
        match shm_param(&t.parameters, &t.name)? {
            Some(at) => {
                if t.contents.is_some() {
                    return Err(Error::field(t.name.as_str(), "has both shared memory and contents"));
                }
                shared.push(SharedInput { name: t.name, datatype: dt, shape: t.shape, at });
            }
            None => in_message.push((t, dt)),
        }
    }
    if !raw.is_empty() && raw.len() != in_message.len() {
        return Err(Error::field(
            "raw_input_contents",
            format!(
                "{} entries for {} inputs not in shared memory: one per such input, or none",
                raw.len(),
                in_message.len()
            ),
        ));
    }
    let mut raw = raw.into_iter();
    let mut inputs = Vec::with_capacity(in_message.len());
    for (t, dt) in in_message {
        let data = match raw.next() {
            Some(bytes) => {
                if t.contents.is_some() {
                    return Err(Error::field(t.name.as_str(), "has both contents and raw_input_contents"));
                }
                TensorData::from_raw(&t.name, dt, &bytes)?
            }
            None => from_contents(&t.name, dt, t.contents.unwrap_or_default())?,
        };
        inputs.push(InputTensor::new(t.name, dt, t.shape, data, false)?);
    }
    let outputs: Vec<RequestedOutput> = r
        .outputs
        .into_iter()
        .map(|o| {
            let shared_memory = shm_param(&o.parameters, &o.name)?;
            Ok(RequestedOutput { name: o.name, binary: Some(true), shared_memory })
        })
        .collect::<Result<_>>()?;
    Ok(InferRequest {
        model_name: r.model_name,
        model_version: Some(r.model_version),
        id: (!r.id.is_empty()).then_some(r.id),
        inputs,
        shared_inputs: shared,
        outputs: (!outputs.is_empty()).then_some(outputs),
        binary_output: true,
    })
}

/// A response as a `ModelInferResponse` with every output in `raw_output_contents`; one
/// written to shared memory has an empty entry there (so that entries stay in output order)
/// and names its region and the bytes written in its parameters.
pub fn response_to_proto(r: InferResponse) -> proto::ModelInferResponse {
    use proto::infer_parameter::ParameterChoice as P;
    let param = |c: P| proto::InferParameter { parameter_choice: Some(c) };
    let mut raw = Vec::with_capacity(r.outputs.len());
    let outputs = r
        .outputs
        .into_iter()
        .map(|(t, placement)| {
            let mut parameters = HashMap::new();
            match placement {
                Placement::SharedMemory(at) => {
                    raw.push(Vec::new());
                    parameters.insert("shared_memory_region".into(), param(P::StringParam(at.region)));
                    parameters.insert("shared_memory_byte_size".into(), param(P::Int64Param(at.byte_size as i64)));
                    parameters.insert("shared_memory_offset".into(), param(P::Int64Param(at.offset as i64)));
                }
                Placement::Json | Placement::Binary => raw.push(t.data.to_raw(t.datatype)),
            }
            proto::model_infer_response::InferOutputTensor {
                name: t.name.into(),
                datatype: t.datatype.as_str().into(),
                shape: t.shape,
                parameters,
                contents: None,
            }
        })
        .collect();
    proto::ModelInferResponse {
        model_name: r.model_name,
        model_version: r.model_version,
        id: r.id.unwrap_or_default(),
        parameters: Default::default(),
        outputs,
        raw_output_contents: raw,
    }
}

#[tonic::async_trait]
impl GrpcInferenceService for KserveService {
    async fn server_live(
        &self,
        _: Request<proto::ServerLiveRequest>,
    ) -> std::result::Result<Response<proto::ServerLiveResponse>, Status> {
        answer("ServerLive", Ok(proto::ServerLiveResponse { live: true }))
    }

    async fn server_ready(
        &self,
        _: Request<proto::ServerReadyRequest>,
    ) -> std::result::Result<Response<proto::ServerReadyResponse>, Status> {
        answer("ServerReady", Ok(proto::ServerReadyResponse { ready: super::server_ready(&self.state) }))
    }

    async fn model_ready(
        &self,
        request: Request<proto::ModelReadyRequest>,
    ) -> std::result::Result<Response<proto::ModelReadyResponse>, Status> {
        let r = request.into_inner();
        let result = super::model(&self.state, &r.name, Some(&r.version))
            .map(|_| proto::ModelReadyResponse { ready: super::server_ready(&self.state) });
        answer("ModelReady", result)
    }

    async fn server_metadata(
        &self,
        _: Request<proto::ServerMetadataRequest>,
    ) -> std::result::Result<Response<proto::ServerMetadataResponse>, Status> {
        answer(
            "ServerMetadata",
            Ok(proto::ServerMetadataResponse {
                name: super::SERVER_NAME.into(),
                version: env!("CARGO_PKG_VERSION").into(),
                extensions: super::extensions(&self.state).iter().map(|e| e.to_string()).collect(),
            }),
        )
    }

    async fn model_metadata(
        &self,
        request: Request<proto::ModelMetadataRequest>,
    ) -> std::result::Result<Response<proto::ModelMetadataResponse>, Status> {
        let r = request.into_inner();
        let result =
            super::model(&self.state, &r.name, Some(&r.version)).map(|(name, version)| proto::ModelMetadataResponse {
                name,
                versions: vec![version],
                platform: super::PLATFORM.into(),
                inputs: specs(&INPUTS),
                outputs: specs(&OUTPUTS),
            });
        answer("ModelMetadata", result)
    }

    async fn model_config(
        &self,
        request: Request<proto::ModelConfigRequest>,
    ) -> std::result::Result<Response<proto::ModelConfigResponse>, Status> {
        let r = request.into_inner();
        let result = super::model(&self.state, &r.name, Some(&r.version))
            .map(|(name, _)| proto::ModelConfigResponse { config: Some(model_config(name)) });
        answer("ModelConfig", result)
    }

    async fn model_infer(
        &self,
        request: Request<proto::ModelInferRequest>,
    ) -> std::result::Result<Response<proto::ModelInferResponse>, Status> {
        let early = crate::server::early_admission::ticket(request.extensions());
        let result = async {
            let ticket = self.state.predictor.admitted(early)?;
            let req = request_from_proto(request.into_inner())?;
            super::infer(&self.state, &ticket, req).await.map(response_to_proto)
        };
        let result = result.await;
        answer("ModelInfer", result)
    }

    async fn system_shared_memory_status(
        &self,
        request: Request<proto::SystemSharedMemoryStatusRequest>,
    ) -> std::result::Result<Response<proto::SystemSharedMemoryStatusResponse>, Status> {
        use proto::system_shared_memory_status_response::RegionStatus;
        let r = request.into_inner();
        let result = self.state.shared_memory.status(&r.name).map(|regions| proto::SystemSharedMemoryStatusResponse {
            regions: regions
                .into_iter()
                .map(|s| {
                    let status =
                        RegionStatus { name: s.name.clone(), key: s.key, offset: s.offset, byte_size: s.byte_size };
                    (s.name, status)
                })
                .collect(),
        });
        answer("SystemSharedMemoryStatus", result)
    }

    async fn system_shared_memory_register(
        &self,
        request: Request<proto::SystemSharedMemoryRegisterRequest>,
    ) -> std::result::Result<Response<proto::SystemSharedMemoryRegisterResponse>, Status> {
        let r = request.into_inner();
        let result = self.state.shared_memory.register(&r.name, &r.key, r.offset, r.byte_size);
        if result.is_ok() {
            tracing::info!(region = %r.name, key = %r.key, offset = r.offset, byte_size = r.byte_size, "shared memory registered");
        }
        answer("SystemSharedMemoryRegister", result.map(|()| proto::SystemSharedMemoryRegisterResponse {}))
    }

    async fn system_shared_memory_unregister(
        &self,
        request: Request<proto::SystemSharedMemoryUnregisterRequest>,
    ) -> std::result::Result<Response<proto::SystemSharedMemoryUnregisterResponse>, Status> {
        let r = request.into_inner();
        let result = self.state.shared_memory.unregister(&r.name);
        answer("SystemSharedMemoryUnregister", result.map(|()| proto::SystemSharedMemoryUnregisterResponse {}))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input(
        name: &str,
        dt: &str,
        shape: &[i64],
        contents: proto::InferTensorContents,
    ) -> proto::model_infer_request::InferInputTensor {
        proto::model_infer_request::InferInputTensor {
            name: name.into(),
            datatype: dt.into(),
            shape: shape.to_vec(),
            parameters: Default::default(),
            contents: Some(contents),
        }
    }

    fn request(inputs: Vec<proto::model_infer_request::InferInputTensor>) -> proto::ModelInferRequest {
        proto::ModelInferRequest { model_name: "default".into(), inputs, ..Default::default() }
    }

    #[test]
    fn typed_and_raw_contents_decode_alike() {
        let pts = proto::InferTensorContents { fp32_contents: vec![1.0, 2.0, 3.0], ..Default::default() };
        let size = proto::InferTensorContents { int_contents: vec![640, 480], ..Default::default() };
        let typed = request_from_proto(request(vec![
            input("points", "FP32", &[1, 3], pts),
            input("image_size", "INT32", &[2], size),
        ]))
        .unwrap();
        let mut raw_req = request(vec![
            input("points", "FP32", &[1, 3], Default::default()),
            input("image_size", "INT32", &[2], Default::default()),
        ]);
        for t in &mut raw_req.inputs {
            t.contents = None;
        }
        raw_req.raw_input_contents = vec![
            [1.0f32, 2.0, 3.0].iter().flat_map(|v| v.to_le_bytes()).collect(),
            [640i32, 480].iter().flat_map(|v| v.to_le_bytes()).collect(),
        ];
        let raw = request_from_proto(raw_req).unwrap();
        assert_eq!(typed.inputs, raw.inputs);
        assert_eq!(typed.inputs[1].data, TensorData::Int(vec![640, 480]));
        assert_eq!(typed.outputs, None);
    }

    #[test]
    fn bad_tensors_are_invalid_argument_naming_the_tensor() {
        let short = proto::InferTensorContents { fp32_contents: vec![1.0, 2.0], ..Default::default() };
        let e = request_from_proto(request(vec![input("points", "FP32", &[1, 3], short)])).unwrap_err();
        assert_eq!(e.field_name(), Some("points"));
        assert_eq!(grpc_code(&e), tonic::Code::InvalidArgument);
        let mut r = request(vec![input("points", "FP32", &[1, 3], Default::default())]);
        r.raw_input_contents = vec![vec![0; 12], vec![0; 4]];
        assert_eq!(request_from_proto(r).unwrap_err().field_name(), Some("raw_input_contents"));
        let e = request_from_proto(request(vec![input("points", "FP16", &[1, 3], Default::default())])).unwrap_err();
        assert_eq!(e.field_name(), Some("points"));
        let pixels = proto::InferTensorContents { uint_contents: vec![1, 256, 3], ..Default::default() };
        let e = request_from_proto(request(vec![input("image_rgb", "UINT8", &[1, 1, 3], pixels)])).unwrap_err();
        assert_eq!(e.field_name(), Some("image_rgb"));
    }

    fn params(region: proto::infer_parameter::ParameterChoice, size: i64) -> HashMap<String, proto::InferParameter> {
        use proto::infer_parameter::ParameterChoice as P;
        let p = |c| proto::InferParameter { parameter_choice: Some(c) };
        HashMap::from([
            ("shared_memory_region".to_string(), p(region)),
            ("shared_memory_byte_size".to_string(), p(P::Int64Param(size))),
            ("shared_memory_offset".to_string(), p(P::Uint64Param(8))),
        ])
    }

    #[test]
    fn inputs_in_shared_memory_have_no_raw_contents_entry() {
        use proto::infer_parameter::ParameterChoice as P;
        let mut image = input("image_rgb", "UINT8", &[2, 2, 3], Default::default());
        image.contents = None;
        image.parameters = params(P::StringParam("cam".into()), 12);
        let mut points = input("points", "FP32", &[1, 3], Default::default());
        points.contents = None;
        let mut r = request(vec![image, points]);
        r.raw_input_contents = vec![[1.0f32, 2.0, 3.0].iter().flat_map(|v| v.to_le_bytes()).collect()];
        r.outputs = vec![proto::model_infer_request::InferRequestedOutputTensor {
            name: "scores".into(),
            parameters: params(P::StringParam("out".into()), 52),
        }];
        let req = request_from_proto(r.clone()).unwrap();
        assert_eq!(req.inputs.len(), 1);
        assert_eq!(req.inputs[0].data, TensorData::F32(vec![1.0, 2.0, 3.0]));
        let at = |region: &str, byte_size| ShmRef { region: region.into(), byte_size, offset: 8 };
        assert_eq!(
            req.shared_inputs,
            vec![SharedInput {
                name: "image_rgb".into(),
                datatype: DataType::U8,
                shape: vec![2, 2, 3],
                at: at("cam", 12)
            }]
        );
        assert_eq!(req.outputs.unwrap()[0].shared_memory, Some(at("out", 52)));

        // one raw entry per input, counting those in shared memory, is one too many
        let mut extra = r.clone();
        extra.raw_input_contents.push(vec![0; 12]);
        assert_eq!(request_from_proto(extra).unwrap_err().field_name(), Some("raw_input_contents"));
        let mut bad = r.clone();
        bad.inputs[0].parameters = params(P::BoolParam(true), 12);
        assert_eq!(request_from_proto(bad).unwrap_err().field_name(), Some("image_rgb"));
        let mut negative = r;
        negative.inputs[0].parameters = params(P::StringParam("cam".into()), -1);
        assert_eq!(request_from_proto(negative).unwrap_err().field_name(), Some("image_rgb"));
    }

    #[test]
    fn an_output_in_shared_memory_keeps_raw_contents_in_output_order() {
        use super::super::tensors::OutputTensor;
        use proto::infer_parameter::ParameterChoice as P;
        let t = |name| OutputTensor { name, datatype: DataType::I32, shape: vec![1], data: TensorData::Int(vec![7]) };
        let at = ShmRef { region: "out".into(), byte_size: 4, offset: 0 };
        let resp = response_to_proto(InferResponse {
            model_name: "default".into(),
            model_version: "1".into(),
            id: None,
            outputs: vec![(t("num_points"), Placement::SharedMemory(at)), (t("scores"), Placement::Binary)],
        });
        assert_eq!(resp.raw_output_contents, vec![vec![], vec![7, 0, 0, 0]]);
        let p = &resp.outputs[0].parameters;
        assert_eq!(p["shared_memory_region"].parameter_choice, Some(P::StringParam("out".into())));
        assert_eq!(p["shared_memory_byte_size"].parameter_choice, Some(P::Int64Param(4)));
        assert!(resp.outputs[1].parameters.is_empty());
    }
}
