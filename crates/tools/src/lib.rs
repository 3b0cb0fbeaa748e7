//! posefuse's tools over data and serving (docs/ARCHITECTURE.md): the load bench
//! ([`loadbench`]), the Waymo segment simulator ([`waymo_sim`]), Waymo batch scoring and
//! keypoint metrics ([`waymo_score`]) and ROS 2 log scoring ([`ros`]).

pub mod loadbench;
pub mod ros;
pub mod waymo_score;
pub mod waymo_sim;
