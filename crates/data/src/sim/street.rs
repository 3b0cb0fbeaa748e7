//! The `street` simulation profile: what real pedestrians wear and carry, and the mixed-pixel
//! returns real LiDARs give at silhouette edges. The clean profile's capsule hands end in a
//! geometric tip a point network finds easily; in real data the hand disappears into a cuff, a bag,
//! a cup or a phone, and thin limbs smear in range. These are what the paper's camera features
//! compensate for (its LiDAR-only wrist OKS is 30 % against 46 % for camera-only).

use rand::Rng;

use super::body::Part;
use super::math::{add, madd, normalize, scale, sub, V3};
use super::poses::{Activity, PersonModel, Slot};
use super::raycast::Shape;
use super::realism::Effect;

/// How much of the street's mess the simulator renders (`posefuse simulate --profile`). The
/// default is the CLI's: `street-hard`, the profile the default bundle is trained on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    /// Tight clothing, empty hands except the activity's own objects, clean first returns.
    Clean,
    /// Loose jackets and coats, hand-held items and shoulder bags, mixed-pixel LiDAR returns.
    Street,
    /// `street` plus the effects that moved the LiDAR-only keypoint profile toward Waymo's
    /// (docs/DATA.md, "Realism against Waymo's anchors"): arms against the torso, dark surfaces
    /// dropping out, and 3D label noise.
    #[serde(rename = "street-hard")]
    #[default]
    StreetHard,
}

impl Profile {
    /// The realism effects the profile turns on.
    pub fn effects(self) -> &'static [Effect] {
        match self {
            Profile::Clean => &[],
            Profile::Street => &[Effect::Dress, Effect::MixedPixels],
            Profile::StreetHard => {
                &[Effect::Dress, Effect::MixedPixels, Effect::Reflectivity, Effect::ArmsIn, Effect::LabelNoise]
            }
        }
    }
}

/// Share of persons in a loose jacket or coat (sleeves over the wrist, wider trunk).
const LOOSE_CLOTHING: f64 = 0.55;
/// Share of persons, among those whose hands are free, holding something.
const HOLDING: f64 = 0.5;
/// Share of persons with a shoulder bag at the hip.
const SHOULDER_BAG: f64 = 0.2;

/// Dresses a posed person for the street profile: loose clothing and things in hand. Keypoints are
/// unchanged (clothing and items never move a joint).
pub fn dress<R: Rng>(rng: &mut R, m: &mut PersonModel) {
    if rng.random_bool(LOOSE_CLOTHING) {
        loosen(rng, m);
    }
    let free = [0, 1].map(|s| hands_free(m.activity) && !raised(m, s) && !m.busy_hands[s]);
    if free.iter().any(|&f| f) && rng.random_bool(HOLDING) {
        let both = free[0] && free[1] && rng.random_bool(0.2);
        let first = if free[0] && free[1] { rng.random_range(0..2usize) } else { usize::from(!free[0]) };
        for (s, &f) in free.iter().enumerate() {
            if s == first || (both && f) {
                let item = hand_item(rng, m, s);
                m.parts.push((item, Part::Accessory, Slot::Gear));
            }
        }
    }
    if m.activity == Activity::Phone {
        // The phone the pose is for, in each raised hand.
        for s in 0..2 {
            if raised(m, s) {
                let c = hand_centre(m, s);
                m.parts.push((
                    Shape::cuboid(c, [0.15, 0.075, 0.012], rng.random_range(0.0..3.2)),
                    Part::Accessory,
                    Slot::Frame,
                ));
            }
        }
    }
    if rng.random_bool(SHOULDER_BAG) {
        let sk = &m.skeleton;
        let s = rng.random_range(0..2usize);
        let hip = sk.keypoints[7 + s];
        let side = scale(sk.lateral, if s == 0 { 1.0 } else { -1.0 });
        let size = [rng.random_range(0.2..0.35), rng.random_range(0.06..0.12), rng.random_range(0.18..0.3)];
        let reach = m.anthro.hip_half + 0.075 * m.anthro.girth * m.anthro.height / 1.7 + 0.5 * size[1];
        let c = add(madd(hip, side, reach), [0.0, 0.0, 0.05]);
        let yaw = sk.lateral[1].atan2(sk.lateral[0]) - std::f64::consts::FRAC_PI_2;
        m.parts.push((Shape::cuboid(c, size, yaw), Part::Accessory, Slot::Gear));
        let shoulder = sk.keypoints[1 + (1 - s)];
        m.parts.push((Shape::capsule(shoulder, add(c, [0.0, 0.0, 0.5 * size[2]]), 0.012), Part::Accessory, Slot::Gear));
    }
}

/// Whether the activity leaves the hands free for an item (its own objects take them otherwise).
fn hands_free(a: Activity) -> bool {
    matches!(
        a,
        Activity::Walking
            | Activity::Standing
            | Activity::Running
            | Activity::Waving
            | Activity::Phone
            | Activity::Crouching
    )
}

/// A hand above the elbow (waving, phone) holds nothing else.
fn raised(m: &PersonModel, s: usize) -> bool {
    m.skeleton.keypoints[5 + s][2] > m.skeleton.keypoints[3 + s][2]
}

fn hand_centre(m: &PersonModel, s: usize) -> V3 {
    let w = m.skeleton.keypoints[5 + s];
    madd(w, normalize(sub(m.skeleton.hand_tips[s], w)), 0.5 * m.anthro.hand)
}

/// Wider sleeves that cover the wrist and part of the hand, a wider trunk and, for coats, a hem
/// over the upper thighs.
fn loosen<R: Rng>(rng: &mut R, m: &mut PersonModel) {
    let [r_ua, r_fa, _, _, _, _, _] = m.anthro.radii();
    let f: f64 = rng.random_range(1.25..1.7);
    let cuff = rng.random_range(0.15..0.6) * m.anthro.hand;
    let coat = rng.random_bool(0.4);
    let trunk = rng.random_range(1.08..1.2);
    let sk = m.skeleton.clone();
    for (shape, part, slot) in m.parts.iter_mut() {
        match *part {
            Part::UpperArm(s) => *shape = Shape::capsule(sk.keypoints[1 + s], sk.keypoints[3 + s], r_ua * f.min(1.45)),
            Part::Forearm(s) => {
                let (e, w) = (sk.keypoints[3 + s], sk.keypoints[5 + s]);
                let end = madd(w, normalize(sub(sk.hand_tips[s], w)), cuff);
                *shape = Shape::capsule(e, end, r_fa * f);
                *slot = Slot::Shirt;
            }
            Part::Chest => *shape = widened(shape, trunk, 1.0),
            Part::Pelvis if coat => *shape = widened(shape, trunk, 1.45),
            _ => {}
        }
    }
}

/// An ellipsoid with its two horizontal semi-axes scaled by `w` and its vertical one by `h`, the
/// extra height hanging below (a coat's hem).
fn widened(shape: &Shape, w: f64, h: f64) -> Shape {
    match *shape {
        Shape::Ellipsoid { c, axes, semi, .. } => {
            let c = madd(c, axes[2], -(h - 1.0) * semi[2]);
            Shape::ellipsoid(c, axes, [semi[0] * w, semi[1] * w, semi[2] * h])
        }
        other => other,
    }
}

/// Something held in hand `s`: a phone, a cup, a shopping bag, a handbag or a closed umbrella.
fn hand_item<R: Rng>(rng: &mut R, m: &PersonModel, s: usize) -> Shape {
    let c = hand_centre(m, s);
    let tip = m.skeleton.hand_tips[s];
    let yaw = rng.random_range(0.0..std::f64::consts::TAU);
    match rng.random_range(0..10) {
        0 | 1 => Shape::cuboid(c, [0.15, 0.075, 0.012], yaw),
        2 | 3 => {
            let r = rng.random_range(0.03..0.045);
            Shape::capsule(add(c, [0.0, 0.0, -0.07]), add(c, [0.0, 0.0, 0.08]), r)
        }
        4..=6 => {
            let size = [rng.random_range(0.25..0.45), rng.random_range(0.08..0.18), rng.random_range(0.25..0.45)];
            Shape::cuboid(add(tip, [0.0, 0.0, 0.02 - 0.5 * size[2]]), size, yaw)
        }
        7 | 8 => {
            let axes = [[yaw.cos(), yaw.sin(), 0.0], [-yaw.sin(), yaw.cos(), 0.0], [0.0, 0.0, 1.0]];
            let semi = [rng.random_range(0.1..0.17), rng.random_range(0.04..0.07), rng.random_range(0.08..0.13)];
            Shape::ellipsoid(add(tip, [0.0, 0.0, 0.03 - semi[2]]), axes, semi)
        }
        _ => {
            let foot = add(c, [0.35 * yaw.cos(), 0.35 * yaw.sin(), -c[2] + 0.05]);
            Shape::capsule(c, foot, 0.03)
        }
    }
}
