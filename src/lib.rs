//! posefuse: multi-modal (camera + LiDAR) 3D pedestrian pose estimation with 2D weak supervision.
//!
//! This package is the `posefuse` binary; its library is only the workspace's crates under their
//! old paths, for the integration tests, benches and examples. The layers are the crates
//! (docs/ARCHITECTURE.md): `posefuse_core` ← `posefuse_data`, `posefuse_serve` ← `posefuse_tools`.

pub use posefuse_core::{error, frame, geometry, image_decode, json, keypoints, metrics, pipeline, sample};
pub use posefuse_core::{Error, Result};
pub use posefuse_data::sim;
pub use posefuse_serve::{eval, runtime, server, service};
pub use posefuse_tools::loadbench;

/// The Waymo Open Dataset v2: the reader and converter (`posefuse_data::waymo`), the segment
/// simulator and the scorer (`posefuse_tools`).
pub mod waymo {
    pub use posefuse_data::waymo::{convert, range, reader, schema, segments, table};
    pub use posefuse_tools::{waymo_score as score, waymo_sim as sim};
}

/// ROS 2 logs: reading and writing (`posefuse_data::ros`), scoring (`posefuse_tools::ros`).
pub mod ros {
    pub use posefuse_data::ros::{build, cdr, log_writer, msgs, record, sync, tf};
    pub use posefuse_tools::ros::{score, viz};
}
