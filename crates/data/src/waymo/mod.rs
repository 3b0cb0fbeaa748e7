//! The Waymo Open Dataset v2 (perception, parquet) in and out: the column names and enums
//! ([`schema`]), casting arrow columns by meaning ([`table`]), a segment reader that streams the
//! large components one row group at a time ([`reader`]), range images to points ([`range`]), a
//! dataset root's segments and the keypoint columns ([`segments`]) and the converter to the
//! simulator's own outputs ([`convert`]). The segment simulator and the scorer, which need the
//! simulator's worlds and the serving code, live in `posefuse-tools`. See docs/WAYMO.md.

pub mod convert;
pub mod range;
pub mod reader;
pub mod schema;
pub mod segments;
pub mod table;
