//! The HTTP API (axum): routes, the JSON extractor whose rejections use the error body, NDJSON
//! streaming, health and metrics endpoints.

use std::sync::atomic::Ordering;

use axum::body::{Body, Bytes};
use axum::extract::{FromRequest, MatchedPath, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures::{Stream, StreamExt};
use serde::de::DeserializeOwned;

use super::errors::{HttpError, HttpResult, IntoHttpResponse as _};
use super::AppState;
use crate::eval::EvaluateResponse;
use crate::service::api::{BatchItem, ErrorBody, HealthResponse, PoseResponse};
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::Frame;
use posefuse_core::json::parse_json;

const NDJSON: &str = "application/x-ndjson";

/// The HTTP routes (gRPC is steered away before reaching them).
pub fn router(state: AppState) -> Router {
    let limit = state.body_limit;
    Router::new()
        .route("/v1/poses", post(poses))
        .route("/v1/poses:batch", post(batch))
        .route("/v1/evaluate", post(evaluate))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/v1/models", get(models))
        .route("/v1/models:reload", post(super::reload::reload))
        .route("/metrics", get(metrics_text))
        .route("/openapi.json", get(openapi))
        .merge(super::viewer::routes())
        .merge(super::kserve::rest::routes())
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(axum::middleware::from_fn(count_requests))
        .layer(axum::extract::DefaultBodyLimit::max(limit))
        .with_state(state)
}

/// The admin listener's routes (`--admin-addr`): model reload without a token, nothing else.
pub fn admin_router(state: AppState) -> Router {
    Router::new()
        .route("/v1/models:reload", post(super::reload::reload_admin))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(axum::extract::DefaultBodyLimit::max(ADMIN_BODY_LIMIT))
        .with_state(state)
}

/// A reload body names one directory.
const ADMIN_BODY_LIMIT: usize = 64 * 1024;

async fn count_requests(req: Request, next: Next) -> Response {
    let route =
        req.extensions().get::<MatchedPath>().map_or_else(|| "unmatched".to_string(), |m| m.as_str().to_string());
    let mut resp = next.run(req).await;
    metrics::counter!("posefuse_http_requests_total", "route" => route.clone(), "status" => resp.status().as_u16().to_string())
        .increment(1);
    resp.extensions_mut().insert(super::request_context::RouteLabel(route));
    resp
}

/// Whether a path is the Open Inference Protocol's, whose errors have its own shape.
fn is_v2(path: &str) -> bool {
    path == "/v2" || path.starts_with("/v2/")
}

async fn method_not_allowed(req: Request) -> Response {
    let e = Error::Malformed(format!("method {} is not allowed on {}", req.method(), req.uri().path()));
    let mut resp = if is_v2(req.uri().path()) { super::errors::v2_response(&e) } else { e.into_response() };
    *resp.status_mut() = StatusCode::METHOD_NOT_ALLOWED;
    resp
}

async fn not_found(req: Request) -> Response {
    if is_v2(req.uri().path()) {
        return super::kserve::rest::not_found(req.uri().clone()).await;
    }
    Error::NotFound(format!("no route for {} {}", req.method(), req.uri().path())).into_response()
}

/// JSON body extractor: content type, size limit and parse errors all answer with the error body
/// (413 over the limit, 400 for syntax, 422 naming the field for missing or mistyped fields).
pub struct ApiJson<T>(pub T);

impl<T: DeserializeOwned + Send + 'static> FromRequest<AppState> for ApiJson<T> {
    type Rejection = HttpError;

    async fn from_request(req: Request, state: &AppState) -> HttpResult<Self> {
        check_json_content_type(req.headers())?;
        let bytes = Bytes::from_request(req, state).await.map_err(|r| bytes_rejection(&r, state.body_limit))?;
        Ok(parse_json_off_executor(bytes).await.map(ApiJson)?)
    }
}

/// Bodies larger than this are parsed on the blocking pool, so that large requests do not hold
/// the async threads (and with them health checks and other clients).
const PARSE_ON_EXECUTOR_MAX: usize = 64 * 1024;

async fn parse_json_off_executor<T: DeserializeOwned + Send + 'static>(bytes: Bytes) -> Result<T> {
    if bytes.len() <= PARSE_ON_EXECUTOR_MAX {
        return parse_json(&bytes);
    }
    tokio::task::spawn_blocking(move || parse_json(&bytes))
        .await
        .map_err(|e| Error::Runtime(format!("parse task failed: {e}")))?
}

pub(super) fn bytes_rejection(r: &axum::extract::rejection::BytesRejection, limit: usize) -> Error {
    if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
        Error::PayloadTooLarge { limit }
    } else {
        Error::Malformed(format!("cannot read the request body: {}", r.body_text()))
    }
}

fn check_json_content_type(headers: &HeaderMap) -> Result<()> {
    match headers.get(header::CONTENT_TYPE).map(|v| v.to_str().unwrap_or("")) {
        None => Ok(()),
        Some(ct) if ct.starts_with("application/json") || ct.contains("+json") => Ok(()),
        Some(ct) => Err(Error::Malformed(format!("Content-Type must be application/json, got `{ct}`"))),
    }
}

/// Estimate the poses of every person of one frame.
#[utoipa::path(post, path = "/v1/poses", request_body = Frame, responses(
    (status = 200, description = "Poses", body = PoseResponse),
    (status = 400, description = "Malformed JSON", body = ErrorBody),
    (status = 413, description = "Body over the limit", body = ErrorBody),
    (status = 422, description = "Invalid field", body = ErrorBody),
    (status = 429, description = "Queue full", body = ErrorBody),
    (status = 503, description = "Warming up", body = ErrorBody),
    (status = 504, description = "Deadline passed", body = ErrorBody),
))]
async fn poses(State(state): State<AppState>, req: Request) -> HttpResult<Json<PoseResponse>> {
    let ticket = state.predictor.admitted(super::early_admission::ticket(req.extensions()))?;
    let ApiJson(frame) = ApiJson::<Frame>::from_request(req, &state).await?;
    Ok(state.predictor.answer_admitted(&ticket, frame, None, state.request_timeout).await.map(Json)?)
}

/// Several frames: a JSON array in and out, or NDJSON (`Content-Type: application/x-ndjson`)
/// streamed in and out. Results keep the input order; a bad frame gives an error item.
#[utoipa::path(post, path = "/v1/poses:batch", request_body = Vec<Frame>, responses(
    (status = 200, description = "One item per frame, in order", body = Vec<BatchItem>),
    (status = 400, description = "Malformed JSON", body = ErrorBody),
    (status = 413, description = "Body over the limit", body = ErrorBody),
    (status = 422, description = "The body is not an array of frames", body = ErrorBody),
))]
async fn batch(State(state): State<AppState>, req: Request) -> Response {
    let is_ndjson = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|ct| ct.starts_with(NDJSON) || ct.starts_with("application/jsonl"));
    if is_ndjson {
        return ndjson_batch(state, req.into_body());
    }
    let values: Vec<Box<serde_json::value::RawValue>> = match ApiJson::from_request(req, &state).await {
        Ok(ApiJson(v)) => v,
        Err(e) => return e.into_response(),
    };
    let (concurrency, timeout) = (state.batch_concurrency, state.request_timeout);
    let predictor = &state.predictor;
    let items: Vec<BatchItem> = futures::stream::iter(values.into_iter().enumerate())
        .map(|(i, v)| async move {
            let parse = async move { parse_json_off_executor::<Frame>(Bytes::from(v.get().to_owned())).await };
            predictor.answer_item(i, parse, timeout).await
        })
        .buffered(concurrency)
        .collect()
        .await;
    Json(items).into_response()
}

fn ndjson_batch(state: AppState, body: Body) -> Response {
    let limit = state.body_limit;
    let concurrency = state.batch_concurrency;
    let (predictor, timeout) = (state.predictor.clone(), state.request_timeout);
    // On drain the lines already read finish; one last item says no more are read.
    let lines =
        super::lifecycle::end_on_drain(ndjson_lines(body.into_data_stream(), limit), state.drain.clone(), || {
            Err(Error::Unavailable("the server is shutting down: no further lines are read".into()))
        });
    let out = lines
        .enumerate()
        .map(move |(i, line)| {
            let predictor = predictor.clone();
            async move { predictor.answer_item(i, async { parse_json::<Frame>(&line?) }, timeout).await }
        })
        .buffered(concurrency)
        .map(|it| {
            let mut line = serde_json::to_vec(&it).unwrap_or_else(|e| {
                format!(r#"{{"index":{},"error":{{"code":"runtime_error","message":"{e}"}}}}"#, it.index).into_bytes()
            });
            line.push(b'\n');
            Ok::<_, std::convert::Infallible>(Bytes::from(line))
        });
    let mut resp = Response::new(Body::from_stream(out));
    resp.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(NDJSON));
    resp
}

/// Splits a byte stream into non-blank lines; a line over `limit` bytes becomes an error item and
/// is skipped.
fn ndjson_lines<S>(stream: S, limit: usize) -> impl Stream<Item = Result<Vec<u8>>> + Send
where
    S: Stream<Item = std::result::Result<Bytes, axum::Error>> + Send + Unpin + 'static,
{
    struct Reader<S> {
        stream: S,
        buf: Vec<u8>,
        eof: bool,
        skipping: bool,
    }
    let reader = Reader { stream, buf: Vec::new(), eof: false, skipping: false };
    futures::stream::unfold(reader, move |mut r| async move {
        loop {
            if let Some(pos) = r.buf.iter().position(|b| *b == b'\n') {
                let mut line: Vec<u8> = r.buf.drain(..=pos).collect();
                line.pop();
                if line.iter().all(u8::is_ascii_whitespace) {
                    continue;
                }
                if line.len() > limit {
                    return Some((Err(Error::PayloadTooLarge { limit }), r));
                }
                return Some((Ok(line), r));
            }
            if r.buf.len() > limit {
                r.buf.clear();
                r.skipping = true;
                return Some((Err(Error::PayloadTooLarge { limit }), r));
            }
            if r.eof {
                if r.buf.iter().all(u8::is_ascii_whitespace) {
                    return None;
                }
                let line = std::mem::take(&mut r.buf);
                if line.len() > limit {
                    return Some((Err(Error::PayloadTooLarge { limit }), r));
                }
                return Some((Ok(line), r));
            }
            match r.stream.next().await {
                Some(Ok(chunk)) => {
                    if r.skipping {
                        if let Some(pos) = chunk.iter().position(|b| *b == b'\n') {
                            r.skipping = false;
                            r.buf.extend_from_slice(&chunk[pos + 1..]);
                        }
                    } else {
                        r.buf.extend_from_slice(&chunk);
                    }
                }
                Some(Err(e)) => {
                    r.eof = true;
                    r.buf.clear();
                    return Some((Err(Error::Malformed(format!("cannot read the request body: {e}"))), r));
                }
                None => r.eof = true,
            }
        }
    })
}

/// Predict frames that carry ground truth and score them (OKS/ACC 3D, MPJPE, PCK, PEM, OKS@2D,
/// per-keypoint OKS), overall and per mode.
#[utoipa::path(post, path = "/v1/evaluate", request_body = Vec<Frame>, responses(
    (status = 200, description = "Predictions and metrics", body = EvaluateResponse),
    (status = 400, description = "Malformed JSON", body = ErrorBody),
    (status = 413, description = "Body over the limit", body = ErrorBody),
    (status = 422, description = "The body is not an array of frames, or ground truth is invalid", body = ErrorBody),
))]
async fn evaluate(
    State(state): State<AppState>,
    ApiJson(values): ApiJson<Vec<Box<serde_json::value::RawValue>>>,
) -> HttpResult<Json<EvaluateResponse>> {
    // Parsed as many at a time as frames are predicted, so a large body cannot hold a blocking
    // thread per item.
    let frames: Vec<Result<Frame>> = futures::stream::iter(values)
        .map(|v| parse_json_off_executor::<Frame>(Bytes::from(v.get().to_owned())))
        .buffered(state.batch_concurrency)
        .collect()
        .await;
    Ok(crate::eval::evaluate_frames(&state.predictor, frames, state.batch_concurrency, state.request_timeout)
        .await
        .map(Json)?)
}

/// Liveness: the process answers.
#[utoipa::path(get, path = "/healthz", responses((status = 200, body = HealthResponse)))]
async fn healthz() -> Json<HealthResponse> {
    Json(HealthResponse { status: "ok".into() })
}

/// Readiness: models loaded and warmed up, not shutting down.
#[utoipa::path(get, path = "/readyz", responses(
    (status = 200, body = HealthResponse), (status = 503, body = HealthResponse)))]
async fn readyz(State(state): State<AppState>) -> (StatusCode, Json<HealthResponse>) {
    let status = if state.shutting_down.load(Ordering::SeqCst) {
        "shutting_down"
    } else if state.ready.load(Ordering::SeqCst) {
        "ready"
    } else {
        "warming_up"
    };
    let code = if status == "ready" { StatusCode::OK } else { StatusCode::SERVICE_UNAVAILABLE };
    (code, Json(HealthResponse { status: status.into() }))
}

/// The loaded bundle's manifest.
#[utoipa::path(get, path = "/v1/models", responses((status = 200, description = "manifest.json", body = Object)))]
async fn models(State(state): State<AppState>) -> Json<serde_json::Value> {
    Json(state.predictor.bundle().raw.clone())
}

/// Prometheus metrics.
#[utoipa::path(get, path = "/metrics", responses((status = 200, description = "Prometheus text format", body = String)))]
async fn metrics_text(State(state): State<AppState>) -> Response {
    match &state.prometheus {
        Some(h) => {
            h.run_upkeep();
            ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], h.render()).into_response()
        }
        None => Error::Unavailable("metrics recorder not installed".into()).into_response(),
    }
}

#[derive(utoipa::OpenApi)]
#[openapi(
    info(title = "posefuse", description = "Multi-modal (camera + LiDAR) 3D pedestrian pose estimation"),
    paths(poses, batch, evaluate, healthz, readyz, models, super::reload::reload, metrics_text, openapi)
)]
struct ApiDoc;

/// The OpenAPI document of this API.
pub fn openapi_doc() -> utoipa::openapi::OpenApi {
    <ApiDoc as utoipa::OpenApi>::openapi()
}

/// OpenAPI 3 description of this API.
#[utoipa::path(get, path = "/openapi.json", responses((status = 200, description = "OpenAPI document")))]
async fn openapi() -> Json<utoipa::openapi::OpenApi> {
    Json(openapi_doc())
}
