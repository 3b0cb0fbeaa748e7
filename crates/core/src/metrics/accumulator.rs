//! Streaming accumulation of the metrics over a data set, mergeable across threads, and the
//! serializable report `posefuse eval` prints and the bundle manifest stores.

use serde::{Deserialize, Serialize};

use super::person::{
    box_scale_2d, box_scale_3d, evaluate_person, evaluate_projected, oks_threshold, PersonEval, OKS_THRESHOLD_COUNT,
};
use crate::error::Result;
use crate::frame::{Box2d, Box3d};
use crate::geometry::Camera;
use crate::keypoints::{K, NAMES};

/// The PCK thresholds reported in 3D, metres.
pub const PCK_THRESHOLDS_3D_M: [f64; 2] = [0.1, 0.2];

/// Sums for one dimension (3D or 2D); every field adds under `merge`.
#[derive(Debug, Clone, Default, PartialEq)]
struct Sums {
    persons: usize,
    /// Persons without a labelled ground-truth keypoint, excluded from every metric.
    skipped: usize,
    oks_sum: f64,
    oks_hits: [usize; OKS_THRESHOLD_COUNT],
    error_sum: f64,
    errors: usize,
    /// Labelled keypoints (denominator of PCK and PEM).
    labelled: usize,
    pck_hits: [usize; PCK_THRESHOLDS_3D_M.len()],
    pem_sum: f64,
    keypoint_oks_sum: [f64; K],
    keypoint_labelled: [usize; K],
}

impl Sums {
    fn add(&mut self, e: &PersonEval) {
        let Some(oks) = e.oks else {
            self.skipped += 1;
            return;
        };
        self.persons += 1;
        self.oks_sum += oks;
        for (i, hits) in self.oks_hits.iter_mut().enumerate() {
            *hits += usize::from(oks >= oks_threshold(i));
        }
        for k in 0..K {
            let Some(kp_oks) = e.per_keypoint_oks[k] else { continue };
            self.keypoint_oks_sum[k] += kp_oks;
            self.keypoint_labelled[k] += 1;
            self.labelled += 1;
            self.pem_sum += super::person::pem_cost(e.errors[k]);
            if let Some(err) = e.errors[k] {
                self.error_sum += err;
                self.errors += 1;
                for (t, hits) in PCK_THRESHOLDS_3D_M.iter().zip(self.pck_hits.iter_mut()) {
                    *hits += usize::from(err <= *t);
                }
            }
        }
    }

    fn merge(&mut self, o: &Sums) {
        self.persons += o.persons;
        self.skipped += o.skipped;
        self.oks_sum += o.oks_sum;
        self.error_sum += o.error_sum;
        self.errors += o.errors;
        self.labelled += o.labelled;
        self.pem_sum += o.pem_sum;
        for (a, b) in self.oks_hits.iter_mut().zip(o.oks_hits) {
            *a += b;
        }
        for (a, b) in self.pck_hits.iter_mut().zip(o.pck_hits) {
            *a += b;
        }
        for (a, b) in self.keypoint_oks_sum.iter_mut().zip(o.keypoint_oks_sum) {
            *a += b;
        }
        for (a, b) in self.keypoint_labelled.iter_mut().zip(o.keypoint_labelled) {
            *a += b;
        }
    }

    fn oks_acc(&self) -> Option<f64> {
        ratio(self.oks_hits.iter().sum::<usize>() as f64, self.persons * OKS_THRESHOLD_COUNT)
    }

    fn per_keypoint(&self) -> Vec<KeypointOks> {
        (0..K)
            .map(|k| KeypointOks {
                name: NAMES[k].to_string(),
                oks: ratio(self.keypoint_oks_sum[k], self.keypoint_labelled[k]),
            })
            .collect()
    }
}

fn ratio(num: f64, den: usize) -> Option<f64> {
    (den > 0).then(|| num / den as f64)
}

/// Accumulates per-person evaluations; `merge` combines accumulators filled in parallel.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MetricsAccumulator {
    d3: Sums,
    d2: Sums,
}

impl MetricsAccumulator {
    /// An empty accumulator.
    pub fn new() -> MetricsAccumulator {
        MetricsAccumulator::default()
    }

    /// Adds a 3D prediction (vehicle frame, metres) scored against its ground truth and 3D box.
    pub fn add_3d(
        &mut self,
        pred_vehicle: &[[f64; 3]],
        gt_vehicle: &[[f64; 3]],
        labelled: &[bool],
        b: &Box3d,
    ) -> Result<()> {
        let e = evaluate_person(pred_vehicle, gt_vehicle, labelled, box_scale_3d(b))?;
        self.add_eval_3d(&e);
        Ok(())
    }

    /// Adds a 2D prediction (image pixels) scored against its ground truth and 2D box.
    pub fn add_2d(&mut self, pred_px: &[[f64; 2]], gt_px: &[[f64; 2]], labelled: &[bool], b: &Box2d) -> Result<()> {
        let e = evaluate_person(pred_px, gt_px, labelled, box_scale_2d(b))?;
        self.add_eval_2d(&e);
        Ok(())
    }

    /// Adds OKS@2D of a 3D prediction: projected with `camera`, scored against 2D ground truth.
    pub fn add_projected(
        &mut self,
        camera: &Camera,
        pred_vehicle: &[[f64; 3]],
        gt_px: &[[f64; 2]],
        labelled: &[bool],
        b: &Box2d,
    ) -> Result<()> {
        let e = evaluate_projected(camera, pred_vehicle, gt_px, labelled, b)?;
        self.add_eval_2d(&e);
        Ok(())
    }

    /// Adds an already computed 3D evaluation (e.g. one with missing predictions).
    pub fn add_eval_3d(&mut self, e: &PersonEval) {
        self.d3.add(e);
    }

    /// Adds an already computed 2D evaluation.
    pub fn add_eval_2d(&mut self, e: &PersonEval) {
        self.d2.add(e);
    }

    /// Folds another accumulator into this one.
    pub fn merge(&mut self, other: &MetricsAccumulator) {
        self.d3.merge(&other.d3);
        self.d2.merge(&other.d2);
    }

    /// The metrics so far; a metric with nothing to average over is `None`.
    pub fn report(&self) -> MetricsReport {
        let (a, b) = (&self.d3, &self.d2);
        MetricsReport {
            count_3d: a.persons,
            skipped_3d: a.skipped,
            oks_acc_3d: a.oks_acc(),
            mean_oks_3d: ratio(a.oks_sum, a.persons),
            mpjpe_3d_m: ratio(a.error_sum, a.errors),
            pck_3d_10cm: ratio(a.pck_hits[0] as f64, a.labelled),
            pck_3d_20cm: ratio(a.pck_hits[1] as f64, a.labelled),
            pem_3d_m: ratio(a.pem_sum, a.labelled),
            per_keypoint_oks_3d: a.per_keypoint(),
            count_2d: b.persons,
            skipped_2d: b.skipped,
            oks_acc_2d: b.oks_acc(),
            mean_oks_2d: ratio(b.oks_sum, b.persons),
            mpjpe_2d_px: ratio(b.error_sum, b.errors),
            per_keypoint_oks_2d: b.per_keypoint(),
        }
    }
}

/// Mean OKS of one keypoint over the persons where it is labelled.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct KeypointOks {
    /// Keypoint name (`keypoints::NAMES`).
    pub name: String,
    /// `None` when the keypoint was never labelled.
    pub oks: Option<f64>,
}

/// Evaluation results. Pooled metrics (MPJPE, PCK, PEM) average over all labelled ground-truth
/// keypoints of all persons; OKS/ACC counts persons. `None`: nothing to average over.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct MetricsReport {
    /// Persons scored in 3D (with at least one labelled 3D keypoint).
    pub count_3d: usize,
    /// Persons without a labelled 3D keypoint, left out.
    pub skipped_3d: usize,
    /// OKS/ACC in 3D (the paper's headline).
    pub oks_acc_3d: Option<f64>,
    /// Mean per-person OKS in 3D.
    pub mean_oks_3d: Option<f64>,
    /// MPJPE in 3D, metres.
    pub mpjpe_3d_m: Option<f64>,
    /// Fraction of labelled 3D keypoints within 0.1 m.
    pub pck_3d_10cm: Option<f64>,
    /// Fraction of labelled 3D keypoints within 0.2 m.
    pub pck_3d_20cm: Option<f64>,
    /// PEM, metres (errors clipped at 0.25 m, missing keypoints cost 0.25 m).
    pub pem_3d_m: Option<f64>,
    /// Per-keypoint mean OKS in 3D, in keypoint order.
    pub per_keypoint_oks_3d: Vec<KeypointOks>,
    /// Persons scored in 2D (with at least one labelled 2D keypoint).
    pub count_2d: usize,
    /// Persons without a labelled 2D keypoint, left out.
    pub skipped_2d: usize,
    /// OKS/ACC in 2D (OKS@2D when fed projected 3D predictions).
    pub oks_acc_2d: Option<f64>,
    /// Mean per-person OKS in 2D.
    pub mean_oks_2d: Option<f64>,
    /// MPJPE in 2D, pixels.
    pub mpjpe_2d_px: Option<f64>,
    /// Per-keypoint mean OKS in 2D, in keypoint order.
    pub per_keypoint_oks_2d: Vec<KeypointOks>,
}

fn cell(v: Option<f64>, unit: &str) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{v:.4}{unit}"))
}

impl MetricsReport {
    /// A plain-text table for terminals.
    pub fn table(&self) -> String {
        let mut rows: Vec<(String, String, String)> = vec![
            ("persons".into(), self.count_3d.to_string(), self.count_2d.to_string()),
            ("skipped (no labelled GT)".into(), self.skipped_3d.to_string(), self.skipped_2d.to_string()),
            ("OKS/ACC".into(), cell(self.oks_acc_3d, ""), cell(self.oks_acc_2d, "")),
            ("mean OKS".into(), cell(self.mean_oks_3d, ""), cell(self.mean_oks_2d, "")),
            ("MPJPE".into(), cell(self.mpjpe_3d_m, " m"), cell(self.mpjpe_2d_px, " px")),
            ("PCK@0.1m".into(), cell(self.pck_3d_10cm, ""), "-".into()),
            ("PCK@0.2m".into(), cell(self.pck_3d_20cm, ""), "-".into()),
            ("PEM".into(), cell(self.pem_3d_m, " m"), "-".into()),
            (String::new(), String::new(), String::new()),
            ("per-keypoint OKS".into(), "3D".into(), "2D".into()),
        ];
        for (k, name) in NAMES.iter().enumerate() {
            let pick = |v: &[KeypointOks]| cell(v.get(k).and_then(|x| x.oks), "");
            rows.push((name.to_string(), pick(&self.per_keypoint_oks_3d), pick(&self.per_keypoint_oks_2d)));
        }
        let mut out = format!("{:<24} {:>12} {:>12}\n", "metric", "3D", "2D");
        for (name, a, b) in rows {
            out.push_str(format!("{name:<24} {a:>12} {b:>12}").trim_end());
            out.push('\n');
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::keypoints::OKS_SCALES;
    use crate::metrics::{evaluate_person_partial, mpjpe, oks_acc, pck, pem};

    fn box3(length: f64, width: f64, height: f64) -> Box3d {
        Box3d { center_x: 10.0, center_y: 0.0, center_z: 0.9, length, width, height, heading: 0.3 }
    }

    /// Prediction (possibly missing), ground truth, labels and box of one person.
    type Labelled = (Vec<Option<[f64; 3]>>, Vec<[f64; 3]>, Vec<bool>, Box3d);

    /// Deterministic persons with varied errors, visibilities and a few missing predictions.
    fn persons() -> Vec<Labelled> {
        (0..9)
            .map(|i| {
                let gt: Vec<[f64; 3]> =
                    (0..K).map(|k| [10.0 + 0.01 * k as f64, 0.1 * i as f64, 0.13 * k as f64]).collect();
                let pred = (0..K)
                    .map(|k| {
                        let e = 0.03 * ((i * 7 + k * 3) % 11) as f64;
                        ((i + k) % 10 != 3).then(|| [gt[k][0] + e, gt[k][1] - 0.5 * e, gt[k][2]])
                    })
                    .collect();
                let labelled = (0..K).map(|k| i != 4 && (i * k) % 5 != 1).collect();
                (pred, gt, labelled, box3(0.5 + 0.05 * i as f64, 0.6, 1.7))
            })
            .collect()
    }

    #[test]
    fn report_matches_the_pure_reductions() {
        let mut acc = MetricsAccumulator::new();
        let mut evals = Vec::new();
        for (pred, gt, vis, b) in persons() {
            let e = evaluate_person_partial(&pred, &gt, &vis, box_scale_3d(&b)).unwrap();
            acc.add_eval_3d(&e);
            evals.push(e);
        }
        let r = acc.report();
        let scored: Vec<PersonEval> = evals.iter().filter(|e| e.oks.is_some()).cloned().collect();
        assert_eq!((r.count_3d, r.skipped_3d), (8, 1));
        let oks: Vec<f64> = scored.iter().filter_map(|e| e.oks).collect();
        let close = |a: Option<f64>, b: Option<f64>| (a.unwrap() - b.unwrap()).abs() < 1e-12;
        assert!(close(r.oks_acc_3d, oks_acc(&oks)));
        assert!(close(r.mean_oks_3d, Some(oks.iter().sum::<f64>() / 8.0)));
        assert!(close(r.mpjpe_3d_m, mpjpe(&scored)));
        assert!(close(r.pck_3d_10cm, pck(&scored, 0.1)));
        assert!(close(r.pck_3d_20cm, pck(&scored, 0.2)));
        assert!(close(r.pem_3d_m, pem(&scored)));
        let nose: Vec<f64> = scored.iter().filter_map(|e| e.per_keypoint_oks[0]).collect();
        assert_eq!(r.per_keypoint_oks_3d[0].name, "nose");
        assert!(close(r.per_keypoint_oks_3d[0].oks, Some(nose.iter().sum::<f64>() / nose.len() as f64)));
        assert_eq!(r.count_2d, 0);
        assert_eq!((r.oks_acc_2d, r.mpjpe_2d_px), (None, None));
    }

    #[test]
    fn merge_equals_accumulating_everything_in_one() {
        let mut whole = MetricsAccumulator::new();
        let (mut left, mut right) = (MetricsAccumulator::new(), MetricsAccumulator::new());
        for (i, (pred, gt, vis, b)) in persons().into_iter().enumerate() {
            let pred: Vec<[f64; 3]> = pred.iter().zip(&gt).map(|(p, g)| p.unwrap_or(*g)).collect();
            whole.add_3d(&pred, &gt, &vis, &b).unwrap();
            let px: Vec<[f64; 2]> = pred.iter().map(|p| [p[0] * 100.0, p[2] * 100.0]).collect();
            let gpx: Vec<[f64; 2]> = gt.iter().map(|p| [p[0] * 100.0, p[2] * 100.0]).collect();
            let b2 = Box2d { center_x: 0.0, center_y: 0.0, width: 40.0, height: 120.0 };
            whole.add_2d(&px, &gpx, &vis, &b2).unwrap();
            let half = if i % 2 == 0 { &mut left } else { &mut right };
            half.add_3d(&pred, &gt, &vis, &b).unwrap();
            half.add_2d(&px, &gpx, &vis, &b2).unwrap();
        }
        // a person with no labelled 3D keypoint, in the half that is merged in
        let (pred, gt, _, b) = persons().remove(0);
        let pred: Vec<[f64; 3]> = pred.iter().zip(&gt).map(|(p, g)| p.unwrap_or(*g)).collect();
        for acc in [&mut whole, &mut right] {
            acc.add_3d(&pred, &gt, &[false; K], &b).unwrap();
        }
        left.merge(&right);
        let (a, b) = (left.report(), whole.report());
        assert_eq!((a.count_3d, a.skipped_3d, a.count_2d, a.skipped_2d), (8, 2, 8, 1));
        assert_eq!((b.skipped_3d, b.skipped_2d), (2, 1));
        let json = |r: &MetricsReport| serde_json::to_value(r).unwrap();
        // sums in a different order may differ in the last bit
        let (ja, jb) = (json(&a), json(&b));
        for key in [
            "oks_acc_3d",
            "mean_oks_3d",
            "mpjpe_3d_m",
            "pck_3d_10cm",
            "pck_3d_20cm",
            "pem_3d_m",
            "oks_acc_2d",
            "mean_oks_2d",
            "mpjpe_2d_px",
        ] {
            let (x, y) = (ja[key].as_f64().unwrap(), jb[key].as_f64().unwrap());
            assert!((x - y).abs() < 1e-12, "{key}: {x} vs {y}");
        }
        assert_eq!(a.per_keypoint_oks_3d.len(), K);
        for (merged, whole) in
            [(&a.per_keypoint_oks_3d, &b.per_keypoint_oks_3d), (&a.per_keypoint_oks_2d, &b.per_keypoint_oks_2d)]
        {
            for (m, w) in merged.iter().zip(whole) {
                assert_eq!(m.name, w.name);
                assert_eq!(m.oks.is_some(), w.oks.is_some(), "{}", m.name);
                if let (Some(x), Some(y)) = (m.oks, w.oks) {
                    assert!((x - y).abs() < 1e-12, "{}: {x} vs {y}", m.name);
                }
            }
        }
    }

    #[test]
    fn hand_computed_report_and_table() {
        // one person, keypoints 0..3 labelled: 0 and 1 exact, 2 at d = s (OKS e^-½), 3 at 0.3 m
        let b = box3(1.0, 1.0, 1.0);
        let gt = vec![[0.0; 3]; K];
        let mut pred = gt.clone();
        pred[2] = [0.0, OKS_SCALES[2], 0.0];
        pred[3] = [0.0, 0.0, 0.3];
        let vis: Vec<bool> = (0..K).map(|k| k < 4).collect();
        let mut acc = MetricsAccumulator::new();
        acc.add_3d(&pred, &gt, &vis, &b).unwrap();
        let r = acc.report();
        let o3 = (-0.09f64 / (2.0 * 0.144 * 0.144)).exp();
        let oks = (2.0 + (-0.5f64).exp() + o3) / 4.0;
        assert!((r.mean_oks_3d.unwrap() - oks).abs() < 1e-12);
        // OKS ≈ 0.6802: passes 0.50, 0.55, 0.60, 0.65 of 10 thresholds
        assert!((oks - 0.6802).abs() < 1e-4, "{oks}");
        assert!((r.oks_acc_3d.unwrap() - 0.4).abs() < 1e-12);
        assert!((r.mpjpe_3d_m.unwrap() - (0.158 + 0.3) / 4.0).abs() < 1e-12);
        assert_eq!((r.pck_3d_10cm, r.pck_3d_20cm), (Some(0.5), Some(0.75)));
        assert!((r.pem_3d_m.unwrap() - (0.158 + 0.25) / 4.0).abs() < 1e-12);
        assert_eq!(r.per_keypoint_oks_3d[4].oks, None);
        assert_eq!(r.per_keypoint_oks_3d[0].oks, Some(1.0));

        // serde_json's default float parser may be one ulp off, hence no exact equality
        let back: MetricsReport = serde_json::from_str(&serde_json::to_string(&r).unwrap()).unwrap();
        assert_eq!((back.count_3d, back.per_keypoint_oks_3d.len(), back.oks_acc_2d), (1, K, None));
        assert!((back.pem_3d_m.unwrap() - r.pem_3d_m.unwrap()).abs() < 1e-15);
        assert_eq!(back.per_keypoint_oks_3d[3].name, "left_elbow");

        let t = r.table();
        let row =
            |name: &str| t.lines().find(|l| l.starts_with(name)).map(|l| l.split_whitespace().collect::<Vec<_>>());
        assert_eq!(row("OKS/ACC"), Some(vec!["OKS/ACC", "0.4000", "-"]), "{t}");
        assert_eq!(row("MPJPE"), Some(vec!["MPJPE", "0.1145", "m", "-"]), "{t}");
        assert_eq!(row("left_shoulder"), Some(vec!["left_shoulder", "1.0000", "-"]), "{t}");
        assert_eq!(row("right_ankle"), Some(vec!["right_ankle", "-", "-"]), "{t}");
    }
}
