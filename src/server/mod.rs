//! HTTP (axum) and gRPC (tonic) front ends on one port, and the CLI commands that share their
//! code path (`Predictor`).

pub mod api;
pub mod errors;
pub mod eval;
pub mod grpc;
pub mod health;
pub mod http;
pub mod kserve;
pub mod metrics;
pub mod predict;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::Request;
use tower::ServiceExt;

use crate::error::{Error, Result};
use crate::frame::RequestedMode;
use crate::runtime::{Bundle, Runtime, RuntimeConfig};
pub use predict::Predictor;

/// Model bundle and ONNX Runtime settings, shared by `serve`, `predict` and `eval`.
#[derive(Debug, Clone, clap::Args)]
pub struct RuntimeArgs {
    /// Model bundle directory (manifest.json + ONNX files).
    #[arg(long, env = "POSEFUSE_MODEL_DIR", default_value = "models/default")]
    pub model_dir: PathBuf,
    /// ONNX Runtime shared library (default: .ort/lib/libonnxruntime.so, installed by scripts/setup.sh).
    #[arg(long, env = "ORT_DYLIB_PATH")]
    pub ort_lib: Option<PathBuf>,
    /// Inference worker threads; each owns its own ONNX Runtime sessions.
    #[arg(long, env = "POSEFUSE_WORKERS", default_value_t = 1)]
    pub workers: usize,
    /// ONNX Runtime intra-op threads per session.
    #[arg(long, env = "POSEFUSE_INTRA_THREADS", default_value_t = 1)]
    pub intra_threads: usize,
    /// Largest inference batch a worker forms from queued jobs.
    #[arg(long, env = "POSEFUSE_MAX_BATCH", default_value_t = 16)]
    pub max_batch: usize,
    /// Microseconds a worker waits for more jobs to fill a batch (0: batch only what is queued).
    #[arg(long, env = "POSEFUSE_BATCH_WAIT_US", default_value_t = 0)]
    pub batch_wait_us: u64,
    /// Inference jobs (one per person and network) that may wait; beyond, requests get 429.
    #[arg(long, env = "POSEFUSE_QUEUE_SIZE", default_value_t = 256)]
    pub queue_size: usize,
}

impl RuntimeArgs {
    /// The runtime configuration these flags describe.
    pub fn runtime_config(&self) -> RuntimeConfig {
        RuntimeConfig {
            ort_lib: self.ort_lib.clone(),
            workers: self.workers,
            intra_threads: self.intra_threads,
            max_batch: self.max_batch,
            batch_wait: Duration::from_micros(self.batch_wait_us),
            queue_size: self.queue_size,
        }
    }
}

/// Arguments of `posefuse serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    #[command(flatten)]
    pub runtime: RuntimeArgs,
    /// Address to listen on (HTTP/1.1, HTTP/2 and gRPC share it).
    #[arg(long, env = "POSEFUSE_ADDR", default_value = "0.0.0.0:8080")]
    pub addr: SocketAddr,
    /// Largest request body (HTTP) or message (gRPC), bytes; NDJSON applies it per line.
    #[arg(long, env = "POSEFUSE_BODY_LIMIT", default_value_t = 32 * 1024 * 1024)]
    pub body_limit: usize,
    /// Per-frame deadline in milliseconds (504 / DEADLINE_EXCEEDED when passed).
    #[arg(long, env = "POSEFUSE_REQUEST_TIMEOUT_MS", default_value_t = 10_000)]
    pub request_timeout_ms: u64,
    /// Frames of one batch or stream predicted concurrently.
    #[arg(long, env = "POSEFUSE_BATCH_CONCURRENCY", default_value_t = 8)]
    pub batch_concurrency: usize,
    /// Log as JSON lines instead of text.
    #[arg(long, env = "POSEFUSE_LOG_JSON")]
    pub log_json: bool,
}

/// Arguments of `posefuse predict`.
#[derive(Debug, clap::Args)]
pub struct PredictArgs {
    /// Frame JSON file (the body of POST /v1/poses).
    pub frame: PathBuf,
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

/// Arguments of `posefuse eval`.
#[derive(Debug, clap::Args)]
pub struct EvalArgs {
    /// Simulator output directory; its requests/*.json fixtures are evaluated.
    #[arg(long, env = "POSEFUSE_EVAL_DATA")]
    pub data: PathBuf,
    /// Force one mode for every person instead of choosing per person.
    #[arg(long, env = "POSEFUSE_EVAL_MODE", value_enum)]
    pub mode: Option<ModeArg>,
    /// Print a machine-readable JSON report instead of tables.
    #[arg(long, env = "POSEFUSE_EVAL_JSON")]
    pub json: bool,
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

/// A mode named on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ModeArg {
    Auto,
    Fusion,
    Lidar,
    Camera,
}

impl From<ModeArg> for RequestedMode {
    fn from(m: ModeArg) -> RequestedMode {
        match m {
            ModeArg::Auto => RequestedMode::Auto,
            ModeArg::Fusion => RequestedMode::Fusion,
            ModeArg::Lidar => RequestedMode::Lidar,
            ModeArg::Camera => RequestedMode::Camera,
        }
    }
}

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
    /// Defaults for a bundle directory (those of `posefuse serve`).
    pub fn new(model_dir: impl Into<PathBuf>) -> ServerConfig {
        ServerConfig {
            model_dir: model_dir.into(),
            runtime: RuntimeConfig::default(),
            body_limit: 32 * 1024 * 1024,
            request_timeout: Duration::from_secs(10),
            batch_concurrency: 8,
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

/// Loads the bundle and starts the runtime (blocking: builds sessions).
pub fn load_runtime(model_dir: &std::path::Path, cfg: &RuntimeConfig) -> Result<Arc<Runtime>> {
    let bundle = Arc::new(Bundle::load(model_dir)?);
    if bundle.trained() == Some(false) {
        tracing::warn!(bundle = %model_dir.display(), "serving an UNTRAINED bundle (tests only)");
    }
    let m = &bundle.manifest;
    tracing::info!(bundle = %model_dir.display(), name = %m.name, version = %m.version, "bundle loaded");
    Ok(Arc::new(Runtime::start(bundle, cfg)?))
}

impl App {
    /// Validates the bundle, builds the sessions and starts warming up (blocking).
    pub fn start(config: &ServerConfig) -> Result<App> {
        let runtime = load_runtime(&config.model_dir, &config.runtime)?;
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

fn init_tracing(json: bool) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,ort=warn"));
    // Colour codes only for a person at a terminal, not in a container's or a collector's log.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(ansi);
    let _ = if json { builder.json().try_init() } else { builder.try_init() };
}

fn tokio_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().enable_all().build()?)
}

/// Runs `posefuse serve`.
pub fn serve_command(a: ServeArgs) -> anyhow::Result<()> {
    init_tracing(a.log_json);
    let config = ServerConfig {
        model_dir: a.runtime.model_dir.clone(),
        runtime: a.runtime.runtime_config(),
        body_limit: a.body_limit,
        request_timeout: Duration::from_millis(a.request_timeout_ms),
        batch_concurrency: a.batch_concurrency,
    };
    tokio_runtime()?.block_on(async move {
        let listener = tokio::net::TcpListener::bind(a.addr)
            .await
            .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", a.addr))?;
        run(config, listener, shutdown_signal()).await?;
        Ok(())
    })
}

/// Starts the runtime for a CLI command and waits for warm-up.
fn cli_predictor(a: &RuntimeArgs) -> anyhow::Result<Predictor> {
    let runtime = load_runtime(&a.model_dir, &a.runtime_config())?;
    if !runtime.wait_ready(Duration::from_secs(300)) {
        anyhow::bail!("the models did not warm up (see the log)");
    }
    Ok(Predictor::new(runtime))
}

/// Runs `posefuse predict`.
pub fn predict_command(a: PredictArgs) -> anyhow::Result<()> {
    init_tracing(false);
    let bytes = std::fs::read(&a.frame).map_err(|e| anyhow::anyhow!("{}: {e}", a.frame.display()))?;
    let frame = http::parse_json(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", a.frame.display()))?;
    let predictor = cli_predictor(&a.runtime)?;
    let resp = tokio_runtime()?.block_on(predictor.predict(frame, None))?;
    println!("{}", serde_json::to_string_pretty(&resp)?);
    Ok(())
}

/// Runs `posefuse eval`.
pub fn eval_command(a: EvalArgs) -> anyhow::Result<()> {
    init_tracing(false);
    let mut frames = eval::load_fixtures(&a.data)?;
    if let Some(m) = a.mode {
        for (_, f) in &mut frames {
            f.mode = m.into();
        }
    }
    let predictor = cli_predictor(&a.runtime)?;
    let report =
        tokio_runtime()?.block_on(eval::evaluate_frames(&predictor, &a.data, a.mode.map(Into::into), frames))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.text());
    }
    Ok(())
}
