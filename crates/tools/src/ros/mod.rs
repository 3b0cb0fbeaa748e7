//! ROS 2 drive logs answered (docs/ROS.md): `posefuse mcap score` reads a log through
//! `posefuse_data::ros`, answers each frame through the serving code and writes the poses as
//! Foxglove scene updates and image annotations ([`viz`]) and the full responses.

pub mod score;
pub mod viz;
