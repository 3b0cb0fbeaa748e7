//! Which way a body faces, from its 3D keypoints: the yaw perception stacks use for intent (is
//! the pedestrian turned toward the road?).
//!
//! A body's left-pointing vector is left minus right, for the shoulders and for the hips; its
//! facing is that vector turned a quarter turn clockwise seen from above (a person whose left is
//! +y faces +x). The shoulders and hips are summed in the horizontal plane, so a twisted torso
//! gives their mean. The confidence says how much the two pairs agree and how far apart they are
//! horizontally: 1 when both point the same way and are at least [`FULL_WIDTH_M`] wide, lower
//! when the pairs disagree or are seen end-on (a lying or badly estimated body).

use crate::keypoints::index_of;

/// Horizontal left-right spread (metres, mean of shoulders and hips) from which the direction is
/// fully trusted; a narrow adult's hips are about this wide.
pub const FULL_WIDTH_M: f64 = 0.15;

/// A body's facing in the frame its keypoints are in.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct Facing {
    /// Yaw about z in radians, (−π, π]: 0 faces +x, π/2 faces +y (the box heading's convention).
    pub yaw: f64,
    /// 0..1: agreement of shoulders and hips times their horizontal spread, relative to
    /// [`FULL_WIDTH_M`].
    pub confidence: f64,
}

fn horizontal_left(kp: &[[f64; 3]], left: &str, right: &str) -> Option<[f64; 2]> {
    let (l, r) = (kp.get(index_of(left)?)?, kp.get(index_of(right)?)?);
    let v = [l[0] - r[0], l[1] - r[1]];
    v.iter().all(|x| x.is_finite()).then_some(v)
}

/// The facing of 13 keypoints in the project's order; `None` when the shoulders or hips are not
/// finite or coincide.
pub fn facing(keypoints: &[[f64; 3]]) -> Option<Facing> {
    let shoulders = horizontal_left(keypoints, "left_shoulder", "right_shoulder")?;
    let hips = horizontal_left(keypoints, "left_hip", "right_hip")?;
    let sum = [shoulders[0] + hips[0], shoulders[1] + hips[1]];
    let (len_s, len_h, len_sum) = (shoulders[0].hypot(shoulders[1]), hips[0].hypot(hips[1]), sum[0].hypot(sum[1]));
    // Pairs that cancel (or coincide) point nowhere; a micrometre is below any keypoint's error.
    if len_sum < 1e-6 {
        return None;
    }
    let agreement = len_sum / (len_s + len_h);
    let spread = ((len_s + len_h) / 2.0 / FULL_WIDTH_M).min(1.0);
    // left (lx, ly) turned clockwise: forward = (ly, −lx)
    Some(Facing { yaw: (-sum[0]).atan2(sum[1]), confidence: agreement * spread })
}

/// The absolute difference of two yaws, radians in [0, π].
pub fn yaw_difference(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::TAU);
    d.min(std::f64::consts::TAU - d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    /// A standing body facing `yaw`: shoulders 0.4 m and hips 0.3 m apart.
    fn body(yaw: f64) -> Vec<[f64; 3]> {
        let left = [-yaw.sin(), yaw.cos()];
        let mut kp = vec![[0.0; 3]; 13];
        let at = |w: f64, z: f64, side: f64| [side * left[0] * w / 2.0, side * left[1] * w / 2.0, z];
        kp[1] = at(0.4, 1.4, 1.0);
        kp[2] = at(0.4, 1.4, -1.0);
        kp[7] = at(0.3, 0.9, 1.0);
        kp[8] = at(0.3, 0.9, -1.0);
        kp
    }

    #[test]
    fn a_body_faces_where_its_left_says() {
        for yaw in [0.0, 0.7, FRAC_PI_2, 2.5, -1.2, -FRAC_PI_2] {
            let f = facing(&body(yaw)).unwrap();
            assert!(yaw_difference(f.yaw, yaw) < 1e-9, "{yaw}: {f:?}");
            assert!((f.confidence - 1.0).abs() < 1e-9, "{f:?}");
        }
        // Facing +x, the person's left is +y (vehicle frame): hand-checked.
        let f = facing(&body(0.0)).unwrap();
        assert!(f.yaw.abs() < 1e-12);
    }

    #[test]
    fn exchanged_sides_face_the_other_way() {
        let mut kp = body(0.3);
        kp.swap(1, 2);
        kp.swap(7, 8);
        assert!(yaw_difference(facing(&kp).unwrap().yaw, 0.3 + PI) < 1e-9);
    }

    #[test]
    fn disagreeing_or_narrow_bodies_are_less_certain() {
        // Hips turned a quarter against the shoulders: agreement √2·0.2… / 0.35.
        let mut kp = body(0.0);
        let hips = body(FRAC_PI_2);
        kp[7] = hips[7];
        kp[8] = hips[8];
        let f = facing(&kp).unwrap();
        let (s, h) = (0.4f64, 0.3f64);
        assert!((f.confidence - s.hypot(h) / (s + h)).abs() < 1e-9, "{f:?}");
        // Half the full width: half the confidence.
        let mut narrow = body(1.0);
        for k in [1, 2, 7, 8] {
            narrow[k][0] *= 0.15 / 0.35 / 2.0;
            narrow[k][1] *= 0.15 / 0.35 / 2.0;
        }
        assert!((facing(&narrow).unwrap().confidence - 0.5).abs() < 1e-9);
        // Opposite pairs cancel; missing keypoints give nothing.
        let mut opposite = body(0.0);
        let turned = body(PI);
        opposite[7] = [turned[7][0] * 4.0 / 3.0, turned[7][1] * 4.0 / 3.0, 0.9];
        opposite[8] = [turned[8][0] * 4.0 / 3.0, turned[8][1] * 4.0 / 3.0, 0.9];
        assert!(facing(&opposite).is_none());
        let mut nan = body(0.0);
        nan[7][0] = f64::NAN;
        assert!(facing(&nan).is_none());
    }

    #[test]
    fn yaw_differences_wrap() {
        assert!((yaw_difference(PI - 0.1, -PI + 0.1) - 0.2).abs() < 1e-12);
        assert!((yaw_difference(0.0, PI) - PI).abs() < 1e-12);
        assert_eq!(yaw_difference(1.0, 1.0), 0.0);
    }
}
