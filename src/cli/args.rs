//! The command line's flags. Every default is the library's own constant, written once there;
//! every flag of `serve` has an environment variable (`POSEFUSE_*`).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use posefuse::eval::HeadingNoise;
use posefuse::frame::RequestedMode;
use posefuse::loadbench::{BenchOptions, LoadOptions};
use posefuse::pipeline::PointFrame;
use posefuse::runtime::{Device, Precision, RuntimeConfig};
use posefuse::server::conn::ConnLimits;
use posefuse::server::ServerConfig;
use posefuse::service::admission::{Line, Sizing};
use posefuse::service::heading_stage::{Refine, AGREE_DEG, SETTLE_DEG};
use posefuse::service::limits::FrameLimits;
use posefuse::sim::realism::Effect;
use posefuse::sim::street::Profile;
use posefuse::sim::SimulateOptions;

const RT: RuntimeConfig = RuntimeConfig::DEFAULT;
const CONN: ConnLimits = ConnLimits::DEFAULT;

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
    /// Where the networks run: cpu, cuda (GPU 0) or cuda:N. CUDA needs ONNX Runtime's GPU build
    /// (`bash scripts/setup.sh --gpu`); without it the server refuses to start.
    #[arg(long, env = "POSEFUSE_DEVICE", default_value = "cpu")]
    pub device: Device,
    /// The camera network's precision: fp32, or int8 where the bundle has an INT8 variant
    /// (docs/BUNDLE.md, "Precision"; default: the bundle manifest's `precision`, else fp32). A
    /// `--heading-model` bundle keeps its own manifest's.
    #[arg(long, env = "POSEFUSE_PRECISION")]
    pub precision: Option<Precision>,
    /// Inference worker threads; each owns its own ONNX Runtime sessions (0: one per 4 cores, at least two on two cores or more).
    #[arg(long, env = "POSEFUSE_WORKERS", default_value_t = 0)]
    pub workers: usize,
    /// ONNX Runtime intra-op threads per session (0: the worker's share of the cores, at most 4).
    #[arg(long, env = "POSEFUSE_INTRA_THREADS", default_value_t = 0)]
    pub intra_threads: usize,
    /// Largest inference batch a worker forms from queued jobs.
    #[arg(long, env = "POSEFUSE_MAX_BATCH", default_value_t = RT.max_batch)]
    pub max_batch: usize,
    /// Microseconds a worker waits for more jobs to fill a batch (0: batch only what is queued;
    /// default: 0 with one worker, 200 with several).
    #[arg(long, env = "POSEFUSE_BATCH_WAIT_US")]
    pub batch_wait_us: Option<u64>,
    /// Inference jobs (one per person and network) that may wait; beyond, requests get 429.
    #[arg(long, env = "POSEFUSE_QUEUE_SIZE", default_value_t = RT.queue_size)]
    pub queue_size: usize,
    /// A bundle that needs no box heading (e.g. models/view), asked first: where a box's heading
    /// disagrees with the facing it predicts, the facing replaces it (docs/BUNDLE.md, "Heading
    /// stage").
    #[arg(long, env = "POSEFUSE_HEADING_MODEL")]
    pub heading_model: Option<PathBuf>,
    /// With --heading-model: a box heading within this many degrees of the predicted facing is
    /// kept (larger: trust the detector's headings more).
    #[arg(long, env = "POSEFUSE_HEADING_AGREE_DEG", default_value_t = AGREE_DEG)]
    pub heading_agree_deg: f64,
    /// Passes that ask a box-frame bundle's point network again with the box turned to the facing
    /// it predicted (docs/BUNDLE.md, "Heading refinement"; 0: off).
    #[arg(long, env = "POSEFUSE_HEADING_REFINE", default_value_t = 0)]
    pub heading_refine: usize,
    /// With --heading-refine: a predicted facing within this many degrees of the heading asked
    /// at ends the refinement.
    #[arg(long, env = "POSEFUSE_HEADING_SETTLE_DEG", default_value_t = SETTLE_DEG)]
    pub heading_settle_deg: f64,
}

impl RuntimeArgs {
    /// The heading refinement these flags describe.
    pub fn refine(&self) -> Refine {
        Refine { passes: self.heading_refine, settle_deg: self.heading_settle_deg }
    }

    /// The heading stage and refinement flags again, for a server this process starts.
    pub fn heading_flags(&self) -> Vec<String> {
        let mut flags = Vec::new();
        if let Some(dir) = &self.heading_model {
            flags.extend(["--heading-model".to_string(), dir.display().to_string()]);
        }
        flags.extend([
            format!("--heading-agree-deg={}", self.heading_agree_deg),
            format!("--heading-refine={}", self.heading_refine),
            format!("--heading-settle-deg={}", self.heading_settle_deg),
        ]);
        flags
    }

    /// The runtime configuration these flags describe (unset sizes from the machine's cores).
    pub fn runtime_config(&self) -> RuntimeConfig {
        let sizing = Sizing::detect();
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
            device: self.device,
            precision: self.precision,
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
    /// An OpenTelemetry collector's OTLP/HTTP address (e.g. http://localhost:4318): each
    /// request's spans (admission, pre-processing, queue, inference, response) are exported to
    /// its /v1/traces in protobuf (docs/OPERATIONS.md, "Following a request").
    #[arg(long, env = "POSEFUSE_OTLP_ENDPOINT")]
    pub otlp_endpoint: Option<String>,
    /// Seconds the drain may take after SIGTERM (once the listener closes); then the process
    /// exits anyway, logging what was cut.
    #[arg(long, env = "POSEFUSE_DRAIN_TIMEOUT", default_value_t = ServerConfig::DRAIN_TIMEOUT_S)]
    pub drain_timeout: u64,
    /// Milliseconds the listener keeps accepting after SIGTERM while readiness already says 503
    /// (time for a load balancer to notice).
    #[arg(long, env = "POSEFUSE_DRAIN_DELAY_MS", default_value_t = 0)]
    pub drain_delay_ms: u64,
    /// Milliseconds a client has to send a request's headers (HTTP/1).
    #[arg(long, env = "POSEFUSE_HEADER_TIMEOUT_MS", default_value_t = CONN.header_read_timeout.as_millis() as u64)]
    pub header_timeout_ms: u64,
    /// Longest pause, in milliseconds, between two chunks of a request body.
    #[arg(long, env = "POSEFUSE_BODY_TIMEOUT_MS", default_value_t = CONN.body_read_timeout.as_millis() as u64)]
    pub body_timeout_ms: u64,
    /// Milliseconds without a byte in either direction after which a connection is closed.
    #[arg(long, env = "POSEFUSE_IDLE_TIMEOUT_MS", default_value_t = CONN.idle_timeout.as_millis() as u64)]
    pub idle_timeout_ms: u64,
    /// Open connections at most (0: the file-descriptor limit less a reserve). At the cap the
    /// connection idle the longest is closed; when none is idle, new ones are closed at once.
    #[arg(long, env = "POSEFUSE_MAX_CONNECTIONS", default_value_t = CONN.max_connections)]
    pub max_connections: usize,
    /// Frames decoded and pre-processed at once (0: one per core).
    #[arg(long, env = "POSEFUSE_DECODE_PERMITS", default_value_t = 0)]
    pub decode_permits: usize,
    /// Requests that may wait for a decode permit; beyond, 429 at once (0: 8 per permit).
    #[arg(long, env = "POSEFUSE_ADMISSION_QUEUE", default_value_t = 0)]
    pub admission_queue: usize,
    /// Milliseconds a frame that finds the server full may wait for a place, before its body is
    /// read, in order of arrival; 429 when the wait is over (0: no line, 429 at once). Makes
    /// admission fair to clients that wait `Retry-After` (docs/OPERATIONS.md, "Admission and
    /// overload").
    #[arg(long, env = "POSEFUSE_ADMISSION_WAIT_MS", default_value_t = Line::DEFAULT.wait.as_millis() as u64)]
    pub admission_wait_ms: u64,
    /// Frames that may wait at once for a place in the line; beyond, 429 at once.
    #[arg(long, env = "POSEFUSE_ADMISSION_WAITERS", default_value_t = Line::DEFAULT.max)]
    pub admission_waiters: usize,
    /// Persons per frame at most (422 beyond).
    #[arg(long, env = "POSEFUSE_MAX_PERSONS", default_value_t = FrameLimits::DEFAULT.max_persons)]
    pub max_persons: usize,
    /// LiDAR points per frame at most (422 beyond).
    #[arg(long, env = "POSEFUSE_MAX_POINTS", default_value_t = FrameLimits::DEFAULT.max_points)]
    pub max_points: usize,
    /// Pixels of one camera image at most, as its calibration declares them (422 beyond; the
    /// image must match its declared size). Images are decoded one at a time, so this bounds a
    /// decode's memory: 3 bytes per pixel, more for a 16-bit PNG (docs/DEPLOY.md, "Memory").
    #[arg(
        long,
        env = "POSEFUSE_MAX_IMAGE_PIXELS",
        default_value_t = FrameLimits::DEFAULT.max_image_pixels,
        value_parser = clap::value_parser!(u64).range(1..=posefuse::service::limits::MAX_IMAGE_PIXELS)
    )]
    pub max_image_pixels: u64,
    /// Serve administration (`POST /v1/models:reload`) without a token on this address, meant
    /// for loopback (e.g. 127.0.0.1:9090); off by default: the serving port refuses it (403).
    #[arg(long, env = "POSEFUSE_ADMIN_ADDR")]
    pub admin_addr: Option<SocketAddr>,
    /// A file whose first line is a token (at least 16 characters) that admits administration on
    /// the serving port as `Authorization: Bearer <token>` (else POSEFUSE_ADMIN_TOKEN).
    #[arg(long)]
    pub admin_token_file: Option<PathBuf>,
    /// The directory a reload may name bundles in (`{"model_dir": "v2"}` is DIR/v2); without it
    /// a reload only reloads the serving bundle.
    #[arg(long, env = "POSEFUSE_MODEL_REPOSITORY")]
    pub model_repository: Option<PathBuf>,
    /// The model name of the Open Inference Protocol (`/v2/models/NAME`), e.g. the
    /// InferenceService's; default: the bundle manifest's name.
    #[arg(long, env = "POSEFUSE_MODEL_NAME")]
    pub model_name: Option<String>,
    /// Offers KServe's system shared-memory extension: clients on this host may register POSIX
    /// shared-memory objects (/dev/shm) and pass tensors through them (docs/KSERVE.md). Off by
    /// default: a registration makes the server read and write an object the client names.
    #[arg(long, env = "POSEFUSE_SYSTEM_SHARED_MEMORY")]
    pub system_shared_memory: bool,
    /// Shared-memory regions registered at once.
    #[arg(long, env = "POSEFUSE_SHARED_MEMORY_REGIONS", default_value_t = posefuse::server::kserve::shared_memory::MAX_REGIONS)]
    pub shared_memory_regions: usize,
}

impl ServeArgs {
    /// The server configuration these flags describe (0 for decode permits and the admission
    /// queue: sized from the cores at start-up); reads the admin token file.
    pub fn server_config(&self) -> posefuse::Result<ServerConfig> {
        let token = posefuse::server::admin::read_token(
            self.admin_token_file.as_deref(),
            std::env::var(posefuse::server::admin::TOKEN_ENV).ok(),
        )?;
        Ok(ServerConfig {
            model_dir: self.runtime.model_dir.clone(),
            runtime: self.runtime.runtime_config(),
            body_limit: self.body_limit,
            request_timeout: Duration::from_millis(self.request_timeout_ms),
            batch_concurrency: self.batch_concurrency,
            drain_timeout: Duration::from_secs(self.drain_timeout),
            drain_delay: Duration::from_millis(self.drain_delay_ms),
            conn: ConnLimits {
                header_read_timeout: Duration::from_millis(self.header_timeout_ms),
                body_read_timeout: Duration::from_millis(self.body_timeout_ms),
                idle_timeout: Duration::from_millis(self.idle_timeout_ms),
                max_connections: self.max_connections,
            },
            decode_permits: self.decode_permits,
            admission_queue: self.admission_queue,
            admission_line: Line { wait: Duration::from_millis(self.admission_wait_ms), max: self.admission_waiters },
            frame_limits: FrameLimits {
                max_persons: self.max_persons,
                max_points: self.max_points,
                max_image_pixels: self.max_image_pixels,
            },
            heading_model_dir: self.runtime.heading_model.clone(),
            heading_agree_deg: self.runtime.heading_agree_deg,
            refine: self.runtime.refine(),
            admin: posefuse::server::admin::AdminConfig {
                addr: self.admin_addr,
                token,
                repository: self.model_repository.clone(),
            },
            v2_model_name: self.model_name.clone(),
            shared_memory: posefuse::server::kserve::shared_memory::SharedMemoryConfig {
                enabled: self.system_shared_memory,
                max_regions: self.shared_memory_regions,
                ..Default::default()
            },
        })
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
    /// The point networks' frame the samples are prepared in (docs/BUNDLE.md, "Point frame").
    #[arg(long, value_enum, default_value_t = PointFrame::BoxHeading)]
    pub frame: PointFrame,
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
    /// `street-hard` (the default bundle's training data: loose clothing, things in hand,
    /// mixed-pixel LiDAR returns at silhouette edges, arms against the torso, dark-surface
    /// dropouts, 3D label noise), `street` (the first two causes only) or `clean` (tight clothing,
    /// empty hands, clean returns: for regression against the earliest results).
    #[arg(long, value_enum, default_value_t = Profile::StreetHard)]
    pub profile: Profile,
    /// Realism effects to add to the profile's, comma-separated (docs/DATA.md, "Realism against
    /// Waymo's anchors"), to measure one cause at a time.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub effects: Vec<Effect>,
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
            frame: a.frame,
            preview: a.preview,
            requests: a.requests,
            points_cap: a.points_cap,
            profile: a.profile,
            effects: a.effects,
            jobs: a.jobs,
        }
    }
}

/// Arguments of `posefuse bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    #[command(flatten)]
    pub load: LoadOptions,
    /// The bundle and thread settings: of the server this starts, and of the raw ceiling.
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

impl From<BenchArgs> for BenchOptions {
    fn from(a: BenchArgs) -> BenchOptions {
        BenchOptions {
            load: a.load,
            runtime: a.runtime.runtime_config(),
            serve_args: a.runtime.heading_flags(),
            model_dir: a.runtime.model_dir,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Runtime {
        #[command(flatten)]
        runtime: RuntimeArgs,
    }

    #[test]
    fn heading_flags_say_again_what_was_set() {
        let given = ["x", "--heading-model", "models/view", "--heading-agree-deg", "45", "--heading-refine", "3"];
        let a = Runtime::try_parse_from(given).unwrap().runtime;
        let again = Runtime::try_parse_from(std::iter::once("x".to_string()).chain(a.heading_flags())).unwrap();
        let b = again.runtime;
        assert_eq!(b.heading_model, Some(PathBuf::from("models/view")));
        assert_eq!((b.heading_agree_deg, b.heading_refine, b.heading_settle_deg), (45.0, 3, SETTLE_DEG));
        let plain = Runtime::try_parse_from(["x"]).unwrap().runtime.heading_flags();
        assert!(!plain.iter().any(|f| f == "--heading-model"), "{plain:?}");
        assert!(plain.contains(&"--heading-refine=0".to_string()), "{plain:?}");
    }

    #[test]
    fn both_simulators_render_the_default_bundles_profile_unless_told_otherwise() {
        #[derive(Parser)]
        struct Sim {
            #[command(flatten)]
            sim: SimulateArgs,
        }
        #[derive(Parser)]
        struct WaymoSim {
            #[command(flatten)]
            sim: super::super::waymo::WaymoSimulateArgs,
        }
        let profile = |more: &[&str]| Sim::try_parse_from(["x", "--out", "d"].iter().chain(more)).unwrap().sim.profile;
        assert_eq!(profile(&[]), Profile::StreetHard);
        assert_eq!(profile(&["--profile", "clean"]), Profile::Clean);
        let waymo =
            |more: &[&str]| WaymoSim::try_parse_from(["x", "--out", "d"].iter().chain(more)).unwrap().sim.profile;
        assert_eq!(waymo(&[]), Profile::StreetHard);
        assert_eq!(waymo(&["--profile", "street"]), Profile::Street);
    }

    #[test]
    fn the_device_flag_reaches_the_runtime() {
        let cfg = |args: &[&str]| Runtime::try_parse_from(args).map(|a| a.runtime.runtime_config().device);
        assert_eq!(cfg(&["x"]).unwrap(), Device::Cpu);
        assert_eq!(cfg(&["x", "--device", "cuda:1"]).unwrap(), Device::Cuda(1));
        assert!(cfg(&["x", "--device", "gpu"]).is_err());
    }

    #[test]
    fn the_precision_flag_reaches_the_runtime() {
        let cfg = |args: &[&str]| Runtime::try_parse_from(args).map(|a| a.runtime.runtime_config().precision);
        assert_eq!(cfg(&["x"]).unwrap(), None, "unset: the bundle's own");
        assert_eq!(cfg(&["x", "--precision", "int8"]).unwrap(), Some(Precision::Int8));
        assert_eq!(cfg(&["x", "--precision", "fp32"]).unwrap(), Some(Precision::Fp32));
        assert!(cfg(&["x", "--precision", "fp16"]).is_err());
    }

    #[derive(Parser)]
    struct Serve {
        #[command(flatten)]
        serve: ServeArgs,
    }

    #[test]
    fn the_frame_limit_flags_reach_the_server() {
        let limits =
            |args: &[&str]| Serve::try_parse_from(args).map(|a| a.serve.server_config().map(|c| c.frame_limits));
        assert_eq!(limits(&["x"]).unwrap().unwrap(), FrameLimits::DEFAULT);
        let given = ["x", "--max-persons", "3", "--max-points", "500", "--max-image-pixels", "2457600"];
        let set = FrameLimits { max_persons: 3, max_points: 500, max_image_pixels: 2_457_600 };
        assert_eq!(limits(&given).unwrap().unwrap(), set);
        // no image at all, or more than the server can ever take, is refused at start
        assert!(limits(&["x", "--max-image-pixels", "0"]).is_err());
        let over = (posefuse::service::limits::MAX_IMAGE_PIXELS + 1).to_string();
        assert!(limits(&["x", "--max-image-pixels", &over]).is_err());
    }

    #[test]
    fn the_admission_line_flags_reach_the_server() {
        let line =
            |args: &[&str]| Serve::try_parse_from(args).map(|a| a.serve.server_config().map(|c| c.admission_line));
        let default = line(&["x"]).unwrap().unwrap();
        assert_eq!(default, Line { wait: Duration::from_secs(2), max: 256 }, "on by default");
        assert_eq!(default, ServerConfig::new("m").admission_line, "one default");
        let set = line(&["x", "--admission-wait-ms", "500", "--admission-waiters", "64"]).unwrap().unwrap();
        assert_eq!(set, Line { wait: Duration::from_millis(500), max: 64 });
        let off = line(&["x", "--admission-wait-ms", "0"]).unwrap().unwrap();
        assert_eq!(off.wait, Duration::ZERO);
    }

    #[derive(Parser)]
    struct Bench {
        #[command(flatten)]
        bench: BenchArgs,
    }

    #[test]
    fn bench_flags_reach_the_bench_options() {
        use posefuse::loadbench::{ImageForm, Protocol};
        let given = ["x", "--data", "d", "--concurrency", "1,16", "--image", "jpeg420,rgb", "--protocol", "grpc"];
        let given = given.into_iter().chain(["--frames", "7", "--no-raw", "--heading-model", "models/view"]);
        let o = BenchOptions::from(Bench::try_parse_from(given).unwrap().bench);
        assert_eq!((o.load.data, o.load.concurrency, o.load.frames), (PathBuf::from("d"), vec![1, 16], 7));
        assert_eq!((o.load.image, o.load.protocol), (vec![ImageForm::Jpeg420, ImageForm::Rgb], Protocol::Grpc));
        assert!(o.load.no_raw && o.load.url.is_none());
        assert_eq!((o.load.duration, o.load.timeout), (10.0, 30.0));
        assert!(o.serve_args.iter().any(|f| f == "--heading-model"), "{:?}", o.serve_args);
        let plain = BenchOptions::from(Bench::try_parse_from(["x", "--data", "d"]).unwrap().bench);
        assert_eq!((plain.load.concurrency, plain.load.image), (vec![1, 4, 16, 64], vec![ImageForm::AsIs]));
        assert!(!plain.load.no_raw);
    }
}
