//! posefuse: multi-modal (camera + LiDAR) 3D pedestrian pose estimation with 2D weak supervision.
//!
//! Data flows one way: request ([`frame`]) → [`pipeline`] (pure) → [`runtime`] → response.

pub mod error;
pub mod frame;
pub mod geometry;
pub mod image_decode;
pub mod keypoints;
pub mod loadbench;
pub mod metrics;
pub mod pipeline;
pub mod runtime;
pub mod server;
pub mod sim;

pub use error::{Error, Result};
