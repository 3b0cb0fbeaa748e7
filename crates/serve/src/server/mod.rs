//! The transports and the server's lifecycle: HTTP (axum) and gRPC (tonic) on one port, the
//! error mapping, health, Prometheus metrics, connections, start-up, readiness, reload and the
//! drain. Every request is answered by [`crate::service::Predictor`]; nothing here decides
//! anything about a pose.

pub mod admin;
pub mod conn;
pub mod early_admission;
pub mod errors;
pub mod grpc;
pub mod health;
pub mod http;
pub mod kserve;
pub mod lifecycle;
pub mod memory;
pub mod metrics;
pub mod peer;
pub mod reload;
pub mod request_context;
pub mod viewer;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::Request;
use tokio_util::sync::CancellationToken;
use tower::ServiceExt;

use crate::runtime::{Runtime, RuntimeConfig};
use crate::service::admission::{self, Admission};
use crate::service::limits::FrameLimits;
use crate::service::Predictor;
use posefuse_core::error::{Error, Result};

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
    /// The waiting line before admission (off: a frame that finds the server full gets 429 at once).
    pub admission_line: admission::Line,
    /// Persons and points per frame.
    pub frame_limits: FrameLimits,
    /// A bundle that needs no heading, asked first for each person's facing (docs/BUNDLE.md,
    /// "Heading stage").
    pub heading_model_dir: Option<PathBuf>,
    /// Degrees within which a box heading agreeing with the heading stage's facing is kept.
    pub heading_agree_deg: f64,
    /// Passes asking the point network again at the facing it predicted (docs/BUNDLE.md,
    /// "Heading refinement").
    pub refine: crate::service::heading_stage::Refine,
    /// Who may reload models, where, and from which repository (`server::admin`).
    pub admin: admin::AdminConfig,
    /// The Open Inference Protocol's model name (`--model-name`); the manifest's when `None`.
    pub v2_model_name: Option<String>,
    /// KServe's system shared-memory extension (`--system-shared-memory`): off by default.
    pub shared_memory: kserve::shared_memory::SharedMemoryConfig,
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
    /// Default drain deadline, seconds.
    pub const DRAIN_TIMEOUT_S: u64 = 30;

    /// Defaults for a bundle directory (those of `posefuse serve`, with the machine-dependent
    /// sizes fixed: 2 decode permits, 64 waiting).
    pub fn new(model_dir: impl Into<PathBuf>) -> ServerConfig {
        ServerConfig {
            model_dir: model_dir.into(),
            runtime: RuntimeConfig::DEFAULT,
            body_limit: Self::BODY_LIMIT,
            request_timeout: Duration::from_millis(Self::REQUEST_TIMEOUT_MS),
            batch_concurrency: Self::BATCH_CONCURRENCY,
            drain_timeout: Duration::from_secs(Self::DRAIN_TIMEOUT_S),
            drain_delay: Duration::ZERO,
            conn: conn::ConnLimits::default(),
            decode_permits: 2,
            admission_queue: 64,
            admission_line: admission::Line::DEFAULT,
            frame_limits: FrameLimits::default(),
            heading_model_dir: None,
            heading_agree_deg: crate::service::heading_stage::AGREE_DEG,
            refine: crate::service::heading_stage::Refine::OFF,
            admin: admin::AdminConfig::default(),
            v2_model_name: None,
            shared_memory: kserve::shared_memory::SharedMemoryConfig::default(),
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
    /// Who may ask it to (`server::admin`).
    pub admin: Arc<admin::AdminConfig>,
    /// The Open Inference Protocol's model name when not the manifest's (`--model-name`).
    pub v2_model_name: Option<Arc<str>>,
    /// The registered shared-memory regions (KServe's extension).
    pub shared_memory: Arc<kserve::shared_memory::SystemSharedMemory>,
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

impl App {
    /// Validates the bundle, builds the sessions and starts warming up (blocking).
    pub fn start(config: &ServerConfig) -> Result<App> {
        let runtime = Runtime::load(&config.model_dir, &config.runtime)?;
        let admission = Admission::with_line(config.decode_permits, config.admission_queue, config.admission_line);
        let mut predictor =
            Predictor::with_admission(runtime, admission).with_limits(config.frame_limits).with_refine(config.refine);
        if let Some(dir) = &config.heading_model_dir {
            predictor = predictor
                .with_heading_stage(Runtime::load(dir, &config.runtime.for_heading_stage())?, config.heading_agree_deg);
        }
        let reloader = reload::Reloader::new(predictor.clone(), config.model_dir.clone(), config.runtime.clone());
        let state = AppState {
            predictor,
            body_limit: config.body_limit,
            request_timeout: config.request_timeout,
            batch_concurrency: config.batch_concurrency.max(1),
            shutting_down: Arc::new(AtomicBool::new(false)),
            drain: CancellationToken::new(),
            reloader: Arc::new(reloader),
            admin: Arc::new(config.admin.clone()),
            v2_model_name: config.v2_model_name.as_deref().map(Arc::from),
            shared_memory: Arc::new(kserve::shared_memory::SystemSharedMemory::new(config.shared_memory.clone())),
            ready: Arc::new(AtomicBool::new(false)),
            prometheus: metrics::install(),
        };
        let manifest = &state.predictor.bundle().manifest;
        metrics::build_info(&manifest.name, &manifest.version, true);
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

    /// Serves the admin routes (model reload, no token) on `listener` until the drain starts:
    /// the `--admin-addr` listener, bounded like the serving port's but to a few connections.
    pub fn serve_admin(&self, listener: tokio::net::TcpListener) -> tokio::task::JoinHandle<()> {
        let (router, drain) = (http::admin_router(self.state.clone()), self.state.drain.clone());
        let limits = conn::ConnLimits { max_connections: ADMIN_CONNECTIONS, ..self.conn.clone() };
        let timeout = self.drain_timeout;
        tracing::info!(addr = ?listener.local_addr().ok(), "serving administration (model reload)");
        tokio::spawn(async move {
            conn::serve(listener, router, limits, Arc::new(conn::Registry::default()), drain, timeout).await;
        })
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
        let body_limit = state.body_limit;
        let app = axum::Router::new()
            .fallback_service(tower::service_fn(move |req: Request| {
                let (h, g) = (http_router.clone(), grpc_router.clone());
                let grpc = is_grpc(&req);
                let admission = admission.clone();
                async move {
                    let req = match early_admission::admit(&admission, req, grpc, body_limit).await {
                        Ok(req) => req,
                        Err(refusal) => return Ok(*refusal),
                    };
                    if grpc {
                        if let Some(status) = kserve::grpc::unimplemented(req.uri().path()) {
                            return Ok(status.into_http());
                        }
                        g.oneshot(req).await
                    } else {
                        h.oneshot(req).await
                    }
                }
            }))
            .layer(axum::middleware::from_fn(request_context::trace_request))
            .layer(axum::middleware::from_fn_with_state(in_flight.clone(), lifecycle::count_in_flight));
        let ready_watch = {
            let (runtime, reporter, ready) = (state.predictor.runtime().clone(), reporter.clone(), state.ready.clone());
            let stage = state.predictor.heading_stage().cloned();
            tokio::spawn(async move {
                while !runtime.is_ready() || stage.as_ref().is_some_and(|s| !s.is_ready()) {
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
        let trim = memory::trim_when_quiet(state.predictor.admission().clone());
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
        trim.abort();
        let runtime = state.predictor.runtime().clone();
        drop(state);
        drop(self);
        // Joining the workers blocks; keep it off the executor.
        let _ = tokio::task::spawn_blocking(move || drop(runtime)).await;
        Ok(())
    }
}

/// Connections the admin listener keeps open at once (operators, not traffic).
const ADMIN_CONNECTIONS: usize = 8;

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

/// `posefuse serve` after parsing: SIGHUP reloads (handled before loading, so that an early one
/// does not kill the process), SIGTERM/Ctrl-C drains; a completed drain exits 0.
pub async fn serve_with_signals(mut config: ServerConfig, addr: SocketAddr) -> Result<()> {
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
        admission_wait_ms = config.admission_line.wait.as_millis() as u64,
        admission_waiters = config.admission_line.max,
        device = %config.runtime.device,
        jpeg_simd = posefuse_core::image_decode::jpeg_simd(),
        "sizing"
    );
    let listener =
        tokio::net::TcpListener::bind(addr).await.map_err(|e| Error::Io(format!("cannot listen on {addr}: {e}")))?;
    let admin_listener = match config.admin.addr {
        Some(a) => {
            if !a.ip().is_loopback() {
                tracing::warn!(addr = %a, "the admin address is not loopback: anyone who reaches it can reload models");
            }
            let l =
                tokio::net::TcpListener::bind(a).await.map_err(|e| Error::Io(format!("cannot listen on {a}: {e}")))?;
            Some(l)
        }
        None => None,
    };
    let app = tokio::task::spawn_blocking(move || App::start(&config))
        .await
        .map_err(|e| Error::Runtime(format!("start-up task failed: {e}")))??;
    let _ = set_reloader.send(Some(app.reloader().clone()));
    let admin = admin_listener.map(|l| app.serve_admin(l));
    app.serve(listener, shutdown_signal()).await?;
    if let Some(a) = admin {
        let _ = a.await;
    }
    Ok(())
}
