//! Per-person keypoint metrics and the pure pooled reductions over many persons.
//!
//! Pooling: MPJPE, PCK and PEM pool every labelled ground-truth keypoint of every person, occluded
//! or not (Waymo's convention: a mean weighted by the keypoint mask, which is 1 for occluded and
//! visible keypoints), so a person with 13 labelled keypoints weighs 13 times one with a single
//! labelled keypoint. OKS is averaged per person first (OKS/ACC counts persons). The mask is the
//! caller's: `frame::Visibility::labelled_mask` gives Waymo's.

use crate::error::{Error, Result};
use crate::frame::{Box2d, Box3d};
use crate::geometry::Camera;
use crate::keypoints::{K, OKS_SCALES};

/// Number of OKS thresholds of OKS/ACC: 0.50, 0.55, …, 0.95.
pub const OKS_THRESHOLD_COUNT: usize = 10;

/// Per-keypoint error clip of PEM and the cost of a missing prediction, metres (Waymo 2023).
pub const PEM_CLIP_M: f64 = 0.25;

/// The `i`-th OKS/ACC threshold, `(50 + 5i) / 100`.
///
/// Computed from integers rather than by repeated addition of 0.05, so each threshold is the
/// double nearest to its decimal value and an OKS of exactly 0.55 passes 0.55.
pub fn oks_threshold(i: usize) -> f64 {
    (50 + 5 * i) as f64 / 100.0
}

/// OKS of one keypoint at distance `d`: `exp(-d² / (2 s²))` with `s = type_scale · box_scale`.
pub fn keypoint_oks(d: f64, type_scale: f64, box_scale: f64) -> f64 {
    let s = type_scale * box_scale;
    (-(d * d) / (2.0 * s * s)).exp()
}

/// Scale of a 3D box: cube root of its volume (metres).
pub fn box_scale_3d(b: &Box3d) -> f64 {
    (b.length * b.width * b.height).cbrt()
}

/// Scale of a 2D box: square root of its area (pixels).
pub fn box_scale_2d(b: &Box2d) -> f64 {
    (b.width * b.height).sqrt()
}

/// The PEM cost of one labelled keypoint: its error clipped at [`PEM_CLIP_M`], or the clip itself
/// when the prediction is missing.
pub fn pem_cost(error: Option<f64>) -> f64 {
    error.map_or(PEM_CLIP_M, |e| e.min(PEM_CLIP_M))
}

/// One person's evaluation against its ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct PersonEval {
    /// Mean OKS over the keypoints labelled in the ground truth; `None` when none is labelled, in
    /// which case the person is excluded from every metric.
    pub oks: Option<f64>,
    /// OKS of each keypoint; `None` where the ground truth is not labelled. A missing prediction
    /// scores 0.
    pub per_keypoint_oks: [Option<f64>; K],
    /// Euclidean error of each keypoint (metres or pixels); `None` where the ground truth is not
    /// labelled or the prediction is missing.
    pub errors: [Option<f64>; K],
}

impl PersonEval {
    /// Whether keypoint `k` is labelled in the ground truth.
    pub fn labelled(&self, k: usize) -> bool {
        self.per_keypoint_oks[k].is_some()
    }

    /// Errors of the labelled keypoints whose prediction exists.
    pub fn labelled_errors(&self) -> impl Iterator<Item = f64> + '_ {
        self.errors.iter().flatten().copied()
    }

    /// PEM costs of the labelled keypoints (missing predictions included).
    pub fn pem_costs(&self) -> impl Iterator<Item = f64> + '_ {
        (0..K).filter(|&k| self.labelled(k)).map(|k| pem_cost(self.errors[k]))
    }

    /// This person's MPJPE (mean error over labelled keypoints with a prediction).
    pub fn mpjpe(&self) -> Option<f64> {
        mean(self.labelled_errors())
    }
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

fn check_len(field: &str, len: usize) -> Result<()> {
    if len == K {
        Ok(())
    } else {
        Err(Error::field(field, format!("needs {K} keypoints, got {len}")))
    }
}

fn all_finite<const D: usize>(p: &[f64; D]) -> bool {
    p.iter().all(|v| v.is_finite())
}

/// Evaluates one person whose every keypoint has a prediction.
///
/// `pred`, `gt` and `labelled` hold [`K`] entries in the project's keypoint order; `box_scale` is
/// [`box_scale_3d`] or [`box_scale_2d`] of the ground-truth box.
pub fn evaluate_person<const D: usize>(
    pred: &[[f64; D]],
    gt: &[[f64; D]],
    labelled: &[bool],
    box_scale: f64,
) -> Result<PersonEval> {
    let pred: Vec<Option<[f64; D]>> = pred.iter().copied().map(Some).collect();
    evaluate_person_partial(&pred, gt, labelled, box_scale)
}

/// Evaluates one person where some predictions may be missing (`None`): a missing prediction of a
/// labelled keypoint scores OKS 0, costs [`PEM_CLIP_M`] in PEM, fails PCK and is left out of MPJPE.
pub fn evaluate_person_partial<const D: usize>(
    pred: &[Option<[f64; D]>],
    gt: &[[f64; D]],
    labelled: &[bool],
    box_scale: f64,
) -> Result<PersonEval> {
    check_len("pred", pred.len())?;
    check_len("gt", gt.len())?;
    check_len("labelled", labelled.len())?;
    if !(box_scale.is_finite() && box_scale > 0.0) {
        return Err(Error::field("box_scale", format!("must be positive and finite, got {box_scale}")));
    }
    let mut per_keypoint_oks = [None; K];
    let mut errors = [None; K];
    for k in 0..K {
        if !labelled[k] {
            continue;
        }
        if !all_finite(&gt[k]) {
            return Err(Error::field(format!("gt[{k}]"), "labelled keypoint is NaN or infinite"));
        }
        per_keypoint_oks[k] = Some(match pred[k] {
            None => 0.0,
            Some(p) if !all_finite(&p) => {
                return Err(Error::field(format!("pred[{k}]"), "is NaN or infinite; pass None for a missing keypoint"))
            }
            Some(p) => {
                let d = (0..D).map(|a| (p[a] - gt[k][a]).powi(2)).sum::<f64>().sqrt();
                errors[k] = Some(d);
                keypoint_oks(d, OKS_SCALES[k], box_scale)
            }
        });
    }
    let oks = mean(per_keypoint_oks.iter().flatten().copied());
    Ok(PersonEval { oks, per_keypoint_oks, errors })
}

/// OKS@2D: the 3D prediction (vehicle frame) projected with the camera, scored against the 2D
/// ground truth with the 2D box's scale. Keypoints behind the camera count as missing.
pub fn evaluate_projected(
    camera: &Camera,
    pred_vehicle: &[[f64; 3]],
    gt_px: &[[f64; 2]],
    labelled: &[bool],
    box_2d: &Box2d,
) -> Result<PersonEval> {
    check_len("pred", pred_vehicle.len())?;
    if let Some(k) = pred_vehicle.iter().position(|p| !all_finite(p)) {
        return Err(Error::field(format!("pred[{k}]"), "is NaN or infinite"));
    }
    evaluate_person_partial(&camera.project_points(pred_vehicle), gt_px, labelled, box_scale_2d(box_2d))
}

/// OKS/ACC: the mean over the 10 thresholds t of the fraction of persons with OKS ≥ t. `None` for
/// no persons.
///
/// Waymo's own `AveragePrecisionAtOKS` counts OKS > t; docs/ARCHITECTURE.md and the paper's table use ≥,
/// which differs only for OKS values exactly on a threshold.
pub fn oks_acc(oks: &[f64]) -> Option<f64> {
    if oks.is_empty() {
        return None;
    }
    let n = oks.len() as f64;
    let sum: f64 = (0..OKS_THRESHOLD_COUNT)
        .map(|i| {
            let t = oks_threshold(i);
            oks.iter().filter(|&&o| o >= t).count() as f64 / n
        })
        .sum();
    Some(sum / OKS_THRESHOLD_COUNT as f64)
}

/// MPJPE pooled over every labelled keypoint (with a prediction) of every person.
pub fn mpjpe(persons: &[PersonEval]) -> Option<f64> {
    mean(persons.iter().flat_map(PersonEval::labelled_errors))
}

/// PCK: the fraction of labelled keypoints with error ≤ `threshold` (Waymo compares with ≤); a
/// missing prediction is incorrect. Pooled over persons.
pub fn pck(persons: &[PersonEval], threshold: f64) -> Option<f64> {
    let hits = persons.iter().flat_map(|p| (0..K).filter(|&k| p.labelled(k)).map(move |k| p.errors[k]));
    mean(hits.map(|e| if e.is_some_and(|e| e <= threshold) { 1.0 } else { 0.0 }))
}

/// PEM (Waymo 2023) with predictions already matched to ground-truth boxes: the pooled mean of
/// [`pem_cost`] over labelled keypoints.
pub fn pem(persons: &[PersonEval]) -> Option<f64> {
    mean(persons.iter().flat_map(PersonEval::pem_costs))
}

#[cfg(test)]
mod tests {
    use super::*;

    const S3: f64 = 0.8;

    fn zeros3() -> Vec<[f64; 3]> {
        vec![[0.0; 3]; K]
    }

    /// Each labelled keypoint k displaced by `f(k) · OKS_SCALES[k] · S3` along x.
    fn displaced(f: impl Fn(usize) -> f64) -> Vec<[f64; 3]> {
        (0..K).map(|k| [f(k) * OKS_SCALES[k] * S3, 0.0, 0.0]).collect()
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn keypoint_oks_matches_the_gaussian() {
        assert_eq!(keypoint_oks(0.0, 0.052, 1.3), 1.0);
        // d = s ⇒ exp(-1/2); d = 2s ⇒ exp(-2)
        assert!(close(keypoint_oks(0.052 * 1.3, 0.052, 1.3), (-0.5f64).exp()));
        assert!(close(keypoint_oks(2.0 * 0.214 * 0.5, 0.214, 0.5), (-2.0f64).exp()));
        assert!(keypoint_oks(5.0, 0.052, 0.8) < 1e-300);
    }

    #[test]
    fn box_scales_are_cube_and_square_roots() {
        let b3 =
            Box3d { center_x: 9.0, center_y: 1.0, center_z: 0.9, length: 0.5, width: 0.4, height: 1.6, heading: 2.0 };
        assert!(close(box_scale_3d(&b3), 0.32f64.cbrt()));
        let b3 = Box3d { length: 2.0, width: 2.0, height: 2.0, ..b3 };
        assert!(close(box_scale_3d(&b3), 2.0));
        let b2 = Box2d { center_x: 100.0, center_y: 50.0, width: 40.0, height: 90.0 };
        assert!(close(box_scale_2d(&b2), 60.0));
    }

    #[test]
    fn person_oks_averages_visible_keypoints_only() {
        // labelled keypoints at d = 1·s (OKS e^-½) and d = 2·s (OKS e^-2); unlabelled ones far away
        let pred = displaced(|k| match k {
            0..=3 => 1.0,
            4..=5 => 2.0,
            _ => 100.0,
        });
        let labelled: Vec<bool> = (0..K).map(|k| k < 6).collect();
        let e = evaluate_person(&pred, &zeros3(), &labelled, S3).unwrap();
        let want = (4.0 * (-0.5f64).exp() + 2.0 * (-2.0f64).exp()) / 6.0;
        assert!(close(e.oks.unwrap(), want), "{:?}", e.oks);
        assert!(close(e.per_keypoint_oks[0].unwrap(), (-0.5f64).exp()));
        assert!(close(e.per_keypoint_oks[5].unwrap(), (-2.0f64).exp()));
        assert_eq!(e.per_keypoint_oks[6], None);
        assert_eq!(e.errors[12], None);
        assert!(close(e.errors[1].unwrap(), 0.158 * S3));
        let want_mpjpe = (0.052 + 0.158 * 2.0 + 0.144 + 2.0 * 0.144 + 2.0 * 0.124) * S3 / 6.0;
        assert!(close(e.mpjpe().unwrap(), want_mpjpe));
    }

    #[test]
    fn perfect_far_and_unlabelled_persons() {
        let gt: Vec<[f64; 3]> = (0..K).map(|k| [10.0 + k as f64 * 0.1, -1.0, 0.2 * k as f64]).collect();
        let perfect = evaluate_person(&gt, &gt, &[true; K], 0.7).unwrap();
        assert_eq!(perfect.oks, Some(1.0));
        assert_eq!(perfect.mpjpe(), Some(0.0));
        let far: Vec<[f64; 3]> = gt.iter().map(|p| [p[0] + 3.0, p[1] + 4.0, p[2]]).collect();
        let far = evaluate_person(&far, &gt, &[true; K], 0.7).unwrap();
        assert!(far.oks.unwrap() < 1e-100);
        assert!(close(far.mpjpe().unwrap(), 5.0));
        let none = evaluate_person(&gt, &gt, &[false; K], 0.7).unwrap();
        assert_eq!(none.oks, None);
        assert_eq!(none.mpjpe(), None);
        assert_eq!(none.pem_costs().count(), 0);
    }

    #[test]
    fn bad_inputs_name_their_field() {
        let field = |r: Result<PersonEval>| match r {
            Err(Error::InvalidField { field, .. }) => field,
            other => panic!("expected a field error, got {other:?}"),
        };
        let z = zeros3();
        assert_eq!(field(evaluate_person(&z[..12], &z, &[true; K], 1.0)), "pred");
        assert_eq!(field(evaluate_person(&z, &z[..1], &[true; K], 1.0)), "gt");
        assert_eq!(field(evaluate_person(&z, &z, &[true; 3], 1.0)), "labelled");
        assert_eq!(field(evaluate_person(&z, &z, &[true; K], 0.0)), "box_scale");
        assert_eq!(field(evaluate_person(&z, &z, &[true; K], f64::NAN)), "box_scale");
        let mut bad = zeros3();
        bad[4][2] = f64::NAN;
        assert_eq!(field(evaluate_person(&bad, &z, &[true; K], 1.0)), "pred[4]");
        assert_eq!(field(evaluate_person(&z, &bad, &[true; K], 1.0)), "gt[4]");
        // an unlabelled ground-truth keypoint may hold anything
        let mut vis = [true; K];
        vis[4] = false;
        assert!(evaluate_person(&z, &bad, &vis, 1.0).unwrap().oks == Some(1.0));
    }

    #[test]
    fn oks_acc_counts_threshold_boundaries_as_passing() {
        assert_eq!(
            (0..OKS_THRESHOLD_COUNT).map(oks_threshold).collect::<Vec<_>>(),
            [0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95]
        );
        // 1.0 passes 10 thresholds, 0.95 passes 10, 0.75 passes 6 (0.50..0.75), 0.5 passes 1,
        // 0.4999 passes none: (10 + 10 + 6 + 1 + 0) / (10 · 5)
        let v = oks_acc(&[1.0, 0.95, 0.75, 0.5, 0.4999]).unwrap();
        assert!(close(v, 27.0 / 50.0), "{v}");
        assert_eq!(oks_acc(&[0.9499999999]), Some(0.9));
        assert_eq!(oks_acc(&[]), None);
    }

    #[test]
    fn pooled_mpjpe_pck_and_pem_with_clipping_and_missing_keypoints() {
        // person a: 2 labelled keypoints, errors 0.05 and 0.15 m
        let mut pa = zeros3();
        pa[0] = [0.05, 0.0, 0.0];
        pa[1] = [0.0, 0.15, 0.0];
        let va: Vec<bool> = (0..K).map(|k| k < 2).collect();
        let a = evaluate_person(&pa, &zeros3(), &va, S3).unwrap();
        // person b: 3 labelled: errors 0.2 (exactly on the PCK@0.2 boundary), 0.4 (clipped to 0.25 in
        // PEM) and a missing prediction
        let mut pb: Vec<Option<[f64; 3]>> = vec![Some([0.0; 3]); K];
        pb[0] = Some([0.0, 0.0, 0.2]);
        pb[1] = Some([0.4, 0.0, 0.0]);
        pb[2] = None;
        let vb: Vec<bool> = (0..K).map(|k| k < 3).collect();
        let b = evaluate_person_partial(&pb, &zeros3(), &vb, S3).unwrap();
        assert_eq!(b.per_keypoint_oks[2], Some(0.0));
        assert_eq!(b.errors[2], None);
        let persons = [a, b];
        // MPJPE pools the 4 measured errors (pooled, not per-person: per-person would be 0.2)
        assert!(close(mpjpe(&persons).unwrap(), (0.05 + 0.15 + 0.2 + 0.4) / 4.0));
        // PCK over 5 labelled keypoints; the missing one is incorrect
        assert!(close(pck(&persons, 0.1).unwrap(), 1.0 / 5.0));
        assert!(close(pck(&persons, 0.2).unwrap(), 3.0 / 5.0));
        // PEM: 0.05 + 0.15 + 0.2 + min(0.4, 0.25) + 0.25 (missing)
        assert!(close(pem(&persons).unwrap(), (0.05 + 0.15 + 0.2 + 0.25 + 0.25) / 5.0));
        assert_eq!(pem_cost(Some(0.1)), 0.1);
        assert_eq!(pem_cost(Some(7.0)), PEM_CLIP_M);
        assert_eq!(pem_cost(None), PEM_CLIP_M);
        assert_eq!(mpjpe(&[]), None);
        assert_eq!(pck(&[], 0.1), None);
    }

    #[test]
    fn projected_oks_scores_the_image_position_of_a_3d_prediction() {
        // identity extrinsic, no distortion: vehicle (x, y, z) → (960 − 1000·y/x, 640 − 1000·z/x)
        let mut ext = vec![0.0; 16];
        for i in 0..4 {
            ext[i * 5] = 1.0;
        }
        let cam = Camera::from_calibration(&crate::frame::CameraCalibration {
            intrinsic: vec![1000.0, 1000.0, 960.0, 640.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            extrinsic: ext,
            width: 1920,
            height: 1280,
        })
        .unwrap();
        let box2d = Box2d { center_x: 960.0, center_y: 640.0, width: 50.0, height: 200.0 };
        let s2 = 100.0; // sqrt(50 · 200)
        let pred: Vec<[f64; 3]> = (0..K).map(|k| [10.0, 0.0, 0.1 * k as f64]).collect();
        // ground truth one type scale (in px) to the right of the projection: OKS e^-½ each
        let gt: Vec<[f64; 2]> = (0..K).map(|k| [960.0 + OKS_SCALES[k] * s2, 640.0 - 10.0 * k as f64]).collect();
        let e = evaluate_projected(&cam, &pred, &gt, &[true; K], &box2d).unwrap();
        assert!(close(e.oks.unwrap(), (-0.5f64).exp()));
        assert!((e.errors[1].unwrap() - 15.8).abs() < 1e-9);
        // behind the camera: a missing keypoint, OKS 0
        let mut behind = pred.clone();
        behind[0] = [-5.0, 0.0, 0.0];
        let e = evaluate_projected(&cam, &behind, &gt, &[true; K], &box2d).unwrap();
        assert_eq!((e.per_keypoint_oks[0], e.errors[0]), (Some(0.0), None));
        assert!(close(e.oks.unwrap(), 12.0 * (-0.5f64).exp() / 13.0));
    }
}
