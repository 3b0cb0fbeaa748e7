//! The Waymo Open Dataset v2 (perception, parquet) in and out: the column names and enums
//! ([`schema`]), casting arrow columns by meaning ([`table`]), a segment reader that streams the
//! large components one row group at a time ([`reader`]), range images to points ([`range`]), a
//! simulator that writes segments in the same layout ([`sim`]) and the converter to the
//! simulator's own outputs ([`convert`]), batch scoring and Waymo's keypoint metrics ([`score`]). See docs/WAYMO.md.

pub mod convert;
pub mod range;
pub mod reader;
pub mod schema;
pub mod score;
pub mod sim;
pub mod table;
