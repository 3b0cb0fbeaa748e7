//! ROS 2 drive logs (MCAP) in (docs/ROS.md); scoring them and writing the results is
//! `posefuse-tools`' `ros` module. `posefuse mcap score` reads a log's camera
//! images, camera infos, LiDAR clouds, static transforms and detector boxes, answers each frame
//! through the serving code and writes the poses as Foxglove scene updates, image annotations
//! and the full responses; `posefuse mcap record` writes a Waymo v2 root (the simulator's
//! segments included) as such a log.

pub mod build;
pub mod cdr;
pub mod log_writer;
pub mod msgs;
pub mod record;
pub mod sync;
pub mod tf;
