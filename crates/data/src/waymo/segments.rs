//! A dataset root's segments and the keypoint list columns that labels and predictions share:
//! what the converter, the scorer and the segment simulator all read or write.

use std::path::Path;

use posefuse_core::error::{Error, Result};

use super::convert::Kp3dLabel;
use super::schema::{col, comp};
use super::table::Columns;

/// The keypoint list columns of `lidar_hkp` (also the layout of predictions).
pub fn write_lidar_keypoints(c: &mut Columns, rows: &[&[Kp3dLabel]]) {
    let l = |i: usize| rows.iter().map(|r| r.iter().map(|k| k.xyz[i]).collect()).collect::<Vec<Vec<f64>>>();
    c.list_i8(col::LHKP_TYPE, &rows.iter().map(|r| r.iter().map(|k| k.kind).collect()).collect::<Vec<_>>());
    c.list_f64(col::LHKP_X, &l(0));
    c.list_f64(col::LHKP_Y, &l(1));
    c.list_f64(col::LHKP_Z, &l(2));
    c.list_bool(col::LHKP_OCCLUDED, &rows.iter().map(|r| r.iter().map(|k| k.occluded).collect()).collect::<Vec<_>>());
}

/// The dataset root's segment names (the files of its `lidar` component).
pub fn segments_in(root: &Path) -> Result<Vec<String>> {
    let dir = root.join(comp::LIDAR);
    let mut out: Vec<String> = std::fs::read_dir(&dir)
        .map_err(|e| Error::Io(format!("component `lidar`: {}: {e}", dir.display())))?
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix(".parquet")).map(str::to_owned))
        .collect();
    out.sort();
    Ok(out)
}
