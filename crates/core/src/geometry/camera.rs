//! Waymo camera model: camera frame x forward (optical axis), y left, z up;
//! `u_n = -y/x`, `v_n = -z/x`, OpenCV distortion, then `u = f_u·u_d + c_u`, `v = f_v·v_d + c_v`.
//!
//! A projection is *valid* only in front of the camera and where the radial distortion factor
//! `1 + k1·r² + k2·r⁴ + k3·r⁶` lies in [`RADIAL_FACTOR_RANGE`], as in Waymo's camera model: far
//! off-axis a strongly barrel-distorted lens's polynomial turns back (and then negative), which
//! folds points outside the field of view into the image (docs/ARCHITECTURE.md, "Conventions").

use crate::error::{Error, Result};
use crate::frame::CameraCalibration;

use super::rigid::{apply, rigid_inverse, Mat4};

/// A validated camera: intrinsics, distortion and both rigid transforms.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub fu: f64,
    pub fv: f64,
    pub cu: f64,
    pub cv: f64,
    /// `[k1, k2, p1, p2, k3]`.
    pub dist: [f64; 5],
    pub width: u32,
    pub height: u32,
    cam_to_vehicle: Mat4,
    vehicle_to_cam: Mat4,
}

/// The radial distortion factors inside which a projection is trusted (Waymo's camera model
/// rejects the others): the distortion polynomial is monotone there for real lenses.
pub const RADIAL_FACTOR_RANGE: (f64, f64) = (0.8, 1.2);

/// Where a vehicle-frame point lands in the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projection {
    /// Pixel coordinates (NaN when `in_front` is false; meaningless when `valid` is false).
    pub uv: [f64; 2],
    /// Depth along the optical axis, metres.
    pub depth: f64,
    /// The point is in front of the camera.
    pub in_front: bool,
    /// The point is in front of the camera and its radial distortion factor is in
    /// [`RADIAL_FACTOR_RANGE`]: only then does `uv` mean where the lens puts it.
    pub valid: bool,
    /// The projection is valid and inside the image.
    pub in_image: bool,
}

impl Camera {
    /// Builds a camera from a calibration, refusing degenerate ones with a field-naming error.
    pub fn from_calibration(c: &CameraCalibration) -> Result<Camera> {
        c.validate()?;
        let mut m = [[0.0; 4]; 4];
        for (i, v) in c.extrinsic.iter().enumerate() {
            m[i / 4][i % 4] = *v;
        }
        if m[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err(Error::field("calibration.extrinsic", "last row must be [0, 0, 0, 1]"));
        }
        // R·R^T must be the identity and det(R) = +1 for a rigid transform.
        for a in 0..3 {
            for b in 0..3 {
                let dot: f64 = (0..3).map(|k| m[a][k] * m[b][k]).sum();
                let want = if a == b { 1.0 } else { 0.0 };
                if (dot - want).abs() > 1e-3 {
                    return Err(Error::field("calibration.extrinsic", "rotation part is not orthonormal"));
                }
            }
        }
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        if det < 0.0 {
            return Err(Error::field("calibration.extrinsic", "rotation part is a reflection (det < 0)"));
        }
        let i = &c.intrinsic;
        Ok(Camera {
            fu: i[0],
            fv: i[1],
            cu: i[2],
            cv: i[3],
            dist: [i[4], i[5], i[6], i[7], i[8]],
            width: c.width,
            height: c.height,
            cam_to_vehicle: m,
            vehicle_to_cam: rigid_inverse(&m),
        })
    }

    /// Builds the calibration record this camera came from.
    pub fn to_calibration(&self) -> CameraCalibration {
        let [k1, k2, p1, p2, k3] = self.dist;
        CameraCalibration {
            intrinsic: vec![self.fu, self.fv, self.cu, self.cv, k1, k2, p1, p2, k3],
            extrinsic: self.cam_to_vehicle.iter().flatten().copied().collect(),
            width: self.width,
            height: self.height,
        }
    }

    /// The camera's position in the vehicle frame.
    pub fn position(&self) -> [f64; 3] {
        [self.cam_to_vehicle[0][3], self.cam_to_vehicle[1][3], self.cam_to_vehicle[2][3]]
    }

    /// Vehicle frame → camera frame.
    pub fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        apply(&self.vehicle_to_cam, p)
    }

    /// Camera frame → vehicle frame.
    pub fn to_vehicle(&self, p: [f64; 3]) -> [f64; 3] {
        apply(&self.cam_to_vehicle, p)
    }

    /// The radial distortion factor `1 + k1·r² + k2·r⁴ + k3·r⁶` at normalized coordinates.
    pub fn radial_factor(&self, un: f64, vn: f64) -> f64 {
        let [k1, k2, _, _, k3] = self.dist;
        let r2 = un * un + vn * vn;
        1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    }

    /// Applies OpenCV distortion to normalized coordinates.
    pub fn distort(&self, un: f64, vn: f64) -> (f64, f64) {
        let [_, _, p1, p2, _] = self.dist;
        let r2 = un * un + vn * vn;
        let radial = self.radial_factor(un, vn);
        let ud = un * radial + 2.0 * p1 * un * vn + p2 * (r2 + 2.0 * un * un);
        let vd = vn * radial + p1 * (r2 + 2.0 * vn * vn) + 2.0 * p2 * un * vn;
        (ud, vd)
    }

    /// Inverts `distort` by Newton's method (converges in a few steps for real lenses).
    pub fn undistort(&self, ud: f64, vd: f64) -> (f64, f64) {
        let (mut u, mut v) = (ud, vd);
        for _ in 0..20 {
            let (fu, fv) = self.distort(u, v);
            let (ru, rv) = (fu - ud, fv - vd);
            if ru.abs() < 1e-15 && rv.abs() < 1e-15 {
                break;
            }
            // Numerical Jacobian: the distortion polynomial is smooth and cheap.
            let h = 1e-7;
            let (a1, b1) = self.distort(u + h, v);
            let (a2, b2) = self.distort(u, v + h);
            let (j11, j21) = ((a1 - fu) / h, (b1 - fv) / h);
            let (j12, j22) = ((a2 - fu) / h, (b2 - fv) / h);
            let det = j11 * j22 - j12 * j21;
            if det.abs() < 1e-12 {
                break;
            }
            u -= (j22 * ru - j12 * rv) / det;
            v -= (-j21 * ru + j11 * rv) / det;
        }
        (u, v)
    }

    /// Projects a vehicle-frame point into the image.
    pub fn project(&self, p: [f64; 3]) -> Projection {
        let c = self.to_camera(p);
        if c[0] <= 1e-6 {
            return Projection {
                uv: [f64::NAN, f64::NAN],
                depth: c[0],
                in_front: false,
                valid: false,
                in_image: false,
            };
        }
        let (un, vn) = (-c[1] / c[0], -c[2] / c[0]);
        let radial = self.radial_factor(un, vn);
        let valid = (RADIAL_FACTOR_RANGE.0..=RADIAL_FACTOR_RANGE.1).contains(&radial);
        let (ud, vd) = self.distort(un, vn);
        let uv = [self.fu * ud + self.cu, self.fv * vd + self.cv];
        let in_image = valid && uv[0] >= 0.0 && uv[1] >= 0.0 && uv[0] < self.width as f64 && uv[1] < self.height as f64;
        Projection { uv, depth: c[0], in_front: true, valid, in_image }
    }

    /// Projects vehicle-frame points into the image; `None` for those without a valid projection
    /// (behind the camera, or where the lens model folds back).
    pub fn project_points(&self, points: &[[f64; 3]]) -> Vec<Option<[f64; 2]>> {
        points
            .iter()
            .map(|&p| {
                let pr = self.project(p);
                pr.valid.then_some(pr.uv)
            })
            .collect()
    }

    /// The vehicle-frame point at pixel `uv` and depth `depth` (metres along the optical axis).
    pub fn unproject(&self, uv: [f64; 2], depth: f64) -> [f64; 3] {
        let (un, vn) = self.undistort((uv[0] - self.cu) / self.fu, (uv[1] - self.cv) / self.fv);
        self.to_vehicle([depth, -un * depth, -vn * depth])
    }

    /// Unit ray direction (vehicle frame) through pixel `uv`.
    pub fn ray(&self, uv: [f64; 2]) -> [f64; 3] {
        let p = self.unproject(uv, 1.0);
        let o = self.position();
        let d = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        [d[0] / n, d[1] / n, d[2] / n]
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A camera 1.5 m forward, 0.1 m left, 2.1 m up, yawed 5° and pitched 2°, mild distortion.
    pub(crate) fn test_camera() -> Camera {
        let (yaw, pitch) = (5f64.to_radians(), 2f64.to_radians());
        let (cy, sy, cp, sp) = (yaw.cos(), yaw.sin(), pitch.cos(), pitch.sin());
        // R = Rz(yaw)·Ry(pitch)
        let r = [[cy * cp, -sy, cy * sp], [sy * cp, cy, sy * sp], [-sp, 0.0, cp]];
        let t = [1.5, 0.1, 2.1];
        let mut ext = Vec::with_capacity(16);
        for i in 0..3 {
            ext.extend_from_slice(&[r[i][0], r[i][1], r[i][2], t[i]]);
        }
        ext.extend_from_slice(&[0.0, 0.0, 0.0, 1.0]);
        Camera::from_calibration(&CameraCalibration {
            intrinsic: vec![2050.0, 2050.0, 960.0, 640.0, -0.08, 0.02, 0.0005, -0.0003, -0.001],
            extrinsic: ext,
            width: 1920,
            height: 1280,
        })
        .unwrap()
    }

    #[test]
    fn project_unproject_round_trip_with_distortion() {
        let cam = test_camera();
        for &p in &[[10.0, 0.5, 1.0], [25.0, -3.0, 0.2], [5.0, 1.5, 2.5], [60.0, 8.0, -1.0], [3.2, -0.9, 0.1]] {
            let pr = cam.project(p);
            assert!(pr.in_front);
            let back = cam.unproject(pr.uv, pr.depth);
            for a in 0..3 {
                let rel = (back[a] - p[a]).abs() / p.iter().map(|v| v.abs()).fold(0.0, f64::max);
                assert!(rel < 1e-6, "axis {a}: {back:?} vs {p:?}");
            }
            // and pixels survive the other way round
            let again = cam.project(back);
            assert!((again.uv[0] - pr.uv[0]).abs() < 1e-6 * pr.uv[0].abs().max(1.0));
        }
    }

    #[test]
    fn undistort_inverts_distort_over_the_image() {
        let cam = test_camera();
        for u in [-0.5, -0.2, 0.0, 0.3, 0.47] {
            for v in [-0.31, 0.0, 0.3] {
                let (ud, vd) = cam.distort(u, v);
                let (uu, vv) = cam.undistort(ud, vd);
                assert!((uu - u).abs() < 1e-9 && (vv - v).abs() < 1e-9, "{u},{v} -> {uu},{vv}");
            }
        }
    }

    #[test]
    fn principal_point_is_straight_ahead_and_axes_follow_waymo() {
        let mut c = test_camera();
        c.dist = [0.0; 5];
        let cam = Camera::from_calibration(&{
            let mut cal = c.to_calibration();
            cal.extrinsic = vec![1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.];
            cal
        })
        .unwrap();
        let p = cam.project([10.0, 0.0, 0.0]);
        assert!((p.uv[0] - 960.0).abs() < 1e-9 && (p.uv[1] - 640.0).abs() < 1e-9);
        // a point to the left (+y) lands left of centre (smaller u); up (+z) lands higher (smaller v)
        assert!(cam.project([10.0, 1.0, 0.0]).uv[0] < 960.0);
        assert!(cam.project([10.0, 0.0, 1.0]).uv[1] < 640.0);
    }

    #[test]
    fn points_behind_the_camera_or_outside_are_flagged() {
        let cam = test_camera();
        let behind = cam.project([-5.0, 0.0, 1.0]);
        assert!(!behind.in_front && !behind.in_image);
        let side = cam.project([5.0, 30.0, 1.0]);
        assert!(side.in_front && !side.in_image);
        assert!(cam.project([20.0, 0.0, 1.5]).in_image);
    }

    /// A Waymo-FRONT-like camera at the origin looking along +x, yawed `yaw`, with strong barrel
    /// distortion (k2 = −0.33, as on real Waymo cameras) and no other distortion term.
    pub(crate) fn barrel_camera(yaw: f64) -> Camera {
        let (s, c) = yaw.sin_cos();
        #[rustfmt::skip]
        let extrinsic = vec![
            c, -s, 0.0, 0.0,
            s, c, 0.0, 0.0,
            0.0, 0.0, 1.0, 1.5,
            0.0, 0.0, 0.0, 1.0,
        ];
        Camera::from_calibration(&CameraCalibration {
            intrinsic: vec![2055.0, 2055.0, 960.0, 640.0, 0.0, -0.33, 0.0, 0.0, 0.0],
            extrinsic,
            width: 1920,
            height: 1280,
        })
        .unwrap()
    }

    /// A point `d` metres away at `deg` degrees left of the optical axis, at the camera's height.
    fn at_bearing(deg: f64, d: f64) -> [f64; 3] {
        let a = deg.to_radians();
        [d * a.cos(), d * a.sin(), 1.5]
    }

    #[test]
    fn projections_are_valid_where_the_lens_model_is_monotone() {
        let cam = barrel_camera(0.0);
        // 0° and 20°: valid and in the image; 30°: valid, beyond the half field of view (24.9°)
        for (deg, in_image) in [(0.0, true), (20.0, true), (-20.0, true), (30.0, false)] {
            let p = cam.project(at_bearing(deg, 10.0));
            assert!(p.in_front && p.valid, "{deg}°: {p:?}");
            assert_eq!(p.in_image, in_image, "{deg}°: {p:?}");
        }
        // 60°, 90° and behind: no valid projection, so never in the image
        for deg in [60.0, 90.0, -90.0, 180.0] {
            let p = cam.project(at_bearing(deg, 10.0));
            assert!(!p.valid && !p.in_image, "{deg}°: {p:?}");
            assert_eq!(cam.project_points(&[at_bearing(deg, 10.0)]), vec![None]);
        }
        assert!(!cam.project(at_bearing(180.0, 10.0)).in_front);
    }

    #[test]
    fn a_point_the_lens_polynomial_folds_into_the_image_is_not_in_it() {
        let cam = barrel_camera(0.0);
        // At 50° the polynomial has turned back: the unchecked pixel lies inside the image,
        // on the wrong side of the axis' bend. Waymo's rule (radial factor in [0.8, 1.2]) refuses it.
        let p = cam.project(at_bearing(50.0, 10.0));
        assert!(p.in_front && !p.valid && !p.in_image, "{p:?}");
        assert!(p.uv[0] >= 0.0 && p.uv[0] < 1920.0 && p.uv[1] >= 0.0 && p.uv[1] < 1280.0, "{p:?}");
        let (un, vn) = (-(50f64.to_radians().tan()), 0.0);
        assert!(cam.radial_factor(un, vn) < RADIAL_FACTOR_RANGE.0);
    }

    #[test]
    fn the_validity_limit_is_where_the_distorted_radius_stops_growing() {
        // With only k2, r_d = r·(1 + k2·r⁴) turns back where 1 + 5·k2·r⁴ = 0, i.e. where the
        // radial factor is exactly 0.8: the lower bound is the monotonicity limit.
        let cam = barrel_camera(0.0);
        let r_turn = (-1.0 / (5.0 * cam.dist[1])).powf(0.25);
        assert!((cam.radial_factor(r_turn, 0.0) - RADIAL_FACTOR_RANGE.0).abs() < 1e-12);
        let rd = |r: f64| cam.distort(r, 0.0).0;
        assert!(rd(r_turn * 0.99) < rd(r_turn) && rd(r_turn * 1.01) < rd(r_turn));
        // a pincushion lens is bounded from above the same way
        let mut pin = cam.clone();
        pin.dist = [0.4, 0.0, 0.0, 0.0, 0.0];
        assert!(pin.project(at_bearing(30.0, 10.0)).valid);
        assert!(!pin.project(at_bearing(40.0, 10.0)).valid, "radial factor 1 + 0.4·tan²(40°) > 1.2");
    }

    #[test]
    fn degenerate_calibrations_are_refused() {
        let mut cal = test_camera().to_calibration();
        cal.extrinsic[0] = 2.0;
        let e = Camera::from_calibration(&cal).unwrap_err();
        assert!(e.to_string().contains("orthonormal"), "{e}");
        let mut cal = test_camera().to_calibration();
        cal.extrinsic[15] = 0.0;
        assert!(Camera::from_calibration(&cal).unwrap_err().to_string().contains("last row"));
        let mut cal = test_camera().to_calibration();
        for c in 0..3 {
            cal.extrinsic[4 + c] = -cal.extrinsic[4 + c];
        }
        assert!(Camera::from_calibration(&cal).unwrap_err().to_string().contains("reflection"));
    }
}
