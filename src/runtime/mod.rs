//! ONNX Runtime loading, model bundle, sessions and batching.

mod batcher;
pub mod bundle;
pub mod env;
mod models;

pub use batcher::{ChainStep, JobOutput, PauseGuard, Runtime, RuntimeConfig};
pub use bundle::{Bundle, Manifest, ModelIo, ModelKind, ModelSpec};
pub use models::Models;
