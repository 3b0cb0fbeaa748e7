//! posefuse's data sources (docs/ARCHITECTURE.md): the simulator ([`sim`]), the Waymo Open Dataset
//! v2 reader and converter ([`waymo`]) and ROS 2 logs ([`ros`]). They produce `Frame`s and
//! prepared samples through `posefuse_core`'s pipeline and sample writer; nothing here serves.

pub mod error;
pub mod ros;
pub mod sim;
pub mod waymo;
