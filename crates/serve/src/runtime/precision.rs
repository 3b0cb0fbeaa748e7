//! Which numeric precision the camera network runs in (`--precision`, `POSEFUSE_PRECISION`, or
//! the manifest's `precision`): the float32 network the trainer exported, or its INT8 variant
//! (`models.camera.variants.int8`, written by `python -m posefuse_train.quantize`; docs/BUNDLE.md,
//! "Precision"). The point networks always run in float32.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use super::device::Device;

/// A network's numeric precision.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    #[default]
    Fp32,
    Int8,
}

impl Precision {
    /// The name used in flags, manifests and `models.<net>.variants`.
    pub fn key(self) -> &'static str {
        match self {
            Precision::Fp32 => "fp32",
            Precision::Int8 => "int8",
        }
    }

    /// The precision a runtime on `device` asks the bundle for (None: the manifest's). INT8
    /// variants are ONNX Runtime's CPU kernels (QOperator), which the CUDA execution provider would
    /// run on the CPU between copies, so on a GPU float32 is served unless INT8 is asked for.
    pub fn asked_on(asked: Option<Precision>, device: Device) -> Option<Precision> {
        asked.or(match device {
            Device::Cuda(_) => Some(Precision::Fp32),
            Device::Cpu => None,
        })
    }
}

impl FromStr for Precision {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Precision, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "fp32" => Ok(Precision::Fp32),
            "int8" => Ok(Precision::Int8),
            _ => Err(format!("unknown precision `{s}`: fp32 or int8")),
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.key())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_ones_are_refused() {
        for p in [Precision::Fp32, Precision::Int8] {
            assert_eq!(p.to_string().parse::<Precision>(), Ok(p));
            assert_eq!(serde_json::to_value(p).unwrap(), serde_json::json!(p.key()));
        }
        assert_eq!(" INT8 ".parse::<Precision>(), Ok(Precision::Int8));
        assert!("fp16".parse::<Precision>().unwrap_err().contains("fp32 or int8"));
    }

    #[test]
    fn a_gpu_serves_float32_unless_int8_is_asked_and_a_cpu_leaves_it_to_the_manifest() {
        assert_eq!(Precision::asked_on(None, Device::Cpu), None);
        assert_eq!(Precision::asked_on(None, Device::Cuda(1)), Some(Precision::Fp32));
        for p in [Precision::Fp32, Precision::Int8] {
            assert_eq!(Precision::asked_on(Some(p), Device::Cpu), Some(p));
            assert_eq!(Precision::asked_on(Some(p), Device::Cuda(0)), Some(p));
        }
    }
}
