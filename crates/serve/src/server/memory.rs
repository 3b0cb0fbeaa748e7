//! Memory handed back after load. The server allocates through the system allocator (glibc's
//! malloc; docs/OPERATIONS.md, "Memory"). A burst leaves free chunks between live ones inside
//! malloc's heaps, and those pages stay resident until `malloc_trim` returns them: once the
//! server has had frames to answer and then admitted none for a whole look, with none left in
//! hand, it trims, once per quiet spell, off the async threads. Under load it never trims (a trim
//! takes every heap's lock in turn), and probes, metrics and other requests that carry no frame
//! neither count as work nor delay a trim.

use std::sync::Arc;
use std::time::Duration;

use crate::service::admission::Admission;

/// How often the server looks whether it has fallen quiet.
pub const LOOK_EVERY: Duration = Duration::from_secs(1);

/// What one look saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Look {
    /// Frames admitted since the server started.
    pub admitted_ever: u64,
    /// Frames admitted and not yet answered.
    pub in_hand: usize,
}

/// Whether to trim at look `now`: no frame in hand, none admitted since the look before
/// (`previous`), and some admitted since the last trim (`trimmed_at`, frames admitted then).
pub fn quiet_after_work(previous: Look, now: Look, trimmed_at: u64) -> bool {
    now.in_hand == 0 && now.admitted_ever == previous.admitted_ever && now.admitted_ever != trimmed_at
}

/// Returns the free pages of malloc's heaps to the OS; whether any were returned.
pub fn release_free_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: malloc_trim only walks malloc's own heaps under their locks.
        unsafe { libc::malloc_trim(0) == 1 }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

/// Looks every [`LOOK_EVERY`] and trims when [`quiet_after_work`] says so, until aborted.
pub fn trim_when_quiet(admission: Arc<Admission>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut previous = Look::default();
        let mut trimmed_at = 0;
        loop {
            tokio::time::sleep(LOOK_EVERY).await;
            let now = Look { admitted_ever: admission.admitted_ever(), in_hand: admission.admitted() };
            if quiet_after_work(previous, now, trimmed_at) {
                trimmed_at = now.admitted_ever;
                let released = tokio::task::spawn_blocking(release_free_memory).await.unwrap_or(false);
                metrics::counter!("posefuse_memory_trims_total").increment(1);
                tracing::debug!(released, "quiet after work: free heap pages returned to the OS");
            }
            previous = now;
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn look(admitted_ever: u64, in_hand: usize) -> Look {
        Look { admitted_ever, in_hand }
    }

    #[test]
    fn trims_once_per_quiet_spell_after_work_and_never_under_load() {
        // a quiet look after work: trim
        assert!(quiet_after_work(look(10, 0), look(10, 0), 0));
        // already trimmed since: not again
        assert!(!quiet_after_work(look(10, 0), look(10, 0), 10));
        // a frame still in hand, or one admitted since the look before: not yet
        assert!(!quiet_after_work(look(10, 1), look(10, 1), 0));
        assert!(!quiet_after_work(look(9, 0), look(10, 0), 0));
        // no frame ever admitted: nothing to give back
        assert!(!quiet_after_work(look(0, 0), look(0, 0), 0));
    }

    /// Resident set size of this process, bytes.
    fn rss() -> u64 {
        let statm = std::fs::read_to_string("/proc/self/statm").unwrap_or_default();
        let pages: u64 = statm.split_whitespace().nth(1).and_then(|v| v.parse().ok()).unwrap_or(0);
        pages * 4096
    }

    /// Test binaries allocate through the system allocator, as the server does. 256 MB in 64 KB
    /// blocks (below malloc's mmap threshold, so inside its heap), each followed by a small block
    /// that stays: freeing the large ones leaves holes the heap cannot shrink past, resident
    /// until trimmed.
    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn freed_holes_in_the_heap_leave_the_process_when_trimmed() {
        let worker = std::thread::spawn(|| {
            let mut kept = Vec::new();
            let mut large = Vec::new();
            for i in 0..4096 {
                large.push(vec![i as u8 | 1; 64 << 10]);
                kept.push(vec![i as u8; 64]);
            }
            let peak = rss();
            drop(std::hint::black_box(large));
            let freed = rss();
            let released = release_free_memory();
            let trimmed = rss();
            drop(std::hint::black_box(kept));
            (peak, freed, released, trimmed)
        });
        let (peak, freed, released, trimmed) = worker.join().unwrap();
        let mb = |b: u64| b as f64 / 1e6;
        assert!(freed > peak.saturating_sub(50 << 20), "freeing alone kept the holes: {} → {} MB", mb(peak), mb(freed));
        assert!(released, "malloc_trim returned nothing");
        assert!(trimmed + (200 << 20) < freed, "the trim returned the holes: {} → {} MB", mb(freed), mb(trimmed));
    }
}
