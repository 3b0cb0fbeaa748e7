//! The `slim-hands` effect: forearms that taper to the wrist and flat hands, in place of the
//! uniform capsules of `body.rs`, so that a wrist at range catches as few LiDAR returns as a real
//! one (docs/DATA.md, "Realism against Waymo's anchors").
//!
//! Sizes at 1.70 m, scaled with height: a wrist of 16.3 cm circumference (radius 2.6 cm), hands
//! 8.4 cm broad and 3 cm thick, the forearm 4.0 cm in radius below the elbow: adult averages of
//! the order anthropometric tables give (men 85 mm, women 75 mm hand breadth, British adults,
//! Pheasant's *Bodyspace*). The uniform capsules are 3.6 cm at the wrist and 6 cm thick at the
//! hand. No random numbers are drawn, so the persons, poses and labels stay those of the same seed
//! without the effect.

use super::body::Part;
use super::math::{cross, madd, norm, normalize, orthogonal, sub};
use super::poses::{PersonModel, Slot};
use super::raycast::Shape;

/// Wrist radius at 1.70 m.
pub const WRIST_RADIUS_M: f64 = 0.026;
/// Half the hand's breadth and half its thickness at 1.70 m.
pub const HAND_HALF_BREADTH_M: f64 = 0.042;
pub const HAND_HALF_THICKNESS_M: f64 = 0.015;
/// The forearm's radius just below the elbow, as a multiple of the uniform capsule's.
const PROXIMAL_FACTOR: f64 = 1.1;

/// Where along the forearm (0 elbow, 1 wrist) each of its three capsules ends, and the share of
/// the way from the proximal to the wrist radius each one has.
const SEGMENTS: [(f64, f64, f64); 3] = [(0.0, 0.45, 0.0), (0.45, 0.75, 0.5), (0.75, 1.0, 1.0)];

/// Replaces the fitted forearms (not sleeves loosened by `dress`) and the hands.
pub fn slim_hands(m: &mut PersonModel) {
    let s = m.anthro.height / 1.7;
    let [_, r_fa, _, _, _, _, _] = m.anthro.radii();
    let (r_prox, r_wrist) = (PROXIMAL_FACTOR * r_fa, WRIST_RADIUS_M * s);
    let sk = &m.skeleton;
    let mut out = Vec::with_capacity(m.parts.len() + 4);
    for (shape, part, slot) in m.parts.drain(..) {
        match (part, slot) {
            (Part::Forearm(i), Slot::Sleeve) => {
                let (elbow, wrist) = (sk.keypoints[3 + i], sk.keypoints[5 + i]);
                for (t0, t1, w) in SEGMENTS {
                    let r = r_prox + w * (r_wrist - r_prox);
                    out.push((Shape::capsule(at(elbow, wrist, t0), at(elbow, wrist, t1), r), part, slot));
                }
            }
            (Part::Hand(i), _) => {
                out.push((flat_hand(sk.keypoints[5 + i], sk.hand_tips[i], sk.lateral, s), part, slot))
            }
            _ => out.push((shape, part, slot)),
        }
    }
    m.parts = out;
}

/// The point a fraction `t` of the way from `a` to `b`.
fn at(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    madd(a, sub(b, a), t)
}

/// An ellipsoid from the wrist to the finger tips, broad across the palm and thin through it. The
/// palm faces the body's side, as a hanging hand's does. The tip is a hand's length from the wrist
/// (`Skeleton::new`).
fn flat_hand(wrist: [f64; 3], tip: [f64; 3], lateral: [f64; 3], s: f64) -> Shape {
    let along = sub(tip, wrist);
    let len = norm(along);
    let d = normalize(along);
    let normal = orthogonal(lateral, d, [1.0, 0.0, 0.0]);
    let breadth = normalize(cross(normal, d));
    let c = at(wrist, tip, 0.5);
    Shape::ellipsoid(c, [d, breadth, normal], [0.5 * len, HAND_HALF_BREADTH_M * s, HAND_HALF_THICKNESS_M * s])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::body::Anthro;
    use crate::sim::math::{dot, scale};
    use crate::sim::poses::{pose_person, Activity};
    use rand::SeedableRng;

    fn person_of(height: f64, activity: Activity) -> PersonModel {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        pose_person(&mut rng, Anthro::new(height, 1.0, |_| 1.0), activity)
    }

    fn person(activity: Activity) -> PersonModel {
        person_of(1.7, activity)
    }

    /// Distance through `shape` along the line `p + t·u`.
    fn chord(shape: &Shape, p: [f64; 3], u: [f64; 3]) -> f64 {
        let o = madd(p, u, -1.0);
        let Some((t0, _)) = shape.intersect(o, u, 0.0) else { return 0.0 };
        let back = madd(p, u, 1.0);
        let Some((t1, _)) = shape.intersect(back, scale(u, -1.0), 0.0) else { return 0.0 };
        2.0 - t0 - t1
    }

    #[test]
    fn forearms_taper_to_the_wrist_and_hands_are_flat() {
        for height in [1.7, 1.19] {
            let before = person_of(height, Activity::Standing);
            let mut after = before.clone();
            slim_hands(&mut after);
            assert_eq!(after.skeleton.keypoints, before.skeleton.keypoints);
            sizes_at(&after, height / 1.7);
        }
    }

    /// The forearms' and hands' sizes of a 1.70 m person scaled by `s`.
    fn sizes_at(after: &PersonModel, s: f64) {
        let kp = &after.skeleton.keypoints;
        for i in 0..2 {
            let forearms: Vec<&Shape> =
                after.parts.iter().filter(|(_, p, _)| *p == Part::Forearm(i)).map(|(s, _, _)| s).collect();
            assert_eq!(forearms.len(), 3);
            let (elbow, wrist) = (kp[3 + i], kp[5 + i]);
            let axis = normalize(sub(wrist, elbow));
            let across = orthogonal([0.0, 0.0, 1.0], axis, [1.0, 0.0, 0.0]);
            let width = |t: f64| {
                let p = at(elbow, wrist, t);
                forearms.iter().map(|s| chord(s, p, across)).fold(0.0, f64::max)
            };
            assert!((width(0.2) - 2.0 * 1.1 * 0.036 * s).abs() < 1e-3, "below the elbow: {}", width(0.2));
            assert!((width(0.9) - 2.0 * WRIST_RADIUS_M * s).abs() < 1e-3, "at the wrist: {}", width(0.9));
            let (hand, _, _) = after.parts.iter().find(|(_, p, _)| *p == Part::Hand(i)).unwrap();
            let mid = at(wrist, after.skeleton.hand_tips[i], 0.5);
            let palm = orthogonal(after.skeleton.lateral, normalize(sub(after.skeleton.hand_tips[i], wrist)), [1.0; 3]);
            assert!((chord(hand, mid, palm) - 2.0 * HAND_HALF_THICKNESS_M * s).abs() < 1e-3);
            let along = normalize(sub(after.skeleton.hand_tips[i], wrist));
            let across_palm = normalize(cross(palm, along));
            assert!((chord(hand, mid, across_palm) - 2.0 * HAND_HALF_BREADTH_M * s).abs() < 1e-3);
            // from the wrist to the finger tips
            assert!((chord(hand, mid, along) - after.anthro.hand).abs() < 1e-3);
            assert!(dot(palm, across_palm).abs() < 1e-9 && norm(palm) > 0.99);
        }
    }

    #[test]
    fn loosened_sleeves_and_the_rest_of_the_body_are_left_alone() {
        let mut before = person(Activity::Walking);
        for (_, part, slot) in before.parts.iter_mut() {
            if *part == Part::Forearm(1) {
                *slot = Slot::Shirt;
            }
        }
        let mut after = before.clone();
        slim_hands(&mut after);
        let untouched = |m: &PersonModel| -> Vec<String> {
            m.parts
                .iter()
                .filter(|(_, p, _)| !matches!(p, Part::Hand(_) | Part::Forearm(0)))
                .map(|x| format!("{x:?}"))
                .collect()
        };
        assert_eq!(untouched(&after), untouched(&before));
        assert_eq!(after.parts.iter().filter(|(_, p, _)| *p == Part::Forearm(0)).count(), 3);
        assert_eq!(after.parts.iter().filter(|(_, p, _)| *p == Part::Forearm(1)).count(), 1);
    }
}
