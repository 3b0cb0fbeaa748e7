//! ONNX Runtime loading, model bundle, sessions and batching.

mod batcher;
pub mod bundle;
pub mod device;
pub mod env;
mod gate;
mod models;
mod precision;

pub use batcher::{ChainStep, JobOutput, Runtime, RuntimeConfig};
pub use bundle::{Bundle, Manifest, ModelIo, ModelKind, ModelSpec};
pub use device::Device;
#[cfg(feature = "test-hooks")]
pub use gate::{hold_warm_up, PauseGuard};
pub use models::Models;
pub use precision::Precision;
