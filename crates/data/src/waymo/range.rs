//! Range images to points, as the dataset's toolkit computes them: row → beam inclination (the
//! calibration's non-uniform values, or uniform between min and max; row 0 is the highest),
//! column → azimuth (`(2·(W − col − 0.5)/W − 1)·π − yaw` with the extrinsic's yaw), spherical to
//! Cartesian in the sensor frame, the extrinsic to the vehicle frame; for a laser with per-pixel
//! poses (TOP), each pixel's vehicle pose at the moment it was measured takes the point to the
//! world and the frame's `vehicle_pose` back to the vehicle frame at the frame's timestamp.

use crate::ensure;

pub use posefuse_core::geometry::rigid::{apply, mat4, mul, rigid_inverse, Mat4};

/// `shape` = [H, W, C] and H·W·C values (channel 0 is the range for LiDAR returns).
#[derive(Debug, Clone, PartialEq)]
pub struct RangeImage {
    pub shape: [usize; 3],
    pub values: Vec<f32>,
}

impl RangeImage {
    /// Builds one from the parquet `values` and `shape` columns, checking they agree.
    pub fn new(values: Vec<f32>, shape: &[i64]) -> crate::error::Result<RangeImage> {
        ensure!(shape.len() == 3 && shape.iter().all(|&s| s > 0), "range image shape {shape:?} is not [H, W, C]");
        let shape = [shape[0] as usize, shape[1] as usize, shape[2] as usize];
        ensure!(
            values.len() == shape[0] * shape[1] * shape[2],
            "range image of shape {shape:?} has {} values, not {}",
            values.len(),
            shape[0] * shape[1] * shape[2]
        );
        Ok(RangeImage { shape, values })
    }

    pub fn height(&self) -> usize {
        self.shape[0]
    }

    pub fn width(&self) -> usize {
        self.shape[1]
    }

    /// Channel `c` of pixel (row, col).
    pub fn at(&self, row: usize, col: usize, c: usize) -> f32 {
        self.values[(row * self.shape[1] + col) * self.shape[2] + c]
    }
}

/// What the conversion needs of a laser's calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserCalibration {
    pub name: i64,
    /// Sensor → vehicle, row-major.
    pub extrinsic: [f64; 16],
    pub inclination_min: f64,
    pub inclination_max: f64,
    /// Non-uniform inclinations, lowest first (as stored); empty for a uniform laser.
    pub inclinations: Vec<f64>,
}

/// The inclination of each row (row 0 highest).
pub fn row_inclinations(cal: &LaserCalibration, height: usize) -> crate::error::Result<Vec<f64>> {
    if !cal.inclinations.is_empty() {
        ensure!(
            cal.inclinations.len() == height,
            "laser {}: {} beam inclinations for a range image of {height} rows",
            cal.name,
            cal.inclinations.len()
        );
        return Ok(cal.inclinations.iter().rev().copied().collect());
    }
    let diff = cal.inclination_max - cal.inclination_min;
    Ok((0..height).rev().map(|i| cal.inclination_min + (i as f64 + 0.5) / height as f64 * diff).collect())
}

/// The azimuth (sensor frame) of each column.
pub fn column_azimuths(extrinsic: &[f64; 16], width: usize) -> Vec<f64> {
    let yaw = extrinsic[4].atan2(extrinsic[0]);
    (0..width)
        .map(|c| ((width - c) as f64 - 0.5) / width as f64)
        .map(|ratio| (ratio * 2.0 - 1.0) * std::f64::consts::PI - yaw)
        .collect()
}

/// The transform of a pose (roll, pitch, yaw, x, y, z): `R = Rz(yaw)·Ry(pitch)·Rx(roll)`.
pub fn pose_matrix(p: [f64; 6]) -> Mat4 {
    let [roll, pitch, yaw, x, y, z] = p;
    let (sr, cr) = roll.sin_cos();
    let (sp, cp) = pitch.sin_cos();
    let (sy, cy) = yaw.sin_cos();
    [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr, x],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr, y],
        [-sp, cp * sr, cp * cr, z],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// The (roll, pitch, yaw, x, y, z) of a rigid transform (inverse of [`pose_matrix`]).
pub fn matrix_pose(m: &Mat4) -> [f64; 6] {
    let pitch = (-m[2][0]).clamp(-1.0, 1.0).asin();
    let roll = m[2][1].atan2(m[2][2]);
    let yaw = m[1][0].atan2(m[0][0]);
    [roll, pitch, yaw, m[0][3], m[1][3], m[2][3]]
}

/// Per-pixel vehicle poses of a sweep ([H, W, 6]: roll, pitch, yaw, x, y, z in the world) and
/// the frame's world-from-vehicle pose.
pub struct SweepPoses<'a> {
    pub pixel_poses: &'a RangeImage,
    pub frame_pose: &'a Mat4,
}

/// The returns of a range image (range > 0) as vehicle-frame points at the frame's timestamp,
/// row by row.
pub fn range_image_points(
    ri: &RangeImage,
    cal: &LaserCalibration,
    poses: Option<SweepPoses<'_>>,
) -> crate::error::Result<Vec<[f32; 3]>> {
    let mut out = Vec::with_capacity(ri.height() * ri.width() / 2);
    convert_pixels(ri, cal, poses, |_, _, p| out.push(p))?;
    Ok(out)
}

/// [`range_image_points`] with each point's pixel: (row, column, point).
pub fn range_image_pixels(
    ri: &RangeImage,
    cal: &LaserCalibration,
    poses: Option<SweepPoses<'_>>,
) -> crate::error::Result<Vec<(usize, usize, [f32; 3])>> {
    let mut out = Vec::new();
    convert_pixels(ri, cal, poses, |r, c, p| out.push((r, c, p)))?;
    Ok(out)
}

fn convert_pixels(
    ri: &RangeImage,
    cal: &LaserCalibration,
    poses: Option<SweepPoses<'_>>,
    mut emit: impl FnMut(usize, usize, [f32; 3]),
) -> crate::error::Result<()> {
    let (h, w) = (ri.height(), ri.width());
    let incl = row_inclinations(cal, h)?;
    let az = column_azimuths(&cal.extrinsic, w);
    let ext = mat4(&cal.extrinsic);
    let frame_inv = match &poses {
        Some(p) => {
            ensure!(
                p.pixel_poses.height() == h && p.pixel_poses.width() == w && p.pixel_poses.shape[2] >= 6,
                "laser {}: pixel poses of shape {:?} for a range image of shape {:?}",
                cal.name,
                p.pixel_poses.shape,
                ri.shape
            );
            Some(rigid_inverse(p.frame_pose))
        }
        None => None,
    };
    let dirs: Vec<[f64; 2]> = az.iter().map(|a| [a.cos(), a.sin()]).collect();
    let rows: Vec<[f64; 2]> = incl.iter().map(|e| [e.cos(), e.sin()]).collect();
    let mut last: Option<([f32; 6], Mat4)> = None;
    for (r, [ce, se]) in rows.iter().enumerate() {
        for (c, [ca, sa]) in dirs.iter().enumerate() {
            let range = ri.at(r, c, 0);
            if range.is_nan() || range <= 0.0 {
                continue;
            }
            let d = range as f64;
            let p = [d * ce * ca, d * ce * sa, d * se];
            let m = match (&poses, &frame_inv) {
                (Some(sp), Some(inv)) => {
                    let base = (r * w + c) * sp.pixel_poses.shape[2];
                    let v: [f32; 6] = std::array::from_fn(|i| sp.pixel_poses.values[base + i]);
                    match &last {
                        Some((lv, m)) if *lv == v => *m,
                        _ => {
                            let m = mul(inv, &mul(&pose_matrix(v.map(f64::from)), &ext));
                            last = Some((v, m));
                            m
                        }
                    }
                }
                _ => ext,
            };
            let q = apply(&m, p);
            emit(r, c, [q[0] as f32, q[1] as f32, q[2] as f32]);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn identity() -> [f64; 16] {
        [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    }

    #[test]
    fn hand_computed_pixel() {
        // 4 rows × 8 columns, uniform inclinations over [-0.4, 0.4]: row 1 is 0.1 rad up
        // (rows are 0.3, 0.1, -0.1, -0.3). A laser at (1, 2, 3) yawed by +90°: column 2 has
        // ratio (8 - 2 - 0.5)/8 = 0.6875, azimuth (2·0.6875 − 1)·π − π/2 = −π/8 in the sensor
        // frame, i.e. π/2 − π/8 = 3π/8 in the vehicle frame.
        let mut ext = identity();
        ext[0] = 0.0;
        ext[1] = -1.0;
        ext[4] = 1.0;
        ext[5] = 0.0;
        ext[3] = 1.0;
        ext[7] = 2.0;
        ext[11] = 3.0;
        let cal = LaserCalibration {
            name: 2,
            extrinsic: ext,
            inclination_min: -0.4,
            inclination_max: 0.4,
            inclinations: vec![],
        };
        let mut values = vec![0.0f32; 4 * 8 * 4];
        values[(8 + 2) * 4] = 10.0;
        let ri = RangeImage::new(values, &[4, 8, 4]).unwrap();
        let pts = range_image_points(&ri, &cal, None).unwrap();
        assert_eq!(pts.len(), 1);
        let (inc, az) = (0.1f64, 3.0 * std::f64::consts::PI / 8.0);
        let want = [1.0 + 10.0 * inc.cos() * az.cos(), 2.0 + 10.0 * inc.cos() * az.sin(), 3.0 + 10.0 * inc.sin()];
        for i in 0..3 {
            assert!((pts[0][i] as f64 - want[i]).abs() < 1e-5, "{:?} vs {want:?}", pts[0]);
        }
        // Non-uniform inclinations are stored lowest first; row 0 takes the last one.
        let cal2 = LaserCalibration { inclinations: vec![-0.2, -0.05, 0.0, 0.25], ..cal };
        assert_eq!(row_inclinations(&cal2, 4).unwrap(), vec![0.25, 0.0, -0.05, -0.2]);
        assert!(row_inclinations(&cal2, 5).is_err());
    }

    #[test]
    fn pose_matrix_round_trips() {
        let p = [0.05, -0.1, 2.5, 10.0, -3.0, 0.5];
        let q = matrix_pose(&pose_matrix(p));
        for i in 0..6 {
            assert!((p[i] - q[i]).abs() < 1e-12);
        }
        let m = pose_matrix(p);
        let back = mul(&rigid_inverse(&m), &m);
        for (r, row) in back.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                assert!((v - if r == c { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
    }
}
