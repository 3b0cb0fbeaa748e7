//! A Waymo-like 64-beam spinning LiDAR on the roof. Only the beams and columns in angular windows
//! around the labelled persons (plus surroundings) are cast, which is what keeps simulation fast;
//! returns are first hits with range noise and random dropouts, in the vehicle frame.

use rand::Rng;
use rand_distr::{Distribution, Normal};

use super::math::{dot, madd, norm, sub, V3};
use super::realism::{Effect, Realism};
use super::scene::{Hit, Scene};
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
/// `footprint` effect: full divergence of the beam (radians). Waymo does not publish its own;
/// 3 mrad is the order of automotive spinning LiDARs, a little more than the column step
/// (2.4 mrad), so neighbouring footprints overlap as on real sensors.
pub const FOOTPRINT_RAD: f64 = 0.003;
/// Weights of the footprint's samples: the centre, then four points on its edge (a Gaussian
/// beam's core carries most of the light).
const FOOTPRINT_WEIGHTS: [f64; 5] = [0.4, 0.15, 0.15, 0.15, 0.15];
/// A surface returns a pulse when it catches at least this share of the footprint's light.
const FOOTPRINT_DETECT: f64 = 0.15;
/// Surfaces closer than this in range merge into one pulse, reported at their light-weighted
/// mean range (a mixed pixel).
const PULSE_MERGE_M: f64 = 0.3;
/// `reflectivity` effect: range (m) at which a 10 % reflective surface at normal incidence is
/// detected half of the time (assumed; the order 64-beam sensors are specified for).
const REFLECTIVITY_HALF_RANGE_M: f64 = 50.0;

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
pub fn scan<R: Rng>(world: &World, realism: impl Into<Realism>, rng: &mut R) -> Vec<Return> {
    let realism = realism.into();
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
                let hit = if realism.has(Effect::Footprint) {
                    footprint_return(scene, o, inc, az, &cands)
                } else {
                    scene.cast(o, d, &cands, MAX_RANGE)
                };
                let Some(hit) = hit else {
                    continue;
                };
                let grazing = dot(hit.normal, d).abs();
                let p_drop = 0.025 + if grazing < 0.15 { 0.3 } else { 0.0 } + 0.1 * (hit.t / MAX_RANGE).powi(2);
                if rng.random_bool(p_drop.min(1.0)) {
                    continue;
                }
                if realism.has(Effect::Reflectivity) && !rng.random_bool(detection_probability(scene, &hit, grazing)) {
                    continue;
                }
                let mut t = hit.t;
                if realism.has(Effect::MixedPixels) && !realism.has(Effect::Footprint) {
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

/// The first return of a beam with a footprint: the nearest surface that catches enough of its
/// light, at the light-weighted range of the surfaces merged into that pulse, reported along the
/// beam's axis (so a limb the footprint's edge touches appears where the axis points). The hit's
/// surface is the merged sample nearest the axis. Replaces the mixed-pixel rule.
pub fn footprint_return(scene: &Scene, o: V3, inc: f64, az: f64, cands: &[u32]) -> Option<Hit> {
    let h = 0.5 * FOOTPRINT_RAD;
    let offsets = [(0.0, 0.0), (h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h)];
    let mut hits: Vec<(f64, Hit)> = offsets
        .iter()
        .zip(FOOTPRINT_WEIGHTS)
        .filter_map(|(&(da, de), w)| {
            scene.cast(o, beam_direction(inc + de, az + da / inc.cos()), cands, MAX_RANGE).map(|hit| (w, hit))
        })
        .collect();
    // Stable: among equal ranges the centre (listed first) stays first.
    hits.sort_by(|a, b| a.1.t.total_cmp(&b.1.t));
    let mut i = 0;
    while i < hits.len() {
        let start = hits[i].1.t;
        let j = hits[i..].iter().position(|(_, h)| h.t - start > PULSE_MERGE_M).map_or(hits.len(), |n| i + n);
        let pulse = &hits[i..j];
        let light: f64 = pulse.iter().map(|(w, _)| w).sum();
        if light >= FOOTPRINT_DETECT {
            let t = pulse.iter().map(|(w, h)| w * h.t).sum::<f64>() / light;
            let core = pulse.iter().max_by(|a, b| a.0.total_cmp(&b.0)).map(|(_, h)| *h)?;
            return Some(Hit { t, ..core });
        }
        i = j;
    }
    None
}

/// Probability that a surface returns enough light to be detected: the received power goes with
/// reflectivity × cos(incidence) / range², and detection is certain well above the half-range
/// power and rare well below it.
fn detection_probability(scene: &Scene, hit: &Hit, cos_incidence: f64) -> f64 {
    let albedo = match hit.prim {
        Some(p) => scene.materials[scene.prims[p as usize].material as usize].base,
        None => scene.ground.asphalt,
    };
    detection_probability_at(nir_reflectivity(albedo), cos_incidence, hit.t)
}

/// Detection probability of a surface of NIR reflectivity `rho` at `cos_incidence` and `range_m`:
/// one half for 10 % at normal incidence at `REFLECTIVITY_HALF_RANGE_M`, halving the miss
/// probability each time the received power grows by that much.
pub fn detection_probability_at(rho: f64, cos_incidence: f64, range_m: f64) -> f64 {
    let power = rho * cos_incidence * (REFLECTIVITY_HALF_RANGE_M / range_m.max(0.1)).powi(2);
    let half = 0.1 / std::f64::consts::LN_2;
    (1.0 - (-power / half).exp()).clamp(0.0, 1.0)
}

/// Near-infrared reflectivity of a surface from its linear-RGB albedo: dark fabrics stay dark
/// (about 5 %), skin and light fabrics reflect more in the near infrared than they look.
pub fn nir_reflectivity(albedo: [f32; 3]) -> f64 {
    let luma = 0.2126 * albedo[0] as f64 + 0.7152 * albedo[1] as f64 + 0.0722 * albedo[2] as f64;
    0.05 + 0.7 * luma.clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    #[test]
    fn a_dark_target_is_missed_half_the_time_at_the_half_range_and_rarely_up_close() {
        assert!(close(detection_probability_at(0.1, 1.0, 50.0), 0.5));
        // Half the range: four times the power, the miss probability to the fourth power.
        assert!(close(detection_probability_at(0.1, 1.0, 25.0), 1.0 - 0.5f64.powi(4)));
        assert!(close(detection_probability_at(0.2, 1.0, 50.0), 0.75));
        assert!(close(detection_probability_at(0.1, 0.5, 50.0), 1.0 - 0.5f64.sqrt()));
        assert!(close(detection_probability_at(0.0, 1.0, 10.0), 0.0));
        assert!(detection_probability_at(0.05, 1.0, 5.0) > 0.999);
        // A return at zero range does not divide by zero.
        assert!(detection_probability_at(0.1, 1.0, 0.0).is_finite());
    }

    #[test]
    fn near_infrared_reflectivity_follows_luma_from_five_to_seventy_five_percent() {
        assert!(close(nir_reflectivity([0.0; 3]), 0.05));
        assert!(close(nir_reflectivity([1.0; 3]), 0.75));
        assert!(close(nir_reflectivity([2.0; 3]), 0.75));
        assert!(close(nir_reflectivity([0.0, 1.0, 0.0]), 0.05 + 0.7 * 0.7152));
        assert!(close(nir_reflectivity([1.0, 0.0, 0.0]), 0.05 + 0.7 * 0.2126));
        assert!(close(nir_reflectivity([0.0, 0.0, 1.0]), 0.05 + 0.7 * 0.0722));
    }
}
