//! Which of a frame's cameras sees a person best: the one in which the person's projected 3D box
//! lies most inside the image, so that its crop holds as much of the body as any camera gives.

use super::{clip_to_image, projected_box, Camera};
use crate::frame::Box3d;

/// How much of a projected 3D box one camera's image holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VisibleShare {
    /// Area of the box clipped to the image over the area of the whole projected box (0..1].
    pub fraction: f64,
    /// Area of the box clipped to the image, pixels².
    pub visible_area: f64,
}

/// The share of `b`'s projected box that `camera`'s image holds; `None` when the box is not
/// wholly in front of the camera or misses the image (as [`projected_box`]).
pub fn visible_share(camera: &Camera, b: &Box3d) -> Option<VisibleShare> {
    let full = projected_box(camera, b)?;
    let clipped = clip_to_image(full, camera.width, camera.height);
    let visible_area = clipped.width.max(0.0) * clipped.height.max(0.0);
    // the whole extent computed as `clip_to_image` computes the clipped one, so that a box wholly
    // inside the image has a fraction of exactly 1 and such ties go to the area
    let extent = |c: f64, s: f64| (c + s / 2.0) - (c - s / 2.0);
    let fraction = visible_area / (extent(full.center_x, full.width) * extent(full.center_y, full.height));
    (fraction.is_finite() && visible_area > 0.0).then_some(VisibleShare { fraction, visible_area })
}

/// The index of the camera that sees `b` best: the largest visible fraction, then the largest
/// visible area, then the first in `cameras`' order; `None` when no camera sees it.
pub fn best_camera(cameras: &[Camera], b: &Box3d) -> Option<usize> {
    let mut best: Option<(usize, VisibleShare)> = None;
    for (i, c) in cameras.iter().enumerate() {
        let Some(s) = visible_share(c, b) else { continue };
        let better = match best {
            None => true,
            Some((_, t)) => (s.fraction, s.visible_area) > (t.fraction, t.visible_area),
        };
        if better {
            best = Some((i, s));
        }
    }
    best.map(|(i, _)| i)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::CameraCalibration;

    /// A 100×80 camera at the vehicle origin, yawed `yaw` about z (0: looking along +x, π/2:
    /// along +y), with focal length `f`.
    fn camera(yaw: f64, f: f64) -> Camera {
        let (s, c) = yaw.sin_cos();
        #[rustfmt::skip]
        let extrinsic = vec![
            c, -s, 0.0, 0.0,
            s, c, 0.0, 0.0,
            0.0, 0.0, 1.0, 0.0,
            0.0, 0.0, 0.0, 1.0,
        ];
        let calibration = CameraCalibration {
            intrinsic: vec![f, f, 50.0, 40.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            extrinsic,
            width: 100,
            height: 80,
        };
        Camera::from_calibration(&calibration).unwrap()
    }

    fn front() -> Camera {
        camera(0.0, 100.0)
    }

    fn left() -> Camera {
        camera(std::f64::consts::FRAC_PI_2, 100.0)
    }

    fn b3(x: f64, y: f64) -> Box3d {
        Box3d { center_x: x, center_y: y, center_z: 0.0, length: 1.0, width: 1.0, height: 2.0, heading: 0.0 }
    }

    #[test]
    fn a_person_ahead_uses_the_front_camera_and_one_to_the_left_the_side_camera() {
        let cams = [front(), left()];
        assert_eq!(best_camera(&cams, &b3(10.0, 0.0)), Some(0));
        assert_eq!(best_camera(&cams, &b3(0.0, 10.0)), Some(1));
        // the order of the cameras does not matter
        assert_eq!(best_camera(&[left(), front()], &b3(0.0, 10.0)), Some(0));
    }

    #[test]
    fn a_box_behind_every_camera_has_none() {
        assert_eq!(best_camera(&[front(), left()], &b3(-10.0, -0.5)), None);
        assert_eq!(best_camera(&[], &b3(10.0, 0.0)), None);
        assert!(visible_share(&front(), &b3(-10.0, 0.0)).is_none());
    }

    #[test]
    fn the_camera_holding_more_of_the_box_wins_over_the_one_showing_more_pixels() {
        // Diagonally ahead-left: the front camera cuts the box at its left edge, a camera yawed
        // 45° has it whole. A longer focal length on the front camera makes its cut-off part
        // larger in pixels than the whole box in the other; the fraction still decides.
        let b = b3(8.0, 2.2);
        let front_tele = camera(0.0, 180.0);
        let diagonal = camera(std::f64::consts::FRAC_PI_4, 60.0);
        let (f, d) = (visible_share(&front_tele, &b).unwrap(), visible_share(&diagonal, &b).unwrap());
        assert!(f.fraction < 1.0 && d.fraction == 1.0, "{f:?} {d:?}");
        assert!(f.visible_area > d.visible_area, "{f:?} {d:?}");
        assert_eq!(best_camera(&[front_tele, diagonal], &b), Some(1));
    }

    #[test]
    fn equal_fractions_go_to_the_larger_visible_area_then_to_the_first_camera() {
        // Wholly inside both: fraction 1 in each; the longer focal length shows it larger.
        let b = b3(10.0, 0.0);
        let (wide, tele) = (camera(0.0, 100.0), camera(0.0, 150.0));
        assert_eq!(visible_share(&wide, &b).unwrap().fraction, 1.0);
        assert_eq!(visible_share(&tele, &b).unwrap().fraction, 1.0);
        assert_eq!(best_camera(&[wide.clone(), tele.clone()], &b), Some(1));
        assert_eq!(best_camera(&[tele, wide.clone()], &b), Some(0));
        assert_eq!(best_camera(&[wide.clone(), wide], &b), Some(0));
    }

    #[test]
    fn the_share_is_the_clipped_part_of_the_projected_box() {
        // Straight ahead at 10 m: the box projects to 100/9.5 × 200/9.5 px, wholly inside.
        let s = visible_share(&front(), &b3(10.0, 0.0)).unwrap();
        assert!((s.visible_area - (100.0 / 9.5) * (200.0 / 9.5)).abs() < 1e-9, "{s:?}");
        // Centred on the image's right edge (u = 100 at y = -5): about half of it is inside.
        let s = visible_share(&front(), &b3(10.0, -5.0)).unwrap();
        assert!(s.fraction > 0.4 && s.fraction < 0.6, "{s:?}");
    }

    /// The camera model's strongly barrel-distorted Waymo-like camera (k2 = −0.33), yawed `yaw`.
    fn barrel(yaw: f64) -> Camera {
        crate::geometry::camera::tests::barrel_camera(yaw)
    }

    /// A pedestrian-size box 10 m away at `deg` degrees left of +x.
    fn pedestrian_at(deg: f64) -> Box3d {
        let a = deg.to_radians();
        Box3d {
            center_x: 10.0 * a.cos(),
            center_y: 10.0 * a.sin(),
            center_z: 0.0,
            length: 0.6,
            width: 0.6,
            height: 1.8,
            heading: 0.0,
        }
    }

    #[test]
    fn a_strongly_distorted_camera_projects_only_boxes_really_in_its_view() {
        let front = barrel(0.0);
        for deg in [0.0, 20.0, -20.0] {
            let b = projected_box(&front, &pedestrian_at(deg)).unwrap_or_else(|| panic!("{deg}°"));
            // a pedestrian at 10 m is about 200 px wide and 370 px high, not a folded sliver
            assert!(b.width < 300.0 && b.height > 300.0 && b.height < 450.0, "{deg}°: {b:?}");
        }
        // 30° is beyond the half field of view; 50° is where the lens polynomial folds back into
        // the image; 60°, 90° and behind have no valid projection at all
        for deg in [30.0, 50.0, 60.0, 90.0, 180.0] {
            assert!(projected_box(&front, &pedestrian_at(deg)).is_none(), "{deg}°");
            assert!(visible_share(&front, &pedestrian_at(deg)).is_none(), "{deg}°");
        }
    }

    #[test]
    fn a_pedestrian_off_the_front_cameras_view_goes_to_the_camera_that_sees_it() {
        let (front, front_left) = (barrel(0.0), barrel(45f64.to_radians()));
        for deg in [45.0, 50.0, 57.0] {
            assert_eq!(best_camera(&[front.clone(), front_left.clone()], &pedestrian_at(deg)), Some(1), "{deg}°");
            assert_eq!(best_camera(std::slice::from_ref(&front), &pedestrian_at(deg)), None, "{deg}°");
        }
        assert_eq!(best_camera(&[front, front_left], &pedestrian_at(5.0)), Some(0));
    }
}
