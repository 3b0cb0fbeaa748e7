//! A Waymo-like 64-beam spinning LiDAR on the roof. Only the beams and columns in angular windows
//! around the labelled persons (plus surroundings) are cast, which is what keeps simulation fast;
//! returns are first hits with range noise and random dropouts, in the vehicle frame.

use rand::Rng;
use rand_distr::{Distribution, Normal};

use super::math::{dot, madd, norm, sub, V3};
use super::scene::Scene;
use super::street::Profile;
use super::world::World;

pub const BEAMS: usize = 64;
pub const COLUMNS: usize = 2650;
pub const MAX_RANGE: f64 = 75.0;
pub const RANGE_NOISE_M: f64 = 0.02;
const TOP_DEG: f64 = 2.4;
const BOTTOM_DEG: f64 = -17.6;
/// Street profile: a return is mixed (range between two surfaces) when a ray this far aside
/// (radians, half a column) ends more than `MIXED_GAP_M` away: the beam's footprint straddles an
/// edge.
const MIXED_OFFSET_RAD: f64 = std::f64::consts::PI / COLUMNS as f64;
const MIXED_GAP_M: f64 = 0.3;
/// Lateral margin (m) of each window beyond the person's footprint.
pub const WINDOW_MARGIN_M: f64 = 1.5;

/// Beam inclinations (radians), top beam first. Spacing is finest around −2° (where distant
/// pedestrians are seen) and grows toward both ends, like the real sensor.
pub fn inclinations() -> [f64; BEAMS] {
    let gap = |deg: f64| 1.0 + 0.15 * (deg + 2.0).abs();
    let fov = TOP_DEG - BOTTOM_DEG;
    // Relative gaps depend on the angle, the angle on the scale: a few fixed-point rounds.
    let mut k = fov / (BEAMS - 1) as f64;
    let mut raw = [0.0; BEAMS];
    for _ in 0..20 {
        for i in 1..BEAMS {
            raw[i] = raw[i - 1] + gap(TOP_DEG - raw[i - 1] * k);
        }
        k = fov / raw[BEAMS - 1];
    }
    raw.map(|r| (TOP_DEG - r * k).to_radians())
}

/// Azimuth (radians) of a column: column 0 starts at +π and azimuth decreases with the column.
pub fn column_azimuth(c: usize) -> f64 {
    std::f64::consts::PI - (c as f64 + 0.5) * std::f64::consts::TAU / COLUMNS as f64
}

/// Continuous column index of an azimuth.
pub fn column_of(az: f64) -> f64 {
    (std::f64::consts::PI - az).rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU * COLUMNS as f64 - 0.5
}

/// Unit direction of a beam at a column.
pub fn beam_direction(inclination: f64, az: f64) -> V3 {
    [inclination.cos() * az.cos(), inclination.cos() * az.sin(), inclination.sin()]
}

/// One LiDAR return.
#[derive(Debug, Clone, Copy)]
pub struct Return {
    pub xyz: [f32; 3],
    /// Object id (`scene::GROUND` for the ground).
    pub object: u32,
    pub prim: Option<u32>,
}

/// An angular window: columns `c0..=c1` (may wrap) and beams `b0..=b1`.
#[derive(Debug, Clone, Copy)]
pub struct Window {
    pub c0: i64,
    pub c1: i64,
    pub b0: usize,
    pub b1: usize,
}

/// The window around a vertical cylinder (centre on the ground, radius, height) seen from `o`.
pub fn window_around(o: V3, center: V3, radius: f64, height: f64, incl: &[f64; BEAMS]) -> Window {
    let v = sub(center, o);
    let rho = (v[0] * v[0] + v[1] * v[1]).sqrt().max(0.5);
    let az = v[1].atan2(v[0]);
    let half = ((radius + WINDOW_MARGIN_M) / rho).atan();
    let cc = column_of(az);
    let dc = half / std::f64::consts::TAU * COLUMNS as f64;
    let near = (rho - radius - WINDOW_MARGIN_M).max(0.3);
    let far = rho + radius + WINDOW_MARGIN_M;
    let top = height + 0.5 - o[2];
    let e_hi = top.atan2(near).max(top.atan2(far));
    let e_lo = (-o[2]).atan2(near);
    let b0 = incl.iter().position(|&e| e <= e_hi).unwrap_or(BEAMS);
    let b1 = incl.iter().rposition(|&e| e >= e_lo).unwrap_or(0);
    Window { c0: (cc - dc).floor() as i64, c1: (cc + dc).ceil() as i64, b0, b1 }
}

fn overlaps_window(scene: &Scene, i: usize, o: V3, az_lo: f64, az_hi: f64, e_lo: f64, e_hi: f64) -> bool {
    let p = &scene.prims[i];
    let v = sub(p.center, o);
    let d = norm(v);
    if d <= p.radius {
        return true;
    }
    let ang = (p.radius / d).asin();
    let az = v[1].atan2(v[0]);
    // Azimuth distance to the window's centre, wrapped.
    let mid = 0.5 * (az_lo + az_hi);
    let da = (az - mid + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
    let el = (v[2] / d).asin();
    da.abs() <= 0.5 * (az_hi - az_lo) + ang && el + ang >= e_lo && el - ang <= e_hi
}

/// Scans the windows around the world's labelled persons. Deterministic given `rng`.
pub fn scan<R: Rng>(world: &World, profile: Profile, rng: &mut R) -> Vec<Return> {
    let incl = inclinations();
    let o = world.lidar_origin;
    let scene = &world.scene;
    let mut done = vec![false; BEAMS * COLUMNS];
    let noise = Normal::new(0.0, RANGE_NOISE_M).ok();
    let mut out = Vec::new();
    for p in &world.persons {
        let r = 0.5 * p.box3d.length.max(p.box3d.width);
        let w = window_around(o, [p.box3d.center_x, p.box3d.center_y, 0.0], r, p.box3d.height, &incl);
        if w.b0 > w.b1 {
            continue;
        }
        // Column azimuths decrease with the index: c1 is the low end.
        let az_hi = column_azimuth(0) - (w.c0 as f64) * std::f64::consts::TAU / COLUMNS as f64;
        let az_lo = column_azimuth(0) - (w.c1 as f64) * std::f64::consts::TAU / COLUMNS as f64;
        let (e_lo, e_hi) = (incl[w.b1], incl[w.b0]);
        let cands: Vec<u32> = (0..scene.prims.len())
            .filter(|&i| overlaps_window(scene, i, o, az_lo - 0.01, az_hi + 0.01, e_lo - 0.01, e_hi + 0.01))
            .map(|i| i as u32)
            .collect();
        for c in w.c0..=w.c1 {
            let col = c.rem_euclid(COLUMNS as i64) as usize;
            let az = column_azimuth(col);
            for (b, &inc) in incl.iter().enumerate().take(w.b1 + 1).skip(w.b0) {
                let cell = b * COLUMNS + col;
                if done[cell] {
                    continue;
                }
                done[cell] = true;
                let d = beam_direction(inc, az);
                let Some(hit) = scene.cast(o, d, &cands, MAX_RANGE) else {
                    continue;
                };
                let grazing = dot(hit.normal, d).abs();
                let p_drop = 0.025 + if grazing < 0.15 { 0.3 } else { 0.0 } + 0.1 * (hit.t / MAX_RANGE).powi(2);
                if rng.random_bool(p_drop.min(1.0)) {
                    continue;
                }
                let mut t = hit.t;
                if profile == Profile::Street {
                    let side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
                    let aside = scene.cast(o, beam_direction(inc, az + side * MIXED_OFFSET_RAD), &cands, MAX_RANGE);
                    match aside {
                        Some(h) if (h.t - t).abs() > MIXED_GAP_M && rng.random_bool(0.5) => {
                            t += rng.random::<f64>() * (h.t - t);
                        }
                        None if rng.random_bool(0.3) => continue,
                        _ => {}
                    }
                }
                let t = t + noise.map_or(0.0, |n| n.sample(rng));
                let x = madd(o, d, t);
                out.push(Return {
                    xyz: [x[0] as f32, x[1] as f32, x[2] as f32],
                    object: scene.object_of(&hit),
                    prim: hit.prim,
                });
            }
        }
    }
    out
}
