//! Diagnostics beside Waymo's metrics: how often the body's facing was read the wrong way round
//! (left and right exchanged) and how far the predicted facing is from the true one.

use serde::{Deserialize, Serialize};

use crate::keypoints::FLIP;
use crate::pipeline::{facing, yaw_difference};

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

/// Swap and facing diagnostics of a set of persons.
#[derive(Debug, Clone, Default)]
pub struct Diagnostics {
    swaps: Vec<bool>,
    facing_errors_deg: Vec<f64>,
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
}

impl Diagnostics {
    /// Adds one person with 3D ground truth.
    pub fn add(&mut self, pred: &[[f64; 3]], gt: &[[f64; 3]], visible: &[bool]) {
        if let Some(s) = left_right_swapped(pred, gt, visible) {
            self.swaps.push(s);
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
    fn medians() {
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
    }
}
