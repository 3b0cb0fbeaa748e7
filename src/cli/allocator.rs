//! The server's allocator: mimalloc, told to hand freed memory back to the OS at once.
//!
//! Requests allocate crops, decoded images and tensors of a few hundred KB to a few MB; the system
//! allocator maps and unmaps them each time (a page fault per 4 KB), mimalloc keeps them for reuse.
//! Its default purge delay (1 s in the bundled v3) is only acted on by later allocator calls of
//! the thread that freed the memory, so after a burst the idle workers keep what the burst needed for as long as
//! they stay idle (744 MB 30 s after a 256-client overload, docs/OPERATIONS.md, "Memory").

/// `mi_option_purge_delay`'s place in mimalloc's `mi_option_e` (the bundled v3 `mimalloc.h`;
/// `options.c` gives its default, 1000): milliseconds before freed memory is purged; 0 purges at
/// once.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Purge freed memory at once instead of after the default delay, unless the environment sets
/// the delay itself (`MIMALLOC_PURGE_DELAY`, docs/OPERATIONS.md).
pub fn purge_freed_memory_at_once() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
        return;
    }
    // SAFETY: mi_option_set stores one integer; mimalloc reads it on its next purge decision.
    unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, 0) }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Resident set size of this process, bytes.
    fn rss() -> u64 {
        let statm = std::fs::read_to_string("/proc/self/statm").unwrap_or_default();
        let pages: u64 = statm.split_whitespace().nth(1).and_then(|v| v.parse().ok()).unwrap_or(0);
        pages * 4096
    }

    /// The binary's global allocator is mimalloc (src/main.rs), so this test allocates through it:
    /// 256 MB in 256 KB blocks, freed by a thread that then waits, alive and allocating nothing, as
    /// an idle worker does. Only when the option above really is the purge delay does the memory
    /// leave the process.
    #[test]
    #[cfg(target_os = "linux")]
    fn freed_memory_leaves_the_process_without_further_allocation() {
        assert_eq!(unsafe { libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY) }, 1000, "mimalloc's default");
        purge_freed_memory_at_once();
        let before = rss();
        let (freed_tx, freed_rx) = std::sync::mpsc::channel();
        let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
        let worker = std::thread::spawn(move || {
            let blocks: Vec<Vec<u8>> = (0..1024).map(|i| vec![i as u8 | 1; 256 << 10]).collect();
            let peak = rss();
            drop(std::hint::black_box(blocks));
            let _ = freed_tx.send(peak);
            let _ = done_rx.recv();
        });
        let peak = freed_rx.recv().unwrap_or(0);
        std::thread::sleep(std::time::Duration::from_millis(300));
        let after = rss();
        let _ = done_tx.send(());
        let _ = worker.join();
        let mb = |b: u64| b as f64 / 1e6;
        assert!(peak > before + (200 << 20), "the blocks were resident: {} → {} MB", mb(before), mb(peak));
        assert!(after < before + (64 << 20), "freed memory stayed: {} → {} → {} MB", mb(before), mb(peak), mb(after));
    }
}
