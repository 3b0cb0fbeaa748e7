//! Admission before work. A frame is admitted (a ticket) before its body is read or parsed:
//! at most `permits + max_waiting` frames are in the server at once, and one more is refused at
//! once (429 with `Retry-After`), before reading, parsing or decoding it. An admitted frame's
//! decode and pre-processing then start only with one of a few permits (about the number of
//! cores), so concurrent requests do not all decode at once: CPU, threads and memory stay
//! bounded at any concurrency.
//!
//! A refusal holds no place, so under a closed loop of clients that send their next frame as
//! soon as an answer comes, the answered clients keep the places and the refused ones may be
//! refused every time they come back. The waiting line ([`Line`], `--admission-wait-ms`, on by
//! default) makes admission fair: a frame that finds the server full waits, before its body is
//! read, for a place, in order of arrival, and is refused only when the line is full or its wait
//! is over (docs/OPERATIONS.md, "Admission and overload").

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tracing::Instrument;

use posefuse_core::error::{Error, Result};

/// The waiting line in front of admission: how long a frame that finds the server full may wait
/// for a place (zero: refused at once), and how many may wait at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Line {
    pub wait: Duration,
    pub max: usize,
}

impl Line {
    /// No line: a frame that finds the server full is refused at once.
    pub const OFF: Line = Line { wait: Duration::ZERO, max: 0 };
    /// Default for `--admission-waiters`.
    pub const MAX_WAITERS: usize = 256;
    /// The server's default: up to 2 s in a line of up to 256 frames. 256 clients that each send
    /// their next frame once answered are all served at about 170 frames/s, none refused
    /// (BENCHMARKS.md, "A fair waiting line").
    pub const DEFAULT: Line = Line { wait: Duration::from_millis(2000), max: Line::MAX_WAITERS };
}

/// The gate in front of pre-processing.
pub struct Admission {
    permits: Arc<Semaphore>,
    total: usize,
    waiting: AtomicUsize,
    /// One per frame in the server (`total + max_waiting`). Tokio's semaphore hands a freed
    /// place to the longest waiter first, so no one overtakes the line.
    places: Arc<Semaphore>,
    /// The places there are: those not available are the frames admitted.
    all_places: usize,
    line: Line,
    in_line: AtomicUsize,
    /// Frames admitted since the gate was made.
    ever: AtomicU64,
}

/// A frame's place in the server, from before its body is read to its response.
pub struct Ticket {
    admission: Arc<Admission>,
    /// `None` once [`Ticket::drop`] has given it back.
    place: Option<OwnedSemaphorePermit>,
}

impl Drop for Ticket {
    fn drop(&mut self) {
        drop(self.place.take());
        metrics::gauge!("posefuse_frames_admitted").set(self.admission.admitted() as f64);
    }
}

/// Held while a frame is being decoded and pre-processed.
pub struct Permit {
    _permit: Option<OwnedSemaphorePermit>,
    admission: Option<Arc<Admission>>,
}

impl Drop for Permit {
    fn drop(&mut self) {
        if let Some(a) = &self.admission {
            a.publish();
        }
    }
}

impl Admission {
    /// `permits` frames pre-processed at once (at least 1), `max_waiting` more may wait; no
    /// waiting line before admission.
    pub fn new(permits: usize, max_waiting: usize) -> Arc<Admission> {
        Admission::with_line(permits, max_waiting, Line::OFF)
    }

    /// As [`Admission::new`], with `line` in front of [`Admission::admit_in_line`].
    pub fn with_line(permits: usize, max_waiting: usize, line: Line) -> Arc<Admission> {
        let permits = permits.clamp(1, Semaphore::MAX_PERMITS);
        let places = permits.saturating_add(max_waiting).min(Semaphore::MAX_PERMITS);
        Arc::new(Admission {
            permits: Arc::new(Semaphore::new(permits)),
            total: permits,
            waiting: AtomicUsize::new(0),
            places: Arc::new(Semaphore::new(places)),
            all_places: places,
            line,
            in_line: AtomicUsize::new(0),
            ever: AtomicU64::new(0),
        })
    }

    /// No bound (command-line tools that run one frame at a time).
    pub fn unbounded() -> Arc<Admission> {
        Admission::new(Semaphore::MAX_PERMITS, usize::MAX / 2)
    }

    /// Admits one frame, or refuses it at once when `permits + max_waiting` frames are in (or
    /// frames wait in the line for a place).
    pub fn admit(self: &Arc<Self>) -> Result<Ticket> {
        match self.places.clone().try_acquire_owned() {
            Ok(place) => Ok(self.ticket(place)),
            Err(_) => Err(self.refuse()),
        }
    }

    /// Admits one frame, waiting in the line for a place when the server is full and the line
    /// is on and not full; refused when it is off or full, or when the wait is over. Dropping
    /// the future leaves the line.
    pub async fn admit_in_line(self: &Arc<Self>) -> Result<Ticket> {
        if let Ok(place) = self.places.clone().try_acquire_owned() {
            return Ok(self.ticket(place));
        }
        let (max, wait) = (self.line.max, self.line.wait);
        if wait.is_zero()
            || self.in_line.fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| (n < max).then_some(n + 1)).is_err()
        {
            return Err(self.refuse());
        }
        struct Leave<'a>(&'a Admission);
        impl Drop for Leave<'_> {
            fn drop(&mut self) {
                self.0.in_line.fetch_sub(1, Ordering::AcqRel);
                metrics::gauge!("posefuse_admission_line").set(self.0.in_line() as f64);
            }
        }
        metrics::gauge!("posefuse_admission_line").set(self.in_line() as f64);
        let leave = Leave(self);
        // A span only for frames that wait, so that a trace shows the wait and the way in costs nothing.
        let place = tokio::time::timeout(wait, self.places.clone().acquire_owned())
            .instrument(tracing::info_span!("admission_line"))
            .await;
        drop(leave);
        match place {
            Ok(Ok(place)) => Ok(self.ticket(place)),
            _ => Err(self.refuse()),
        }
    }

    fn ticket(self: &Arc<Self>, place: OwnedSemaphorePermit) -> Ticket {
        self.ever.fetch_add(1, Ordering::AcqRel);
        metrics::gauge!("posefuse_frames_admitted").set(self.admitted() as f64);
        Ticket { admission: self.clone(), place: Some(place) }
    }

    fn refuse(&self) -> Error {
        metrics::counter!("posefuse_admission_refused_total").increment(1);
        Error::Overloaded
    }

    /// Frames waiting in the line for a place now (their bodies not read).
    pub fn in_line(&self) -> usize {
        self.in_line.load(Ordering::Relaxed)
    }

    /// Frames admitted now.
    pub fn admitted(&self) -> usize {
        self.all_places - self.places.available_permits()
    }

    /// Frames admitted since the gate was made.
    pub fn admitted_ever(&self) -> u64 {
        self.ever.load(Ordering::Acquire)
    }

    /// Frames being pre-processed now.
    pub fn active(&self) -> usize {
        self.total - self.permits.available_permits()
    }

    /// Requests waiting for a permit now.
    pub fn waiting(&self) -> usize {
        self.waiting.load(Ordering::Relaxed)
    }

    fn publish(&self) {
        metrics::gauge!("posefuse_preprocess_in_flight").set(self.active() as f64);
        metrics::gauge!("posefuse_admission_waiting").set(self.waiting() as f64);
    }

    /// Takes a decode permit for an admitted frame, waiting for one if needed (admission
    /// bounds how many wait). Dropping the future leaves the line.
    pub async fn enter(self: &Arc<Self>, _admitted: &Ticket) -> Result<Permit> {
        if let Ok(p) = self.permits.clone().try_acquire_owned() {
            self.publish();
            return Ok(Permit { _permit: Some(p), admission: Some(self.clone()) });
        }
        self.waiting.fetch_add(1, Ordering::AcqRel);
        struct Leave<'a>(&'a Admission);
        impl Drop for Leave<'_> {
            fn drop(&mut self) {
                self.0.waiting.fetch_sub(1, Ordering::AcqRel);
                self.0.publish();
            }
        }
        let leave = Leave(self);
        self.publish();
        let permit = self.permits.clone().acquire_owned().await.map_err(|_| Error::Unavailable("shutting down".into()));
        drop(leave);
        Ok(Permit { _permit: Some(permit?), admission: Some(self.clone()) })
    }
}

/// Defaults chosen from the machine's cores (logged at start-up).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sizing {
    pub cores: usize,
    /// Inference worker threads.
    pub workers: usize,
    /// ONNX Runtime intra-op threads per session.
    pub intra_threads: usize,
    /// Frames decoded and pre-processed at once.
    pub decode_permits: usize,
    /// Requests that may wait for a decode permit.
    pub admission_queue: usize,
    /// Microseconds a worker waits to fill a batch.
    pub batch_wait_us: u64,
}

impl Sizing {
    /// Defaults for `cores` CPU cores: one inference worker per 4 cores, and at least two where
    /// there are two cores, with half of its share of the cores as intra-op threads (the other
    /// half decodes), one decode permit per core, a waiting line of 8 per permit, and a short
    /// batch wait on machines with more than one worker. Two workers on two cores: while one
    /// runs a batch the other can start the next, so a bundle whose networks cost as much as its
    /// decoding keeps both cores busy (the default bundle 0.6.0 serves 1.19× the frames/s at 16
    /// clients, 0.2.0's networks as many; BENCHMARKS.md, "Two inference workers on two cores").
    pub fn for_cores(cores: usize) -> Sizing {
        let cores = cores.max(1);
        let workers = cores.div_ceil(4).max(cores.min(2));
        let intra_threads = (cores / workers / 2).clamp(1, 4);
        Sizing {
            cores,
            workers,
            intra_threads,
            decode_permits: cores,
            admission_queue: 8 * cores,
            batch_wait_us: if workers > 1 { 200 } else { 0 },
        }
    }

    /// Defaults for this machine: its cores as [`std::thread::available_parallelism`] counts
    /// them. On Linux that is the CPU affinity mask capped by the cgroup's CPU quota (cgroup v2
    /// `cpu.max`, or v1 `cpu.cfs_quota_us` over `cpu.cfs_period_us`), rounded down and at least
    /// 1, so a container limited to 2 CPUs is sized for 2, one limited to 1.5 CPUs for 1, and one
    /// without a CPU limit for every core of its node (docs/OPERATIONS.md, "Sizing").
    pub fn detect() -> Sizing {
        Sizing::for_cores(std::thread::available_parallelism().map_or(1, |n| n.get()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn a_full_line_is_refused_at_once_and_a_freed_permit_admits_the_next() {
        let a = Admission::new(1, 1);
        let (t1, t2) = (a.admit().unwrap(), a.admit().unwrap());
        let t = std::time::Instant::now();
        assert!(matches!(a.admit(), Err(Error::Overloaded)));
        assert!(t.elapsed() < Duration::from_millis(50));
        let first = a.enter(&t1).await.unwrap();
        assert_eq!(a.active(), 1);
        let a2 = a.clone();
        let second = tokio::spawn(async move { a2.enter(&t2).await.map(|_| ()) });
        while a.waiting() == 0 {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        drop(first);
        second.await.unwrap().unwrap();
        assert_eq!((a.active(), a.waiting(), a.admitted()), (0, 0, 1));
        drop(t1);
        assert!(a.admit().is_ok());
    }

    #[tokio::test]
    async fn leaving_the_line_frees_its_place() {
        let a = Admission::new(1, 1);
        let (t1, t2) = (a.admit().unwrap(), a.admit().unwrap());
        let _held = a.enter(&t1).await.unwrap();
        let r = tokio::time::timeout(Duration::from_millis(20), a.enter(&t2)).await;
        assert!(r.is_err(), "waits while the permit is held");
        assert_eq!(a.waiting(), 0);
        drop(t2);
        assert_eq!(a.admitted(), 1);
    }

    async fn until(what: impl Fn() -> bool) {
        let t = std::time::Instant::now();
        while !what() {
            assert!(t.elapsed() < Duration::from_secs(5), "never happened");
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    }

    #[tokio::test]
    async fn the_line_admits_in_order_of_arrival_and_nobody_overtakes_it() {
        use futures::FutureExt;
        let a = Admission::with_line(1, 0, Line { wait: Duration::from_secs(10), max: 2 });
        let held = a.admit().unwrap();
        let in_line = |a: &Arc<Admission>| {
            let a = a.clone();
            tokio::spawn(async move { a.admit_in_line().await })
        };
        let first = in_line(&a);
        until(|| a.in_line() == 1).await;
        let second = in_line(&a);
        until(|| a.in_line() == 2).await;
        // the line is full: refused at once, and a frame that may not wait is refused too
        assert!(matches!(a.admit_in_line().now_or_never(), Some(Err(Error::Overloaded))));
        assert!(matches!(a.admit(), Err(Error::Overloaded)));
        drop(held);
        let first = first.await.unwrap().unwrap();
        assert_eq!((a.in_line(), a.admitted()), (1, 1));
        // a place freed while someone waits is theirs, not a newcomer's
        drop(first);
        until(|| a.in_line() == 0).await;
        assert!(matches!(a.admit(), Err(Error::Overloaded)));
        let second = second.await.unwrap().unwrap();
        assert_eq!(a.admitted(), 1);
        drop(second);
        assert!(a.admit().is_ok());
        assert_eq!(a.admitted_ever(), 4);
    }

    #[tokio::test]
    async fn a_wait_that_ends_is_a_refusal_and_leaves_no_trace() {
        use futures::FutureExt;
        let a = Admission::with_line(1, 1, Line { wait: Duration::from_millis(30), max: 4 });
        let (t1, _t2) = (a.admit().unwrap(), a.admit().unwrap());
        let t = std::time::Instant::now();
        assert!(matches!(a.admit_in_line().await, Err(Error::Overloaded)));
        assert!(t.elapsed() >= Duration::from_millis(30));
        assert_eq!(a.in_line(), 0);
        // leaving the line early (the caller went away) frees its place in it as well
        let mut left = Box::pin(a.admit_in_line());
        assert!((&mut left).now_or_never().is_none());
        assert_eq!(a.in_line(), 1);
        drop(left);
        assert_eq!(a.in_line(), 0);
        drop(t1);
        let _t3 = a.admit_in_line().now_or_never().unwrap().unwrap();
        assert_eq!(a.admitted(), 2);
    }

    /// The names of the spans made while it is set (this thread's default subscriber).
    struct SpanNames(Arc<std::sync::Mutex<Vec<&'static str>>>);

    impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for SpanNames {
        fn on_new_span(
            &self,
            attrs: &tracing::span::Attributes<'_>,
            _: &tracing::span::Id,
            _: tracing_subscriber::layer::Context<'_, S>,
        ) {
            self.0.lock().unwrap().push(attrs.metadata().name());
        }
    }

    #[tokio::test]
    async fn only_a_frame_that_waits_gets_a_span_for_its_wait() {
        use tracing_subscriber::layer::SubscriberExt;
        let names = Arc::new(std::sync::Mutex::new(Vec::new()));
        let _default = tracing::subscriber::set_default(tracing_subscriber::registry().with(SpanNames(names.clone())));
        let a = Admission::with_line(1, 0, Line { wait: Duration::from_millis(10), max: 1 });
        let held = a.admit_in_line().await.unwrap();
        assert!(names.lock().unwrap().is_empty(), "the way in: {:?}", names.lock().unwrap());
        assert!(matches!(a.admit_in_line().await, Err(Error::Overloaded)));
        assert_eq!(*names.lock().unwrap(), ["admission_line"]);
        drop(held);
    }

    #[tokio::test]
    async fn without_a_line_a_full_server_refuses_at_once() {
        use futures::FutureExt;
        for line in [Line::OFF, Line { wait: Duration::from_secs(1), max: 0 }, Line { wait: Duration::ZERO, max: 8 }] {
            let a = Admission::with_line(1, 0, line);
            let held = a.admit_in_line().now_or_never().unwrap().unwrap();
            assert!(matches!(a.admit_in_line().now_or_never(), Some(Err(Error::Overloaded))), "{line:?}");
            assert_eq!(a.in_line(), 0);
            drop(held);
        }
    }

    #[test]
    fn sizing_follows_the_cores() {
        let one = Sizing::for_cores(1);
        assert_eq!((one.workers, one.intra_threads, one.decode_permits, one.batch_wait_us), (1, 1, 1, 0));
        let two = Sizing::for_cores(2);
        assert_eq!((two.workers, two.intra_threads, two.decode_permits, two.batch_wait_us), (2, 1, 2, 200));
        let four = Sizing::for_cores(4);
        assert_eq!((four.workers, four.intra_threads, four.decode_permits), (2, 1, 4));
        let twelve = Sizing::for_cores(12);
        assert_eq!((twelve.workers, twelve.intra_threads), (3, 2));
        let sixteen = Sizing::for_cores(16);
        assert_eq!((sixteen.workers, sixteen.intra_threads, sixteen.decode_permits), (4, 2, 16));
        assert_eq!(Sizing::for_cores(0).cores, 1);
    }
}
