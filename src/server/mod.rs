//! HTTP (axum) and gRPC (tonic) front ends on one port, and the CLI commands that share their
//! code path (`Predictor`).

pub mod admission;
pub mod api;
pub mod conn;
pub mod errors;
pub mod eval;
pub mod grpc;
pub mod health;
pub mod http;
pub mod lifecycle;
pub mod limits;
pub mod metrics;
pub mod predict;
pub mod reload;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::Request;
use tokio_util::sync::CancellationToken;
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
    /// Inference worker threads; each owns its own ONNX Runtime sessions (0: one per 4 cores).
    #[arg(long, env = "POSEFUSE_WORKERS", default_value_t = 0)]
    pub workers: usize,
    /// ONNX Runtime intra-op threads per session (0: the worker's share of the cores, at most 4).
    #[arg(long, env = "POSEFUSE_INTRA_THREADS", default_value_t = 0)]
    pub intra_threads: usize,
    /// Largest inference batch a worker forms from queued jobs.
    #[arg(long, env = "POSEFUSE_MAX_BATCH", default_value_t = 16)]
    pub max_batch: usize,
    /// Microseconds a worker waits for more jobs to fill a batch (0: batch only what is queued;
    /// default: 0 with one worker, 200 with several).
    #[arg(long, env = "POSEFUSE_BATCH_WAIT_US")]
    pub batch_wait_us: Option<u64>,
    /// Inference jobs (one per person and network) that may wait; beyond, requests get 429.
    #[arg(long, env = "POSEFUSE_QUEUE_SIZE", default_value_t = 256)]
    pub queue_size: usize,
}

impl RuntimeArgs {
    /// The runtime configuration these flags describe (unset sizes from the machine's cores).
    pub fn runtime_config(&self) -> RuntimeConfig {
        let sizing = admission::Sizing::detect();
        let workers = if self.workers == 0 { sizing.workers } else { self.workers };
        let intra_threads = if self.intra_threads == 0 { sizing.intra_threads } else { self.intra_threads };
        let batch_wait_us = self.batch_wait_us.unwrap_or(if workers > 1 { sizing.batch_wait_us.max(200) } else { 0 });
        RuntimeConfig {
            ort_lib: self.ort_lib.clone(),
            workers,
            intra_threads,
            max_batch: self.max_batch,
            batch_wait: Duration::from_micros(batch_wait_us),
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
    /// Seconds the drain may take after SIGTERM (once the listener closes); then the process
    /// exits anyway, logging what was cut.
    #[arg(long, env = "POSEFUSE_DRAIN_TIMEOUT", default_value_t = 30)]
    pub drain_timeout: u64,
    /// Milliseconds the listener keeps accepting after SIGTERM while readiness already says 503
    /// (time for a load balancer to notice).
    #[arg(long, env = "POSEFUSE_DRAIN_DELAY_MS", default_value_t = 0)]
    pub drain_delay_ms: u64,
    /// Milliseconds a client has to send a request's headers (HTTP/1).
    #[arg(long, env = "POSEFUSE_HEADER_TIMEOUT_MS", default_value_t = 10_000)]
    pub header_timeout_ms: u64,
    /// Longest pause, in milliseconds, between two chunks of a request body.
    #[arg(long, env = "POSEFUSE_BODY_TIMEOUT_MS", default_value_t = 30_000)]
    pub body_timeout_ms: u64,
    /// Milliseconds without a byte in either direction after which a connection is closed.
    #[arg(long, env = "POSEFUSE_IDLE_TIMEOUT_MS", default_value_t = 60_000)]
    pub idle_timeout_ms: u64,
    /// Open connections at most (0: the file-descriptor limit less a reserve). At the cap the
    /// connection idle the longest is closed; when none is idle, new ones are closed at once.
    #[arg(long, env = "POSEFUSE_MAX_CONNECTIONS", default_value_t = 0)]
    pub max_connections: usize,
    /// Frames decoded and pre-processed at once (0: one per core).
    #[arg(long, env = "POSEFUSE_DECODE_PERMITS", default_value_t = 0)]
    pub decode_permits: usize,
    /// Requests that may wait for a decode permit; beyond, 429 at once (0: 8 per permit).
    #[arg(long, env = "POSEFUSE_ADMISSION_QUEUE", default_value_t = 0)]
    pub admission_queue: usize,
    /// Persons per frame at most (422 beyond).
    #[arg(long, env = "POSEFUSE_MAX_PERSONS", default_value_t = 256)]
    pub max_persons: usize,
    /// LiDAR points per frame at most (422 beyond).
    #[arg(long, env = "POSEFUSE_MAX_POINTS", default_value_t = 1_000_000)]
    pub max_points: usize,
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
    /// How long the drain may take once the listener closes.
    pub drain_timeout: Duration,
    /// How long the listener keeps accepting after the shutdown signal (readiness already 503).
    pub drain_delay: Duration,
    /// Timeouts and the connection cap.
    pub conn: conn::ConnLimits,
    /// Frames decoded and pre-processed at once.
    pub decode_permits: usize,
    /// Requests that may wait for a decode permit before 429.
    pub admission_queue: usize,
    /// Persons and points per frame.
    pub frame_limits: limits::FrameLimits,
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
            drain_timeout: Duration::from_secs(30),
            drain_delay: Duration::ZERO,
            conn: conn::ConnLimits::default(),
            decode_permits: 2,
            admission_queue: 64,
            frame_limits: limits::FrameLimits::default(),
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
    /// Cancelled when the drain starts (the listener closes): streams stop reading input.
    pub drain: CancellationToken,
    /// Swaps bundles while serving.
    pub reloader: Arc<reload::Reloader>,
    /// Warm-up done and the gRPC health status published (what /readyz reports).
    pub ready: Arc<AtomicBool>,
    pub prometheus: Option<metrics_exporter_prometheus::PrometheusHandle>,
}

/// A loaded server: bundle validated, sessions built, warm-up under way.
pub struct App {
    state: AppState,
    drain_timeout: Duration,
    drain_delay: Duration,
    conn: conn::ConnLimits,
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
        let admission = admission::Admission::new(config.decode_permits, config.admission_queue);
        let predictor = Predictor::with_admission(runtime, admission).with_limits(config.frame_limits);
        let reloader = reload::Reloader::new(predictor.clone(), config.model_dir.clone(), config.runtime.clone());
        let state = AppState {
            predictor,
            body_limit: config.body_limit,
            request_timeout: config.request_timeout,
            batch_concurrency: config.batch_concurrency.max(1),
            shutting_down: Arc::new(AtomicBool::new(false)),
            drain: CancellationToken::new(),
            reloader: Arc::new(reloader),
            ready: Arc::new(AtomicBool::new(false)),
            prometheus: metrics::install(),
        };
        Ok(App {
            state,
            drain_timeout: config.drain_timeout,
            drain_delay: config.drain_delay,
            conn: config.conn.clone(),
        })
    }

    /// Swaps bundles while serving (`POST /v1/models:reload`, SIGHUP).
    pub fn reloader(&self) -> &Arc<reload::Reloader> {
        &self.state.reloader
    }

    /// The predictor (runtime access for tests and tools).
    pub fn predictor(&self) -> &Predictor {
        &self.state.predictor
    }

    /// Serves on `listener` until `shutdown` completes, then drains: readiness goes 503 /
    /// NOT_SERVING at once, the listener keeps accepting for the drain delay, then closes;
    /// requests in hand finish, streams stop reading, and after the drain timeout whatever is
    /// left is cut (logged). Returns Ok in every case of a completed drain.
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
        let in_flight = Arc::new(lifecycle::InFlight::default());
        let admission = state.predictor.admission().clone();
        let app = axum::Router::new()
            .fallback_service(tower::service_fn(move |mut req: Request| {
                let (h, g) = (http_router.clone(), grpc_router.clone());
                // A unary frame is admitted before its message is read (429 at once when full).
                let admitted = (is_grpc(&req) && req.uri().path() == grpc::PREDICT_PATH).then(|| admission.admit());
                async move {
                    if let Some(admitted) = admitted {
                        match admitted {
                            Ok(ticket) => {
                                req.extensions_mut().insert(Arc::new(ticket));
                            }
                            Err(e) => return Ok(errors::grpc_status(&e).into_http()),
                        }
                    }
                    if is_grpc(&req) {
                        g.oneshot(req).await
                    } else {
                        h.oneshot(req).await
                    }
                }
            }))
            .layer(axum::middleware::from_fn_with_state(in_flight.clone(), lifecycle::count_in_flight));
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
        let drain = state.drain.clone();
        let delay = self.drain_delay;
        let on_shutdown = {
            let reporter = reporter.clone();
            let drain = drain.clone();
            async move {
                shutdown.await;
                flag.store(true, Ordering::SeqCst);
                reporter.set_service_status("", tonic_health::ServingStatus::NotServing).await;
                reporter.set_service_status(grpc_name, tonic_health::ServingStatus::NotServing).await;
                tracing::info!(drain_delay_ms = delay.as_millis() as u64, "shutting down: readiness is 503");
                tokio::time::sleep(delay).await;
                tracing::info!("draining: listener closed, finishing in-flight requests, streams told to end");
                drain.cancel();
            }
        };
        let addr = listener.local_addr().ok();
        let mut limits = self.conn.clone();
        if limits.max_connections == 0 {
            limits.max_connections = conn::default_max_connections(conn::raise_fd_limit());
        }
        tracing::info!(?addr, max_connections = limits.max_connections, "serving HTTP and gRPC");
        let registry = Arc::new(conn::Registry::default());
        let (_, report) =
            tokio::join!(on_shutdown, conn::serve(listener, app, limits, registry, drain.clone(), self.drain_timeout));
        let cut_requests = in_flight.get();
        if report.connections_cut > 0 || cut_requests > 0 {
            tracing::warn!(
                connections = report.connections_cut,
                requests = cut_requests,
                "drain deadline passed: cut what was still open"
            );
        } else {
            tracing::info!("drained: every connection finished");
        }
        ready_watch.abort();
        let runtime = state.predictor.runtime().clone();
        drop(state);
        drop(self);
        // Joining the workers blocks; keep it off the executor.
        let _ = tokio::task::spawn_blocking(move || drop(runtime)).await;
        Ok(())
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
    lifecycle::terminate().await
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
        drain_timeout: Duration::from_secs(a.drain_timeout),
        drain_delay: Duration::from_millis(a.drain_delay_ms),
        conn: conn::ConnLimits {
            header_read_timeout: Duration::from_millis(a.header_timeout_ms),
            body_read_timeout: Duration::from_millis(a.body_timeout_ms),
            idle_timeout: Duration::from_millis(a.idle_timeout_ms),
            max_connections: a.max_connections,
        },
        decode_permits: a.decode_permits,
        admission_queue: a.admission_queue,
        frame_limits: limits::FrameLimits { max_persons: a.max_persons, max_points: a.max_points },
    };
    tokio_runtime()?.block_on(serve_with_signals(config, a.addr))
}

/// `posefuse serve` after parsing: SIGHUP reloads (handled before loading, so that an early one
/// does not kill the process), SIGTERM/Ctrl-C drains; a completed drain exits 0.
pub async fn serve_with_signals(mut config: ServerConfig, addr: SocketAddr) -> anyhow::Result<()> {
    let (set_reloader, reloader) = tokio::sync::watch::channel(None);
    #[cfg(unix)]
    lifecycle::reload_on_hangup(reloader)?;
    #[cfg(not(unix))]
    drop(reloader);
    let sizing = admission::Sizing::detect();
    if config.decode_permits == 0 {
        config.decode_permits = sizing.decode_permits;
    }
    if config.admission_queue == 0 {
        config.admission_queue = 8 * config.decode_permits;
    }
    tracing::info!(
        cores = sizing.cores,
        workers = config.runtime.workers,
        intra_threads = config.runtime.intra_threads,
        batch_wait_us = config.runtime.batch_wait.as_micros() as u64,
        decode_permits = config.decode_permits,
        admission_queue = config.admission_queue,
        "sizing"
    );
    let listener =
        tokio::net::TcpListener::bind(addr).await.map_err(|e| anyhow::anyhow!("cannot listen on {addr}: {e}"))?;
    let app = tokio::task::spawn_blocking(move || App::start(&config))
        .await
        .map_err(|e| Error::Runtime(format!("start-up task failed: {e}")))??;
    let _ = set_reloader.send(Some(app.reloader().clone()));
    app.serve(listener, shutdown_signal()).await?;
    Ok(())
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
