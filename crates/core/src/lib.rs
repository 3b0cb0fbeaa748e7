//! posefuse's pure layer: the request types ([`frame`]), keypoint conventions, sensor geometry,
//! the pre-processing pipeline, metrics, image decoding and the training-sample schema
//! ([`sample`]). Nothing here serves, reads a model or starts a thread: the crate does not depend
//! on ONNX Runtime, tokio or a transport (docs/ARCHITECTURE.md).

pub mod error;
pub mod frame;
pub mod geometry;
pub mod image_decode;
pub mod json;
pub mod keypoints;
pub mod metrics;
pub mod pipeline;
pub mod sample;

pub use error::{Error, Result};
