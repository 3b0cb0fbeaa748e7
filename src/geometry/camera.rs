//! Waymo camera model: camera frame x forward (optical axis), y left, z up;
//! `u_n = -y/x`, `v_n = -z/x`, OpenCV distortion, then `u = f_u·u_d + c_u`, `v = f_v·v_d + c_v`.

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

/// Where a vehicle-frame point lands in the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projection {
    /// Pixel coordinates (meaningless when `in_front` is false).
    pub uv: [f64; 2],
    /// Depth along the optical axis, metres.
    pub depth: f64,
    /// The point is in front of the camera.
    pub in_front: bool,
    /// The point is in front of the camera and inside the image.
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

    /// Applies OpenCV distortion to normalized coordinates.
    pub fn distort(&self, un: f64, vn: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = un * un + vn * vn;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
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
            return Projection { uv: [f64::NAN, f64::NAN], depth: c[0], in_front: false, in_image: false };
        }
        let (ud, vd) = self.distort(-c[1] / c[0], -c[2] / c[0]);
        let uv = [self.fu * ud + self.cu, self.fv * vd + self.cv];
        let in_image = uv[0] >= 0.0 && uv[1] >= 0.0 && uv[0] < self.width as f64 && uv[1] < self.height as f64;
        Projection { uv, depth: c[0], in_front: true, in_image }
    }

    /// Projects vehicle-frame points into the image; `None` for those behind the camera.
    pub fn project_points(&self, points: &[[f64; 3]]) -> Vec<Option<[f64; 2]>> {
        points
            .iter()
            .map(|&p| {
                let pr = self.project(p);
                pr.in_front.then_some(pr.uv)
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
mod tests {
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
