//! The transport-free service: one frame in, poses out. It validates the frame once
//! (`valid_frame`), plans it (`plan`: cameras, 2D boxes, each person's mode or skip, crops), runs
//! the pure [`posefuse_core::pipeline`] and the [`crate::runtime`], and assembles the response with its
//! timings. HTTP, gRPC, the CLI and the evaluation all call [`Predictor`]; none of them decides
//! anything about a pose. See docs/ARCHITECTURE.md.

pub mod admission;
pub mod api;
mod cameras;
mod crop_cache;
pub mod heading_stage;
pub mod limits;
mod plan;
pub mod policy;
mod predict;
mod valid_frame;

pub use plan::{planned_inputs, PlannedInput};
pub use predict::{Predictor, MAX_PERSONS};
