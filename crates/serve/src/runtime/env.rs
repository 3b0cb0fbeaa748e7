//! Loading the ONNX Runtime shared library. ONNX Runtime allows one environment per process, so
//! it is created once and shared by every runtime (several servers run in one test process).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use posefuse_core::error::{Error, Result};

/// Where the set-up script puts the library.
pub const DEFAULT_ORT_LIB: &str = ".ort/lib/libonnxruntime.so";

static ENVIRONMENT: OnceLock<std::result::Result<ort::environment::Environment, String>> = OnceLock::new();

/// The library path: the explicit one, else `ORT_DYLIB_PATH`, else [`DEFAULT_ORT_LIB`].
pub fn resolve_lib(explicit: Option<&Path>) -> PathBuf {
    explicit
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os("ORT_DYLIB_PATH").filter(|v| !v.is_empty()).map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from(DEFAULT_ORT_LIB))
}

/// Loads ONNX Runtime from `lib` (first call) and returns the process-wide environment.
pub fn environment(lib: &Path) -> Result<ort::environment::Environment> {
    ENVIRONMENT
        .get_or_init(|| {
            if !lib.is_file() {
                return Err(format!(
                    "ONNX Runtime library not found at {} (run `bash scripts/setup.sh` to install it into \
                     .ort/lib, or point --ort-lib / ORT_DYLIB_PATH at libonnxruntime.so)",
                    lib.display()
                ));
            }
            let builder = ort::init_from(lib).map_err(|e| {
                format!("cannot load ONNX Runtime from {}: {e} (run `bash scripts/setup.sh`)", lib.display())
            })?;
            builder
                .with_name("posefuse")
                .build()
                .map_err(|e| format!("cannot create the ONNX Runtime environment: {e}"))
        })
        .clone()
        .map_err(Error::Runtime)
}
