//! `posefuse bench`: load a server with simulator request fixtures at several concurrencies and
//! set the numbers beside the raw ONNX Runtime ceiling on the same persons.
//!
//! Per concurrency step: frames/s and persons/s answered, p50 and p99 of the answered requests,
//! the count of every status, and the server's peak resident memory (VmRSS of `/proc/PID/status`
//! sampled every 10 ms; VmHWM, the lifetime peak, at the end). The raw ceiling runs the camera and
//! point-fusion sessions of the same bundle directly, on the model inputs of the same persons:
//! per frame (its persons in one batch, one thread) and for throughput (batches of `max_batch`
//! on `workers` threads, each session with `intra_threads`), i.e. the server's thread settings.

mod shared_memory;

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use base64::Engine;
use posefuse_data::error::Context;
use posefuse_data::{bail, invalid};

use posefuse_core::frame::{Frame, RgbPixels};
use posefuse_core::pipeline::fusion_input;
use posefuse_serve::runtime::RuntimeConfig;
use posefuse_serve::runtime::{env, Bundle, ModelKind, Models};
use posefuse_serve::server::grpc::proto;
use posefuse_serve::service::api::Mode;
use posefuse_serve::service::planned_inputs;

/// How the bench sends each frame's camera image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum ImageForm {
    /// The fixture's JPEG as written by the simulator.
    AsIs,
    /// Re-encoded as JPEG, quality 92, chroma subsampled 4:2:0 (what most cameras write).
    Jpeg420,
    /// Re-encoded as JPEG, quality 92, no chroma subsampling (4:4:4).
    Jpeg444,
    /// Decoded RGB8 pixels (`image_rgb`).
    Rgb,
    /// Decoded RGB8 pixels and the LiDAR points in POSIX shared memory, written once per fixture
    /// and named by an Open Inference Protocol request (`POST /v2/models/NAME/infer`; HTTP only).
    RgbShm,
}

/// Transport of the requests.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Protocol {
    /// `POST /v1/poses` with a JSON body.
    Http,
    /// gRPC `Predict` (image and pixels as bytes).
    Grpc,
}

/// The load `posefuse bench` puts on a server: its command line's flags, declared once here and
/// flattened into the binary's `bench` command.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct LoadOptions {
    /// Server to load (HTTP base URL; gRPC on the same port). Absent: start `posefuse serve` on a
    /// free local port with the runtime flags below, and measure it.
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_URL"))]
    pub url: Option<String>,
    /// Process id of the server behind --url, for its memory.
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_SERVER_PID"))]
    pub server_pid: Option<u32>,
    /// Simulator output directory: its `requests/*.json` fixtures are sent.
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_DATA"))]
    pub data: PathBuf,
    /// Concurrent clients, one step each (comma-separated).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "POSEFUSE_BENCH_CONCURRENCY", value_delimiter = ',', default_value = "1,4,16,64")
    )]
    pub concurrency: Vec<usize>,
    /// Seconds of load per step.
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_DURATION", default_value_t = 10.0))]
    pub duration: f64,
    /// Image forms to send, one table block each (comma-separated).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "POSEFUSE_BENCH_IMAGE", value_enum, value_delimiter = ',', default_value = "as-is")
    )]
    pub image: Vec<ImageForm>,
    /// Transport.
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_PROTOCOL", value_enum, default_value = "http"))]
    pub protocol: Protocol,
    /// Fixtures used (the first N frames, in file-name order).
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_FRAMES", default_value_t = 40))]
    pub frames: usize,
    /// Seconds after which a request counts as hung (status `timeout`).
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_TIMEOUT", default_value_t = 30.0))]
    pub timeout: f64,
    /// Skip the raw ONNX Runtime ceiling.
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_NO_RAW"))]
    pub no_raw: bool,
    /// Also write what was measured to this file as JSON (the fixtures, the runtime, the raw
    /// reference and every step), for scripts that keep the numbers of several runs.
    #[cfg_attr(feature = "cli", arg(long, env = "POSEFUSE_BENCH_JSON"))]
    pub json: Option<PathBuf>,
}

/// What `posefuse bench` runs: the load, and the bundle and settings of the server it starts.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    pub load: LoadOptions,
    /// The bundle: of the server this starts, and of the raw ceiling.
    pub model_dir: PathBuf,
    /// Thread settings: of the server this starts, and of the raw ceiling.
    pub runtime: RuntimeConfig,
    /// Further `posefuse serve` flags of the server this starts (its heading stage and
    /// refinement); the raw ceiling runs the bundle alone.
    pub serve_args: Vec<String>,
}

/// One fixture prepared for sending.
struct Prepared {
    /// The HTTP route: `/v1/poses`, or the Open Inference Protocol's infer route.
    http_path: String,
    http_body: Vec<u8>,
    grpc: proto::PredictRequest,
    persons: usize,
}

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

fn fixture_image(frame: &Frame) -> posefuse_data::error::Result<image::RgbImage> {
    let text = frame.image.as_ref().ok_or_else(|| invalid!("a fixture without an image"))?;
    let bytes = base64::engine::general_purpose::STANDARD.decode(text).context("a fixture's image")?;
    Ok(image::load_from_memory(&bytes)?.into_rgb8())
}

fn encode_jpeg(img: &image::RgbImage, sampling: jpeg_encoder::SamplingFactor) -> posefuse_data::error::Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut enc = jpeg_encoder::Encoder::new(&mut out, posefuse_core::sample::JPEG_QUALITY);
    enc.set_sampling_factor(sampling);
    let (w, h) = (
        u16::try_from(img.width()).context("a JPEG's width")?,
        u16::try_from(img.height()).context("a JPEG's height")?,
    );
    enc.encode(img.as_raw(), w, h, jpeg_encoder::ColorType::Rgb).context("encoding a JPEG")?;
    Ok(out)
}

/// The frame as sent in `form`: the JSON frame (with `image` or `image_rgb`) and its gRPC twin.
/// Prepares fixture `index` for `form`; `objects` and `model` serve the shared-memory form.
fn prepare(
    index: usize,
    frame: &Frame,
    form: ImageForm,
    objects: &mut shared_memory::Objects,
    model: &str,
) -> posefuse_data::error::Result<Prepared> {
    let mut f = frame.clone();
    for p in &mut f.persons {
        p.ground_truth = None;
    }
    let file_bytes = |f: &Frame| -> posefuse_data::error::Result<Vec<u8>> {
        base64::engine::general_purpose::STANDARD
            .decode(f.image.as_deref().unwrap_or_default())
            .context("a fixture's image")
    };
    let (image, pixels) = match form {
        ImageForm::AsIs => (file_bytes(&f)?, None),
        ImageForm::Jpeg420 => (encode_jpeg(&fixture_image(&f)?, jpeg_encoder::SamplingFactor::R_4_2_0)?, None),
        ImageForm::Jpeg444 => (encode_jpeg(&fixture_image(&f)?, jpeg_encoder::SamplingFactor::R_4_4_4)?, None),
        ImageForm::Rgb => {
            let img = fixture_image(&f)?;
            (Vec::new(), Some(RgbPixels { width: img.width(), height: img.height(), pixels: img.into_raw() }))
        }
        ImageForm::RgbShm => {
            let img = fixture_image(&f)?;
            let http_body = shared_memory::write_frame(objects, model, index, &f, img.as_raw())?;
            let grpc = posefuse_serve::server::grpc::frame_to_proto(&f, Vec::new())?;
            let http_path = format!("/v2/models/{model}/infer");
            return Ok(Prepared { http_path, http_body, grpc, persons: f.persons.len() });
        }
    };
    f.image = (!image.is_empty()).then(|| b64(&image));
    f.image_rgb = pixels;
    let http_body = serde_json::to_vec(&f)?;
    // the image as file bytes (the pixels travel in `f.image_rgb`)
    let grpc = posefuse_serve::server::grpc::frame_to_proto(&f, image)?;
    Ok(Prepared { http_path: "/v1/poses".into(), http_body, grpc, persons: f.persons.len() })
}

/// Resident memory of a process, from `/proc/PID/status` (kB lines `VmRSS`, `VmHWM`).
fn proc_kb(pid: u32, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Samples VmRSS every 10 ms until stopped; the peak in kB.
struct RssSampler {
    stop: Arc<AtomicBool>,
    peak: Arc<AtomicU64>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl RssSampler {
    fn start(pid: Option<u32>) -> RssSampler {
        let (stop, peak) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
        let thread = pid.map(|pid| {
            let (stop, peak) = (stop.clone(), peak.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    if let Some(kb) = proc_kb(pid, "VmRSS:") {
                        peak.fetch_max(kb, Ordering::Relaxed);
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
            })
        });
        RssSampler { stop, peak, thread }
    }

    fn finish(mut self) -> Option<u64> {
        self.stop.store(true, Ordering::Relaxed);
        let t = self.thread.take()?;
        t.join().ok()?;
        Some(self.peak.load(Ordering::Relaxed))
    }
}

/// What one concurrency step measured.
struct Step {
    clients: usize,
    wall: Duration,
    latencies: Vec<Duration>,
    persons: usize,
    statuses: std::collections::BTreeMap<String, usize>,
    peak_rss_kb: Option<u64>,
    /// Clients with at least one request answered.
    clients_answered: usize,
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    sorted[((sorted.len() as f64 - 1.0) * p).round() as usize]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// How long a refused client waits before its next request when the answer names no time
/// (gRPC's `RESOURCE_EXHAUSTED`): the server's `Retry-After` on HTTP.
const RETRY_AFTER_DEFAULT: Duration = Duration::from_secs(1);

/// One request: the status label ("200", "429", gRPC code names, "timeout", "error"), and the
/// back-off the server asked for when it refused the request.
async fn send(
    protocol: Protocol,
    http: &reqwest::Client,
    grpc: &mut Option<proto::posefuse_client::PosefuseClient<tonic::transport::Channel>>,
    url: &str,
    p: &Prepared,
    timeout: Duration,
) -> (String, Option<Duration>) {
    match protocol {
        Protocol::Http => {
            let req = http
                .post(format!("{url}{}", p.http_path))
                .header("content-type", "application/json")
                .body(p.http_body.clone())
                .timeout(timeout);
            match req.send().await {
                Ok(r) => {
                    let status = r.status();
                    let retry = (status == reqwest::StatusCode::TOO_MANY_REQUESTS).then(|| retry_after(r.headers()));
                    match r.bytes().await {
                        Ok(_) => (status.as_u16().to_string(), retry),
                        Err(e) if e.is_timeout() => ("timeout".into(), None),
                        Err(_) => ("error".into(), None),
                    }
                }
                Err(e) if e.is_timeout() => ("timeout".into(), None),
                Err(_) => ("error".into(), None),
            }
        }
        Protocol::Grpc => {
            let Some(client) = grpc.as_mut() else { return ("error".into(), None) };
            match tokio::time::timeout(timeout, client.predict(p.grpc.clone())).await {
                Ok(Ok(_)) => ("200".into(), None),
                Ok(Err(s)) => {
                    let retry = (s.code() == tonic::Code::ResourceExhausted).then_some(RETRY_AFTER_DEFAULT);
                    (format!("{:?}", s.code()), retry)
                }
                Err(_) => ("timeout".into(), None),
            }
        }
    }
}

/// The `Retry-After` of a 429 in seconds (the server sends whole seconds).
fn retry_after(headers: &reqwest::header::HeaderMap) -> Duration {
    headers
        .get(reqwest::header::RETRY_AFTER)
        .and_then(|v| v.to_str().ok()?.trim().parse::<u64>().ok())
        .map_or(RETRY_AFTER_DEFAULT, Duration::from_secs)
}

/// How one step loads the server.
#[derive(Clone, Copy)]
struct Load {
    protocol: Protocol,
    clients: usize,
    duration: Duration,
    timeout: Duration,
}

async fn run_step(
    load: Load,
    url: &str,
    pid: Option<u32>,
    frames: Arc<Vec<Prepared>>,
) -> posefuse_data::error::Result<Step> {
    let Load { protocol, clients, duration, timeout } = load;
    let sampler = RssSampler::start(pid);
    let started = Instant::now();
    let mut tasks = Vec::with_capacity(clients);
    for c in 0..clients {
        let (frames, url) = (frames.clone(), url.to_string());
        let mut grpc = match protocol {
            Protocol::Grpc => Some(
                proto::posefuse_client::PosefuseClient::connect(url.clone())
                    .await
                    .with_context(|| format!("connecting to {url}"))?
                    .max_decoding_message_size(64 << 20)
                    .max_encoding_message_size(64 << 20),
            ),
            Protocol::Http => None,
        };
        tasks.push(tokio::spawn(async move {
            let http = reqwest::Client::new();
            let mut out: Vec<(Duration, String, usize)> = Vec::new();
            let mut i = c * 7;
            while started.elapsed() < duration {
                let p = &frames[i % frames.len()];
                let t = Instant::now();
                let (status, retry) = send(protocol, &http, &mut grpc, &url, p, timeout).await;
                out.push((t.elapsed(), status, p.persons));
                i += 1;
                // A refused client waits as the server asked, as well-behaved clients do; without
                // it a full server is measured against a retry storm on the same cores.
                if let Some(wait) = retry {
                    let left = duration.saturating_sub(started.elapsed());
                    tokio::time::sleep(wait.min(left)).await;
                }
            }
            out
        }));
    }
    let mut step = Step {
        clients,
        wall: Duration::ZERO,
        latencies: Vec::new(),
        persons: 0,
        statuses: Default::default(),
        peak_rss_kb: None,
        clients_answered: 0,
    };
    for t in tasks {
        let out = t.await.context("a bench client")?;
        step.clients_answered += usize::from(out.iter().any(|(_, status, _)| status == "200"));
        for (d, status, persons) in out {
            if status == "200" {
                step.latencies.push(d);
                step.persons += persons;
            }
            *step.statuses.entry(status).or_default() += 1;
        }
    }
    step.wall = started.elapsed();
    step.peak_rss_kb = sampler.finish();
    step.latencies.sort();
    Ok(step)
}

/// The raw ONNX Runtime numbers on the persons of `frames`.
struct Raw {
    /// Per frame: camera + point fusion on the frame's persons as one batch.
    frame_p50: Duration,
    /// Frames the p50 is taken over, and their inference time.
    frames_timed: usize,
    timed: Duration,
    /// Persons per second, batches of `max_batch` on `workers` threads.
    persons_per_s: f64,
}

/// Most inference time the raw per-frame p50 is taken over (a step's duration when shorter), and
/// the fewest and the most rounds of the frames.
const RAW_FRAME_SECS: f64 = 3.0;
const RAW_FRAME_MIN_ROUNDS: usize = 3;
const RAW_FRAME_MAX_ROUNDS: usize = 1000;

/// Whether the raw per-frame reference has timed enough after `rounds` timed rounds: at least
/// [`RAW_FRAME_MIN_ROUNDS`], and `measured` has reached `enough`.
fn timed_enough(rounds: usize, measured: Duration, enough: Duration) -> bool {
    rounds >= RAW_FRAME_MIN_ROUNDS && measured >= enough
}

/// One person's camera input `[3, S, S]` and point-fusion input `[N, 3 + K]`.
type PersonInputs = (Vec<f32>, Vec<f32>);

/// Camera inputs and fusion inputs of every fusion person of `frames`, as the server plans them
/// (`service::planned_inputs`) and chains them (`pipeline::fusion_input`).
fn raw_inputs(
    models: &mut Models,
    bundle: &Bundle,
    frames: &[Frame],
) -> posefuse_data::error::Result<Vec<Vec<PersonInputs>>> {
    let cfg = bundle.config();
    let mut out = Vec::new();
    for frame in frames {
        let mut persons = Vec::new();
        for p in planned_inputs(frame.clone(), cfg)? {
            let (Mode::Fusion, Some(x)) = (p.mode, p.image) else { continue };
            let hm = models.run(ModelKind::Camera, 1, &x)?;
            persons.push((x.clone(), fusion_input(&hm, &p.points.xyz, &p.points.uv, cfg)));
        }
        out.push(persons);
    }
    if out.iter().all(Vec::is_empty) {
        bail!("no person of these frames runs in fusion mode: the raw ceiling needs camera and LiDAR");
    }
    Ok(out)
}

fn raw_ceiling(args: &BenchOptions, frames: &[Frame]) -> posefuse_data::error::Result<Raw> {
    let rt = &args.runtime;
    let bundle = Bundle::load(&args.model_dir)?;
    let ort_env = env::environment(&env::resolve_lib(rt.ort_lib.as_deref()))?;
    let mut models = Models::load(&ort_env, &bundle, rt.intra_threads, rt.device)?;
    let inputs = raw_inputs(&mut models, &bundle, frames)?;
    let batch_of = |persons: &[&(Vec<f32>, Vec<f32>)]| {
        let cam: Vec<f32> = persons.iter().flat_map(|p| p.0.iter().copied()).collect();
        let fus: Vec<f32> = persons.iter().flat_map(|p| p.1.iter().copied()).collect();
        (cam, fus)
    };
    // One frame's persons as one camera batch and one point batch, timed.
    let mut run_frame = |persons: &[PersonInputs]| -> posefuse_data::error::Result<Duration> {
        let refs: Vec<&PersonInputs> = persons.iter().collect();
        let (cam, fus) = batch_of(&refs);
        let t = Instant::now();
        models.run(ModelKind::Camera, refs.len(), &cam)?;
        models.run(ModelKind::PointFusion, refs.len(), &fus)?;
        Ok(t.elapsed())
    };
    let frames: Vec<&Vec<PersonInputs>> = inputs.iter().filter(|p| !p.is_empty()).collect();
    // One round to warm up, then rounds until RAW_FRAME_SECS have been timed (three rounds, a few
    // hundred milliseconds, swung the p50 by 15 % from run to run).
    for persons in &frames {
        run_frame(persons)?;
    }
    let mut per_frame = Vec::new();
    let (mut measured, enough) = (Duration::ZERO, Duration::from_secs_f64(args.load.duration.min(RAW_FRAME_SECS)));
    for rounds in 0..RAW_FRAME_MAX_ROUNDS {
        if timed_enough(rounds, measured, enough) {
            break;
        }
        for persons in &frames {
            let took = run_frame(persons)?;
            per_frame.push(took);
            measured += took;
        }
    }
    per_frame.sort();
    // throughput: every worker thread with its own sessions, batches of max_batch
    let all: Arc<Vec<(Vec<f32>, Vec<f32>)>> = Arc::new(inputs.into_iter().flatten().collect());
    if all.is_empty() {
        bail!("no person of the fixtures has both a crop and LiDAR points");
    }
    let b = rt.max_batch.max(1);
    let secs = args.load.duration.min(10.0);
    let done = Arc::new(AtomicU64::new(0));
    let mut sessions = vec![models];
    for _ in 1..rt.workers.max(1) {
        sessions.push(Models::load(&ort_env, &bundle, rt.intra_threads, rt.device)?);
    }
    let started = Instant::now();
    let mut threads = Vec::new();
    for (w, mut m) in sessions.into_iter().enumerate() {
        let (all, done) = (all.clone(), done.clone());
        threads.push(std::thread::spawn(move || -> posefuse_data::error::Result<()> {
            let mut i = w * 13;
            while started.elapsed().as_secs_f64() < secs {
                let refs: Vec<&(Vec<f32>, Vec<f32>)> = (0..b).map(|k| &all[(i + k) % all.len()]).collect();
                let cam: Vec<f32> = refs.iter().flat_map(|p| p.0.iter().copied()).collect();
                let fus: Vec<f32> = refs.iter().flat_map(|p| p.1.iter().copied()).collect();
                m.run(ModelKind::Camera, b, &cam)?;
                m.run(ModelKind::PointFusion, b, &fus)?;
                done.fetch_add(b as u64, Ordering::Relaxed);
                i += b;
            }
            Ok(())
        }));
    }
    for t in threads {
        t.join().map_err(|_| invalid!("raw ONNX Runtime thread panicked"))??;
    }
    let persons_per_s = done.load(Ordering::Relaxed) as f64 / started.elapsed().as_secs_f64();
    Ok(Raw { frame_p50: percentile(&per_frame, 0.5), frames_timed: per_frame.len(), timed: measured, persons_per_s })
}

/// A `posefuse serve` child on a free loopback port.
struct Spawned {
    child: Child,
    url: String,
}

impl Drop for Spawned {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn spawn_server(args: &BenchOptions) -> posefuse_data::error::Result<Spawned> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
    let r = &args.runtime;
    let mut cmd = Command::new(std::env::current_exe()?);
    cmd.arg("serve")
        .arg("--addr")
        .arg(format!("127.0.0.1:{port}"))
        .arg("--model-dir")
        .arg(&args.model_dir)
        .args(["--workers", &r.workers.to_string(), "--intra-threads", &r.intra_threads.to_string()])
        .args(["--max-batch", &r.max_batch.to_string()])
        .args(["--batch-wait-us", &r.batch_wait.as_micros().to_string()])
        .args(["--queue-size", &r.queue_size.to_string()])
        .args(["--device", &r.device.to_string()])
        .args(r.precision.iter().flat_map(|p| ["--precision".to_string(), p.to_string()]))
        .args(&args.serve_args)
        .args(if args.load.image.contains(&ImageForm::RgbShm) {
            // one region per fixture
            let regions = args.load.frames.max(posefuse_serve::server::kserve::shared_memory::MAX_REGIONS);
            vec!["--system-shared-memory".to_string(), "--shared-memory-regions".to_string(), regions.to_string()]
        } else {
            Vec::new()
        })
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    if let Some(lib) = &r.ort_lib {
        cmd.arg("--ort-lib").arg(lib);
    }
    let child = cmd.spawn().context("starting posefuse serve")?;
    Ok(Spawned { child, url: format!("http://127.0.0.1:{port}") })
}

async fn wait_ready(url: &str) -> posefuse_data::error::Result<()> {
    let client = reqwest::Client::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    while Instant::now() < deadline {
        if let Ok(r) = client.get(format!("{url}/readyz")).send().await {
            if r.status().is_success() {
                return Ok(());
            }
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    bail!("{url} did not become ready within 120 s")
}

/// What one step of the bench measured (one image form at one concurrency). Times are written
/// to JSON in milliseconds (`p50_ms`, `p99_ms`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct StepReport {
    #[serde(rename = "image")]
    pub form: ImageForm,
    pub clients: usize,
    /// Clients that had at least one request answered: fewer than `clients` means some were
    /// refused every time they asked (each waits its `Retry-After`, while the others' next
    /// requests take the places their answers free).
    pub clients_answered: usize,
    /// Requests answered with 200.
    pub answered: usize,
    /// Persons in the answered requests.
    pub persons: usize,
    pub frames_per_s: f64,
    pub persons_per_s: f64,
    #[serde(rename = "p50_ms", serialize_with = "as_ms")]
    pub p50: Duration,
    #[serde(rename = "p99_ms", serialize_with = "as_ms")]
    pub p99: Duration,
    /// Every status seen, with its count (`"200"`, `"429"`, transport errors by name).
    pub statuses: std::collections::BTreeMap<String, usize>,
    /// The server's peak resident memory during the step (None: no process to read it from).
    pub peak_rss_mb: Option<f64>,
}

/// The settings a bench ran with.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BenchSetup {
    pub bundle: PathBuf,
    /// The frames sent (cycled through) and their persons.
    pub frames: usize,
    pub persons: usize,
    pub device: String,
    pub workers: usize,
    pub intra_threads: usize,
    pub max_batch: usize,
    pub protocol: Protocol,
    pub step_s: f64,
}

/// What `posefuse bench` measured: the raw ONNX Runtime reference (unless `no_raw`) and each step.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BenchReport {
    pub setup: BenchSetup,
    #[serde(rename = "raw_frame_p50_ms", serialize_with = "as_ms_opt")]
    pub raw_frame_p50: Option<Duration>,
    /// Frames the raw p50 is taken over, and their inference time.
    pub raw_frames_timed: usize,
    #[serde(rename = "raw_timed_ms", serialize_with = "as_ms")]
    pub raw_timed: Duration,
    pub raw_persons_per_s: Option<f64>,
    pub steps: Vec<StepReport>,
    /// The server's lifetime peak resident memory (VmHWM) at the end.
    pub server_peak_rss_mb: Option<f64>,
}

fn as_ms<S: serde::Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_f64(ms(*d))
}

fn as_ms_opt<S: serde::Serializer>(d: &Option<Duration>, s: S) -> Result<S::Ok, S::Error> {
    match d {
        Some(d) => s.serialize_some(&ms(*d)),
        None => s.serialize_none(),
    }
}

fn mb(kb: u64) -> f64 {
    kb as f64 / 1024.0
}

/// What a step measured, as reported: rates over its wall time, p50 and p99 of the answered
/// requests' latencies (sorted by `run_step`).
fn step_report(form: ImageForm, s: Step) -> StepReport {
    let secs = s.wall.as_secs_f64();
    StepReport {
        form,
        clients: s.clients,
        answered: s.latencies.len(),
        persons: s.persons,
        frames_per_s: s.latencies.len() as f64 / secs,
        persons_per_s: s.persons as f64 / secs,
        p50: percentile(&s.latencies, 0.5),
        p99: percentile(&s.latencies, 0.99),
        statuses: s.statuses,
        clients_answered: s.clients_answered,
        peak_rss_mb: s.peak_rss_kb.map(mb),
    }
}

/// One step's row of the printed table: the numbers of its report, set beside the raw reference.
fn table_row(s: &StepReport, raw: Option<&Raw>) -> String {
    let statuses: Vec<String> = s.statuses.iter().map(|(k, v)| format!("{k}: {v}")).collect();
    let ratio = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.2}"));
    format!(
        "| {:?} | {} | {} | {:.1} | {:.1} | {:.2} | {:.2} | {} | {} | {} | {} |",
        s.form,
        s.clients,
        s.clients_answered,
        s.frames_per_s,
        s.persons_per_s,
        ms(s.p50),
        ms(s.p99),
        ratio(raw.map(|r| ms(s.p50) / ms(r.frame_p50))),
        ratio(raw.map(|r| s.persons_per_s / r.persons_per_s)),
        statuses.join(", "),
        s.peak_rss_mb.map_or("–".to_string(), |mb| format!("{mb:.0}")),
    )
}

/// Runs `posefuse bench`: prints its table and returns what it measured.
pub fn run_bench(args: BenchOptions) -> posefuse_data::error::Result<BenchReport> {
    let mut frames: Vec<Frame> =
        posefuse_serve::eval::load_fixtures(&args.load.data)?.into_iter().map(|(_, f)| f).collect();
    frames.truncate(args.load.frames.max(1));
    let persons: usize = frames.iter().map(|f| f.persons.len()).sum();
    println!(
        "fixtures: {} frames, {} persons ({:.2} per frame) from {}",
        frames.len(),
        persons,
        persons as f64 / frames.len() as f64,
        args.load.data.display()
    );
    if args.load.image.contains(&ImageForm::RgbShm) && args.load.protocol != Protocol::Http {
        bail!("--image rgb-shm sends Open Inference Protocol requests over HTTP: use --protocol http");
    }
    let r = &args.runtime;
    println!(
        "runtime: bundle {} | workers {} | intra-op threads {} | max batch {} | protocol {:?} | {} s per step",
        args.model_dir.display(),
        r.workers,
        r.intra_threads,
        r.max_batch,
        args.load.protocol,
        args.load.duration
    );
    let raw = if args.load.no_raw { None } else { Some(raw_ceiling(&args, &frames)?) };
    if let Some(raw) = &raw {
        println!(
            "raw ONNX Runtime (camera + point fusion): per frame p50 {:.3} ms ({} frames timed) | ceiling {:.0} persons/s",
            ms(raw.frame_p50),
            raw.frames_timed,
            raw.persons_per_s
        );
    }
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let spawned = if args.load.url.is_none() { Some(spawn_server(&args)?) } else { None };
    let url = args.load.url.clone().or_else(|| spawned.as_ref().map(|s| s.url.clone())).unwrap_or_default();
    let url = url.trim_end_matches('/').to_string();
    let pid = args.load.server_pid.or_else(|| spawned.as_ref().map(|s| s.child.id()));
    rt.block_on(wait_ready(&url))?;
    println!();
    let mut report = BenchReport {
        setup: BenchSetup {
            bundle: args.model_dir.clone(),
            frames: frames.len(),
            persons,
            device: r.device.to_string(),
            workers: r.workers,
            intra_threads: r.intra_threads,
            max_batch: r.max_batch,
            protocol: args.load.protocol,
            step_s: args.load.duration,
        },
        server_peak_rss_mb: None,
        raw_frame_p50: raw.as_ref().map(|r| r.frame_p50),
        raw_frames_timed: raw.as_ref().map_or(0, |r| r.frames_timed),
        raw_timed: raw.as_ref().map_or(Duration::ZERO, |r| r.timed),
        raw_persons_per_s: raw.as_ref().map(|r| r.persons_per_s),
        steps: Vec::new(),
    };
    println!(
        "| image | clients | clients answered | frames/s | persons/s | p50 ms | p99 ms | p50 / raw | persons/s / raw | statuses | peak RSS MB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let model = Bundle::load(&args.model_dir)?.manifest.name.clone();
    for &form in &args.load.image {
        let mut objects = shared_memory::Objects::default();
        let prepared: Vec<Prepared> = frames
            .iter()
            .enumerate()
            .map(|(i, f)| prepare(i, f, form, &mut objects, &model))
            .collect::<posefuse_data::error::Result<_>>()?;
        if form == ImageForm::RgbShm {
            rt.block_on(shared_memory::register(&url, &objects))?;
        }
        let prepared = Arc::new(prepared);
        let load = Load {
            protocol: args.load.protocol,
            clients: 1,
            duration: Duration::from_secs_f64(args.load.duration),
            timeout: Duration::from_secs_f64(args.load.timeout),
        };
        // warm-up, one client for a second (at most one step's duration)
        let warm = Duration::from_secs_f64(args.load.duration.min(1.0));
        rt.block_on(run_step(Load { duration: warm, ..load }, &url, None, prepared.clone()))?;
        for &clients in &args.load.concurrency {
            let s = rt.block_on(run_step(Load { clients: clients.max(1), ..load }, &url, pid, prepared.clone()))?;
            if s.latencies.is_empty() {
                bail!("{form:?} at {clients} clients: no request was answered with 200 ({:?})", s.statuses);
            }
            let step = step_report(form, s);
            println!("{}", table_row(&step, raw.as_ref()));
            report.steps.push(step);
        }
        if form == ImageForm::RgbShm {
            rt.block_on(shared_memory::unregister(&url, &objects))?;
        }
    }
    report.server_peak_rss_mb = pid.and_then(|p| proc_kb(p, "VmHWM:")).map(mb);
    if let Some(hwm) = report.server_peak_rss_mb {
        println!("\nserver VmHWM (lifetime peak RSS): {hwm:.0} MB");
    }
    drop(spawned);
    if let Some(path) = &args.load.json {
        let text = serde_json::to_string_pretty(&report).context("the bench report as JSON")?;
        std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_step_is_reported_as_rates_over_its_wall_time() {
        let ms = Duration::from_millis;
        let step = Step {
            clients: 4,
            wall: Duration::from_secs(2),
            latencies: vec![ms(10), ms(20), ms(30), ms(40), ms(90)],
            persons: 8,
            statuses: [("200".to_string(), 5), ("429".to_string(), 2)].into(),
            peak_rss_kb: Some(3 * 1024),
            clients_answered: 3,
        };
        let r = step_report(ImageForm::Rgb, step);
        assert_eq!((r.form, r.clients, r.clients_answered, r.answered, r.persons), (ImageForm::Rgb, 4, 3, 5, 8));
        assert_eq!((r.frames_per_s, r.persons_per_s), (2.5, 4.0));
        assert_eq!((r.p50, r.p99), (ms(30), ms(90)));
        assert_eq!(r.statuses["429"], 2);
        assert_eq!(r.peak_rss_mb, Some(3.0));
    }

    #[test]
    fn a_table_row_shows_the_steps_numbers_beside_the_raw_reference() {
        let step = StepReport {
            form: ImageForm::Jpeg420,
            clients: 16,
            clients_answered: 15,
            answered: 900,
            persons: 1800,
            frames_per_s: 150.04,
            persons_per_s: 300.0,
            p50: Duration::from_micros(12_345),
            p99: Duration::from_micros(40_000),
            statuses: [("200".to_string(), 900), ("429".to_string(), 3)].into(),
            peak_rss_mb: Some(211.6),
        };
        let raw = Raw {
            frame_p50: Duration::from_micros(5_000),
            frames_timed: 100,
            timed: Duration::from_secs(1),
            persons_per_s: 400.0,
        };
        assert_eq!(
            table_row(&step, Some(&raw)),
            "| Jpeg420 | 16 | 15 | 150.0 | 300.0 | 12.35 | 40.00 | 2.47 | 0.75 | 200: 900, 429: 3 | 212 |"
        );
        let no_raw = StepReport { peak_rss_mb: None, ..step };
        assert_eq!(
            table_row(&no_raw, None),
            "| Jpeg420 | 16 | 15 | 150.0 | 300.0 | 12.35 | 40.00 | – | – | 200: 900, 429: 3 | – |"
        );
    }

    #[test]
    fn the_raw_reference_times_three_rounds_then_until_it_has_enough() {
        let (short, enough) = (Duration::from_millis(10), Duration::from_secs(1));
        // three timed rounds always run, however much they measured
        for rounds in 0..RAW_FRAME_MIN_ROUNDS {
            assert!(!timed_enough(rounds, enough * 2, enough), "after {rounds} rounds");
        }
        // then rounds go on until `enough` is measured, and no further
        assert!(!timed_enough(RAW_FRAME_MIN_ROUNDS, short, enough));
        assert!(!timed_enough(40, enough - short, enough));
        assert!(timed_enough(RAW_FRAME_MIN_ROUNDS, enough, enough));
        assert!(timed_enough(40, enough * 2, enough));
    }

    #[test]
    fn a_refused_client_waits_the_servers_retry_after() {
        let mut h = reqwest::header::HeaderMap::new();
        assert_eq!(retry_after(&h), RETRY_AFTER_DEFAULT);
        h.insert(reqwest::header::RETRY_AFTER, " 3".parse().unwrap());
        assert_eq!(retry_after(&h), Duration::from_secs(3));
        // an HTTP date or garbage: the default
        h.insert(reqwest::header::RETRY_AFTER, "Wed, 21 Oct 2026 07:28:00 GMT".parse().unwrap());
        assert_eq!(retry_after(&h), RETRY_AFTER_DEFAULT);
    }
}
