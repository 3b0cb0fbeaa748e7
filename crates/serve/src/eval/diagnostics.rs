//! Diagnostics beside Waymo's metrics: how often the body's facing was read the wrong way round
//! (left and right exchanged) and how far the predicted facing is from the true one, overall and by
//! how the person stands to the sensor (front, side or back turned to it), since a LiDAR sees the
//! same silhouette from the front and the back and only the camera tells them apart.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use posefuse_core::keypoints::FLIP;
use posefuse_core::pipeline::{facing, yaw_difference, NOMINAL_LIDAR_ORIGIN};

/// Persons with fewer keypoints visible together with their mirror are not judged for a swap.
pub const MIN_VISIBLE_PAIRS: usize = 4;

/// Whether `pred` is closer to the truth with left and right exchanged than to the truth itself
/// (summed over keypoints visible on both sides); `None` with fewer than [`MIN_VISIBLE_PAIRS`].
pub fn left_right_swapped(pred: &[[f64; 3]], gt: &[[f64; 3]], visible: &[bool]) -> Option<bool> {
    let dist =
        |a: &[f64; 3], b: &[f64; 3]| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
    let (mut direct, mut mirrored, mut n) = (0.0, 0.0, 0);
    for k in 0..pred.len().min(gt.len()).min(visible.len()) {
        let m = FLIP[k];
        if visible[k] && visible.get(m).copied().unwrap_or(false) && pred[k].iter().all(|v| v.is_finite()) {
            direct += dist(&pred[k], &gt[k]);
            mirrored += dist(&pred[k], &gt[m]);
            n += 1;
        }
    }
    (n >= MIN_VISIBLE_PAIRS).then_some(mirrored < direct)
}

/// How a person stands to the sensor, from the true facing: `front` within 45° of facing it,
/// `back` within 45° of facing away, `side` otherwise.
pub fn view_of(gt: &[[f64; 3]], sensor: [f64; 3]) -> Option<&'static str> {
    let f = facing(gt)?;
    let hips = [gt.get(7)?, gt.get(8)?];
    let to_sensor = (sensor[1] - (hips[0][1] + hips[1][1]) / 2.0).atan2(sensor[0] - (hips[0][0] + hips[1][0]) / 2.0);
    let off = yaw_difference(f.yaw, to_sensor).to_degrees();
    Some(if off <= 45.0 {
        "front"
    } else if off >= 135.0 {
        "back"
    } else {
        "side"
    })
}

/// Swap and facing diagnostics of a set of persons.
#[derive(Debug, Clone, Default)]
pub struct Diagnostics {
    swaps: Vec<bool>,
    facing_errors_deg: Vec<f64>,
    swaps_by_view: BTreeMap<&'static str, Vec<bool>>,
}

/// Left/right swaps of the persons standing one way to the sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ViewSwaps {
    /// Persons judged.
    pub judged: usize,
    /// Share of them predicted with left and right exchanged.
    pub swap_rate: f64,
}

/// What [`Diagnostics`] report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct DiagnosticsReport {
    /// Persons judged for a swap (enough visible left/right pairs).
    pub swap_judged: usize,
    /// Share of them predicted with left and right exchanged.
    pub left_right_swap_rate: Option<f64>,
    /// Persons whose true and predicted facing both exist.
    pub facing_judged: usize,
    /// Median angle between predicted and true facing, degrees.
    pub facing_error_median_deg: Option<f64>,
    /// Swaps by how the person stands to the sensor (`front`, `side`, `back`; see [`view_of`]).
    #[serde(default)]
    pub swaps_by_view: BTreeMap<String, ViewSwaps>,
}

impl Diagnostics {
    /// Adds one person with 3D ground truth.
    pub fn add(&mut self, pred: &[[f64; 3]], gt: &[[f64; 3]], visible: &[bool]) {
        if let Some(s) = left_right_swapped(pred, gt, visible) {
            self.swaps.push(s);
            if let Some(view) = view_of(gt, NOMINAL_LIDAR_ORIGIN) {
                self.swaps_by_view.entry(view).or_default().push(s);
            }
        }
        let shoulders_and_hips_visible = [1, 2, 7, 8].iter().all(|&k| visible.get(k).copied().unwrap_or(false));
        if let (true, Some(p), Some(t)) = (shoulders_and_hips_visible, facing(pred), facing(gt)) {
            self.facing_errors_deg.push(yaw_difference(p.yaw, t.yaw).to_degrees());
        }
    }

    /// Merges another set.
    pub fn merge(&mut self, other: &Diagnostics) {
        self.swaps.extend_from_slice(&other.swaps);
        self.facing_errors_deg.extend_from_slice(&other.facing_errors_deg);
        for (view, s) in &other.swaps_by_view {
            self.swaps_by_view.entry(view).or_default().extend_from_slice(s);
        }
    }

    /// The report.
    pub fn report(&self) -> DiagnosticsReport {
        let rate = (!self.swaps.is_empty())
            .then(|| self.swaps.iter().filter(|s| **s).count() as f64 / self.swaps.len() as f64);
        DiagnosticsReport {
            swap_judged: self.swaps.len(),
            left_right_swap_rate: rate,
            facing_judged: self.facing_errors_deg.len(),
            facing_error_median_deg: median(&self.facing_errors_deg),
            swaps_by_view: self
                .swaps_by_view
                .iter()
                .map(|(view, s)| {
                    let swap_rate = s.iter().filter(|s| **s).count() as f64 / s.len() as f64;
                    (view.to_string(), ViewSwaps { judged: s.len(), swap_rate })
                })
                .collect(),
        }
    }
}

fn median(v: &[f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    Some(if n % 2 == 1 { s[n / 2] } else { (s[n / 2 - 1] + s[n / 2]) / 2.0 })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A body facing +x (its left is +y): shoulders, hips, knees, ankles, elbows, wrists.
    fn body() -> Vec<[f64; 3]> {
        let mut kp = vec![[0.0, 0.0, 1.6]; 13];
        for (k, z, w) in
            [(1, 1.4, 0.2), (3, 1.1, 0.25), (5, 0.8, 0.25), (7, 0.9, 0.15), (9, 0.5, 0.12), (11, 0.1, 0.12)]
        {
            kp[k] = [0.0, w, z];
            kp[k + 1] = [0.0, -w, z];
        }
        kp
    }

    fn mirrored(kp: &[[f64; 3]]) -> Vec<[f64; 3]> {
        (0..13).map(|k| kp[FLIP[k]]).collect()
    }

    #[test]
    fn a_mirrored_prediction_is_a_swap_and_faces_backwards() {
        let gt = body();
        let visible = vec![true; 13];
        assert_eq!(left_right_swapped(&gt, &gt, &visible), Some(false));
        assert_eq!(left_right_swapped(&mirrored(&gt), &gt, &visible), Some(true));
        let mut d = Diagnostics::default();
        d.add(&gt, &gt, &visible);
        d.add(&mirrored(&gt), &gt, &visible);
        d.add(&gt, &gt, &visible);
        let r = d.report();
        assert_eq!((r.swap_judged, r.facing_judged), (3, 3));
        assert!((r.left_right_swap_rate.unwrap() - 1.0 / 3.0).abs() < 1e-12);
        // errors 0, 180, 0 degrees: the median is 0
        assert_eq!(r.facing_error_median_deg, Some(0.0));
        let mut two = Diagnostics::default();
        two.add(&mirrored(&gt), &gt, &visible);
        two.add(&mirrored(&gt), &gt, &visible);
        two.merge(&d);
        // 180, 180, 0, 180, 0

        assert_eq!(two.report().facing_error_median_deg, Some(180.0));
    }

    #[test]
    fn too_few_visible_pairs_are_not_judged() {
        let gt = body();
        let mut visible = vec![false; 13];
        // a keypoint counts when it and its mirror are both visible
        for k in [0, 1, 2, 3] {
            visible[k] = true;
        }
        assert_eq!(left_right_swapped(&gt, &gt, &visible), None);
        visible[4] = true;
        assert_eq!(left_right_swapped(&gt, &gt, &visible), Some(false));
        visible[7] = true;
        let mut d = Diagnostics::default();
        visible[8] = false; // a hip unseen: no facing truth
        d.add(&gt, &gt, &visible);
        let r = d.report();
        assert_eq!((r.swap_judged, r.facing_judged, r.facing_error_median_deg), (1, 0, None));
    }

    #[test]
    fn swaps_are_counted_by_how_the_person_stands_to_the_sensor() {
        let sensor = NOMINAL_LIDAR_ORIGIN;
        let at = |kp: Vec<[f64; 3]>, x: f64, y: f64| -> Vec<[f64; 3]> {
            kp.into_iter().map(|p| [p[0] + x, p[1] + y, p[2]]).collect()
        };
        // the body faces +x: seen from a sensor ahead of it, it shows its front; behind it, its back
        let front = at(body(), -8.0, 0.0);
        let back = at(body(), 12.0, 0.0);
        let side = at(body(), sensor[0], 10.0);
        assert_eq!(view_of(&front, sensor), Some("front"));
        assert_eq!(view_of(&back, sensor), Some("back"));
        assert_eq!(view_of(&side, sensor), Some("side"));
        let visible = vec![true; 13];
        let mut d = Diagnostics::default();
        d.add(&mirrored(&back), &back, &visible);
        d.add(&back, &back, &visible);
        d.add(&front, &front, &visible);
        let mut more = Diagnostics::default();
        more.add(&mirrored(&side), &side, &visible);
        d.merge(&more);
        let r = d.report().swaps_by_view;
        assert_eq!(r["back"], ViewSwaps { judged: 2, swap_rate: 0.5 });
        assert_eq!(r["front"], ViewSwaps { judged: 1, swap_rate: 0.0 });
        assert_eq!(r["side"], ViewSwaps { judged: 1, swap_rate: 1.0 });
    }

    #[test]
    fn medians() {
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
    }
}
