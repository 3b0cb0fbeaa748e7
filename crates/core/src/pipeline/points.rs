//! Point input: the LiDAR points inside a person's 3D box, in model-input coordinates, with their
//! projections into the crop, reduced to exactly N by a choice seeded from the points themselves.

use rand::{seq::index, Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{CropTransform, PipelineConfig, PointFrame};
use crate::geometry::{BoxFrame, Camera};

/// All points of one person (inside the box grown by `box_margin`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PersonPoints {
    /// Model-input coordinates (metres from the box centre, in the box frame when rotated).
    pub local: Vec<[f32; 3]>,
    /// The same points in the vehicle frame, as they arrived.
    pub vehicle: Vec<[f32; 3]>,
}

impl PersonPoints {
    pub fn len(&self) -> usize {
        self.local.len()
    }

    pub fn is_empty(&self) -> bool {
        self.local.is_empty()
    }

    /// Every point's projection in model-input pixels (see [`model_uv`]).
    pub fn model_uv(&self, camera: Option<&Camera>, crop: Option<&CropTransform>) -> Vec<[f32; 2]> {
        self.vehicle.iter().map(|p| model_uv(p, camera, crop)).collect()
    }
}

/// A vehicle-frame point's projection in model-input pixels; NaN without a valid projection
/// (behind the camera, or where the lens model folds back) or without a camera and a crop.
pub fn model_uv(p: &[f32; 3], camera: Option<&Camera>, crop: Option<&CropTransform>) -> [f32; 2] {
    match (camera, crop) {
        (Some(cam), Some(t)) => {
            let pr = cam.project([p[0] as f64, p[1] as f64, p[2] as f64]);
            if pr.valid {
                let mp = t.to_model(pr.uv);
                [mp[0] as f32, mp[1] as f32]
            } else {
                [f32::NAN; 2]
            }
        }
        _ => [f32::NAN; 2],
    }
}

/// Exactly N points for the point network, with their model-input pixels and which in-box point
/// each row is.
#[derive(Debug, Clone, PartialEq)]
pub struct PointInput {
    pub xyz: Vec<[f32; 3]>,
    pub uv: Vec<[f32; 2]>,
    pub indices: Vec<usize>,
}

/// The model-input frame of a person's box under `cfg` (see [`PointFrame`]): the box's centre and
/// size, turned to the frame's x axis.
pub fn model_frame(b: &BoxFrame, cfg: &PipelineConfig) -> BoxFrame {
    match cfg.point_frame() {
        PointFrame::BoxHeading => *b,
        PointFrame::Centred => b.turned_to(0.0),
        PointFrame::View => {
            let o = cfg.view_origin;
            let (dx, dy) = (b.center[0] - o[0], b.center[1] - o[1]);
            // A box centred on the origin's vertical has no ray: any x will do, the vehicle's is stable.
            b.turned_to(if dx == 0.0 && dy == 0.0 { 0.0 } else { dy.atan2(dx) })
        }
    }
}

/// Vehicle frame → model-input coordinates.
pub fn to_local(b: &BoxFrame, p: [f64; 3], cfg: &PipelineConfig) -> [f64; 3] {
    model_frame(b, cfg).to_local(p)
}

/// Model-input coordinates → vehicle frame.
pub fn from_local(b: &BoxFrame, q: [f64; 3], cfg: &PipelineConfig) -> [f64; 3] {
    model_frame(b, cfg).to_vehicle(q)
}

/// The points of `points` (vehicle frame) inside `b` grown by `cfg.box_margin`. Projection waits
/// for [`point_input`]: only the N chosen points need it.
pub fn gather_points(points: &[[f32; 3]], b: &BoxFrame, cfg: &PipelineConfig) -> PersonPoints {
    let m = cfg.box_margin;
    // An axis-aligned bound of the rotated box rejects most of a sweep with three compares.
    let reach = ((b.size[0] / 2.0 + m).powi(2) + (b.size[1] / 2.0 + m).powi(2)).sqrt();
    let lo = [b.center[0] - reach, b.center[1] - reach, b.center[2] - b.size[2] / 2.0 - m].map(|v| (v - 1e-3) as f32);
    let hi = [b.center[0] + reach, b.center[1] + reach, b.center[2] + b.size[2] / 2.0 + m].map(|v| (v + 1e-3) as f32);
    let half = [b.size[0] / 2.0 + m, b.size[1] / 2.0 + m, b.size[2] / 2.0 + m];
    let model = model_frame(b, cfg);
    let mut out = PersonPoints::default();
    for p in points {
        if p[0] < lo[0] || p[0] > hi[0] || p[1] < lo[1] || p[1] > hi[1] || p[2] < lo[2] || p[2] > hi[2] {
            continue;
        }
        let q = [p[0] as f64, p[1] as f64, p[2] as f64];
        let boxed = b.to_local(q);
        if (0..3).any(|a| boxed[a].abs() > half[a]) {
            continue;
        }
        let l = if cfg.point_frame() == PointFrame::BoxHeading { boxed } else { model.to_local(q) };
        out.local.push([l[0] as f32, l[1] as f32, l[2] as f32]);
        out.vehicle.push(*p);
    }
    out
}

/// Model-input points of a box frame with heading `from` in the frame of the same box turned to
/// heading `to` (the frames share their centre; only the yaw differs).
pub fn turn_points(xyz: &[[f32; 3]], from: f64, to: f64) -> Vec<[f32; 3]> {
    let (s, c) = (from - to).sin_cos();
    xyz.iter()
        .map(|p| {
            let (x, y) = (p[0] as f64, p[1] as f64);
            [(c * x - s * y) as f32, (s * x + c * y) as f32, p[2]]
        })
        .collect()
}

/// FNV-1a over the points' bit patterns, a 32-bit word at a time: the same points always give
/// the same selection.
pub fn input_seed(points: &[[f32; 3]]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for v in points.iter().flatten() {
        h ^= v.to_bits() as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// `n` indices into `0..count`: a sorted sample without replacement when there are enough points,
/// otherwise every point once and random repeats for the rest. Empty when `count` is 0.
pub fn select_indices(count: usize, n: usize, seed: u64) -> Vec<usize> {
    if count == 0 {
        return Vec::new();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    if count >= n {
        let mut idx = index::sample(&mut rng, count, n).into_vec();
        idx.sort_unstable();
        idx
    } else {
        let mut idx: Vec<usize> = (0..count).collect();
        idx.extend((count..n).map(|_| rng.random_range(0..count)));
        idx
    }
}

/// The network's N points for a person with their model-input pixels (NaN without a camera and
/// a crop), or `None` when the box holds no points.
pub fn point_input(
    pp: &PersonPoints,
    camera: Option<&Camera>,
    crop: Option<&CropTransform>,
    cfg: &PipelineConfig,
) -> Option<PointInput> {
    if pp.is_empty() {
        return None;
    }
    let indices = select_indices(pp.len(), cfg.num_points as usize, input_seed(&pp.vehicle));
    Some(PointInput {
        xyz: indices.iter().map(|&i| pp.local[i]).collect(),
        uv: indices.iter().map(|&i| model_uv(&pp.vehicle[i], camera, crop)).collect(),
        indices,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::Box3d;

    fn person_box_3d() -> Box3d {
        Box3d {
            center_x: 10.0,
            center_y: 2.0,
            center_z: 0.9,
            length: 0.6,
            width: 0.8,
            height: 1.8,
            heading: std::f64::consts::FRAC_PI_2,
        }
    }

    fn person_box() -> BoxFrame {
        BoxFrame::new(&person_box_3d())
    }

    #[test]
    fn turned_points_are_the_same_vehicle_points() {
        let b = BoxFrame::new(&Box3d { heading: 0.4, ..person_box_3d() });
        let local = [[0.2f32, -0.1, 0.5], [-0.3, 0.25, -0.7]];
        let turned = turn_points(&local, 0.4, 2.5);
        let other = b.turned_to(2.5);
        for (l, t) in local.iter().zip(&turned) {
            let v1 = b.to_vehicle([l[0] as f64, l[1] as f64, l[2] as f64]);
            let v2 = other.to_vehicle([t[0] as f64, t[1] as f64, t[2] as f64]);
            for a in 0..3 {
                assert!((v1[a] - v2[a]).abs() < 1e-6, "{v1:?} {v2:?}");
            }
        }
        // a quarter turn of the box turns its points a quarter turn back
        let q = turn_points(&[[1.0, 0.0, 0.3]], 0.0, std::f64::consts::FRAC_PI_2)[0];
        assert!(q[0].abs() < 1e-6 && (q[1] + 1.0).abs() < 1e-6 && q[2] == 0.3, "{q:?}");
    }

    #[test]
    fn gathers_inside_the_rotated_box_only() {
        let cfg = PipelineConfig::default();
        let b = person_box();
        // heading 90°: the box's length (0.6) runs along vehicle y, its width (0.8) along x.
        // in; in the margin along its length; out; in the top margin; out above; out beside its
        // width; in the bottom margin (below the ground plane of the box)
        let pts = [
            [10.35, 2.0, 0.9],
            [10.0, 2.4, 0.9],
            [10.0, 2.5, 0.9],
            [10.0, 2.0, 1.9],
            [10.0, 2.0, 1.96],
            [10.6, 2.0, 0.9],
            [10.0, 2.0, -0.05],
        ];
        let pp = gather_points(&pts, &b, &cfg);
        assert_eq!(pp.vehicle, vec![pts[0], pts[1], pts[3], pts[6]]);
        // local: x along heading (vehicle +y), y to the left of it (vehicle −x)
        let l = pp.local[0];
        assert!((l[0] - 0.0).abs() < 1e-6 && (l[1] + 0.35).abs() < 1e-6 && l[2].abs() < 1e-6);
        assert!(pp.model_uv(None, None).iter().all(|uv| uv[0].is_nan()));
        let q = from_local(&b, [0.1, -0.35, 0.2], &cfg);
        let back = to_local(&b, q, &cfg);
        assert!((back[0] - 0.1).abs() < 1e-12 && (back[1] + 0.35).abs() < 1e-12 && (back[2] - 0.2).abs() < 1e-12);
        let unrotated = PipelineConfig { rotate_by_heading: false, ..cfg.clone() };
        let l = to_local(&b, [10.35, 2.0, 0.9], &unrotated);
        assert!((l[0] - 0.35).abs() < 1e-12 && l[1].abs() < 1e-12 && l[2].abs() < 1e-12);
        let view = cfg.in_frame(PointFrame::View);
        let pv = gather_points(&pts, &b, &view);
        assert_eq!(pv.vehicle, pp.vehicle, "the frame changes coordinates, not membership");
    }

    #[test]
    fn the_view_frame_looks_from_the_sensor_and_ignores_the_heading() {
        let cfg =
            PipelineConfig { view_origin: [1.0, -1.0, 2.0], ..PipelineConfig::default() }.in_frame(PointFrame::View);
        // box centre (10, 2): the ray from (1, −1) runs along (9, 3)
        let ray = 3f64.atan2(9.0);
        for heading in [0.0, 1.0, -2.5, std::f64::consts::PI] {
            let b = BoxFrame::new(&Box3d { heading, ..person_box_3d() });
            assert!((model_frame(&b, &cfg).heading - ray).abs() < 1e-12);
            // a point 0.3 m further along the ray: +x; 0.2 m to the ray's left: +y; z relative
            let (c, s) = (ray.cos(), ray.sin());
            let p = [10.0 + 0.3 * c - 0.2 * s, 2.0 + 0.3 * s + 0.2 * c, 1.2];
            let l = to_local(&b, p, &cfg);
            assert!((l[0] - 0.3).abs() < 1e-12 && (l[1] - 0.2).abs() < 1e-12 && (l[2] - 0.3).abs() < 1e-12, "{l:?}");
            let back = from_local(&b, l, &cfg);
            assert!((0..3).all(|a| (back[a] - p[a]).abs() < 1e-12));
        }
        // the sensor itself is on the −x side of every person
        let b = BoxFrame::new(&person_box_3d());
        assert!(to_local(&b, [1.0, -1.0, 2.0], &cfg)[0] < -9.0);
        let over = BoxFrame::new(&Box3d { center_x: 1.0, center_y: -1.0, ..person_box_3d() });
        assert_eq!(model_frame(&over, &cfg).heading, 0.0);
    }

    #[test]
    fn selection_is_deterministic_exact_and_covers_small_sets() {
        let a = select_indices(1000, 256, 7);
        assert_eq!(a, select_indices(1000, 256, 7));
        assert_ne!(a, select_indices(1000, 256, 8));
        assert_eq!(a.len(), 256);
        assert!(a.windows(2).all(|w| w[0] < w[1]) && *a.last().unwrap_or(&0) < 1000);
        let b = select_indices(10, 256, 1);
        assert_eq!(b.len(), 256);
        assert_eq!(&b[..10], &(0..10).collect::<Vec<_>>()[..]);
        assert!(b.iter().all(|&i| i < 10));
        assert!(select_indices(0, 256, 1).is_empty());
    }

    #[test]
    fn point_input_is_seeded_by_the_points() {
        let cfg = PipelineConfig { num_points: 16, ..PipelineConfig::default() };
        let b = person_box();
        let pts: Vec<[f32; 3]> =
            (0..40).map(|i| [10.0, 2.0 + (i as f32 - 20.0) * 0.01, 0.2 + 0.03 * i as f32]).collect();
        let pp = gather_points(&pts, &b, &cfg);
        let a = point_input(&pp, None, None, &cfg).unwrap_or_else(|| panic!("points expected"));
        assert_eq!(a.xyz.len(), 16);
        let again = point_input(&pp, None, None, &cfg).unwrap_or_else(|| panic!("points expected"));
        assert_eq!((&a.indices, &a.xyz), (&again.indices, &again.xyz));
        for (row, &i) in a.indices.iter().enumerate() {
            assert_eq!(a.xyz[row], pp.local[i]);
        }
        assert_ne!(input_seed(&pts), input_seed(&pts[1..]));
        assert!(point_input(&PersonPoints::default(), None, None, &cfg).is_none());
    }
}
