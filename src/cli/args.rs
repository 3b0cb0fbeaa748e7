//! The command line's flags. Every default is the library's own constant, written once there;
//! every flag of `serve` has an environment variable (`POSEFUSE_*`).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use posefuse::eval::HeadingNoise;
use posefuse::frame::RequestedMode;
use posefuse::runtime::RuntimeConfig;
use posefuse::server::ServerConfig;
use posefuse::sim::street::Profile;
use posefuse::sim::SimulateOptions;

const RT: RuntimeConfig = RuntimeConfig::DEFAULT;

/// Model bundle and ONNX Runtime settings, shared by `serve`, `predict` and `eval`.
#[derive(Debug, Clone, clap::Args)]
pub struct RuntimeArgs {
    /// Model bundle directory (manifest.json + ONNX files).
    #[arg(long, env = "POSEFUSE_MODEL_DIR", default_value = ServerConfig::MODEL_DIR)]
    pub model_dir: PathBuf,
    /// ONNX Runtime shared library (default: $ORT_DYLIB_PATH, else .ort/lib/libonnxruntime.so,
    /// installed by scripts/setup.sh).
    #[arg(long)]
    pub ort_lib: Option<PathBuf>,
    /// Inference worker threads; each owns its own ONNX Runtime sessions.
    #[arg(long, env = "POSEFUSE_WORKERS", default_value_t = RT.workers)]
    pub workers: usize,
    /// ONNX Runtime intra-op threads per session.
    #[arg(long, env = "POSEFUSE_INTRA_THREADS", default_value_t = RT.intra_threads)]
    pub intra_threads: usize,
    /// Largest inference batch a worker forms from queued jobs.
    #[arg(long, env = "POSEFUSE_MAX_BATCH", default_value_t = RT.max_batch)]
    pub max_batch: usize,
    /// Microseconds a worker waits for more jobs to fill a batch (0: batch only what is queued).
    #[arg(long, env = "POSEFUSE_BATCH_WAIT_US", default_value_t = RT.batch_wait.as_micros() as u64)]
    pub batch_wait_us: u64,
    /// Inference jobs (one per person and network) that may wait; beyond, requests get 429.
    #[arg(long, env = "POSEFUSE_QUEUE_SIZE", default_value_t = RT.queue_size)]
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
    #[arg(long, env = "POSEFUSE_BODY_LIMIT", default_value_t = ServerConfig::BODY_LIMIT)]
    pub body_limit: usize,
    /// Per-frame deadline in milliseconds (504 / DEADLINE_EXCEEDED when passed).
    #[arg(long, env = "POSEFUSE_REQUEST_TIMEOUT_MS", default_value_t = ServerConfig::REQUEST_TIMEOUT_MS)]
    pub request_timeout_ms: u64,
    /// Frames of one batch or stream predicted concurrently.
    #[arg(long, env = "POSEFUSE_BATCH_CONCURRENCY", default_value_t = ServerConfig::BATCH_CONCURRENCY)]
    pub batch_concurrency: usize,
    /// Log as JSON lines instead of text.
    #[arg(long, env = "POSEFUSE_LOG_JSON")]
    pub log_json: bool,
}

impl ServeArgs {
    /// The server configuration these flags describe.
    pub fn server_config(&self) -> ServerConfig {
        ServerConfig {
            model_dir: self.runtime.model_dir.clone(),
            runtime: self.runtime.runtime_config(),
            body_limit: self.body_limit,
            request_timeout: Duration::from_millis(self.request_timeout_ms),
            batch_concurrency: self.batch_concurrency,
        }
    }
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
    pub mode: Option<RequestedMode>,
    /// Frames predicted concurrently (results do not depend on it).
    #[arg(long, default_value_t = ServerConfig::BATCH_CONCURRENCY)]
    pub concurrency: usize,
    /// Turn every request box's heading by this many degrees (random sign per person), or by a
    /// uniformly random angle with `uniform`: how much a bundle relies on the detector's heading.
    #[arg(long)]
    pub heading_noise: Option<HeadingNoise>,
    /// Seed of the heading errors.
    #[arg(long, default_value_t = 0)]
    pub noise_seed: u64,
    /// Print a machine-readable JSON report instead of tables.
    #[arg(long, env = "POSEFUSE_EVAL_JSON")]
    pub json: bool,
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

/// Arguments of `posefuse health`.
#[derive(Debug, clap::Args)]
pub struct HealthArgs {
    /// The server's address; a wildcard (0.0.0.0, [::]) means this host, so `serve`'s
    /// POSEFUSE_ADDR works unchanged.
    #[arg(long, env = "POSEFUSE_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Seconds to wait for the answer.
    #[arg(long, default_value_t = 3)]
    pub timeout_s: u64,
}

/// Arguments of `posefuse simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Number of pedestrians (prepared samples) to generate.
    #[arg(long, default_value_t = 100)]
    pub count: usize,
    /// Random seed; the same seed and arguments give byte-identical output.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Side S of the camera crops.
    #[arg(long, default_value_t = 256)]
    pub image_size: u32,
    /// Write PNG contact sheets to OUT/preview.
    #[arg(long)]
    pub preview: bool,
    /// Frames (from the first) that also get a request fixture in OUT/requests. Default: every
    /// frame when --count is at most 1000, otherwise the first 200.
    #[arg(long)]
    pub requests: Option<usize>,
    /// Most in-box points kept per sample in `points_xyz`/`points_uv` (P in docs/DATA.md).
    #[arg(long, default_value_t = 1024)]
    pub points_cap: usize,
    /// `clean` (tight clothing, empty hands, clean returns) or `street` (loose clothing, things in
    /// hand, mixed-pixel LiDAR returns at silhouette edges).
    #[arg(long, value_enum, default_value_t = Profile::Clean)]
    pub profile: Profile,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub jobs: Option<usize>,
}

impl From<SimulateArgs> for SimulateOptions {
    fn from(a: SimulateArgs) -> SimulateOptions {
        SimulateOptions {
            count: a.count,
            seed: a.seed,
            out: a.out,
            image_size: a.image_size,
            preview: a.preview,
            requests: a.requests,
            points_cap: a.points_cap,
            profile: a.profile,
            jobs: a.jobs,
        }
    }
}
