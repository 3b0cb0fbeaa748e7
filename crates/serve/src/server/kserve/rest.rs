//! The Open Inference Protocol over HTTP: health, metadata and inference under `/v2`, with the
//! binary tensor data extension (`Inference-Header-Content-Length`, `binary_data_size`,
//! `binary_data_output`, per-output `binary_data`). Errors are `{"error": "..."}`.

use axum::body::Bytes;
use axum::extract::{FromRequest, Path, Request, State};
use axum::http::{header, HeaderMap, HeaderName, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;
use serde_json::{json, Map, Value};

use super::super::errors::v2_response;
use super::super::http::bytes_rejection;
use super::super::AppState;
use super::shared_memory::ShmRef;
use super::shared_tensors::SharedInput;
use super::tensors::{DataType, InputTensor, Placement, RequestedOutput, TensorData, TensorSpec, INPUTS, OUTPUTS};
use super::{InferRequest, InferResponse};
use posefuse_core::error::{Error, Result};
use posefuse_core::json::parse_json;

/// Length of the JSON part of a body that carries binary tensor data after it.
pub const HEADER_LENGTH: HeaderName = HeaderName::from_static("inference-header-content-length");

/// The `/v2` routes.
pub fn routes() -> Router<AppState> {
    Router::new()
        .route("/v2", get(server_metadata))
        .route("/v2/health/live", get(live))
        .route("/v2/health/ready", get(ready))
        .route("/v2/models/{name}", get(model_metadata))
        .route("/v2/models/{name}/versions/{version}", get(model_metadata_version))
        .route("/v2/models/{name}/config", get(model_config))
        .route("/v2/models/{name}/versions/{version}/config", get(model_config_version))
        .route("/v2/models/{name}/ready", get(model_ready))
        .route("/v2/models/{name}/versions/{version}/ready", get(model_ready_version))
        .route("/v2/models/{name}/infer", post(infer))
        .route("/v2/models/{name}/versions/{version}/infer", post(infer_version))
        .merge(super::rest_shared_memory::routes())
}

/// An error answered in the protocol's shape.
struct V2Error(Error);

impl From<Error> for V2Error {
    fn from(e: Error) -> Self {
        V2Error(e)
    }
}

impl IntoResponse for V2Error {
    fn into_response(self) -> Response {
        v2_response(&self.0)
    }
}

type V2Result<T> = std::result::Result<T, V2Error>;

async fn server_metadata(State(state): State<AppState>) -> Json<Value> {
    Json(json!({
        "name": super::SERVER_NAME,
        "version": env!("CARGO_PKG_VERSION"),
        "extensions": super::extensions(&state),
    }))
}

/// 200 while the process answers.
async fn live() -> Json<Value> {
    Json(json!({ "live": true }))
}

/// 200 when ready, 400 (the protocol's "4xx") when warming up or shutting down.
async fn ready(State(state): State<AppState>) -> Response {
    let ready = super::server_ready(&state);
    (health_status(ready), Json(json!({ "ready": ready }))).into_response()
}

fn health_status(ok: bool) -> StatusCode {
    if ok {
        StatusCode::OK
    } else {
        StatusCode::BAD_REQUEST
    }
}

fn specs_json(specs: &[TensorSpec]) -> Vec<Value> {
    specs.iter().map(|s| json!({ "name": s.name, "datatype": s.datatype.as_str(), "shape": s.shape })).collect()
}

fn metadata(state: &AppState, name: &str, version: Option<&str>) -> V2Result<Json<Value>> {
    let (name, version) = super::model(state, name, version)?;
    Ok(Json(json!({
        "name": name,
        "versions": [version],
        "platform": super::PLATFORM,
        "inputs": specs_json(&INPUTS),
        "outputs": specs_json(&OUTPUTS),
    })))
}

async fn model_metadata(State(state): State<AppState>, Path(name): Path<String>) -> V2Result<Json<Value>> {
    metadata(&state, &name, None)
}

async fn model_metadata_version(
    State(state): State<AppState>,
    Path((name, version)): Path<(String, String)>,
) -> V2Result<Json<Value>> {
    metadata(&state, &name, Some(&version))
}

/// Triton's model configuration (what `tritonclient`'s `get_model_config` reads).
async fn model_config(State(state): State<AppState>, Path(name): Path<String>) -> V2Result<Json<Value>> {
    let (name, _) = super::model(&state, &name, None)?;
    Ok(Json(super::config::config_json(&name)))
}

async fn model_config_version(
    State(state): State<AppState>,
    Path((name, version)): Path<(String, String)>,
) -> V2Result<Json<Value>> {
    let (name, _) = super::model(&state, &name, Some(&version))?;
    Ok(Json(super::config::config_json(&name)))
}

/// Any other `/v2` path: 404 in the protocol's error shape (Triton's clients read `error` as text).
pub async fn not_found(uri: axum::http::Uri) -> Response {
    v2_response(&Error::NotFound(format!(
        "no route for {}: posefuse serves the endpoints in docs/KSERVE.md",
        uri.path()
    )))
}

fn readiness(state: &AppState, name: &str, version: Option<&str>) -> V2Result<Response> {
    let (name, _) = super::model(state, name, version)?;
    let ready = super::server_ready(state);
    Ok((health_status(ready), Json(json!({ "name": name, "ready": ready }))).into_response())
}

async fn model_ready(State(state): State<AppState>, Path(name): Path<String>) -> V2Result<Response> {
    readiness(&state, &name, None)
}

async fn model_ready_version(
    State(state): State<AppState>,
    Path((name, version)): Path<(String, String)>,
) -> V2Result<Response> {
    readiness(&state, &name, Some(&version))
}

async fn infer(State(state): State<AppState>, Path(name): Path<String>, req: Request) -> V2Result<Response> {
    run_infer(&state, name, None, req).await
}

async fn infer_version(
    State(state): State<AppState>,
    Path((name, version)): Path<(String, String)>,
    req: Request,
) -> V2Result<Response> {
    run_infer(&state, name, Some(version), req).await
}

/// Admitted (early, or now) before the body is read, then parsed and answered.
async fn run_infer(state: &AppState, name: String, version: Option<String>, req: Request) -> V2Result<Response> {
    let ticket = state.predictor.admitted(crate::server::early_admission::ticket(req.extensions()))?;
    let headers = req.headers().clone();
    let body = Bytes::from_request(req, state).await.map_err(|r| bytes_rejection(&r, state.body_limit))?;
    let req = parse_request(&headers, &body, name, version)?;
    let resp = super::infer(state, &ticket, req).await?;
    Ok(encode_response(resp)?)
}

#[derive(Debug, Deserialize)]
struct RequestJson {
    #[serde(default)]
    id: Option<String>,
    #[serde(default)]
    parameters: Map<String, Value>,
    inputs: Vec<InputJson>,
    #[serde(default)]
    outputs: Option<Vec<OutputJson>>,
}

#[derive(Debug, Deserialize)]
struct InputJson {
    name: String,
    shape: Vec<i64>,
    datatype: String,
    #[serde(default)]
    parameters: Map<String, Value>,
    #[serde(default)]
    data: Option<Value>,
}

#[derive(Debug, Deserialize)]
struct OutputJson {
    name: String,
    #[serde(default)]
    parameters: Map<String, Value>,
}

/// Where a tensor lies in shared memory, from its `shared_memory_region`,
/// `shared_memory_byte_size` and `shared_memory_offset` parameters; `None` without a region.
fn shm_param(params: &Map<String, Value>, tensor: &str) -> Result<Option<ShmRef>> {
    let Some(region) = params.get("shared_memory_region") else { return Ok(None) };
    let region =
        region.as_str().ok_or_else(|| Error::field(tensor, "parameter `shared_memory_region` must be a string"))?;
    let number = |key: &str| -> Result<Option<u64>> {
        match params.get(key) {
            None => Ok(None),
            Some(v) => v
                .as_u64()
                .map(Some)
                .ok_or_else(|| Error::field(tensor, format!("parameter `{key}` must be a non-negative integer"))),
        }
    };
    let byte_size = number("shared_memory_byte_size")?.ok_or_else(|| {
        Error::field(tensor, "parameter `shared_memory_byte_size` is required with `shared_memory_region`")
    })?;
    Ok(Some(ShmRef { region: region.into(), byte_size, offset: number("shared_memory_offset")?.unwrap_or(0) }))
}

fn bool_param(params: &Map<String, Value>, key: &str, field: &str) -> Result<Option<bool>> {
    match params.get(key) {
        None => Ok(None),
        Some(v) => {
            v.as_bool().map(Some).ok_or_else(|| Error::field(field, format!("parameter `{key}` must be a boolean")))
        }
    }
}

/// A request body (JSON, or JSON followed by binary tensor data) as an inference request.
pub fn parse_request(headers: &HeaderMap, body: &[u8], name: String, version: Option<String>) -> Result<InferRequest> {
    if let Some(enc) = headers.get(header::CONTENT_ENCODING) {
        let enc = enc.to_str().unwrap_or("?");
        if !enc.eq_ignore_ascii_case("identity") {
            return Err(Error::Malformed(format!(
                "Content-Encoding `{enc}` is not supported; send the body uncompressed"
            )));
        }
    }
    let (json_part, mut binary) = match headers.get(&HEADER_LENGTH) {
        None => (body, &[][..]),
        Some(v) => {
            let n = v.to_str().ok().and_then(|s| s.trim().parse::<usize>().ok()).ok_or_else(|| {
                Error::Malformed("Inference-Header-Content-Length must be a non-negative integer".into())
            })?;
            if n > body.len() {
                return Err(Error::Malformed(format!(
                    "Inference-Header-Content-Length is {n} but the body has {} bytes",
                    body.len()
                )));
            }
            body.split_at(n)
        }
    };
    let r: RequestJson = parse_json(&super::non_finite::quote_non_finite(json_part))?;
    let mut inputs = Vec::with_capacity(r.inputs.len());
    let mut shared_inputs = Vec::new();
    for input in r.inputs {
        let name = input.name;
        let dt = DataType::parse(&name, &input.datatype)?;
        if let Some(at) = shm_param(&input.parameters, &name)? {
            if input.data.is_some() || input.parameters.contains_key("binary_data_size") {
                return Err(Error::field(name.as_str(), "has both shared memory and `data` or `binary_data_size`"));
            }
            shared_inputs.push(SharedInput { name, datatype: dt, shape: input.shape, at });
            continue;
        }
        let size = match input.parameters.get("binary_data_size") {
            None => None,
            Some(v) => Some(v.as_u64().and_then(|n| usize::try_from(n).ok()).ok_or_else(|| {
                Error::field(name.as_str(), "parameter `binary_data_size` must be a non-negative integer")
            })?),
        };
        let (data, text) = match (size, &input.data) {
            (Some(_), Some(_)) => {
                return Err(Error::field(name.as_str(), "has both `data` and `binary_data_size`"));
            }
            (Some(n), None) => {
                if n > binary.len() {
                    return Err(Error::field(
                        name.as_str(),
                        format!("binary_data_size is {n} but only {} bytes of binary data remain", binary.len()),
                    ));
                }
                let (this, rest) = binary.split_at(n);
                binary = rest;
                (TensorData::from_raw(&name, dt, this)?, false)
            }
            (None, Some(v)) => (TensorData::from_json(&name, dt, v)?, true),
            (None, None) => return Err(Error::field(name.as_str(), "has neither `data` nor `binary_data_size`")),
        };
        inputs.push(InputTensor::new(name, dt, input.shape, data, text)?);
    }
    if !binary.is_empty() {
        return Err(Error::Malformed(format!(
            "{} bytes of binary data are not claimed by any input's binary_data_size",
            binary.len()
        )));
    }
    let binary_output = bool_param(&r.parameters, "binary_data_output", "parameters")?.unwrap_or(false);
    let outputs = match r.outputs {
        None => None,
        Some(outs) => Some(
            outs.into_iter()
                .map(|o| {
                    if o.parameters.contains_key("classification") {
                        return Err(Error::field(o.name.as_str(), "the classification extension is not supported"));
                    }
                    let binary = bool_param(&o.parameters, "binary_data", &o.name)?;
                    let shared_memory = shm_param(&o.parameters, &o.name)?;
                    Ok(RequestedOutput { name: o.name, binary, shared_memory })
                })
                .collect::<Result<Vec<_>>>()?,
        ),
    };
    Ok(InferRequest {
        model_name: name,
        model_version: version,
        id: r.id,
        inputs,
        shared_inputs,
        outputs,
        binary_output,
    })
}

/// A response as JSON, or as JSON followed by the binary outputs when any output is binary.
pub fn encode_response(r: InferResponse) -> Result<Response> {
    let mut binary = Vec::new();
    let any_binary = r.outputs.iter().any(|(_, p)| *p == Placement::Binary);
    let outputs: Vec<Value> = r
        .outputs
        .iter()
        .map(|(t, placement)| {
            let mut o = json!({ "name": t.name, "datatype": t.datatype.as_str(), "shape": t.shape });
            match placement {
                Placement::Binary => {
                    let raw = t.data.to_raw(t.datatype);
                    o["parameters"] = json!({ "binary_data_size": raw.len() });
                    binary.extend(raw);
                }
                Placement::Json => o["data"] = t.data.to_json(),
                Placement::SharedMemory(at) => {
                    o["parameters"] = json!({
                        "shared_memory_region": at.region,
                        "shared_memory_byte_size": at.byte_size,
                        "shared_memory_offset": at.offset,
                    });
                }
            }
            o
        })
        .collect();
    let mut head = json!({ "model_name": r.model_name, "model_version": r.model_version, "outputs": outputs });
    if let Some(id) = r.id {
        head["id"] = Value::String(id);
    }
    let head = serde_json::to_vec(&head).map_err(|e| Error::Runtime(format!("encoding the response: {e}")))?;
    if !any_binary {
        return Ok(([(header::CONTENT_TYPE, "application/json")], head).into_response());
    }
    let head_len = HeaderValue::from(head.len());
    let mut body = head;
    body.extend(binary);
    let mut resp = ([(header::CONTENT_TYPE, "application/octet-stream")], body).into_response();
    resp.headers_mut().insert(HEADER_LENGTH, head_len);
    Ok(resp)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field_of<T: std::fmt::Debug>(r: Result<T>) -> String {
        match r {
            Err(e) => e.field_name().unwrap_or(e.code()).to_string(),
            Ok(v) => panic!("parsed: {v:?}"),
        }
    }

    fn parse(headers: &HeaderMap, body: &[u8]) -> Result<InferRequest> {
        parse_request(headers, body, "default".into(), None)
    }

    #[test]
    fn json_and_binary_inputs_parse_to_the_same_tensors() {
        let json_body = br#"{"id": "r1", "inputs": [
            {"name": "points", "shape": [2, 3], "datatype": "FP32", "data": [[1, 2, 3], [4, 5, 6.5]]},
            {"name": "mode", "shape": [1], "datatype": "BYTES", "data": ["lidar"]}],
            "outputs": [{"name": "scores", "parameters": {"binary_data": true}}]}"#;
        let a = parse(&HeaderMap::new(), json_body).unwrap();
        assert_eq!(a.id.as_deref(), Some("r1"));
        assert_eq!(a.inputs[0].data, TensorData::F32(vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5]));
        assert!(a.inputs[1].text);
        assert_eq!(a.outputs, Some(vec![RequestedOutput::named("scores", Some(true))]));
        assert!(!a.binary_output);

        let pts: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.5].iter().flat_map(|v| v.to_le_bytes()).collect();
        let mode = TensorData::Bytes(vec![b"lidar".to_vec()]).to_raw(DataType::Bytes);
        let head = format!(
            r#"{{"inputs": [
            {{"name": "points", "shape": [2, 3], "datatype": "FP32", "parameters": {{"binary_data_size": {}}}}},
            {{"name": "mode", "shape": [1], "datatype": "BYTES", "parameters": {{"binary_data_size": {}}}}}],
            "parameters": {{"binary_data_output": true}}}}"#,
            pts.len(),
            mode.len()
        );
        let mut body = head.clone().into_bytes();
        body.extend(&pts);
        body.extend(&mode);
        let mut headers = HeaderMap::new();
        headers.insert(HEADER_LENGTH, HeaderValue::from(head.len()));
        let b = parse(&headers, &body).unwrap();
        assert_eq!(b.inputs[0].data, a.inputs[0].data);
        assert_eq!(b.inputs[1].data, a.inputs[1].data);
        assert!(!b.inputs[1].text);
        assert!(b.binary_output);
        assert_eq!(b.outputs, None);

        // Binary data that does not add up is an error.
        body.push(0);
        assert_eq!(field_of(parse(&headers, &body)), "malformed_request");
        body.truncate(body.len() - 3);
        assert_eq!(field_of(parse(&headers, &body)), "mode");
        headers.insert(HEADER_LENGTH, HeaderValue::from(body.len() + 1));
        assert_eq!(field_of(parse(&headers, &body)), "malformed_request");
    }

    #[test]
    fn shared_memory_parameters_place_inputs_and_outputs() {
        let body = br#"{"inputs": [
            {"name": "image_rgb", "shape": [2, 3, 3], "datatype": "UINT8",
             "parameters": {"shared_memory_region": "cam", "shared_memory_byte_size": 18, "shared_memory_offset": 64}},
            {"name": "mode", "shape": [1], "datatype": "BYTES", "data": ["lidar"]}],
            "outputs": [{"name": "keypoints_3d",
                         "parameters": {"shared_memory_region": "out", "shared_memory_byte_size": 156}},
                        {"name": "mode"}]}"#;
        let r = parse(&HeaderMap::new(), body).unwrap();
        assert_eq!(r.inputs.len(), 1);
        assert_eq!(
            r.shared_inputs,
            vec![SharedInput {
                name: "image_rgb".into(),
                datatype: DataType::U8,
                shape: vec![2, 3, 3],
                at: ShmRef { region: "cam".into(), byte_size: 18, offset: 64 },
            }]
        );
        let outs = r.outputs.unwrap();
        assert_eq!(outs[0].shared_memory, Some(ShmRef { region: "out".into(), byte_size: 156, offset: 0 }));
        assert_eq!(outs[1].shared_memory, None);

        let one = |params: &str| {
            format!(
                r#"{{"inputs": [{{"name": "points", "shape": [1, 3], "datatype": "FP32", "parameters": {params}}}]}}"#
            )
        };
        for bad in [
            r#"{"shared_memory_region": "r"}"#,
            r#"{"shared_memory_region": 7, "shared_memory_byte_size": 12}"#,
            r#"{"shared_memory_region": "r", "shared_memory_byte_size": -12}"#,
            r#"{"shared_memory_region": "r", "shared_memory_byte_size": 12, "shared_memory_offset": "0"}"#,
            r#"{"shared_memory_region": "r", "shared_memory_byte_size": 12, "binary_data_size": 12}"#,
        ] {
            assert_eq!(field_of(parse(&HeaderMap::new(), one(bad).as_bytes())), "points", "{bad}");
        }
    }

    #[test]
    fn outputs_in_shared_memory_name_their_region_and_carry_no_data() {
        use super::super::tensors::OutputTensor;
        let t =
            |name| OutputTensor { name, datatype: DataType::I32, shape: vec![2], data: TensorData::Int(vec![1, 2]) };
        let at = ShmRef { region: "out".into(), byte_size: 8, offset: 16 };
        let resp = InferResponse {
            model_name: "default".into(),
            model_version: "1".into(),
            id: None,
            outputs: vec![(t("num_points"), Placement::SharedMemory(at)), (t("scores"), Placement::Json)],
        };
        let r = encode_response(resp).unwrap();
        assert_eq!(r.headers()[header::CONTENT_TYPE], "application/json");
        let body = futures::executor::block_on(axum::body::to_bytes(r.into_body(), 1 << 20)).unwrap();
        let v: Value = serde_json::from_slice(&body).unwrap();
        let o = &v["outputs"][0];
        assert_eq!(o.get("data"), None);
        assert_eq!(
            o["parameters"],
            json!({"shared_memory_region": "out", "shared_memory_byte_size": 8, "shared_memory_offset": 16})
        );
        assert_eq!(v["outputs"][1]["data"], json!([1, 2]));
    }

    #[test]
    fn bad_requests_name_the_tensor_or_field() {
        let h = HeaderMap::new();
        let one = |input: &str| format!(r#"{{"inputs": [{input}]}}"#);
        assert_eq!(
            field_of(parse(
                &h,
                one(r#"{"name": "points", "shape": [1, 3], "datatype": "FP32", "data": [1, 2]}"#).as_bytes()
            )),
            "points"
        );
        assert_eq!(
            field_of(parse(
                &h,
                one(r#"{"name": "points", "shape": [1, 3], "datatype": "FLOAT", "data": [1, 2, 3]}"#).as_bytes()
            )),
            "points"
        );
        assert_eq!(
            field_of(parse(&h, one(r#"{"name": "points", "shape": [1, 3], "datatype": "FP32"}"#).as_bytes())),
            "points"
        );
        assert_eq!(
            field_of(parse(&h, one(r#"{"name": "points", "datatype": "FP32", "data": []}"#).as_bytes())),
            "inputs[0].shape"
        );
        assert_eq!(field_of(parse(&h, b"{not json")), "malformed_request");
        let outputs = r#"{"inputs": [], "outputs": [{"name": "scores", "parameters": {"binary_data": "yes"}}]}"#;
        assert_eq!(field_of(parse(&h, outputs.as_bytes())), "scores");
        let mut gz = HeaderMap::new();
        gz.insert(header::CONTENT_ENCODING, HeaderValue::from_static("gzip"));
        assert_eq!(field_of(parse(&gz, b"{}")), "malformed_request");
    }
}
