//! posefuse: multi-modal (camera + LiDAR) 3D pedestrian pose estimation with 2D weak supervision.
//!
//! Data flows one way: request ([`frame`]) → [`service`] (validation, decode, mode policy) →
//! [`pipeline`] (pure) → [`runtime`] → response; [`server`] carries it over HTTP and gRPC and
//! [`eval`] scores it. See docs/ARCHITECTURE.md.

pub mod error;
pub mod eval;
pub mod frame;
mod frame_cameras;
mod frame_points;
pub mod geometry;
pub mod image_decode;
pub mod keypoints;
pub mod loadbench;
pub mod metrics;
pub mod pipeline;
pub mod ros;
pub mod runtime;
pub mod server;
pub mod service;
pub mod sim;
pub mod waymo;

pub use error::{Error, Result};
