//! The transport-free service: one frame in, poses out. It validates the frame, decodes the image
//! and points, derives missing 2D boxes, chooses each person's mode (or skips the person), runs
//! the pure [`posefuse_core::pipeline`] and the [`crate::runtime`], and assembles the response with its
//! timings. HTTP, gRPC, the CLI and the evaluation all call [`Predictor`]; none of them decides
//! anything about a pose. See docs/ARCHITECTURE.md.

pub mod admission;
pub mod api;
mod cameras;
pub mod heading_stage;
pub mod limits;
pub mod policy;
mod predict;

pub use predict::{Predictor, MAX_PERSONS};
