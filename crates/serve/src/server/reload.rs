//! Model swap without a restart: `POST /v1/models:reload` (or SIGHUP) loads a bundle (the
//! serving directory again, or one named in the body), validates it, warms it up beside the
//! serving runtime and then switches new requests to it at once. Requests already running finish
//! on the runtime they started on, which is shut down when the last of them is done. A bundle
//! that fails leaves the serving one in place; the reason is in the response and the log. Who may
//! reload, and which bundles a request may name, is `server::admin`'s.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::State;
use axum::http::HeaderMap;
use axum::Json;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::errors::HttpResult;
use super::AppState;
use crate::runtime::{Runtime, RuntimeConfig};
use crate::service::api::{ErrorBody, ModelRef};
use crate::service::Predictor;
use posefuse_core::error::{Error, Result};

/// Body of `POST /v1/models:reload` (optional).
#[derive(Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ReloadRequest {
    /// Bundle to load: a directory in the model repository (`--model-repository`), relative to
    /// it; the serving bundle when absent.
    #[serde(default)]
    pub model_dir: Option<String>,
}

/// Answer of a reload that switched bundles.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct ReloadResponse {
    /// The bundle now serving.
    pub model: ModelRef,
    /// Its directory.
    pub model_dir: String,
    /// The bundle it replaced.
    pub previous: ModelRef,
}

/// Loads bundles beside the serving one and swaps them in.
pub struct Reloader {
    predictor: Predictor,
    runtime: RuntimeConfig,
    model_dir: Mutex<PathBuf>,
    /// One reload at a time.
    busy: tokio::sync::Mutex<()>,
    warm_up_timeout: Duration,
}

fn model_ref(rt: &Runtime) -> ModelRef {
    let m = &rt.bundle().manifest;
    ModelRef { name: m.name.clone(), version: m.version.clone() }
}

impl Reloader {
    /// A reloader for `predictor`, whose runtime was loaded from `model_dir` with `runtime`.
    pub fn new(predictor: Predictor, model_dir: PathBuf, runtime: RuntimeConfig) -> Reloader {
        Reloader {
            predictor,
            runtime,
            model_dir: Mutex::new(model_dir),
            busy: tokio::sync::Mutex::new(()),
            warm_up_timeout: Duration::from_secs(300),
        }
    }

    /// The directory of the bundle serving now.
    pub fn model_dir(&self) -> PathBuf {
        self.model_dir.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Loads, validates and warms up the bundle in `dir` (default: the serving directory), then
    /// switches to it. On failure the serving bundle stays; the error names `model_dir`.
    pub async fn reload(&self, dir: Option<PathBuf>) -> Result<ReloadResponse> {
        let _one_at_a_time = self.busy.lock().await;
        let dir = dir.unwrap_or_else(|| self.model_dir());
        tracing::info!(bundle = %dir.display(), "reload: loading beside the serving bundle");
        let (cfg, path, timeout) = (self.runtime.clone(), dir.clone(), self.warm_up_timeout);
        let loaded = tokio::task::spawn_blocking(move || -> Result<Arc<Runtime>> {
            let rt = crate::runtime::Runtime::load(&path, &cfg)?;
            if !rt.wait_ready(timeout) {
                return Err(Error::Bundle("the models did not warm up (see the log)".into()));
            }
            Ok(rt)
        })
        .await
        .map_err(|e| Error::Runtime(format!("reload task failed: {e}")))
        .and_then(|r| r);
        let new = match loaded {
            Ok(rt) => rt,
            Err(e) => {
                tracing::warn!(bundle = %dir.display(), "reload refused, the serving bundle stays: {e}");
                return Err(Error::field("model_dir", format!("{}: {e}", dir.display())));
            }
        };
        let model = model_ref(&new);
        let old = self.predictor.swap(new);
        let previous = model_ref(&old);
        super::metrics::build_info(&previous.name, &previous.version, false);
        super::metrics::build_info(&model.name, &model.version, true);
        *self.model_dir.lock().unwrap_or_else(|p| p.into_inner()) = dir.clone();
        tracing::info!(
            bundle = %dir.display(), name = %model.name, version = %model.version,
            previous = %previous.version, "reloaded: new requests use the new bundle"
        );
        retire(old);
        Ok(ReloadResponse { model, model_dir: dir.display().to_string(), previous })
    }
}

/// Shuts a replaced runtime down once the requests still using it are done (off the executor:
/// joining its workers blocks).
fn retire(old: Arc<Runtime>) {
    tokio::spawn(async move {
        while Arc::strong_count(&old) > 1 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let _ = tokio::task::spawn_blocking(move || drop(old)).await;
    });
}

/// Load a bundle beside the serving one and switch to it without dropping a request. On the
/// serving port only with `Authorization: Bearer <admin token>`; on `--admin-addr` without.
#[utoipa::path(post, path = "/v1/models:reload", request_body(content = Option<ReloadRequest>), responses(
    (status = 200, description = "Switched to the new bundle", body = ReloadResponse),
    (status = 400, description = "Malformed JSON", body = ErrorBody),
    (status = 403, description = "Administration is not allowed here (no or a wrong admin token)", body = ErrorBody),
    (status = 422, description = "The bundle does not load, or is not in the model repository; the serving one stays", body = ErrorBody),
))]
pub async fn reload(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Bytes,
) -> HttpResult<Json<ReloadResponse>> {
    super::admin::authorize(&headers, state.admin.token.as_deref())?;
    Ok(reload_unguarded(&state, &body).await?)
}

/// The admin listener's reload: no token (the listener is the lock).
pub async fn reload_admin(State(state): State<AppState>, body: Bytes) -> HttpResult<Json<ReloadResponse>> {
    Ok(reload_unguarded(&state, &body).await?)
}

async fn reload_unguarded(state: &AppState, body: &[u8]) -> Result<Json<ReloadResponse>> {
    let req: ReloadRequest = if body.iter().all(u8::is_ascii_whitespace) {
        ReloadRequest::default()
    } else {
        posefuse_core::json::parse_json(body)?
    };
    let dir = match req.model_dir.as_deref() {
        Some(name) => Some(super::admin::resolve_bundle(state.admin.repository.as_deref(), name)?),
        None => None,
    };
    state.reloader.reload(dir).await.map(Json)
}
