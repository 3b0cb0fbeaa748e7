//! The transports and the server's lifecycle: HTTP (axum) and gRPC (tonic) on one port, the
//! error mapping, health, Prometheus metrics, start-up, readiness and shutdown. Every request is
//! answered by [`crate::service::Predictor`]; nothing here decides anything about a pose.

pub mod errors;
pub mod grpc;
pub mod health;
pub mod http;
pub mod kserve;
pub mod metrics;
pub mod viewer;

use std::future::Future;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::Request;
use tower::ServiceExt;

use crate::error::{Error, Result};
use crate::runtime::{Runtime, RuntimeConfig};
use crate::service::Predictor;

/// Everything `run` needs.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    pub model_dir: PathBuf,
    pub runtime: RuntimeConfig,
    pub body_limit: usize,
    pub request_timeout: Duration,
    pub batch_concurrency: usize,
}

impl ServerConfig {
    /// Default bundle directory.
    pub const MODEL_DIR: &'static str = "models/default";
    /// Default body (HTTP) and message (gRPC) limit, bytes.
    pub const BODY_LIMIT: usize = 32 * 1024 * 1024;
    /// Default per-frame deadline, milliseconds.
    pub const REQUEST_TIMEOUT_MS: u64 = 10_000;
    /// Default frames of one batch or stream predicted concurrently.
    pub const BATCH_CONCURRENCY: usize = 8;

    /// Defaults for a bundle directory (those of `posefuse serve`).
    pub fn new(model_dir: impl Into<PathBuf>) -> ServerConfig {
        ServerConfig {
            model_dir: model_dir.into(),
            runtime: RuntimeConfig::DEFAULT,
            body_limit: Self::BODY_LIMIT,
            request_timeout: Duration::from_millis(Self::REQUEST_TIMEOUT_MS),
            batch_concurrency: Self::BATCH_CONCURRENCY,
        }
    }
}

/// State shared by every handler (cheap to clone).
#[derive(Clone)]
pub struct AppState {
    pub predictor: Predictor,
    pub body_limit: usize,
    pub request_timeout: Duration,
    pub batch_concurrency: usize,
    pub shutting_down: Arc<AtomicBool>,
    /// Warm-up done and the gRPC health status published (what /readyz reports).
    pub ready: Arc<AtomicBool>,
    pub prometheus: Option<metrics_exporter_prometheus::PrometheusHandle>,
}

/// A loaded server: bundle validated, sessions built, warm-up under way.
pub struct App {
    state: AppState,
}

impl App {
    /// Validates the bundle, builds the sessions and starts warming up (blocking).
    pub fn start(config: &ServerConfig) -> Result<App> {
        let runtime = Runtime::load(&config.model_dir, &config.runtime)?;
        let state = AppState {
            predictor: Predictor::new(runtime),
            body_limit: config.body_limit,
            request_timeout: config.request_timeout,
            batch_concurrency: config.batch_concurrency.max(1),
            shutting_down: Arc::new(AtomicBool::new(false)),
            ready: Arc::new(AtomicBool::new(false)),
            prometheus: metrics::install(),
        };
        Ok(App { state })
    }

    /// The predictor (runtime access for tests and tools).
    pub fn predictor(&self) -> &Predictor {
        &self.state.predictor
    }

    /// Serves on `listener` until `shutdown` completes, then finishes in-flight requests.
    pub async fn serve(
        self,
        listener: tokio::net::TcpListener,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> Result<()> {
        let state = self.state.clone();
        let (reporter, health_service) = tonic_health::server::health_reporter();
        let grpc_name =
            <grpc::proto::posefuse_server::PosefuseServer<grpc::GrpcService> as tonic::server::NamedService>::NAME;
        reporter.set_service_status("", tonic_health::ServingStatus::NotServing).await;
        reporter.set_service_status(grpc_name, tonic_health::ServingStatus::NotServing).await;
        let http_router = http::router(state.clone());
        let grpc_router = grpc::router(state.clone(), health_service);
        // One port: `Content-Type: application/grpc…` goes to tonic, everything else to the HTTP routes.
        let app = axum::Router::new().fallback_service(tower::service_fn(move |req: Request| {
            let (h, g) = (http_router.clone(), grpc_router.clone());
            async move {
                if is_grpc(&req) {
                    g.oneshot(req).await
                } else {
                    h.oneshot(req).await
                }
            }
        }));
        let ready_watch = {
            let (runtime, reporter, ready) = (state.predictor.runtime().clone(), reporter.clone(), state.ready.clone());
            tokio::spawn(async move {
                while !runtime.is_ready() {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                reporter.set_service_status("", tonic_health::ServingStatus::Serving).await;
                reporter.set_service_status(grpc_name, tonic_health::ServingStatus::Serving).await;
                // Only now, so that /readyz and gRPC health never disagree.
                ready.store(true, Ordering::SeqCst);
                tracing::info!("warmed up: ready");
            })
        };
        let flag = state.shutting_down.clone();
        let on_shutdown = {
            let reporter = reporter.clone();
            async move {
                shutdown.await;
                flag.store(true, Ordering::SeqCst);
                tracing::info!("shutting down: finishing in-flight requests");
                reporter.set_service_status("", tonic_health::ServingStatus::NotServing).await;
                reporter.set_service_status(grpc_name, tonic_health::ServingStatus::NotServing).await;
            }
        };
        let addr = listener.local_addr().ok();
        tracing::info!(?addr, "serving HTTP and gRPC");
        // Responses go out as several small writes (headers, body, gRPC trailers); Nagle's
        // algorithm would hold them back for the peer's delayed ACK (~40 ms).
        let listener = axum::serve::ListenerExt::tap_io(listener, |tcp: &mut tokio::net::TcpStream| {
            let _ = tcp.set_nodelay(true);
        });
        let served = axum::serve(listener, app).with_graceful_shutdown(on_shutdown).await;
        ready_watch.abort();
        let runtime = state.predictor.runtime().clone();
        drop(state);
        drop(self);
        // Joining the workers blocks; keep it off the executor.
        let _ = tokio::task::spawn_blocking(move || drop(runtime)).await;
        served.map_err(|e| Error::Io(format!("server: {e}")))
    }
}

fn is_grpc(req: &Request) -> bool {
    req.headers()
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|ct| ct.starts_with("application/grpc"))
}

/// Starts a server on `listener` and serves until `shutdown` completes: the library entry point
/// used by `posefuse serve` and by the integration tests.
pub async fn run(
    config: ServerConfig,
    listener: tokio::net::TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<()> {
    let app = tokio::task::spawn_blocking(move || App::start(&config))
        .await
        .map_err(|e| Error::Runtime(format!("start-up task failed: {e}")))??;
    app.serve(listener, shutdown).await
}

/// Completes on SIGTERM or Ctrl-C.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}
