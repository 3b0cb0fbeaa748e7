//! The inference queue: requests post jobs into one bounded channel; worker threads (each owning
//! its own sessions) take whatever is queued, up to `max_batch` jobs, optionally waiting
//! `batch_wait` for more, and run one batch per network. A fusion person is one job: its camera
//! output becomes its point input on the worker, so it crosses threads once, not twice. Inference
//! never runs on the async executor, and a full queue is refused at once instead of growing
//! latency without bound.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TrySendError};
use tokio::sync::oneshot;

use super::bundle::{Bundle, ModelKind};
use super::gate::Gate;
use super::models::Models;
use super::precision::Precision;
use posefuse_core::error::{Error, Result};

/// Thread and queue settings of the runtime.
#[derive(Debug, Clone)]
pub struct RuntimeConfig {
    /// ONNX Runtime shared library (None: `ORT_DYLIB_PATH`, else `.ort/lib/libonnxruntime.so`).
    pub ort_lib: Option<PathBuf>,
    /// Worker threads, each with its own sessions.
    pub workers: usize,
    /// ONNX Runtime intra-op threads per session.
    pub intra_threads: usize,
    /// Most jobs run together in one batch.
    pub max_batch: usize,
    /// How long a worker waits for more jobs once it has one (zero: take only what is queued).
    pub batch_wait: Duration,
    /// Jobs that may wait in the queue before requests are refused.
    pub queue_size: usize,
    /// Where the sessions run.
    pub device: super::Device,
    /// The camera network's precision (None: the bundle manifest's).
    pub precision: Option<super::Precision>,
}

impl RuntimeConfig {
    /// The defaults (those of `posefuse serve`, whose flags show them).
    pub const DEFAULT: RuntimeConfig = RuntimeConfig {
        ort_lib: None,
        workers: 1,
        intra_threads: 1,
        max_batch: 16,
        batch_wait: Duration::ZERO,
        queue_size: 256,
        device: super::Device::Cpu,
        precision: None,
    };

    /// The configuration a heading-stage bundle loads with: this one, its camera at its own
    /// manifest's precision. `--precision` names the main bundle's camera; a heading model
    /// without that variant (models/view has no INT8 file) would otherwise refuse to load.
    pub fn for_heading_stage(&self) -> RuntimeConfig {
        RuntimeConfig { precision: None, ..self.clone() }
    }
}

impl Default for RuntimeConfig {
    fn default() -> Self {
        RuntimeConfig::DEFAULT
    }
}

/// What a job gives back.
#[derive(Debug, Clone)]
pub struct JobOutput {
    /// This item's output (`io.output_len()` floats); for a chain, the point network's.
    pub data: Vec<f32>,
    /// A chain's camera output (its heatmaps).
    pub camera: Option<Vec<f32>>,
    /// Time spent waiting in the queue.
    pub queue: Duration,
    /// Time of the batch's inference calls (both networks for a chain).
    pub inference: Duration,
    /// Time a chain spent turning camera output into point input.
    pub between: Duration,
    /// Size of the (last) batch it ran in.
    pub batch: usize,
}

/// Turns a chain's camera output into its point network's input.
pub type ChainStep = Box<dyn FnOnce(&[f32]) -> Vec<f32> + Send>;

enum Work {
    Single { kind: ModelKind, input: Vec<f32> },
    Chain { camera: Vec<f32>, point: ModelKind, then: ChainStep },
}

struct Job {
    work: Work,
    enqueued: Instant,
    reply: oneshot::Sender<Result<JobOutput>>,
    /// The span the job was queued from (a request's), parent of its `inference` span.
    parent: tracing::Span,
    /// Open while the job waits: a worker taking it ends the wait.
    queue: tracing::Span,
}

/// A camera-batch entry: the item, its input, and for a chain the point network and the step.
type CameraEntry = (Item, Vec<f32>, Option<(ModelKind, ChainStep)>);

/// A job's place in the batches of one worker round.
struct Item {
    job_reply: oneshot::Sender<Result<JobOutput>>,
    /// From the start of the job's first network to the reply.
    span: tracing::Span,
    /// A point job's `queue` span, open until its batch starts (after the round's camera batch),
    /// and the request span its `inference` span then opens under.
    waiting: Option<(tracing::Span, tracing::Span)>,
    queue: Duration,
    camera: Option<Vec<f32>>,
    inference: Duration,
    between: Duration,
}

/// The sessions' owner threads and the queue in front of them.
pub struct Runtime {
    bundle: Arc<Bundle>,
    tx: Option<Sender<Job>>,
    warmed: Arc<AtomicUsize>,
    gate: Arc<Gate>,
    workers: Vec<JoinHandle<()>>,
    max_batch: usize,
}

impl Runtime {
    /// Loads and validates the bundle in `model_dir` and starts a runtime on it (blocking:
    /// builds the sessions).
    pub fn load(model_dir: &std::path::Path, cfg: &RuntimeConfig) -> Result<Arc<Runtime>> {
        let bundle = Arc::new(Bundle::load_at(model_dir, Precision::asked_on(cfg.precision, cfg.device))?);
        if bundle.trained() == Some(false) {
            tracing::warn!(bundle = %model_dir.display(), "serving an UNTRAINED bundle (tests only)");
        }
        let m = &bundle.manifest;
        tracing::info!(
            bundle = %model_dir.display(),
            name = %m.name,
            version = %m.version,
            precision = %bundle.precision,
            device = %cfg.device,
            "bundle loaded"
        );
        Ok(Arc::new(Runtime::start(bundle, cfg)?))
    }

    /// Loads ONNX Runtime, builds every worker's sessions (refusing a bundle whose ONNX files
    /// disagree with its manifest) and returns; warm-up continues on the workers ([`Runtime::is_ready`]).
    pub fn start(bundle: Arc<Bundle>, cfg: &RuntimeConfig) -> Result<Runtime> {
        let lib = super::env::resolve_lib(cfg.ort_lib.as_deref());
        let env = super::env::environment(&lib)?;
        cfg.device.check(&lib)?;
        let workers_n = cfg.workers.max(1);
        let max_batch = cfg.max_batch.max(1);
        let (tx, rx) = crossbeam_channel::bounded::<Job>(cfg.queue_size.max(1));
        let warmed = Arc::new(AtomicUsize::new(0));
        let gate = Arc::new(Gate::default());
        let (built_tx, built_rx) = std::sync::mpsc::channel::<Result<()>>();
        let mut workers = Vec::with_capacity(workers_n);
        for i in 0..workers_n {
            let (rx, env, bundle, warmed, gate, built_tx) =
                (rx.clone(), env.clone(), bundle.clone(), warmed.clone(), gate.clone(), built_tx.clone());
            let (intra, device) = (cfg.intra_threads, cfg.device);
            let batch_wait = cfg.batch_wait;
            let handle = std::thread::Builder::new()
                .name(format!("posefuse-worker-{i}"))
                .spawn(move || {
                    let mut models = match Models::load(&env, &bundle, intra, device) {
                        Ok(m) => {
                            let _ = built_tx.send(Ok(()));
                            m
                        }
                        Err(e) => {
                            let _ = built_tx.send(Err(e));
                            return;
                        }
                    };
                    drop(built_tx);
                    gate.wait_open();
                    if let Err(e) = warm_up(&mut models, max_batch) {
                        tracing::error!(worker = i, "warm-up failed: {e}");
                        return;
                    }
                    warmed.fetch_add(1, Ordering::SeqCst);
                    worker_loop(&mut models, &rx, &gate, max_batch, batch_wait);
                })
                .map_err(|e| Error::Runtime(format!("cannot start worker thread: {e}")))?;
            workers.push(handle);
        }
        drop(built_tx);
        let mut runtime = Runtime { bundle, tx: Some(tx), warmed, gate, workers, max_batch };
        for _ in 0..workers_n {
            match built_rx.recv() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => {
                    runtime.shutdown();
                    return Err(e);
                }
                Err(_) => {
                    runtime.shutdown();
                    return Err(Error::Runtime("a worker thread stopped while loading the models".into()));
                }
            }
        }
        Ok(runtime)
    }

    /// The bundle the sessions were built from.
    pub fn bundle(&self) -> &Arc<Bundle> {
        &self.bundle
    }

    /// All workers have warmed up.
    pub fn is_ready(&self) -> bool {
        self.warmed.load(Ordering::SeqCst) == self.workers.len()
    }

    /// Blocks until warm-up is done or `timeout` passes; returns readiness.
    pub fn wait_ready(&self, timeout: Duration) -> bool {
        let end = Instant::now() + timeout;
        while !self.is_ready() {
            if Instant::now() >= end || self.workers.iter().all(|w| w.is_finished()) {
                return self.is_ready();
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        true
    }

    /// Largest batch a worker forms.
    pub fn max_batch(&self) -> usize {
        self.max_batch
    }

    /// Pauses the workers (they finish the batch in hand) until the guard is dropped: lets tests
    /// fill the queue deterministically.
    #[cfg(feature = "test-hooks")]
    pub fn pause(&self) -> super::gate::PauseGuard {
        super::gate::PauseGuard::new(&self.gate)
    }

    /// Queues one item for `kind` and waits for its output. Refuses at once when the queue is full.
    pub async fn infer(&self, kind: ModelKind, input: Vec<f32>) -> Result<JobOutput> {
        self.check_len(kind, input.len())?;
        self.submit(Work::Single { kind, input }).await
    }

    /// Runs the camera network on `camera`, `then` on its output, and the `point` network on
    /// that, in one job: the camera output is returned beside the point output.
    pub async fn infer_chain(&self, camera: Vec<f32>, point: ModelKind, then: ChainStep) -> Result<JobOutput> {
        self.check_len(ModelKind::Camera, camera.len())?;
        if point == ModelKind::Camera {
            return Err(Error::Runtime("a chain ends in a point network".into()));
        }
        self.submit(Work::Chain { camera, point, then }).await
    }

    fn check_len(&self, kind: ModelKind, len: usize) -> Result<()> {
        let want = self.bundle.io(kind).input_len();
        if len != want {
            return Err(Error::Runtime(format!("{}: input of {len} floats, expected {want}", kind.key())));
        }
        Ok(())
    }

    async fn submit(&self, work: Work) -> Result<JobOutput> {
        let (reply, rx) = oneshot::channel();
        let tx = self.tx.as_ref().ok_or_else(|| Error::Unavailable("shutting down".into()))?;
        let queue = tracing::info_span!("queue", model = kind_of(&work).key());
        let job = Job { work, enqueued: Instant::now(), reply, parent: tracing::Span::current(), queue };
        match tx.try_send(job) {
            Ok(()) => metrics::gauge!("posefuse_queue_depth").set(tx.len() as f64),
            Err(TrySendError::Full(_)) => return Err(Error::Overloaded),
            Err(TrySendError::Disconnected(_)) => return Err(Error::Unavailable("shutting down".into())),
        }
        rx.await.map_err(|_| Error::Runtime("the inference worker stopped".into()))?
    }

    fn shutdown(&mut self) {
        self.gate.open();
        self.tx.take();
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}

impl Drop for Runtime {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// First runs allocate ONNX Runtime's buffers; do them before the server reports ready.
fn warm_up(models: &mut Models, max_batch: usize) -> Result<()> {
    for kind in ModelKind::ALL {
        let len = models.io(kind).input_len();
        for batch in [1, max_batch] {
            models.run(kind, batch, &vec![0.0; len * batch])?;
        }
    }
    Ok(())
}

fn worker_loop(models: &mut Models, rx: &Receiver<Job>, gate: &Gate, max_batch: usize, batch_wait: Duration) {
    while let Ok(first) = rx.recv() {
        gate.wait_open();
        let mut jobs = vec![first];
        let deadline = Instant::now() + batch_wait;
        while jobs.len() < max_batch {
            let next = if batch_wait.is_zero() { rx.try_recv().ok() } else { rx.recv_deadline(deadline).ok() };
            match next {
                Some(j) => jobs.push(j),
                None => break,
            }
        }
        metrics::gauge!("posefuse_queue_depth").set(rx.len() as f64);
        // Callers that gave up (timeout, disconnect) are not worth computing for.
        jobs.retain(|j| !j.reply.is_closed());
        run_round(models, jobs);
    }
}

/// One round: the camera batch (camera jobs and chains) first, then chains' point inputs, then
/// one batch per point network; between the stages, jobs whose callers gave up are dropped. A
/// job's queue wait runs until its network starts on it: a point job waits for the round's
/// camera batch as well, and a chain's point input from its smoothing to its point batch.
fn run_round(models: &mut Models, jobs: Vec<Job>) {
    let started = Instant::now();
    let item = |reply, enqueued: Instant, kind: ModelKind, parent: tracing::Span, queue_span: tracing::Span| {
        let queue = started.saturating_duration_since(enqueued);
        let (span, waiting) = if kind == ModelKind::Camera {
            metrics::histogram!("posefuse_queue_wait_seconds", "model" => kind.key()).record(queue.as_secs_f64());
            drop(queue_span);
            (inference_span(&parent, kind), None)
        } else {
            (tracing::Span::none(), Some((queue_span, parent)))
        };
        Item {
            job_reply: reply,
            span,
            waiting,
            queue,
            camera: None,
            inference: Duration::ZERO,
            between: Duration::ZERO,
        }
    };
    let mut camera: Vec<CameraEntry> = Vec::new();
    // each point input with the time it was ready from (what its queue wait counts so far)
    let mut points: [Vec<(Item, Vec<f32>, Instant)>; 3] = Default::default();
    for j in jobs {
        let it = item(j.reply, j.enqueued, kind_of(&j.work), j.parent, j.queue);
        match j.work {
            Work::Single { kind: ModelKind::Camera, input } => camera.push((it, input, None)),
            Work::Single { kind, input } => points[slot(kind)].push((it, input, started)),
            Work::Chain { camera: input, point, then } => camera.push((it, input, Some((point, then)))),
        }
    }
    if !camera.is_empty() {
        let inputs: Vec<&[f32]> = camera.iter().map(|c| c.1.as_slice()).collect();
        let (outputs, took) = run_batch(models, ModelKind::Camera, &inputs);
        let batch = outputs.len();
        for ((mut it, _, chain), out) in camera.into_iter().zip(outputs) {
            it.inference += took;
            match (out, chain) {
                // its caller gave up while the camera ran: no smoothing, no point network
                (Ok(_), Some(_)) if it.job_reply.is_closed() => {}
                (Ok(h), Some((kind, then))) => {
                    let t = Instant::now();
                    let next = then(&h);
                    let ready = Instant::now();
                    it.between = ready - t;
                    it.camera = Some(h);
                    let want = models.io(kind).input_len();
                    if next.len() == want {
                        points[slot(kind)].push((it, next, ready));
                    } else {
                        let e = format!("{}: chained input of {} floats, expected {want}", kind.key(), next.len());
                        reply(it, Err(Error::Runtime(e)), 1);
                    }
                }
                (out, _) => reply(it, out, batch),
            }
        }
    }
    for (kind, mut group) in ModelKind::ALL.into_iter().zip(points) {
        group.retain(|(it, _, _)| !it.job_reply.is_closed());
        if group.is_empty() {
            continue;
        }
        let start = Instant::now();
        for (it, _, ready) in &mut group {
            let (queue, waited) = point_wait(it.queue, *ready, start, it.camera.is_some());
            it.queue = queue;
            metrics::histogram!("posefuse_queue_wait_seconds", "model" => kind.key()).record(waited.as_secs_f64());
            if let Some((queue_span, parent)) = it.waiting.take() {
                drop(queue_span);
                it.span = inference_span(&parent, kind);
            }
        }
        let inputs: Vec<&[f32]> = group.iter().map(|g| g.1.as_slice()).collect();
        let (outputs, took) = run_batch(models, kind, &inputs);
        let batch = outputs.len();
        for ((mut it, _, _), out) in group.into_iter().zip(outputs) {
            it.inference += took;
            reply(it, out, batch);
        }
    }
}

/// The `inference` span of a job whose first network starts now, under the request's span.
fn inference_span(parent: &tracing::Span, kind: ModelKind) -> tracing::Span {
    tracing::info_span!(parent: parent, "inference", model = kind.key(), batch = tracing::field::Empty)
}

/// A point job's queue wait when its batch starts at `start`: its whole wait (`queue` so far, to
/// the round's start, plus from `ready` on) and the wait recorded under its network, which for a
/// chain is only the time since its input was ready (its camera part is the camera's).
fn point_wait(queue: Duration, ready: Instant, start: Instant, chained: bool) -> (Duration, Duration) {
    let wait = start.saturating_duration_since(ready);
    let queue = queue + wait;
    (queue, if chained { wait } else { queue })
}

/// The network a job starts with.
fn kind_of(work: &Work) -> ModelKind {
    match work {
        Work::Single { kind, .. } => *kind,
        Work::Chain { .. } => ModelKind::Camera,
    }
}

fn slot(kind: ModelKind) -> usize {
    ModelKind::ALL.iter().position(|k| *k == kind).unwrap_or(0)
}

fn reply(it: Item, out: Result<Vec<f32>>, batch: usize) {
    it.span.record("batch", batch);
    let _ = it.job_reply.send(out.map(|data| JobOutput {
        data,
        camera: it.camera,
        queue: it.queue,
        inference: it.inference,
        between: it.between,
        batch,
    }));
}

/// One inference call over `inputs`; each item's output, or the call's error for every item.
fn run_batch(models: &mut Models, kind: ModelKind, inputs: &[&[f32]]) -> (Vec<Result<Vec<f32>>>, Duration) {
    let started = Instant::now();
    let batch = inputs.len();
    let mut input = Vec::with_capacity(batch * models.io(kind).input_len());
    for x in inputs {
        input.extend_from_slice(x);
    }
    let result = models.run(kind, batch, &input);
    let inference = started.elapsed();
    metrics::histogram!("posefuse_inference_seconds", "model" => kind.key()).record(inference.as_secs_f64());
    metrics::histogram!("posefuse_batch_size", "model" => kind.key()).record(batch as f64);
    let out_len = models.io(kind).output_len();
    let outputs = (0..batch)
        .map(|i| match &result {
            Ok(all) => Ok(all[i * out_len..(i + 1) * out_len].to_vec()),
            Err(e) => Err(Error::Runtime(e.to_string())),
        })
        .collect();
    (outputs, inference)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_job_waits_until_its_batch_starts_and_a_chain_counts_its_own_part() {
        let (ms, ready) = (Duration::from_millis, Instant::now());
        let start = ready + ms(3);
        assert_eq!(point_wait(ms(2), ready, start, false), (ms(5), ms(5)), "a single job: all of its wait");
        assert_eq!(point_wait(ms(2), ready, start, true), (ms(5), ms(3)), "a chain: its point part");
        assert_eq!(point_wait(ms(2), start, ready, true), (ms(2), ms(0)), "started before ready: no wait");
    }

    #[test]
    fn a_heading_stage_keeps_everything_but_the_main_cameras_precision() {
        let main = RuntimeConfig {
            workers: 3,
            intra_threads: 2,
            max_batch: 5,
            batch_wait: Duration::from_millis(7),
            queue_size: 11,
            precision: Some(super::super::Precision::Int8),
            ..RuntimeConfig::DEFAULT
        };
        let stage = main.for_heading_stage();
        assert_eq!(stage.precision, None);
        assert_eq!(
            (stage.workers, stage.intra_threads, stage.max_batch, stage.batch_wait, stage.queue_size),
            (3, 2, 5, Duration::from_millis(7), 11)
        );
    }
}
