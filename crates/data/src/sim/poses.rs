//! Pose families (gait cycles, standing, waving, phone, crouching, riding, pushing, carrying) and
//! the objects that go with them, all in the body frame.

use rand::Rng;
use rand_distr::{Distribution, Normal};

use super::body::{Anthro, Limb, Part, Pose, Skeleton};
use super::math::{add, madd, scale, V3};
use super::raycast::Shape;

/// What the person is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activity {
    Walking,
    Running,
    Standing,
    Waving,
    Phone,
    Crouching,
    Cycling,
    Scooter,
    Stroller,
    CarryBox,
    CarryBag,
}

impl Activity {
    pub const ALL: [Activity; 11] = [
        Activity::Walking,
        Activity::Running,
        Activity::Standing,
        Activity::Waving,
        Activity::Phone,
        Activity::Crouching,
        Activity::Cycling,
        Activity::Scooter,
        Activity::Stroller,
        Activity::CarryBox,
        Activity::CarryBag,
    ];
    const WEIGHTS: [f64; 11] = [0.33, 0.08, 0.18, 0.07, 0.05, 0.05, 0.07, 0.04, 0.05, 0.04, 0.04];

    pub fn sample<R: Rng>(rng: &mut R) -> Activity {
        let mut u = rng.random_range(0.0..Self::WEIGHTS.iter().sum::<f64>());
        for (a, w) in Self::ALL.iter().zip(Self::WEIGHTS) {
            if u < w {
                return *a;
            }
            u -= w;
        }
        Activity::Walking
    }

    pub fn name(&self) -> &'static str {
        match self {
            Activity::Walking => "walking",
            Activity::Running => "running",
            Activity::Standing => "standing",
            Activity::Waving => "waving",
            Activity::Phone => "phone",
            Activity::Crouching => "crouching",
            Activity::Cycling => "cycling",
            Activity::Scooter => "scooter",
            Activity::Stroller => "stroller",
            Activity::CarryBox => "carry_box",
            Activity::CarryBag => "carry_bag",
        }
    }
}

/// Colour slot of a primitive; the scene turns slots into materials per person.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    Skin,
    Head,
    Shirt,
    Sleeve,
    Pants,
    Shin,
    Shoes,
    Gear,
    Frame,
    Tyre,
}

/// A posed person in the body frame: keypoints, parts and the objects they carry or ride.
#[derive(Debug, Clone)]
pub struct PersonModel {
    pub anthro: Anthro,
    pub activity: Activity,
    pub skeleton: Skeleton,
    pub parts: Vec<(Shape, Part, Slot)>,
    /// Hands placed in a pocket, crossed or behind the back: they hold nothing else.
    pub busy_hands: [bool; 2],
}

fn n<R: Rng>(rng: &mut R, mean: f64, sd: f64) -> f64 {
    Normal::new(mean, sd).map(|d| d.sample(rng)).unwrap_or(mean)
}

const FWD: V3 = [1.0, 0.0, 0.0];
const BACK: V3 = [-1.0, 0.0, 0.0];
const UP: V3 = [0.0, 0.0, 1.0];

fn arm(flex: f64, abd: f64, bend: f64) -> Limb {
    Limb::Angles { flex, abd, bend, toward: [1.0, 0.0, 0.6] }
}

fn leg(flex: f64, abd: f64, knee: f64) -> Limb {
    Limb::Angles { flex, abd, bend: knee, toward: BACK }
}

fn base_pose() -> Pose {
    Pose {
        pelvis: [0.0, 0.0, 1.0],
        grounded: true,
        trunk_pitch: 0.03,
        trunk_roll: 0.0,
        twist: 0.0,
        head_yaw: 0.0,
        head_pitch: 0.0,
        legs: [leg(0.0, 0.05, 0.05), leg(0.0, 0.05, 0.05)],
        arms: [arm(0.0, 0.12, 0.15), arm(0.0, 0.12, 0.15)],
        foot_pitch: [0.0; 2],
    }
}

/// A gait cycle at phase `phi`; `run` in [0, 1] blends walking into running.
fn gait(phi: f64, run: f64, stride: f64) -> Pose {
    let mut p = base_pose();
    let amp_h = (0.36 + 0.3 * run) * stride;
    let amp_k = 0.9 + 0.9 * run;
    let amp_a = (0.3 + 0.35 * run) * stride;
    for s in 0..2 {
        let ph = phi + s as f64 * std::f64::consts::PI;
        let flex = 0.04 + 0.1 * run + amp_h * ph.sin();
        let knee = 0.06 + 0.25 * run + amp_k * (ph + 0.3).cos().max(0.0).powi(2);
        p.legs[s] = leg(flex, 0.04, knee);
        p.foot_pitch[s] = 0.35 * (ph + 0.7).cos().max(0.0) - 0.1 * (ph - 1.2).cos().max(0.0);
        let elbow = 0.25 + 1.1 * run + 0.25 * (-ph.sin()).max(0.0);
        p.arms[s] = arm(-amp_a * ph.sin() + 0.05, 0.1 + 0.05 * run, elbow);
    }
    p.trunk_pitch = 0.04 + 0.18 * run;
    p.twist = 0.06 * phi.sin();
    p
}

/// Samples the activity and pose of one person (body frame).
/// With `arms_in` (the `arms-in` effect), some free arms are held against the torso.
pub fn sample_person<R: Rng>(rng: &mut R, anthro: Anthro, arms_in: bool) -> PersonModel {
    let activity = Activity::sample(rng);
    pose_person_with(rng, anthro, activity, arms_in)
}

/// Samples a pose of the given activity (body frame).
pub fn pose_person<R: Rng>(rng: &mut R, anthro: Anthro, activity: Activity) -> PersonModel {
    pose_person_with(rng, anthro, activity, false)
}

/// Share of persons with free arms (walking, standing, waving, phone) who hold
/// them against the torso under the `arms-in` effect.
const ARMS_IN: f64 = 0.45;

/// How a person holds arms against the torso.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ArmsIn {
    /// Hands in the front pockets: the hand disappears, the wrist sits at the hip.
    Pockets,
    /// Forearms folded across the chest (standing only).
    Crossed,
    /// Hands clasped behind the back.
    Behind,
    /// Arms hanging close to the body with a small swing.
    Close,
}

fn arms_in_style<R: Rng>(rng: &mut R, activity: Activity) -> ArmsIn {
    match rng.random_range(0..10) {
        0..=3 => ArmsIn::Pockets,
        4 | 5 if activity == Activity::Standing => ArmsIn::Crossed,
        4 | 5 => ArmsIn::Pockets,
        6 => ArmsIn::Behind,
        _ => ArmsIn::Close,
    }
}

/// Puts arm `s` (0 left, 1 right) against the torso in `style`.
fn arm_in<R: Rng>(rng: &mut R, style: ArmsIn, s: usize, limb: &mut Limb) {
    let sign = if s == 0 { 1.0 } else { -1.0 };
    *limb = match style {
        ArmsIn::Pockets => Limb::Angles {
            flex: rng.random_range(0.0..0.12),
            abd: rng.random_range(0.0..0.06),
            bend: rng.random_range(0.45..0.8),
            toward: [1.0, -0.2 * sign, 0.0],
        },
        ArmsIn::Crossed => Limb::Angles {
            flex: rng.random_range(0.3..0.55),
            abd: rng.random_range(0.03..0.12),
            bend: rng.random_range(1.9..2.3),
            toward: [0.5, -sign, 0.3],
        },
        ArmsIn::Behind => Limb::Angles {
            flex: rng.random_range(-0.45..-0.25),
            abd: rng.random_range(0.03..0.1),
            bend: rng.random_range(1.0..1.5),
            toward: [-0.3, -sign, 0.0],
        },
        ArmsIn::Close => match *limb {
            Limb::Angles { flex, bend, toward, .. } => {
                Limb::Angles { flex: 0.4 * flex, abd: rng.random_range(0.0..0.04), bend, toward }
            }
            reach => reach,
        },
    };
}

fn pose_person_with<R: Rng>(rng: &mut R, anthro: Anthro, activity: Activity, arms_in: bool) -> PersonModel {
    let a = &anthro;
    let h = a.height;
    let phi = rng.random_range(0.0..std::f64::consts::TAU);
    let mut extra: Vec<(Shape, Slot)> = Vec::new();
    let mut pose = match activity {
        Activity::Walking | Activity::CarryBag => gait(phi, 0.0, rng.random_range(0.6..1.25)),
        Activity::Running => gait(phi, rng.random_range(0.6..1.0), rng.random_range(0.8..1.2)),
        Activity::Standing | Activity::Waving | Activity::Phone => {
            let mut p = base_pose();
            for s in 0..2 {
                p.legs[s] = leg(n(rng, 0.0, 0.06), rng.random_range(0.02..0.14), rng.random_range(0.02..0.15));
                p.arms[s] = arm(n(rng, 0.0, 0.12), rng.random_range(0.06..0.25), rng.random_range(0.05..0.5));
            }
            p.trunk_roll = n(rng, 0.0, 0.03);
            if rng.random_bool(0.15) {
                // hands on hips
                for s in 0..2 {
                    p.arms[s] = Limb::Angles { flex: -0.2, abd: 0.55, bend: 1.7, toward: [0.3, -1.0, 0.2] };
                }
            }
            p
        }
        Activity::Crouching => {
            let mut p = base_pose();
            let (f, k) = (rng.random_range(1.2..2.0), rng.random_range(1.8..2.4));
            for s in 0..2 {
                p.legs[s] = leg(f + n(rng, 0.0, 0.1), rng.random_range(0.15..0.4), k + n(rng, 0.0, 0.1));
                p.arms[s] = arm(rng.random_range(0.4..1.3), rng.random_range(0.1..0.4), rng.random_range(0.3..1.3));
                p.foot_pitch[s] = -0.1;
            }
            p.trunk_pitch = rng.random_range(0.35..0.9);
            p.head_pitch = -0.3;
            p
        }
        Activity::Cycling => {
            let s = h / 1.75;
            let saddle = [-0.25 * s, 0.0, 0.9 * s.max(0.62)];
            let crank = [0.02 * s, 0.0, 0.3 * s.max(0.62)];
            let grips = [[0.42 * s, 0.22 * s, 1.0 * s.max(0.62)], [0.42 * s, -0.22 * s, 1.0 * s.max(0.62)]];
            let mut p = base_pose();
            p.grounded = false;
            p.pelvis = add(saddle, [0.0, 0.0, 0.07 * s]);
            p.trunk_pitch = rng.random_range(0.25..0.6);
            for (sd, grip) in grips.iter().enumerate() {
                let ph = phi + sd as f64 * std::f64::consts::PI;
                let pedal = add(crank, [0.17 * s * ph.cos(), if sd == 0 { 0.11 } else { -0.11 }, 0.17 * s * ph.sin()]);
                p.legs[sd] = Limb::Reach { target: add(pedal, [0.0, 0.0, a.ankle_h]), mid_dir: [1.0, 0.0, 0.4] };
                p.arms[sd] = Limb::Reach { target: *grip, mid_dir: [-0.6, if sd == 0 { 0.5 } else { -0.5 }, -0.3] };
                p.foot_pitch[sd] = 0.15;
            }
            let wr = 0.34 * s.max(0.6);
            for x in [-0.55 * s, 0.5 * s] {
                extra.push((Shape::ellipsoid([x, 0.0, wr], [FWD, [0.0, 1.0, 0.0], UP], [wr, 0.025, wr]), Slot::Tyre));
            }
            let bb = crank;
            extra.push((Shape::capsule([-0.55 * s, 0.0, wr], bb, 0.02), Slot::Frame));
            extra.push((Shape::capsule(bb, saddle, 0.022), Slot::Frame));
            extra.push((Shape::capsule(saddle, [0.35 * s, 0.0, grips[0][2] - 0.1], 0.022), Slot::Frame));
            extra.push((Shape::capsule(bb, [0.35 * s, 0.0, grips[0][2] - 0.1], 0.025), Slot::Frame));
            extra.push((Shape::capsule([0.5 * s, 0.0, wr], [0.38 * s, 0.0, grips[0][2]], 0.02), Slot::Frame));
            extra.push((Shape::capsule(grips[0], grips[1], 0.015), Slot::Frame));
            extra.push((Shape::cuboid(add(saddle, [0.0, 0.0, 0.02]), [0.24, 0.12, 0.05], 0.0), Slot::Gear));
            p
        }
        Activity::Scooter => {
            let s = h / 1.75;
            let deck_z = 0.1;
            let handle_z = 0.95 * s.max(0.65);
            let mut p = base_pose();
            p.grounded = false;
            let push = rng.random_bool(0.5);
            p.legs[0] = Limb::Reach { target: [0.05, 0.05, deck_z + 0.025 + a.ankle_h], mid_dir: [1.0, 0.0, 0.0] };
            p.legs[1] = if push {
                Limb::Reach { target: [-0.35 * s, -0.15, a.ankle_h], mid_dir: [1.0, 0.0, 0.0] }
            } else {
                Limb::Reach { target: [-0.22, -0.05, deck_z + 0.025 + a.ankle_h], mid_dir: [1.0, 0.0, 0.0] }
            };
            p.pelvis = [-0.08, 0.0, deck_z + a.hip_h * if push { 0.93 } else { 0.97 }];
            p.trunk_pitch = rng.random_range(0.05..0.3);
            for sd in 0..2 {
                let y = if sd == 0 { 0.2 } else { -0.2 };
                p.arms[sd] = Limb::Reach { target: [0.42 * s, y, handle_z], mid_dir: [-0.5, y, -0.5] };
            }
            extra.push((Shape::cuboid([0.0, 0.0, deck_z], [0.75, 0.14, 0.04], 0.0), Slot::Frame));
            extra.push((Shape::capsule([0.4, 0.0, deck_z], [0.44 * s, 0.0, handle_z], 0.02), Slot::Frame));
            extra.push((Shape::capsule([0.44 * s, 0.22, handle_z], [0.44 * s, -0.22, handle_z], 0.018), Slot::Gear));
            for x in [-0.38, 0.42] {
                extra.push((
                    Shape::ellipsoid([x, 0.0, 0.07], [FWD, [0.0, 1.0, 0.0], UP], [0.07, 0.02, 0.07]),
                    Slot::Tyre,
                ));
            }
            p
        }
        Activity::Stroller => {
            let mut p = gait(phi, 0.0, rng.random_range(0.5..0.9));
            let hz = a.hip_h * 1.02;
            let hx = 0.45 * h / 1.7;
            for sd in 0..2 {
                let y = if sd == 0 { 0.2 } else { -0.2 };
                p.arms[sd] = Limb::Reach { target: [hx, y, hz], mid_dir: [-0.4, y, -0.6] };
            }
            p.trunk_pitch = 0.12;
            extra.push((Shape::capsule([hx, 0.26, hz], [hx, -0.26, hz], 0.017), Slot::Frame));
            for y in [0.24, -0.24] {
                extra.push((Shape::capsule([hx, y, hz], [hx + 0.45, y, 0.55], 0.015), Slot::Frame));
            }
            extra.push((Shape::cuboid([hx + 0.62, 0.0, 0.62], [0.6, 0.46, 0.42], 0.0), Slot::Gear));
            extra.push((
                Shape::ellipsoid([hx + 0.8, 0.0, 0.82], [FWD, [0.0, 1.0, 0.0], UP], [0.25, 0.24, 0.2]),
                Slot::Gear,
            ));
            for (x, y) in [(hx + 0.4, 0.2), (hx + 0.4, -0.2), (hx + 0.85, 0.2), (hx + 0.85, -0.2)] {
                extra.push((Shape::ellipsoid([x, y, 0.1], [FWD, [0.0, 1.0, 0.0], UP], [0.1, 0.02, 0.1]), Slot::Tyre));
            }
            p
        }
        Activity::CarryBox => {
            let mut p = gait(phi, 0.0, rng.random_range(0.5..0.9));
            let size = [rng.random_range(0.25..0.45), rng.random_range(0.3..0.5), rng.random_range(0.2..0.4)];
            let c = [0.12 + a.trunk_depth() + size[0] / 2.0, 0.0, a.hip_h + 0.12 * h];
            for sd in 0..2 {
                let y = if sd == 0 { size[1] / 2.0 } else { -size[1] / 2.0 };
                p.arms[sd] = Limb::Reach { target: add(c, [0.0, y, -size[2] * 0.2]), mid_dir: [-0.3, y, -1.0] };
            }
            p.trunk_pitch = -0.05;
            extra.push((Shape::cuboid(c, size, 0.0), Slot::Gear));
            p
        }
    };
    let mut busy_hands = [false; 2];
    let mut pocketed = [false; 2];
    let free = matches!(activity, Activity::Walking | Activity::Standing | Activity::Waving | Activity::Phone);
    if arms_in && free && rng.random_bool(ARMS_IN) {
        let style = arms_in_style(rng, activity);
        let one = style == ArmsIn::Pockets && rng.random_bool(0.3);
        let first = rng.random_range(0..2usize);
        for s in 0..2 {
            if !one || s == first {
                arm_in(rng, style, s, &mut pose.arms[s]);
                busy_hands[s] = style != ArmsIn::Close;
                pocketed[s] = style == ArmsIn::Pockets;
            }
        }
    }
    match activity {
        Activity::Waving => {
            let both = rng.random_bool(0.3);
            let first = rng.random_range(0..2usize);
            for sd in 0..2 {
                if sd == first || both {
                    (busy_hands[sd], pocketed[sd]) = (false, false);
                    pose.arms[sd] = Limb::Angles {
                        flex: rng.random_range(-0.2..0.8),
                        abd: rng.random_range(1.6..2.9),
                        bend: rng.random_range(0.1..1.3),
                        toward: [0.3, 0.0, 1.0],
                    };
                }
            }
        }
        Activity::Phone => {
            let both = rng.random_bool(0.4);
            let first = rng.random_range(0..2usize);
            for sd in 0..2 {
                if sd == first || both {
                    (busy_hands[sd], pocketed[sd]) = (false, false);
                    let y = if sd == 0 { 0.4 } else { -0.4 };
                    pose.arms[sd] = Limb::Angles {
                        flex: rng.random_range(0.2..0.6),
                        abd: rng.random_range(0.05..0.3),
                        bend: rng.random_range(1.6..2.2),
                        toward: [0.6, -y, 1.0],
                    };
                }
            }
            pose.head_pitch = rng.random_range(0.25..0.6);
        }
        _ => {}
    }
    if !matches!(activity, Activity::Crouching | Activity::Phone) {
        pose.head_yaw = n(rng, 0.0, 0.35).clamp(-1.2, 1.2);
        pose.head_pitch += n(rng, 0.0, 0.1);
    }
    let skeleton = Skeleton::new(a, &pose);
    let mut parts: Vec<(Shape, Part, Slot)> = skeleton
        .shapes(a)
        .into_iter()
        .filter(|(_, part)| !matches!(part, Part::Hand(s) if pocketed[*s]))
        .map(|(sh, part)| {
            let slot = match part {
                Part::Head => Slot::Head,
                Part::Neck | Part::Hand(_) => Slot::Skin,
                Part::Chest | Part::UpperArm(_) => Slot::Shirt,
                Part::Forearm(_) => Slot::Sleeve,
                Part::Pelvis | Part::Thigh(_) => Slot::Pants,
                Part::Shin(_) => Slot::Shin,
                _ => Slot::Shoes,
            };
            (sh, part, slot)
        })
        .collect();
    if activity == Activity::CarryBag {
        let sd = rng.random_range(0..2usize);
        let w = skeleton.keypoints[5 + sd];
        let size = [rng.random_range(0.25..0.4), 0.1, rng.random_range(0.2..0.35)];
        extra.push((Shape::cuboid(add(w, [0.0, 0.0, -0.06 - size[2] / 2.0]), size, 0.0), Slot::Gear));
    }
    if matches!(activity, Activity::Walking | Activity::Standing | Activity::Phone | Activity::Running)
        && rng.random_bool(0.25)
    {
        // backpack on the back of the chest
        let chest = madd(skeleton.pelvis, skeleton.spine, 0.6 * a.torso_len);
        let back = scale([skeleton.spine[2], 0.0, -skeleton.spine[0]], -1.0);
        let c = madd(chest, back, a.trunk_depth() + 0.09);
        extra.push((Shape::ellipsoid(c, [back, [0.0, 1.0, 0.0], skeleton.spine], [0.11, 0.16, 0.22]), Slot::Gear));
    }
    parts.extend(extra.into_iter().map(|(s, slot)| (s, Part::Accessory, slot)));
    PersonModel { anthro, activity, skeleton, parts, busy_hands }
}
