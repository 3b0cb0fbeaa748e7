//! KServe's system shared-memory extension over HTTP (docs/KSERVE.md, "System shared memory"):
//! register, unregister and status under `/v2/systemsharedmemory`, as Triton serves them and
//! `tritonclient.http` calls them. Errors are the protocol's `{"error": "..."}`.

use axum::body::Bytes;
use axum::extract::{FromRequest, Path, Request, State};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;
use serde_json::{json, Value};

use super::super::errors::v2_response;
use super::super::http::bytes_rejection;
use super::super::AppState;
use super::shared_memory::RegionStatus;
use posefuse_core::error::Result;
use posefuse_core::json::parse_json;

/// The `/v2/systemsharedmemory` routes.
pub fn routes() -> Router<AppState> {
    Router::new()
        .route("/v2/systemsharedmemory/status", get(status_all))
        .route("/v2/systemsharedmemory/region/{name}/status", get(status_one))
        .route("/v2/systemsharedmemory/region/{name}/register", post(register))
        .route("/v2/systemsharedmemory/region/{name}/unregister", post(unregister_one))
        .route("/v2/systemsharedmemory/unregister", post(unregister_all))
}

/// The body of a registration.
#[derive(Debug, Deserialize)]
struct RegisterJson {
    key: String,
    #[serde(default)]
    offset: u64,
    byte_size: u64,
}

fn answer(r: Result<Value>) -> Response {
    match r {
        Ok(v) => Json(v).into_response(),
        Err(e) => v2_response(&e),
    }
}

fn status_json(regions: Vec<RegionStatus>) -> Value {
    Value::Array(
        regions
            .into_iter()
            .map(|r| json!({ "name": r.name, "key": r.key, "offset": r.offset, "byte_size": r.byte_size }))
            .collect(),
    )
}

async fn status_all(State(state): State<AppState>) -> Response {
    answer(state.shared_memory.status("").map(status_json))
}

async fn status_one(State(state): State<AppState>, Path(name): Path<String>) -> Response {
    answer(state.shared_memory.status(&name).map(status_json))
}

async fn register(State(state): State<AppState>, Path(name): Path<String>, req: Request) -> Response {
    let r = async {
        let body = Bytes::from_request(req, &state).await.map_err(|r| bytes_rejection(&r, state.body_limit))?;
        let b: RegisterJson = parse_json(&body)?;
        state.shared_memory.register(&name, &b.key, b.offset, b.byte_size)?;
        tracing::info!(region = %name, key = %b.key, offset = b.offset, byte_size = b.byte_size, "shared memory registered");
        Ok(json!({}))
    };
    answer(r.await)
}

async fn unregister_one(State(state): State<AppState>, Path(name): Path<String>) -> Response {
    answer(state.shared_memory.unregister(&name).map(|()| json!({})))
}

async fn unregister_all(State(state): State<AppState>) -> Response {
    answer(state.shared_memory.unregister("").map(|()| json!({})))
}
