//! Boxes seen from the camera: a 3D box's projected 2D box, and 2D boxes against the image.

use super::{box2d_from_points, BoxFrame, Camera};
use crate::frame::{Box2d, Box3d};

/// Whether a 2D box overlaps the image at all.
pub fn overlaps_image(b: &Box2d, width: u32, height: u32) -> bool {
    let (x0, x1) = (b.center_x - b.width / 2.0, b.center_x + b.width / 2.0);
    let (y0, y1) = (b.center_y - b.height / 2.0, b.center_y + b.height / 2.0);
    x1 > 0.0 && y1 > 0.0 && x0 < width as f64 && y0 < height as f64
}

/// The 2D box of the projected 3D box corners, when every corner has a valid projection (in
/// front of the camera, where the lens model does not fold back) and the box overlaps the image.
pub fn projected_box(camera: &Camera, b: &Box3d) -> Option<Box2d> {
    let mut uv = Vec::with_capacity(8);
    for c in BoxFrame::new(b).corners() {
        let p = camera.project(c);
        if !p.valid {
            return None;
        }
        uv.push(p.uv);
    }
    box2d_from_points(uv)
        .filter(|bb| bb.width > 0.0 && bb.height > 0.0 && overlaps_image(bb, camera.width, camera.height))
}

/// The part of a box inside the image (for derived boxes of persons close to the camera).
pub fn clip_to_image(b: Box2d, width: u32, height: u32) -> Box2d {
    let x0 = (b.center_x - b.width / 2.0).max(0.0);
    let x1 = (b.center_x + b.width / 2.0).min(width as f64);
    let y0 = (b.center_y - b.height / 2.0).max(0.0);
    let y1 = (b.center_y + b.height / 2.0).min(height as f64);
    Box2d { center_x: (x0 + x1) / 2.0, center_y: (y0 + y1) / 2.0, width: x1 - x0, height: y1 - y0 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::CameraCalibration;

    /// A forward-looking camera at the origin: camera frame = vehicle frame.
    fn camera() -> Camera {
        let mut ext = vec![0.0; 16];
        for i in 0..4 {
            ext[i * 5] = 1.0;
        }
        Camera::from_calibration(&CameraCalibration {
            intrinsic: vec![100.0, 100.0, 50.0, 40.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            extrinsic: ext,
            width: 100,
            height: 80,
        })
        .unwrap()
    }

    fn b3(x: f64, y: f64) -> Box3d {
        Box3d { center_x: x, center_y: y, center_z: 0.0, length: 1.0, width: 1.0, height: 2.0, heading: 0.0 }
    }

    #[test]
    fn projected_box_of_a_box_straight_ahead() {
        // Corners at x = 9.5 (near face) project to u = 50 ± 100·0.5/9.5, v = 40 ± 100·1/9.5.
        let b = projected_box(&camera(), &b3(10.0, 0.0)).unwrap();
        assert!((b.center_x - 50.0).abs() < 1e-9 && (b.center_y - 40.0).abs() < 1e-9);
        assert!((b.width - 100.0 / 9.5).abs() < 1e-9 && (b.height - 200.0 / 9.5).abs() < 1e-9);
    }

    #[test]
    fn boxes_behind_or_beside_the_camera_have_no_projection() {
        assert!(projected_box(&camera(), &b3(-10.0, 0.0)).is_none());
        // Far to the left: u = 50 - 100·20/10 < 0 for every corner.
        assert!(projected_box(&camera(), &b3(10.0, 20.0)).is_none());
        // Straddling the image plane (a corner behind the camera).
        assert!(projected_box(&camera(), &b3(0.2, 0.0)).is_none());
    }

    #[test]
    fn oversized_boxes_are_clipped() {
        let c = clip_to_image(Box2d { center_x: 90.0, center_y: 40.0, width: 40.0, height: 200.0 }, 100, 80);
        assert_eq!((c.center_x, c.center_y, c.width, c.height), (85.0, 40.0, 30.0, 80.0));
    }

    #[test]
    fn overlap_with_the_image() {
        let b = |cx, cy| Box2d { center_x: cx, center_y: cy, width: 10.0, height: 10.0 };
        assert!(overlaps_image(&b(50.0, 40.0), 100, 80));
        assert!(overlaps_image(&b(-4.0, 40.0), 100, 80));
        assert!(!overlaps_image(&b(-5.0, 40.0), 100, 80));
        assert!(!overlaps_image(&b(50.0, 85.0), 100, 80));
    }
}
