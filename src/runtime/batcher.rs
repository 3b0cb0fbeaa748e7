//! The inference queue: requests post jobs into one bounded channel; worker threads (each owning
//! its own sessions) take whatever is queued, up to `max_batch` jobs, optionally waiting
//! `batch_wait` for more, and run one batch per network. Inference never runs on the async
//! executor, and a full queue is refused at once instead of growing latency without bound.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TrySendError};
use tokio::sync::oneshot;

use super::bundle::{Bundle, ModelKind};
use super::models::Models;
use crate::error::{Error, Result};

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
}

impl Default for RuntimeConfig {
    fn default() -> Self {
        RuntimeConfig {
            ort_lib: None,
            workers: 1,
            intra_threads: 1,
            max_batch: 16,
            batch_wait: Duration::ZERO,
            queue_size: 256,
        }
    }
}

/// What a job gives back.
#[derive(Debug, Clone)]
pub struct JobOutput {
    /// This item's output (`io.output_len()` floats).
    pub data: Vec<f32>,
    /// Time spent waiting in the queue.
    pub queue: Duration,
    /// Time of the batch's inference call.
    pub inference: Duration,
    /// Size of the batch it ran in.
    pub batch: usize,
}

struct Job {
    kind: ModelKind,
    input: Vec<f32>,
    enqueued: Instant,
    reply: oneshot::Sender<Result<JobOutput>>,
}

/// Stops workers from taking jobs while held (load-shedding and drain tests, maintenance).
#[derive(Default)]
struct Gate {
    paused: Mutex<bool>,
    resumed: Condvar,
}

impl Gate {
    fn wait_open(&self) {
        let mut paused = self.paused.lock().unwrap_or_else(|p| p.into_inner());
        while *paused {
            paused = self.resumed.wait(paused).unwrap_or_else(|p| p.into_inner());
        }
    }

    fn set(&self, value: bool) {
        *self.paused.lock().unwrap_or_else(|p| p.into_inner()) = value;
        self.resumed.notify_all();
    }
}

/// Holds the workers paused until dropped.
pub struct PauseGuard {
    gate: Arc<Gate>,
}

impl Drop for PauseGuard {
    fn drop(&mut self) {
        self.gate.set(false);
    }
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
    /// Loads ONNX Runtime, builds every worker's sessions (refusing a bundle whose ONNX files
    /// disagree with its manifest) and returns; warm-up continues on the workers ([`Runtime::is_ready`]).
    pub fn start(bundle: Arc<Bundle>, cfg: &RuntimeConfig) -> Result<Runtime> {
        let lib = super::env::resolve_lib(cfg.ort_lib.as_deref());
        let env = super::env::environment(&lib)?;
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
            let intra = cfg.intra_threads;
            let batch_wait = cfg.batch_wait;
            let handle = std::thread::Builder::new()
                .name(format!("posefuse-worker-{i}"))
                .spawn(move || {
                    let mut models = match Models::load(&env, &bundle, intra) {
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

    /// Pauses the workers (they finish the batch in hand) until the guard is dropped.
    pub fn pause(&self) -> PauseGuard {
        self.gate.set(true);
        PauseGuard { gate: self.gate.clone() }
    }

    /// Queues one item for `kind` and waits for its output. Refuses at once when the queue is full.
    pub async fn infer(&self, kind: ModelKind, input: Vec<f32>) -> Result<JobOutput> {
        let want = self.bundle.io(kind).input_len();
        if input.len() != want {
            return Err(Error::Runtime(format!("{}: input of {} floats, expected {want}", kind.key(), input.len())));
        }
        let (reply, rx) = oneshot::channel();
        let tx = self.tx.as_ref().ok_or_else(|| Error::Unavailable("shutting down".into()))?;
        match tx.try_send(Job { kind, input, enqueued: Instant::now(), reply }) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => return Err(Error::Overloaded),
            Err(TrySendError::Disconnected(_)) => return Err(Error::Unavailable("shutting down".into())),
        }
        rx.await.map_err(|_| Error::Runtime("the inference worker stopped".into()))?
    }

    fn shutdown(&mut self) {
        self.gate.set(false);
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
        // Callers that gave up (timeout, disconnect) are not worth computing for.
        jobs.retain(|j| !j.reply.is_closed());
        let mut by_kind: [Vec<Job>; 3] = Default::default();
        for j in jobs {
            let slot = ModelKind::ALL.iter().position(|k| *k == j.kind).unwrap_or(0);
            by_kind[slot].push(j);
        }
        for (kind, group) in ModelKind::ALL.into_iter().zip(by_kind) {
            if !group.is_empty() {
                run_batch(models, kind, group);
            }
        }
    }
}

fn run_batch(models: &mut Models, kind: ModelKind, jobs: Vec<Job>) {
    let started = Instant::now();
    let batch = jobs.len();
    let mut input = Vec::with_capacity(batch * models.io(kind).input_len());
    for j in &jobs {
        input.extend_from_slice(&j.input);
    }
    let result = models.run(kind, batch, &input);
    let inference = started.elapsed();
    metrics::histogram!("posefuse_inference_seconds", "model" => kind.key()).record(inference.as_secs_f64());
    metrics::histogram!("posefuse_batch_size", "model" => kind.key()).record(batch as f64);
    let out_len = models.io(kind).output_len();
    for (i, j) in jobs.into_iter().enumerate() {
        let queue = started.saturating_duration_since(j.enqueued);
        metrics::histogram!("posefuse_queue_wait_seconds", "model" => kind.key()).record(queue.as_secs_f64());
        let item = match &result {
            Ok(all) => Ok(JobOutput { data: all[i * out_len..(i + 1) * out_len].to_vec(), queue, inference, batch }),
            Err(e) => Err(Error::Runtime(e.to_string())),
        };
        let _ = j.reply.send(item);
    }
}
