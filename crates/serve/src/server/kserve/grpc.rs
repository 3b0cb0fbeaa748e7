//! The Open Inference Protocol over gRPC: `inference.GRPCInferenceService`
//! (proto/inference.proto). Inputs arrive as typed `contents` or as `raw_input_contents`;
//! outputs always go out as `raw_output_contents` (as Triton's clients expect). Errors are gRPC
//! statuses from the one mapping in `server::errors`.

use tonic::{Request, Response, Status};

use super::super::errors::{grpc_code, grpc_status};
use super::super::metrics::count_grpc as count;
use super::super::AppState;
use super::tensors::{DataType, InputTensor, RequestedOutput, TensorData, TensorSpec, INPUTS, OUTPUTS};
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
pub const METHODS: [&str; 7] =
    ["ServerLive", "ServerReady", "ModelReady", "ServerMetadata", "ModelMetadata", "ModelInfer", "ModelConfig"];

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
        DataType::U8 | DataType::U16 | DataType::U32 => {
            TensorData::UInt(c.uint_contents.into_iter().map(u64::from).collect())
        }
        DataType::U64 => TensorData::UInt(c.uint64_contents),
        DataType::F32 => TensorData::F32(c.fp32_contents),
        DataType::F64 => TensorData::F64(c.fp64_contents),
        DataType::Bytes => TensorData::Bytes(c.bytes_contents),
        DataType::F16 | DataType::Bf16 => {
            return Err(Error::field(name, format!("datatype {} is not supported by this model", dt.as_str())))
        }
    })
}

/// A `ModelInferRequest` as an inference request (tensors checked against their shapes).
pub fn request_from_proto(r: proto::ModelInferRequest) -> Result<InferRequest> {
    let raw = r.raw_input_contents;
    if !raw.is_empty() && raw.len() != r.inputs.len() {
        return Err(Error::field(
            "raw_input_contents",
            format!("{} entries for {} inputs: one per input, or none", raw.len(), r.inputs.len()),
        ));
    }
    let mut raw = raw.into_iter();
    let mut inputs = Vec::with_capacity(r.inputs.len());
    for t in r.inputs {
        let dt = DataType::parse(&t.name, &t.datatype)?;
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
    let outputs: Vec<RequestedOutput> =
        r.outputs.into_iter().map(|o| RequestedOutput { name: o.name, binary: Some(true) }).collect();
    Ok(InferRequest {
        model_name: r.model_name,
        model_version: Some(r.model_version),
        id: (!r.id.is_empty()).then_some(r.id),
        inputs,
        outputs: (!outputs.is_empty()).then_some(outputs),
        binary_output: true,
    })
}

/// A response as a `ModelInferResponse` with every output in `raw_output_contents`.
pub fn response_to_proto(r: InferResponse) -> proto::ModelInferResponse {
    let mut raw = Vec::with_capacity(r.outputs.len());
    let outputs = r
        .outputs
        .into_iter()
        .map(|(t, _)| {
            raw.push(t.data.to_raw(t.datatype));
            proto::model_infer_response::InferOutputTensor {
                name: t.name.into(),
                datatype: t.datatype.as_str().into(),
                shape: t.shape,
                parameters: Default::default(),
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
                extensions: super::EXTENSIONS.iter().map(|e| e.to_string()).collect(),
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
    }
}
