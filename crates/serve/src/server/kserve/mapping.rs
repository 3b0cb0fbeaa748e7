//! A read-only mapping of a shared-memory object that another process owns, read without the risk
//! that makes mappings dangerous: the owner may shrink the object at any time, and touching a
//! mapped page past its new end raises SIGBUS, which kills a process by default.
//!
//! Every read goes through [`Mapping::copy_rows`], which names the mapping it is about to read in
//! a thread-local before copying. A SIGBUS handler, installed once, looks at that range: a
//! fault inside it replaces the faulting page with a private page of zeros (the copy then runs to
//! its end), marks the read as failed and the mapping as poisoned; any other SIGBUS goes to the
//! handler that was there before. The same trick as Wayland compositors reading clients'
//! `wl_shm` buffers.
//!
//! Why a mapping at all: a crop reads its window's rectangle a row at a time, and one positioned
//! read (`pread`) per row cost a system call per row, 0.3 ms per shared-memory request
//! (docs/KSERVE.md, "System shared memory").
//!
//! The client is trusted not to write what it asked to be read until the response comes (the
//! protocol's contract); bytes it writes meanwhile may arrive torn, as with a positioned read.
//! The copy reads through raw pointers only: no Rust reference to the mapped bytes is ever made.

use std::fs::File;
use std::os::fd::AsRawFd;
use std::ptr::NonNull;
use std::sync::atomic::{compiler_fence, AtomicBool, AtomicUsize, Ordering};
use std::sync::OnceLock;

// Atomics, though no other thread touches them: the signal handler runs on this thread between
// any two instructions, and only atomics (with the fences below) are ordered against it.
thread_local! {
    /// The mapped addresses this thread is copying from now, `[start, end)`; empty otherwise.
    static READING: [AtomicUsize; 2] = const { [AtomicUsize::new(0), AtomicUsize::new(0)] };
    /// Whether a page of [`READING`] faulted (lay past the object's end).
    static FAULTED: AtomicBool = const { AtomicBool::new(false) };
}

/// The SIGBUS action found before ours, restored for faults that are not reads of a mapping.
/// Or the error code of a failed installation, which leaves every later mapping refused.
static PREVIOUS: OnceLock<Result<libc::sigaction, i32>> = OnceLock::new();
static PAGE: OnceLock<usize> = OnceLock::new();

/// A read touched a page past the end of the object (it shrank), now or in an earlier read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PastTheEnd;

/// `len` bytes of an object from `offset`, mapped read-only and shared.
#[derive(Debug)]
pub struct Mapping {
    /// The page-aligned start of the mapping.
    base: NonNull<u8>,
    /// Bytes mapped from `base`.
    mapped: usize,
    /// Where byte 0 of the region lies from `base`.
    lead: usize,
    len: usize,
    /// A page of it was replaced by zeros after a fault: it no longer shows the object.
    poisoned: AtomicBool,
}

// SAFETY: the mapping is read-only and only read through raw pointers by `copy_rows`; unmapping
// happens once, in `drop`, when no thread holds it any more.
unsafe impl Send for Mapping {}
// SAFETY: as above; the poisoned flag is atomic.
unsafe impl Sync for Mapping {}

impl Mapping {
    /// Maps `len` (> 0) bytes of `file` from `offset`.
    pub fn new(file: &File, offset: u64, len: u64) -> std::io::Result<Mapping> {
        install_handler()?;
        let page = page_size();
        let lead = usize::try_from(offset % page as u64).map_err(|_| too_large())?;
        let start = offset - lead as u64;
        let len = usize::try_from(len).map_err(|_| too_large())?;
        let mapped = lead.checked_add(len).filter(|&m| m > 0).ok_or_else(too_large)?;
        let start = libc::off_t::try_from(start).map_err(|_| too_large())?;
        // SAFETY: a new read-only shared mapping of a file we hold open; the kernel picks the
        // address, and the result is checked.
        let p = unsafe {
            libc::mmap(std::ptr::null_mut(), mapped, libc::PROT_READ, libc::MAP_SHARED, file.as_raw_fd(), start)
        };
        if p == libc::MAP_FAILED {
            return Err(std::io::Error::last_os_error());
        }
        let base = NonNull::new(p.cast::<u8>()).ok_or_else(|| std::io::Error::other("mmap returned null"))?;
        Ok(Mapping { base, mapped, lead, len, poisoned: AtomicBool::new(false) })
    }

    /// Copies `out.len() / row` rows of `row` bytes, the first at byte `first` of the mapping and
    /// each `stride` bytes after the one before, into `out` (rows back to back). Callers check the
    /// bounds; a row outside the mapping is refused with a panic-free `Err` as well.
    pub fn copy_rows(&self, first: usize, stride: usize, row: usize, out: &mut [u8]) -> Result<(), PastTheEnd> {
        let rows = out.len().checked_div(row).unwrap_or(0);
        if rows == 0 {
            return self.intact();
        }
        let last_end =
            (rows - 1).checked_mul(stride).and_then(|s| s.checked_add(first)).and_then(|s| s.checked_add(row));
        if out.len() != rows * row || last_end.is_none_or(|e| e > self.len) {
            return Err(PastTheEnd);
        }
        self.intact()?;
        // SAFETY: `first..last_end` lies inside the mapping (checked above), which lives as long
        // as `self`; `out` is ours and does not overlap it.
        let src = unsafe { self.base.as_ptr().add(self.lead + first) };
        // A fault anywhere in this mapping during the copy is this copy's.
        let base = self.base.as_ptr() as usize;
        set_reading((base, base + self.mapped));
        FAULTED.with(|f| f.store(false, Ordering::Relaxed));
        // The handler is invisible to the compiler: the fences keep the range set and the flag
        // read on their sides of the copy.
        compiler_fence(Ordering::SeqCst);
        for (i, dst) in out.chunks_exact_mut(row).enumerate() {
            // SAFETY: as above; each row lies inside `first..last_end`.
            unsafe { std::ptr::copy_nonoverlapping(src.add(i * stride), dst.as_mut_ptr(), row) };
        }
        compiler_fence(Ordering::SeqCst);
        set_reading((0, 0));
        if FAULTED.with(|f| f.swap(false, Ordering::Relaxed)) {
            self.poisoned.store(true, Ordering::Relaxed);
        }
        self.intact()
    }

    fn intact(&self) -> Result<(), PastTheEnd> {
        if self.poisoned.load(Ordering::Relaxed) {
            Err(PastTheEnd)
        } else {
            Ok(())
        }
    }
}

impl Drop for Mapping {
    fn drop(&mut self) {
        // SAFETY: the mapping made in `new` (pages a fault replaced included), unmapped once.
        unsafe { libc::munmap(self.base.as_ptr().cast(), self.mapped) };
    }
}

fn set_reading((start, end): (usize, usize)) {
    READING.with(|r| {
        r[0].store(start, Ordering::Relaxed);
        r[1].store(end, Ordering::Relaxed);
    });
}

fn too_large() -> std::io::Error {
    std::io::Error::other("the region is too large to map")
}

fn page_size() -> usize {
    // SAFETY: sysconf has no preconditions.
    *PAGE.get_or_init(|| usize::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }).unwrap_or(4096).max(1))
}

fn install_handler() -> std::io::Result<()> {
    page_size();
    // One installation: the lock makes a second thread wait for the first.
    let installed = PREVIOUS.get_or_init(|| {
        // SAFETY: a zeroed sigaction is a valid value; the handler is async-signal-safe (it reads
        // thread-locals without destructors, calls mmap or sigaction, and sets a flag).
        unsafe {
            let mut ours: libc::sigaction = std::mem::zeroed();
            ours.sa_sigaction = on_sigbus as *const () as usize;
            ours.sa_flags = libc::SA_SIGINFO | libc::SA_ONSTACK;
            libc::sigemptyset(&mut ours.sa_mask);
            let mut previous: libc::sigaction = std::mem::zeroed();
            if libc::sigaction(libc::SIGBUS, &ours, &mut previous) == 0 {
                Ok(previous)
            } else {
                Err(std::io::Error::last_os_error().raw_os_error().unwrap_or(0))
            }
        }
    });
    match installed {
        Ok(_) => Ok(()),
        Err(code) => Err(std::io::Error::from_raw_os_error(*code)),
    }
}

extern "C" fn on_sigbus(sig: libc::c_int, info: *mut libc::siginfo_t, _ctx: *mut libc::c_void) {
    // SAFETY: the kernel passes a valid siginfo for a SA_SIGINFO handler.
    let addr = unsafe { (*info).si_addr() } as usize;
    let (start, end) = READING.with(|r| (r[0].load(Ordering::Relaxed), r[1].load(Ordering::Relaxed)));
    if (start..end).contains(&addr) {
        let page = PAGE.get().copied().unwrap_or(4096);
        let at = addr & !(page - 1);
        // SAFETY: replaces one page of our own read-only mapping (the fault lies inside the range
        // `copy_rows` named) with private zeros, so that the interrupted copy can go on.
        let p = unsafe {
            libc::mmap(
                at as *mut libc::c_void,
                page,
                libc::PROT_READ,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS | libc::MAP_FIXED,
                -1,
                0,
            )
        };
        if p != libc::MAP_FAILED {
            FAULTED.with(|f| f.store(true, Ordering::Relaxed));
            return;
        }
    }
    // Not a read of ours: the previous action takes the fault when the instruction runs again.
    if let Some(Ok(previous)) = PREVIOUS.get() {
        // SAFETY: restores an action the kernel gave us.
        unsafe { libc::sigaction(sig, previous, std::ptr::null_mut()) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn object(bytes: &[u8]) -> (tempfile::NamedTempFile, File) {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(bytes).unwrap();
        let file = File::open(f.path()).unwrap();
        (f, file)
    }

    fn rows(m: &Mapping, first: usize, stride: usize, row: usize, n: usize) -> Result<Vec<u8>, PastTheEnd> {
        let mut out = vec![0xAA; row * n];
        m.copy_rows(first, stride, row, &mut out).map(|()| out)
    }

    #[test]
    fn rows_are_copied_from_their_places_at_any_offset() {
        let bytes: Vec<u8> = (0..=255).cycle().take(3 * 4096 + 100).collect();
        let (_keep, file) = object(&bytes);
        for offset in [0usize, 1, 4095, 4096, 5000] {
            let m = Mapping::new(&file, offset as u64, (bytes.len() - offset) as u64).unwrap();
            let got = rows(&m, 7, 2000, 5, 3).unwrap();
            let want: Vec<u8> = (0..3).flat_map(|i| bytes[offset + 7 + i * 2000..][..5].to_vec()).collect();
            assert_eq!(got, want, "offset {offset}");
            assert_eq!(rows(&m, 0, 0, 0, 0).unwrap(), Vec::<u8>::new());
            let whole = rows(&m, 0, 1, bytes.len() - offset, 1).unwrap();
            assert_eq!(whole, bytes[offset..]);
        }
    }

    #[test]
    fn rows_outside_the_mapping_or_of_the_wrong_size_are_refused() {
        let (_keep, file) = object(&[1; 64]);
        let m = Mapping::new(&file, 8, 32).unwrap();
        assert_eq!(rows(&m, 28, 0, 4, 1).unwrap(), vec![1; 4]);
        assert_eq!(rows(&m, 29, 0, 4, 1), Err(PastTheEnd), "one byte past the end");
        assert_eq!(rows(&m, 0, 16, 4, 3), Err(PastTheEnd), "the third row starts past the end");
        assert_eq!(rows(&m, usize::MAX, 1, 4, 2), Err(PastTheEnd), "overflow");
        let mut odd = [0u8; 5];
        assert_eq!(m.copy_rows(0, 4, 4, &mut odd), Err(PastTheEnd), "not whole rows");
        assert!(Mapping::new(&file, 0, 0).is_err(), "nothing to map");
    }

    #[test]
    fn a_dropped_mapping_is_unmapped() {
        let (keep, file) = object(&[3; 64]);
        let mapped = || {
            let maps = std::fs::read_to_string("/proc/self/maps").unwrap();
            maps.lines().filter(|l| l.ends_with(keep.path().to_str().unwrap())).count()
        };
        let m = Mapping::new(&file, 0, 64).unwrap();
        assert_eq!(mapped(), 1);
        drop(m);
        assert_eq!(mapped(), 0, "a region unregistered and answered leaves no mapping behind");
    }

    /// Set in the child process of the test below, to the directory it makes its object in.
    const CHILD: &str = "POSEFUSE_TEST_SIGBUS_DIR";

    #[test]
    fn a_fault_outside_a_read_is_left_to_the_previous_action() {
        let page = page_size();
        if let Some(dir) = std::env::var_os(CHILD) {
            let path = std::path::Path::new(&dir).join("obj");
            std::fs::write(&path, vec![7u8; 2 * page]).unwrap();
            let m = Mapping::new(&File::open(&path).unwrap(), 0, 2 * page as u64).unwrap();
            assert_eq!(rows(&m, 0, 0, 1, 1).unwrap(), vec![7], "the handler is installed");
            File::options().write(true).open(&path).unwrap().set_len(0).unwrap();
            // SAFETY: deliberately touches a mapped page past the object's end, outside a read.
            let v = unsafe { std::ptr::read_volatile(m.base.as_ptr().add(page)) };
            panic!("read {v} past the end without a fault");
        }
        let dir = tempfile::tempdir().unwrap();
        let name = format!("{}::a_fault_outside_a_read_is_left_to_the_previous_action", module_path!());
        let name = name.split_once("::").map_or(name.as_str(), |(_, rest)| rest);
        let out = std::process::Command::new(std::env::current_exe().unwrap())
            .args(["--exact", name, "--test-threads", "1"])
            .env(CHILD, dir.path())
            .output()
            .unwrap();
        use std::os::unix::process::ExitStatusExt;
        assert_eq!(out.status.signal(), Some(libc::SIGBUS), "{out:?}");
    }

    #[test]
    fn a_shrunk_object_faults_into_an_error_not_a_crash_and_stays_refused() {
        let page = page_size();
        let (keep, file) = object(&vec![7u8; 4 * page]);
        let m = Mapping::new(&file, 0, 4 * page as u64).unwrap();
        assert_eq!(rows(&m, page, 0, 16, 1).unwrap(), vec![7; 16], "touched before the shrink");
        File::options().write(true).open(keep.path()).unwrap().set_len(page as u64).unwrap();
        assert_eq!(rows(&m, 0, 0, 16, 1).unwrap(), vec![7; 16], "the page still inside the object");
        assert_eq!(rows(&m, 0, page, 8, 4), Err(PastTheEnd), "rows 2 to 4 lie past the new end");
        assert_eq!(rows(&m, 0, 0, 16, 1), Err(PastTheEnd), "poisoned: a page shows zeros now");
        let other = Mapping::new(&file, 0, page as u64).unwrap();
        assert_eq!(rows(&other, 0, 0, 16, 1).unwrap(), vec![7; 16], "a fresh mapping reads again");
    }
}
