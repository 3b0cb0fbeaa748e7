//! KServe's system shared-memory extension (docs/KSERVE.md, "System shared memory"): a client on
//! the same host registers a POSIX shared-memory object (its `shm_open` key, e.g. `/cam0`) as a
//! named region, then names a region, offset and size in an input's or output's parameters
//! instead of sending the bytes through the socket. [`SystemSharedMemory`] is the one owner of
//! the registered regions; it is off unless the server is started with `--system-shared-memory`,
//! since a registration makes the server read and write an object the client names.
//!
//! Inputs are read through a read-only mapping of the object (`mapping`), outputs written with
//! positioned writes (`pwrite`). The client owns the object and may write it, shrink it or unlink
//! it while it is registered: a read that touches a page past a shrunk object's end faults into
//! an error rather than a crash (`mapping` says how), a read whose bytes lie past the object's
//! end now is a 400 naming the tensor, and writes never grow the object. The object is opened and
//! mapped at registration and held until unregistration, so an unlinked key stays readable, and a
//! request that resolved its regions keeps them until it answers (unregistering a region in use
//! is safe).

use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::os::unix::fs::{FileExt, OpenOptionsExt};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};

use super::mapping::Mapping;
use posefuse_core::error::{Error, Result};

/// Where POSIX shared-memory objects live on Linux (`shm_open("/k")` is `/dev/shm/k`).
pub const SHM_DIR: &str = "/dev/shm";
/// Default for `--shared-memory-regions`.
pub const MAX_REGIONS: usize = 64;

/// How the extension is configured at start-up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SharedMemoryConfig {
    /// Whether clients may register regions at all.
    pub enabled: bool,
    /// The directory keys are confined to.
    pub dir: PathBuf,
    /// Regions registered at once.
    pub max_regions: usize,
}

impl Default for SharedMemoryConfig {
    fn default() -> Self {
        SharedMemoryConfig { enabled: false, dir: PathBuf::from(SHM_DIR), max_regions: MAX_REGIONS }
    }
}

/// A registered region as status reports it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RegionStatus {
    pub name: String,
    pub key: String,
    pub offset: u64,
    pub byte_size: u64,
}

/// One registered region: `byte_size` bytes from `offset` of the object `key`.
#[derive(Debug)]
pub struct Region {
    status: RegionStatus,
    file: File,
    map: Mapping,
    writable: bool,
}

/// Where a tensor lies in a region: the `shared_memory_region`, `shared_memory_byte_size` and
/// `shared_memory_offset` parameters of an input or a requested output.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShmRef {
    pub region: String,
    pub byte_size: u64,
    pub offset: u64,
}

/// The registered regions.
#[derive(Debug, Default)]
pub struct SystemSharedMemory {
    config: SharedMemoryConfig,
    regions: Mutex<BTreeMap<String, Arc<Region>>>,
}

impl SystemSharedMemory {
    pub fn new(config: SharedMemoryConfig) -> Self {
        SystemSharedMemory { config, regions: Mutex::new(BTreeMap::new()) }
    }

    /// Whether clients may register regions.
    pub fn enabled(&self) -> bool {
        self.config.enabled
    }

    fn check_enabled(&self) -> Result<()> {
        if self.config.enabled {
            Ok(())
        } else {
            Err(Error::Forbidden(
                "system shared memory is off; start the server with --system-shared-memory (docs/KSERVE.md)".into(),
            ))
        }
    }

    fn regions(&self) -> MutexGuard<'_, BTreeMap<String, Arc<Region>>> {
        // A panic while holding the lock leaves the map itself whole, so its contents stay usable.
        self.regions.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Registers `byte_size` bytes from `offset` of the object `key` as region `name`. The
    /// object is opened now (read-write when allowed) and must already hold the whole region.
    pub fn register(&self, name: &str, key: &str, offset: u64, byte_size: u64) -> Result<()> {
        self.check_enabled()?;
        if name.is_empty() {
            return Err(Error::field("name", "a region needs a name"));
        }
        if byte_size == 0 {
            return Err(Error::field("byte_size", "must be positive"));
        }
        let end =
            offset.checked_add(byte_size).ok_or_else(|| Error::field("offset", "offset + byte_size overflows"))?;
        let path = self.config.dir.join(object_name(key)?);
        if self.regions().contains_key(name) {
            return Err(Error::field("name", format!("region `{name}` is already registered; unregister it first")));
        }
        let (file, writable) = open_object(&path, key)?;
        let len = file.metadata().map_err(|e| Error::field("key", format!("`{key}`: {e}")))?.len();
        if end > len {
            return Err(Error::field(
                "byte_size",
                format!("offset {offset} + byte_size {byte_size} runs past the end of `{key}` ({len} bytes)"),
            ));
        }
        let status = RegionStatus { name: name.into(), key: key.into(), offset, byte_size };
        let region = Region::new(status, file, writable)?;
        let mut regions = self.regions();
        if regions.contains_key(name) {
            return Err(Error::field("name", format!("region `{name}` is already registered; unregister it first")));
        }
        if regions.len() >= self.config.max_regions {
            return Err(Error::field(
                "name",
                format!(
                    "{} regions are registered, the most --shared-memory-regions allows; unregister one first",
                    regions.len()
                ),
            ));
        }
        regions.insert(name.into(), Arc::new(region));
        Ok(())
    }

    /// Unregisters region `name`, or every region when `name` is empty. A name that is not
    /// registered is not an error (as Triton). Requests that already hold the region finish.
    pub fn unregister(&self, name: &str) -> Result<()> {
        self.check_enabled()?;
        let mut regions = self.regions();
        if name.is_empty() {
            regions.clear();
        } else {
            regions.remove(name);
        }
        Ok(())
    }

    /// The status of region `name`, or of every region when `name` is empty.
    pub fn status(&self, name: &str) -> Result<Vec<RegionStatus>> {
        self.check_enabled()?;
        let regions = self.regions();
        if name.is_empty() {
            return Ok(regions.values().map(|r| r.status.clone()).collect());
        }
        regions
            .get(name)
            .map(|r| vec![r.status.clone()])
            .ok_or_else(|| Error::NotFound(format!("system shared memory region `{name}` is not registered")))
    }

    /// The region a tensor names, held for the request (`tensor` names it in errors).
    pub fn region(&self, tensor: &str, at: &ShmRef) -> Result<Arc<Region>> {
        self.check_enabled()?;
        self.regions()
            .get(&at.region)
            .cloned()
            .ok_or_else(|| Error::field(tensor, format!("shared memory region `{}` is not registered", at.region)))
    }
}

impl Region {
    fn new(status: RegionStatus, file: File, writable: bool) -> Result<Region> {
        let map = Mapping::new(&file, status.offset, status.byte_size)
            .map_err(|e| Error::field("key", format!("`{}` cannot be mapped: {e}", status.key)))?;
        Ok(Region { status, file, map, writable })
    }

    /// Where `at` lies in the object, checked against the region's bounds.
    fn span(&self, tensor: &str, at: &ShmRef) -> Result<u64> {
        let end = at.offset.checked_add(at.byte_size);
        if end.is_none_or(|e| e > self.status.byte_size) {
            return Err(Error::field(
                tensor,
                format!(
                    "shared_memory_offset {} + shared_memory_byte_size {} runs past region `{}` ({} bytes)",
                    at.offset, at.byte_size, self.status.name, self.status.byte_size
                ),
            ));
        }
        Ok(self.status.offset + at.offset)
    }

    /// Whether `at` lies in the region (`tensor` names it in the error).
    pub fn check_span(&self, tensor: &str, at: &ShmRef) -> Result<()> {
        self.span(tensor, at).map(|_| ())
    }

    /// The `at.byte_size` bytes at `at` (the caller bounds the size first).
    pub fn read(&self, tensor: &str, at: &ShmRef) -> Result<Vec<u8>> {
        let len =
            usize::try_from(at.byte_size).map_err(|_| Error::field(tensor, "shared_memory_byte_size is too large"))?;
        let mut buf = vec![0u8; len];
        self.read_into(tensor, at.offset, &mut buf)?;
        Ok(buf)
    }

    /// Fills `buf` from `offset` bytes into the region.
    pub fn read_into(&self, tensor: &str, offset: u64, buf: &mut [u8]) -> Result<()> {
        self.read_rows(tensor, offset, 0, buf.len(), buf)
    }

    /// Fills `out` with rows of `row` bytes, the first `offset` bytes into the region and each
    /// `stride` bytes after the one before (an image's rectangle: one copy per row, no system
    /// call but the check that the object still holds them).
    pub fn read_rows(&self, tensor: &str, offset: u64, stride: u64, row: usize, out: &mut [u8]) -> Result<()> {
        if row == 0 && !out.is_empty() || row != 0 && !out.len().is_multiple_of(row) {
            return Err(Error::Runtime(format!("{} bytes asked for in rows of {row}", out.len())));
        }
        let rows = out.len().checked_div(row).unwrap_or(0) as u64;
        let last = rows.saturating_sub(1).checked_mul(stride).and_then(|s| s.checked_add(offset));
        let span = last.and_then(|l| l.checked_add(row as u64)).map(|end| end.saturating_sub(offset));
        let at = ShmRef { region: String::new(), byte_size: span.unwrap_or(u64::MAX), offset };
        let end = self.span(tensor, &at)? + at.byte_size;
        let (first, stride) = (usize::try_from(offset), usize::try_from(stride));
        let (Ok(first), Ok(stride)) = (first, stride) else {
            return Err(Error::field(tensor, "shared_memory_offset is too large"));
        };
        if self.map.copy_rows(first, stride, row, out).is_err() {
            // The mapping shows zeros where the object was cut: nothing read through it is right.
            return Err(Error::field(
                tensor,
                format!(
                    "shared memory object `{}` shrank while region `{}` was registered; unregister and register it again",
                    self.status.key, self.status.name
                ),
            ));
        }
        let len = self.file.metadata().map_err(|e| self.io_error(e))?.len();
        if len < end {
            return Err(self.shrunk(tensor, len));
        }
        Ok(())
    }

    /// Writes `bytes` at `at` (which must have room for them); never past the object's end.
    pub fn write(&self, tensor: &str, at: &ShmRef, bytes: &[u8]) -> Result<()> {
        let start = self.span(tensor, at)?;
        if bytes.len() as u64 > at.byte_size {
            return Err(Error::field(
                tensor,
                format!("is {} bytes but shared_memory_byte_size is {}", bytes.len(), at.byte_size),
            ));
        }
        if !self.writable {
            return Err(Error::field(
                tensor,
                format!(
                    "shared memory region `{}` was registered read-only (the server may not write `{}`)",
                    self.status.name, self.status.key
                ),
            ));
        }
        let len = self.file.metadata().map_err(|e| self.io_error(e))?.len();
        if start + bytes.len() as u64 > len {
            return Err(self.shrunk(tensor, len));
        }
        self.file.write_all_at(bytes, start).map_err(|e| self.io_error(e))
    }

    fn shrunk(&self, tensor: &str, len: u64) -> Error {
        Error::field(
            tensor,
            format!(
                "shared memory object `{}` shrank to {len} bytes after region `{}` was registered",
                self.status.key, self.status.name
            ),
        )
    }

    fn io_error(&self, e: std::io::Error) -> Error {
        Error::Io(format!("shared memory region `{}`: {e}", self.status.name))
    }
}

/// The object's file name for a `shm_open` key: `/name` (or `name`), one path component of
/// letters, digits, `.`, `_` and `-`, so that a key can only name an object in the shared-memory
/// directory.
pub fn object_name(key: &str) -> Result<&str> {
    let name = key.strip_prefix('/').unwrap_or(key);
    let ok = !name.is_empty()
        && name.len() <= 255
        && name != "."
        && name != ".."
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'));
    if ok {
        Ok(name)
    } else {
        Err(Error::field(
            "key",
            format!("`{key}` is not a shared memory key: expected `/name`, the name letters, digits, `.`, `_` or `-`"),
        ))
    }
}

/// Opens the object read-write, else read-only; never through a symbolic link, and only a
/// regular file.
fn open_object(path: &std::path::Path, key: &str) -> Result<(File, bool)> {
    let open = |write: bool| OpenOptions::new().read(true).write(write).custom_flags(libc::O_NOFOLLOW).open(path);
    let (file, writable) = match open(true) {
        Ok(f) => (f, true),
        Err(e) if read_only_will_do(e.kind()) => (open(false).map_err(|e| open_error(key, &e))?, false),
        Err(e) => return Err(open_error(key, &e)),
    };
    let meta = file.metadata().map_err(|e| open_error(key, &e))?;
    if !meta.is_file() {
        return Err(Error::field("key", format!("`{key}` is not a shared memory object")));
    }
    Ok((file, writable))
}

/// Whether an object the server may not open for writing is opened read-only instead (inputs
/// only; an output written to it is then a 400).
fn read_only_will_do(kind: std::io::ErrorKind) -> bool {
    matches!(kind, std::io::ErrorKind::PermissionDenied | std::io::ErrorKind::ReadOnlyFilesystem)
}

fn open_error(key: &str, e: &std::io::Error) -> Error {
    match e.kind() {
        std::io::ErrorKind::NotFound => {
            Error::field("key", format!("no shared memory object `{key}`: create it (shm_open) before registering"))
        }
        _ => Error::field("key", format!("`{key}` cannot be opened: {e}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn memory(dir: &std::path::Path) -> SystemSharedMemory {
        SystemSharedMemory::new(SharedMemoryConfig { enabled: true, dir: dir.into(), max_regions: 2 })
    }

    fn at(region: &str, offset: u64, byte_size: u64) -> ShmRef {
        ShmRef { region: region.into(), byte_size, offset }
    }

    fn field_of<T: std::fmt::Debug>(r: Result<T>) -> String {
        match r {
            Err(e) => e.field_name().unwrap_or(e.code()).to_string(),
            Ok(v) => panic!("succeeded: {v:?}"),
        }
    }

    #[test]
    fn keys_name_one_object_in_the_directory() {
        assert_eq!(object_name("/cam0").unwrap(), "cam0");
        assert_eq!(object_name("psm_1a2b.x-y").unwrap(), "psm_1a2b.x-y");
        for bad in ["", "/", "/..", "..", ".", "/a/b", "../etc/passwd", "/a b", "/a\0"] {
            assert!(object_name(bad).is_err(), "{bad:?}");
        }
        assert!(object_name(&"a".repeat(256)).is_err());
    }

    #[test]
    fn a_region_reads_and_writes_within_its_bounds() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("obj"), (0u8..32).collect::<Vec<_>>()).unwrap();
        let m = memory(dir.path());
        assert!(m.enabled());
        m.register("r", "/obj", 8, 16).unwrap();
        let r = m.region("points", &at("r", 0, 4)).unwrap();
        assert_eq!(r.read("points", &at("r", 0, 4)).unwrap(), vec![8, 9, 10, 11]);
        assert_eq!(r.read("points", &at("r", 12, 4)).unwrap(), vec![20, 21, 22, 23]);
        assert_eq!(field_of(r.read("points", &at("r", 12, 5))), "points");
        assert_eq!(field_of(r.read("points", &at("r", u64::MAX, 2))), "points");
        let mut rows = [0u8; 6];
        r.read_rows("points", 1, 5, 3, &mut rows).unwrap();
        assert_eq!(rows, [9, 10, 11, 14, 15, 16], "two rows of 3, 5 bytes apart");
        for (row, len) in [(4, 5), (0, 2)] {
            let e = r.read_rows("points", 0, 4, row, &mut rows[..len]).unwrap_err();
            assert!(matches!(e, Error::Runtime(_)), "{len} bytes in rows of {row}: {e}");
        }
        r.write("scores", &at("r", 2, 3), &[7, 7]).unwrap();
        assert_eq!(std::fs::read(dir.path().join("obj")).unwrap()[8..14], [8, 9, 7, 7, 12, 13]);
        assert_eq!(field_of(r.write("scores", &at("r", 0, 1), &[1, 2])), "scores");
        assert_eq!(field_of(r.write("scores", &at("r", 15, 2), &[1])), "scores");
        assert_eq!(
            m.status("").unwrap(),
            vec![RegionStatus { name: "r".into(), key: "/obj".into(), offset: 8, byte_size: 16 }]
        );
    }

    #[test]
    fn registration_is_checked_and_bounded() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("obj"), [0u8; 16]).unwrap();
        std::os::unix::fs::symlink(dir.path().join("obj"), dir.path().join("link")).unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        let m = memory(dir.path());
        assert_eq!(field_of(m.register("r", "/missing", 0, 4)), "key");
        assert_eq!(field_of(m.register("r", "/link", 0, 4)), "key", "a symbolic link is not followed");
        let e = m.register("r", "/sub", 0, 4).unwrap_err();
        assert!(e.to_string().contains("cannot be opened"), "a directory is not opened read-only instead: {e}");
        assert_eq!(field_of(m.register("r", "/../obj", 0, 4)), "key");
        assert_eq!(field_of(m.register("r", "/obj", 8, 9)), "byte_size");
        assert_eq!(field_of(m.register("r", "/obj", 0, 0)), "byte_size");
        assert_eq!(field_of(m.register("", "/obj", 0, 4)), "name");
        m.register("a", "/obj", 0, 16).unwrap();
        assert_eq!(field_of(m.register("a", "/obj", 0, 4)), "name", "registered twice");
        m.register("b", "/obj", 8, 8).unwrap();
        assert_eq!(field_of(m.register("c", "/obj", 0, 4)), "name", "over max_regions");
        assert_eq!(field_of(m.status("c")), "not_found");
        m.unregister("c").unwrap();
        m.unregister("a").unwrap();
        m.register("c", "/obj", 0, 4).unwrap();
        m.unregister("").unwrap();
        assert!(m.status("").unwrap().is_empty());
    }

    #[test]
    fn writes_fill_their_span_and_the_object_to_its_end_exactly() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("obj"), [0u8; 16]).unwrap();
        let m = memory(dir.path());
        m.register("r", "/obj", 8, 8).unwrap();
        let r = m.region("scores", &at("r", 0, 8)).unwrap();
        r.write("scores", &at("r", 0, 8), &[1; 8]).unwrap();
        r.write("scores", &at("r", 6, 2), &[2; 2]).unwrap();
        assert_eq!(std::fs::read(dir.path().join("obj")).unwrap()[8..], [1, 1, 1, 1, 1, 1, 2, 2]);
    }

    #[test]
    fn an_object_the_server_may_not_write_is_opened_read_only_and_errors_say_why() {
        use std::io::ErrorKind;
        assert!(read_only_will_do(ErrorKind::PermissionDenied) && read_only_will_do(ErrorKind::ReadOnlyFilesystem));
        assert!(!read_only_will_do(ErrorKind::NotFound) && !read_only_will_do(ErrorKind::IsADirectory));
        let dir = tempfile::tempdir().unwrap();
        let m = memory(dir.path());
        let e = m.register("r", "/missing", 0, 4).unwrap_err();
        assert!(e.to_string().contains("create it (shm_open) before registering"), "{e}");
        std::fs::write(dir.path().join("obj"), [0u8; 4]).unwrap();
        let status = RegionStatus { name: "r".into(), key: "/obj".into(), offset: 0, byte_size: 4 };
        let region = Region::new(status, File::open(dir.path().join("obj")).unwrap(), false).unwrap();
        let e = region.write("scores", &at("r", 0, 4), &[0; 4]).unwrap_err();
        assert!(e.to_string().contains("read-only"), "{e}");
    }

    #[test]
    fn a_held_region_outlives_unregistration_and_unlinking() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obj");
        std::fs::write(&path, [5u8; 8]).unwrap();
        let m = memory(dir.path());
        m.register("r", "/obj", 0, 8).unwrap();
        let held = m.region("image_rgb", &at("r", 0, 8)).unwrap();
        m.unregister("r").unwrap();
        std::fs::remove_file(&path).unwrap();
        assert_eq!(held.read("image_rgb", &at("r", 0, 8)).unwrap(), vec![5; 8]);
        assert_eq!(field_of(m.region("image_rgb", &at("r", 0, 8))), "image_rgb");
    }

    #[test]
    fn a_shrunk_object_is_an_error_naming_the_tensor() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obj");
        std::fs::write(&path, [1u8; 64]).unwrap();
        let m = memory(dir.path());
        m.register("r", "/obj", 0, 64).unwrap();
        let r = m.region("points", &at("r", 0, 64)).unwrap();
        File::options().write(true).open(&path).unwrap().set_len(10).unwrap();
        let e = r.read("points", &at("r", 0, 64)).unwrap_err();
        assert_eq!(e.field_name(), Some("points"));
        assert!(e.to_string().contains("shrank to 10 bytes"), "{e}");
        assert_eq!(field_of(r.write("scores", &at("r", 8, 8), &[0; 8])), "scores");
        assert_eq!(std::fs::metadata(&path).unwrap().len(), 10, "a write never grows the object");
    }

    #[test]
    fn an_object_shrunk_past_a_page_faults_into_an_error_and_its_region_stays_refused() {
        // SAFETY: sysconf has no preconditions.
        let page = usize::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }).unwrap();
        let page_u64 = page as u64;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obj");
        std::fs::write(&path, vec![1u8; 3 * page]).unwrap();
        let m = memory(dir.path());
        m.register("r", "/obj", 0, 3 * page_u64).unwrap();
        let r = m.region("image_rgb", &at("r", 0, 16)).unwrap();
        File::options().write(true).open(&path).unwrap().set_len(page_u64).unwrap();
        assert_eq!(r.read("points", &at("r", 0, 16)).unwrap(), vec![1; 16], "bytes the object still holds");
        let mut rows = vec![0u8; 3 * 8];
        let e = r.read_rows("image_rgb", 0, page_u64, 8, &mut rows).unwrap_err();
        assert_eq!(e.field_name(), Some("image_rgb"));
        assert!(e.to_string().contains("register it again"), "{e}");
        std::fs::write(&path, vec![1u8; 3 * page]).unwrap();
        let e = r.read("points", &at("r", 0, 16)).unwrap_err();
        assert!(e.to_string().contains("register it again"), "grown again, the mapping still shows zeros: {e}");
        m.unregister("r").unwrap();
        m.register("r", "/obj", 0, 3 * page_u64).unwrap();
        let r = m.region("points", &at("r", 0, 16)).unwrap();
        assert_eq!(r.read("points", &at("r", 2 * page_u64, 16)).unwrap(), vec![1; 16], "registered again, it reads");
    }

    #[test]
    fn everything_is_refused_while_off() {
        let m = SystemSharedMemory::new(SharedMemoryConfig::default());
        assert!(!m.enabled());
        assert_eq!(field_of(m.register("r", "/obj", 0, 4)), "forbidden");
        assert_eq!(field_of(m.status("")), "forbidden");
        assert_eq!(field_of(m.unregister("")), "forbidden");
        assert_eq!(field_of(m.region("points", &at("r", 0, 4))), "forbidden");
    }
}
