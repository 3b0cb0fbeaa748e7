//! Where the networks run (`--device`, `POSEFUSE_DEVICE`): ONNX Runtime's CPU provider, or its
//! CUDA execution provider on one GPU. CUDA needs ONNX Runtime's GPU build (the
//! `onnxruntime-gpu` wheel, `bash scripts/setup.sh --gpu`); asking for it from a build without it
//! is one clear error at start-up, never a silent fall-back to the CPU (docs/OPERATIONS.md,
//! "Devices").

use std::fmt;
use std::str::FromStr;

use ort::ep::{ExecutionProvider, ExecutionProviderDispatch};

use posefuse_core::error::{Error, Result};

/// A device for the sessions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Device {
    #[default]
    Cpu,
    /// The CUDA execution provider on GPU `N` (its CUDA device ordinal).
    Cuda(u32),
}

impl FromStr for Device {
    type Err = String;

    /// `cpu`, `cuda` (GPU 0) or `cuda:N`.
    fn from_str(s: &str) -> std::result::Result<Device, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "cpu" => Ok(Device::Cpu),
            "cuda" => Ok(Device::Cuda(0)),
            other => other
                .strip_prefix("cuda:")
                .and_then(|n| n.parse::<u32>().ok())
                .filter(|&n| n <= i32::MAX as u32)
                .map(Device::Cuda)
                .ok_or_else(|| format!("unknown device `{s}`: cpu, cuda or cuda:N")),
        }
    }
}

impl fmt::Display for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Device::Cpu => f.write_str("cpu"),
            Device::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

impl Device {
    /// Checks, once ONNX Runtime is loaded from `lib`, that it can run on this device.
    pub fn check(self, lib: &std::path::Path) -> Result<()> {
        match self {
            Device::Cpu => Ok(()),
            Device::Cuda(_) => {
                let available = ort::ep::CUDA::is_available().map_err(|e| Error::Runtime(e.to_string()))?;
                cuda_verdict(self, available, lib)
            }
        }
    }

    /// The execution providers a session on this device registers, each an error if it cannot
    /// be (no fall-back to the CPU). The CPU provider is ONNX Runtime's own, always there.
    pub(super) fn providers(self) -> Vec<ExecutionProviderDispatch> {
        match self {
            Device::Cpu => Vec::new(),
            Device::Cuda(n) => vec![ort::ep::CUDA::default().with_device_id(n as i32).build().error_on_failure()],
        }
    }
}

/// The start-up verdict on CUDA: whether the loaded ONNX Runtime has its provider.
fn cuda_verdict(device: Device, available: bool, lib: &std::path::Path) -> Result<()> {
    if available {
        return Ok(());
    }
    Err(Error::Runtime(format!(
        "--device {device}: the ONNX Runtime at {} has no CUDA execution provider (it is the CPU build); \
         install the GPU build with `bash scripts/setup.sh --gpu`, or serve with --device cpu",
        lib.display()
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_parse_and_print_back() {
        for (given, want) in [("cpu", Device::Cpu), ("CUDA", Device::Cuda(0)), ("cuda:3", Device::Cuda(3))] {
            let d: Device = given.parse().unwrap();
            assert_eq!(d, want, "{given}");
            assert_eq!(d.to_string().parse::<Device>().unwrap(), d);
        }
        for bad in ["gpu", "cuda:", "cuda:-1", "cuda:x", "cuda:4294967295", "rocm:0", ""] {
            let e = bad.parse::<Device>().unwrap_err();
            assert!(e.contains("cpu, cuda or cuda:N"), "{bad}: {e}");
        }
        assert_eq!(Device::default(), Device::Cpu);
    }

    #[test]
    fn only_cuda_registers_a_provider() {
        assert!(Device::Cpu.providers().is_empty());
        assert_eq!(Device::Cuda(2).providers().len(), 1);
    }

    #[test]
    fn cuda_without_its_provider_is_one_clear_error() {
        let lib = std::path::Path::new("/x/libonnxruntime.so");
        assert!(cuda_verdict(Device::Cuda(1), true, lib).is_ok());
        let e = cuda_verdict(Device::Cuda(1), false, lib).unwrap_err().to_string();
        assert!(e.contains("--device cuda:1") && e.contains("/x/libonnxruntime.so"), "{e}");
        assert!(e.contains("scripts/setup.sh --gpu") && e.contains("--device cpu"), "{e}");
    }
}
