//! How long this machine takes to wake a thread that has slept, by how long it slept: the part of
//! a request's latency that is neither posefuse's work nor ONNX Runtime's. A request crosses
//! threads where it waits: the async task that holds it sleeps while the inference worker runs
//! the networks, and is woken by the worker's answer; the client sleeps until the response comes.
//! On a virtual machine whose idle vCPUs the host deschedules, a wake after a long sleep costs
//! far more than one after a short sleep (BENCHMARKS.md, "Where one shared-memory request's time
//! goes, and what a wake costs").
//!
//! `cargo bench --bench wake` prints the p50 and p90 wake latency per sleep; under `cargo test`
//! it runs a few rounds only.

use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Busy for `d`, as an inference worker is while the waiting thread sleeps.
fn busy(d: Duration) {
    let t = Instant::now();
    while t.elapsed() < d {
        std::hint::spin_loop();
    }
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// A thread blocked on a channel, woken by a send after it slept `sleep`: microseconds from the
/// send to the woken thread running, once per round.
fn thread_wakes(sleep: Duration, rounds: usize) -> Vec<f64> {
    let (tx, rx) = mpsc::channel::<Instant>();
    let woken = std::thread::spawn(move || rx.iter().map(|sent| sent.elapsed().as_secs_f64() * 1e6).collect());
    for _ in 0..rounds {
        busy(sleep);
        if tx.send(Instant::now()).is_err() {
            break;
        }
    }
    drop(tx);
    woken.join().unwrap_or_default()
}

/// The server's case: an async task awaiting a worker thread's answer (a oneshot), woken after
/// it slept `sleep`.
fn task_wakes(sleep: Duration, rounds: usize) -> Vec<f64> {
    let Ok(rt) = tokio::runtime::Builder::new_multi_thread().enable_all().build() else {
        return Vec::new();
    };
    let (jobs, queue) = mpsc::channel::<tokio::sync::oneshot::Sender<Instant>>();
    let worker = std::thread::spawn(move || {
        for reply in queue {
            busy(sleep);
            let _ = reply.send(Instant::now());
        }
    });
    let waits = rt.block_on(async move {
        let task = tokio::spawn(async move {
            let mut waits = Vec::with_capacity(rounds);
            for _ in 0..rounds {
                let (reply, answer) = tokio::sync::oneshot::channel();
                if jobs.send(reply).is_err() {
                    break;
                }
                if let Ok(sent) = answer.await {
                    waits.push(sent.elapsed().as_secs_f64() * 1e6);
                }
            }
            waits
        });
        task.await.unwrap_or_default()
    });
    let _ = worker.join();
    waits
}

fn main() {
    let bench = std::env::args().any(|a| a == "--bench");
    let rounds = if bench { 400 } else { 5 };
    println!("| sleep µs | thread woken: p50 µs | p90 µs | async task woken: p50 µs | p90 µs |");
    println!("|---|---|---|---|---|");
    for sleep_us in [50u64, 200, 400, 800, 1600, 3200] {
        let sleep = Duration::from_micros(sleep_us);
        let (mut thread, mut task) = (thread_wakes(sleep, rounds), task_wakes(sleep, rounds));
        assert!(!thread.is_empty() && !task.is_empty(), "every round wakes its thread");
        println!(
            "| {sleep_us} | {:.1} | {:.1} | {:.1} | {:.1} |",
            percentile(&mut thread, 0.5),
            percentile(&mut thread, 0.9),
            percentile(&mut task, 0.5),
            percentile(&mut task, 0.9)
        );
    }
}
