//! The articulated person: anthropometrics, a pose description (angles or reach targets per limb)
//! and forward kinematics to Waymo-style keypoints (joint centres inside the body; the nose on the
//! face surface) plus the body parts as capsules and ellipsoids.
//!
//! Body frame: origin on the ground under the body, x forward (the heading), y to the person's
//! left, z up. Side index 0 is left (+y), 1 is right (−y).

use rand::Rng;
use rand_distr::{Distribution, Normal};

use super::math::{add, cross, madd, normalize, orthogonal, scale, sub, V3};
use super::raycast::Shape;
use posefuse_core::keypoints::K;

/// Which body part a primitive belongs to (used by the occlusion rule and the materials).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Part {
    Head,
    Neck,
    Chest,
    Pelvis,
    UpperArm(usize),
    Forearm(usize),
    Hand(usize),
    Thigh(usize),
    Shin(usize),
    Foot(usize),
    /// Carried or ridden objects (bag, box, bicycle, stroller...).
    Accessory,
    /// Not a person (cars, poles, buildings...).
    Thing,
}

/// The body parts a keypoint sits in: a camera ray toward the keypoint must end on one of them.
pub fn keypoint_parts(k: usize) -> [Part; 3] {
    match k {
        0 => [Part::Head, Part::Head, Part::Head],
        1 | 2 => [Part::Chest, Part::UpperArm(k - 1), Part::Neck],
        3 | 4 => [Part::UpperArm(k - 3), Part::Forearm(k - 3), Part::Forearm(k - 3)],
        5 | 6 => [Part::Forearm(k - 5), Part::Hand(k - 5), Part::Hand(k - 5)],
        7 | 8 => [Part::Pelvis, Part::Thigh(k - 7), Part::Thigh(k - 7)],
        9 | 10 => [Part::Thigh(k - 9), Part::Shin(k - 9), Part::Shin(k - 9)],
        _ => [Part::Shin(k - 11), Part::Foot(k - 11), Part::Foot(k - 11)],
    }
}

/// Body measurements of one person (metres).
#[derive(Debug, Clone)]
pub struct Anthro {
    pub height: f64,
    /// Girth factor: 1 is average, larger is broader.
    pub girth: f64,
    pub head_h: f64,
    pub neck_len: f64,
    pub hip_h: f64,
    pub torso_len: f64,
    pub shoulder_half: f64,
    pub shoulder_drop: f64,
    pub hip_half: f64,
    pub thigh: f64,
    pub shin: f64,
    pub ankle_h: f64,
    pub upper_arm: f64,
    pub forearm: f64,
    pub hand: f64,
    pub foot: f64,
}

fn jitter<R: Rng>(rng: &mut R, sd: f64) -> f64 {
    Normal::new(1.0, sd).map(|n| n.sample(rng)).unwrap_or(1.0).clamp(1.0 - 3.0 * sd, 1.0 + 3.0 * sd)
}

impl Anthro {
    /// Adults (heights around 1.70 ± 0.09 m) and, one in seven, children of 1.0–1.45 m.
    pub fn sample<R: Rng>(rng: &mut R) -> Anthro {
        let height = if rng.random_bool(0.14) {
            rng.random_range(1.0..1.45)
        } else {
            Normal::new(1.70f64, 0.09).map(|n| n.sample(rng)).unwrap_or(1.7).clamp(1.45, 2.0)
        };
        let girth = rng.random_range(0.85..1.3);
        Anthro::new(height, girth, |sd| jitter(rng, sd))
    }

    /// Measurements for a height and girth; `jit(sd)` returns a multiplicative variation.
    pub fn new(height: f64, girth: f64, mut jit: impl FnMut(f64) -> f64) -> Anthro {
        let h = height;
        // Children have relatively larger heads and shorter legs.
        let cf = ((1.5 - h) / 0.5).clamp(0.0, 1.0);
        let head_h = h * (0.13 + 0.05 * cf) * jit(0.04);
        let neck_len = h * 0.045 * jit(0.08);
        let hip_h = h * (0.52 - 0.04 * cf) * jit(0.025);
        let neck_base = h - head_h - neck_len;
        let ankle_h = h * 0.039;
        let leg = hip_h - ankle_h;
        let thigh_frac = 0.5 * jit(0.03);
        Anthro {
            height: h,
            girth,
            head_h,
            neck_len,
            hip_h,
            torso_len: neck_base - hip_h,
            shoulder_half: h * (0.105 - 0.01 * cf) * (1.0 + 0.1 * (girth - 1.0)) * jit(0.04),
            shoulder_drop: h * 0.028,
            hip_half: h * 0.05 * girth.sqrt() * jit(0.05),
            thigh: leg * thigh_frac,
            shin: leg * (1.0 - thigh_frac),
            ankle_h,
            upper_arm: h * 0.172 * jit(0.03),
            forearm: h * 0.152 * jit(0.03),
            hand: h * 0.085 * jit(0.05),
            foot: h * 0.15 * jit(0.04),
        }
    }

    fn hs(&self) -> f64 {
        self.height / 1.7
    }

    /// Radii of the limb capsules: upper arm, forearm, hand, thigh, shin, foot, neck.
    pub fn radii(&self) -> [f64; 7] {
        let (g, s) = (self.girth, self.hs());
        [0.045 * g * s, 0.036 * g * s, 0.03 * s, 0.08 * g * s, 0.055 * g * s, 0.04 * s, 0.055 * g.sqrt() * s]
    }

    /// Half-depth of the trunk (chest and pelvis ellipsoids).
    pub fn trunk_depth(&self) -> f64 {
        0.11 * self.girth * self.hs()
    }
}

/// How a limb is placed: joint angles, or a target for its end (two-bone inverse kinematics).
#[derive(Debug, Clone, Copy)]
pub enum Limb {
    /// `flex`: swing forward from hanging down (rad); `abd`: raise sideways (rad, π/2 =
    /// horizontal); `bend`: elbow/knee angle; the lower segment turns toward `toward`.
    Angles { flex: f64, abd: f64, bend: f64, toward: V3 },
    /// End of the limb at `target` (body frame), middle joint pushed toward `mid_dir`.
    Reach { target: V3, mid_dir: V3 },
}

/// A full pose in the body frame.
#[derive(Debug, Clone)]
pub struct Pose {
    /// Pelvis (hip-joint midpoint) position; its height is ignored when `grounded`.
    pub pelvis: V3,
    /// Lower the body until the lowest foot touches the ground.
    pub grounded: bool,
    pub trunk_pitch: f64,
    pub trunk_roll: f64,
    pub twist: f64,
    pub head_yaw: f64,
    pub head_pitch: f64,
    pub legs: [Limb; 2],
    pub arms: [Limb; 2],
    /// Toe-down angle of each foot.
    pub foot_pitch: [f64; 2],
}

/// Joint positions from forward kinematics (body frame).
#[derive(Debug, Clone)]
pub struct Skeleton {
    pub keypoints: [V3; K],
    pub pelvis: V3,
    pub spine: V3,
    pub lateral: V3,
    pub neck_base: V3,
    pub neck_top: V3,
    pub head_center: V3,
    pub facing: V3,
    pub head_up: V3,
    pub heels: [V3; 2],
    pub toes: [V3; 2],
    pub hand_tips: [V3; 2],
}

fn side_sign(s: usize) -> f64 {
    if s == 0 {
        1.0
    } else {
        -1.0
    }
}

/// Middle and end joints of a two-segment limb.
fn limb_joints(root: V3, l1: f64, l2: f64, limb: &Limb, side: f64) -> (V3, V3) {
    match *limb {
        Limb::Angles { flex, abd, bend, toward } => {
            let d1 = normalize([flex.sin() * abd.cos(), side * abd.sin(), -flex.cos() * abd.cos()]);
            let t = orthogonal(toward, d1, [1.0, 0.0, 0.0]);
            let d2 = add(scale(d1, bend.cos()), scale(t, bend.sin()));
            let mid = madd(root, d1, l1);
            (mid, madd(mid, d2, l2))
        }
        Limb::Reach { target, mid_dir } => {
            let v = sub(target, root);
            let dist = super::math::norm(v).clamp((l1 - l2).abs() + 1e-3, l1 + l2 - 1e-4);
            let u = normalize(v);
            let a = (l1 * l1 - l2 * l2 + dist * dist) / (2.0 * dist);
            let h = (l1 * l1 - a * a).max(0.0).sqrt();
            let b = orthogonal(mid_dir, u, [0.0, 0.0, 1.0]);
            let mid = add(madd(root, u, a), scale(b, h));
            (mid, madd(root, u, dist))
        }
    }
}

impl Skeleton {
    /// Forward kinematics of `pose` for a person with measurements `a`.
    pub fn new(a: &Anthro, pose: &Pose) -> Skeleton {
        let mut sk = Skeleton::at(a, pose, pose.pelvis);
        if pose.grounded {
            let r_foot = a.radii()[5];
            let low = (0..2).map(|s| sk.heels[s][2].min(sk.toes[s][2])).fold(f64::INFINITY, f64::min) - r_foot;
            let mut p = pose.pelvis;
            p[2] -= low;
            sk = Skeleton::at(a, pose, p);
        }
        sk
    }

    fn at(a: &Anthro, pose: &Pose, pelvis: V3) -> Skeleton {
        let mut kp = [[0.0; 3]; K];
        let (sp, cp) = pose.trunk_pitch.sin_cos();
        let spine = normalize([sp, -pose.trunk_roll.sin(), cp * pose.trunk_roll.cos()]);
        let (st, ct) = pose.twist.sin_cos();
        let lateral = orthogonal([-st, ct, 0.0], spine, [0.0, 1.0, 0.0]);
        let neck_base = madd(pelvis, spine, a.torso_len);
        let neck_top = madd(neck_base, spine, a.neck_len);
        let (sy, cy) = pose.head_yaw.sin_cos();
        let (sph, cph) = pose.head_pitch.sin_cos();
        let facing = normalize([cy * cph, sy * cph, -sph]);
        let head_up = orthogonal(spine, facing, [0.0, 0.0, 1.0]);
        let head_center = add(madd(neck_top, head_up, 0.5 * a.head_h * 0.85), scale(facing, 0.012 * a.height));
        // The nose tip sits on the face surface, a little below the head's centre.
        kp[0] = add(madd(head_center, facing, 0.5 * a.head_h * 0.78 * 0.97), scale(head_up, -0.25 * 0.5 * a.head_h));
        let mut heels = [[0.0; 3]; 2];
        let mut toes = [[0.0; 3]; 2];
        let mut hand_tips = [[0.0; 3]; 2];
        for s in 0..2 {
            let sign = side_sign(s);
            let shoulder = add(madd(neck_base, spine, -a.shoulder_drop), scale(lateral, sign * a.shoulder_half));
            let (elbow, wrist) = limb_joints(shoulder, a.upper_arm, a.forearm, &pose.arms[s], sign);
            kp[1 + s] = shoulder;
            kp[3 + s] = elbow;
            kp[5 + s] = wrist;
            hand_tips[s] = madd(wrist, normalize(sub(wrist, elbow)), a.hand);
            let hip = madd(pelvis, [0.0, 1.0, 0.0], sign * a.hip_half);
            let (knee, ankle) = limb_joints(hip, a.thigh, a.shin, &pose.legs[s], sign);
            kp[7 + s] = hip;
            kp[9 + s] = knee;
            kp[11 + s] = ankle;
            let p = pose.foot_pitch[s];
            let fd = normalize([p.cos(), sign * 0.12, -p.sin()]);
            let down = normalize(cross(fd, cross([0.0, 0.0, 1.0], fd)));
            let base = madd(ankle, down, -0.5 * a.ankle_h);
            toes[s] = madd(base, fd, 0.7 * a.foot);
            heels[s] = madd(base, fd, -0.18 * a.foot);
        }
        Skeleton {
            keypoints: kp,
            pelvis,
            spine,
            lateral,
            neck_base,
            neck_top,
            head_center,
            facing,
            head_up,
            heels,
            toes,
            hand_tips,
        }
    }

    /// The body parts as primitives (body frame).
    pub fn shapes(&self, a: &Anthro) -> Vec<(Shape, Part)> {
        let [r_ua, r_fa, r_hand, r_th, r_sh, r_foot, r_neck] = a.radii();
        let kp = &self.keypoints;
        let depth = a.trunk_depth();
        let fwd = orthogonal(cross(self.lateral, self.spine), self.spine, [1.0, 0.0, 0.0]);
        let mut out = Vec::with_capacity(18);
        out.push((
            Shape::ellipsoid(
                self.head_center,
                [self.facing, cross(self.head_up, self.facing), self.head_up],
                [0.5 * a.head_h * 0.78, 0.5 * a.head_h * 0.68, 0.5 * a.head_h],
            ),
            Part::Head,
        ));
        out.push((Shape::capsule(self.neck_base, self.neck_top, r_neck), Part::Neck));
        let chest_c = madd(self.pelvis, self.spine, 0.66 * a.torso_len);
        out.push((
            Shape::ellipsoid(
                chest_c,
                [fwd, self.lateral, self.spine],
                [depth, a.shoulder_half + 0.035 * a.girth * a.height / 1.7, 0.31 * a.torso_len],
            ),
            Part::Chest,
        ));
        let pelvis_c = madd(self.pelvis, self.spine, 0.2 * a.torso_len);
        out.push((
            Shape::ellipsoid(
                pelvis_c,
                [fwd, self.lateral, self.spine],
                [depth * 0.95, a.hip_half + 0.075 * a.girth * a.height / 1.7, 0.3 * a.torso_len],
            ),
            Part::Pelvis,
        ));
        for s in 0..2 {
            out.push((Shape::capsule(kp[1 + s], kp[3 + s], r_ua), Part::UpperArm(s)));
            out.push((Shape::capsule(kp[3 + s], kp[5 + s], r_fa), Part::Forearm(s)));
            let hd = normalize(sub(self.hand_tips[s], kp[5 + s]));
            out.push((Shape::capsule(madd(kp[5 + s], hd, 0.3 * r_hand), self.hand_tips[s], r_hand), Part::Hand(s)));
            out.push((Shape::capsule(kp[7 + s], kp[9 + s], r_th), Part::Thigh(s)));
            out.push((Shape::capsule(kp[9 + s], kp[11 + s], r_sh), Part::Shin(s)));
            out.push((Shape::capsule(self.heels[s], self.toes[s], r_foot), Part::Foot(s)));
        }
        out
    }

    /// How far (m) the first camera hit may lie from each keypoint and still count as seeing it:
    /// the thickness of the body around the joint plus 6 cm.
    pub fn visibility_tolerance(a: &Anthro) -> [f64; K] {
        let [r_ua, r_fa, r_hand, r_th, r_sh, r_foot, _] = a.radii();
        let d = a.trunk_depth();
        let mut t = [0.0; K];
        t[0] = 0.06;
        for s in 0..2 {
            t[1 + s] = d.max(r_ua) + 0.06;
            t[3 + s] = r_ua.max(r_fa) + 0.06;
            t[5 + s] = r_fa.max(r_hand) + 0.06;
            t[7 + s] = d.max(r_th) + 0.06;
            t[9 + s] = r_th.max(r_sh) + 0.06;
            t[11 + s] = r_sh.max(r_foot) + 0.06;
        }
        t
    }
}
