//! A heading stage in front of a bundle that reads the body's facing from the box heading: a
//! bundle that needs no heading (the view frame, docs/BUNDLE.md "Point frame") answers first, and
//! each person's box takes the facing it predicted wherever the detector's heading disagrees with
//! it. Exact headings are kept (the heading-aligned networks are at their best with them); wrong
//! ones, 180° flips included, are replaced.

use posefuse_core::frame::Box3d;
use posefuse_core::pipeline::yaw_difference;

use super::api::PoseResponse;

/// Default of `agree_deg`: a box heading within this many degrees of the first stage's facing is
/// kept as given. The stage's facing is off by about 10° (median) on the street held-out set; a
/// larger value trusts the detector more (docs/BUNDLE.md, "Heading stage", measures 30–90°).
pub const AGREE_DEG: f64 = 30.0;

/// Asking the point network again with the box turned to the facing it predicted, so a heading a
/// few tens of degrees off (the stage's estimate, or the detector's) moves toward the body's own
/// (docs/BUNDLE.md, "Heading refinement"). Only the point network runs again; the camera's
/// heatmaps are reused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refine {
    /// Passes at most (0: off).
    pub passes: usize,
    /// A pass whose predicted facing is within this many degrees of the heading it was asked at
    /// ends the refinement.
    pub settle_deg: f64,
}

impl Refine {
    /// No refinement.
    pub const OFF: Refine = Refine { passes: 0, settle_deg: SETTLE_DEG };
}

/// Default of [`Refine::settle_deg`].
pub const SETTLE_DEG: f64 = 5.0;

/// The persons' 3D `boxes` with each answered person's heading replaced by the facing `first`
/// predicted for it, where the two disagree by more than `agree_deg` degrees. Persons the first
/// stage skipped, or answered without a facing, keep their heading.
pub fn estimated_boxes(mut boxes: Vec<Box3d>, first: &PoseResponse, agree_deg: f64) -> Vec<Box3d> {
    let skipped: Vec<usize> = first.skipped.iter().map(|s| s.index).collect();
    let answered = boxes.iter_mut().enumerate().filter(|(i, _)| !skipped.contains(i)).map(|(_, b)| b);
    for (b, pose) in answered.zip(&first.persons) {
        if let Some(f) = pose.facing {
            if yaw_difference(f.yaw, b.heading).to_degrees() > agree_deg {
                b.heading = f.yaw;
            }
        }
    }
    boxes
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::api::{ErrorDetail, Mode, ModelRef, PersonPose, SkippedPerson, Timings};
    use posefuse_core::pipeline::Facing;

    fn boxes(headings: &[f64]) -> Vec<Box3d> {
        let b = |i: usize, heading: f64| Box3d {
            center_x: 10.0,
            center_y: i as f64,
            center_z: 0.9,
            length: 0.6,
            width: 0.7,
            height: 1.8,
            heading,
        };
        headings.iter().enumerate().map(|(i, h)| b(i, *h)).collect()
    }

    fn pose(id: &str, facing: Option<f64>) -> PersonPose {
        PersonPose {
            id: id.into(),
            camera: None,
            mode: Mode::Lidar,
            mode_reason: String::new(),
            num_points: 100,
            box_2d: None,
            keypoints: Vec::new(),
            facing: facing.map(|yaw| Facing { yaw, confidence: 0.9 }),
        }
    }

    #[test]
    fn disagreeing_headings_take_the_facing_and_the_rest_stay() {
        let deg = f64::to_radians;
        // p0: 20° off, kept; p1: 180° off, replaced; p2: skipped by the first stage; p3: no facing;
        // p4: 40° off across ±180°, replaced
        let f = boxes(&[deg(10.0), deg(0.0), deg(90.0), deg(45.0), deg(170.0)]);
        let first = PoseResponse {
            frame_id: None,
            model: ModelRef { name: "view".into(), version: "0".into() },
            persons: vec![
                pose("p0", Some(deg(30.0))),
                pose("p1", Some(deg(180.0))),
                pose("p3", None),
                pose("p4", Some(deg(-150.0))),
            ],
            skipped: vec![SkippedPerson {
                index: 2,
                id: "p2".into(),
                error: ErrorDetail { code: "no_points".into(), message: String::new(), field: None },
            }],
            timings: Timings::default(),
        };
        let out = estimated_boxes(f.clone(), &first, AGREE_DEG);
        let h: Vec<f64> = out.iter().map(|b| b.heading.to_degrees()).collect();
        let want = [10.0, 180.0, 90.0, 45.0, -150.0];
        for (got, want) in h.iter().zip(want) {
            assert!((got - want).abs() < 1e-9, "{h:?}");
        }
        // trusting the detector up to 45°: p4 (40° off) keeps its heading too
        let out = estimated_boxes(f, &first, 45.0);
        assert!((out[4].heading.to_degrees() - 170.0).abs() < 1e-9);
        assert!((out[1].heading.to_degrees() - 180.0).abs() < 1e-9);
    }
}
