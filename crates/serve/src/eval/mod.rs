//! Evaluation: frames with ground truth answered by the service and scored with `posefuse_core::metrics`
//! (the same accumulator the trainer's numbers are checked against), overall and per mode. One
//! path, [`evaluate_frames`], serves both `POST /v1/evaluate` and `posefuse eval`; reading a
//! data set's request fixtures lives here too.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use futures::StreamExt;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::service::api::{BatchItem, Mode, ModelRef, PoseResponse};
use crate::service::Predictor;
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Frame, RequestedMode, Visibility};
use posefuse_core::geometry::Camera;
use posefuse_core::json::{from_value, parse_json};
use posefuse_core::metrics::{MetricsAccumulator, MetricsReport};

mod diagnostics;
mod heading_noise;

pub use diagnostics::{left_right_swapped, view_of, Diagnostics, DiagnosticsReport, ViewSwaps};
pub use heading_noise::{perturb_headings, HeadingNoise};

/// Predictions and metrics over frames with ground truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct EvaluateResponse {
    /// Per-frame results, in request order.
    pub predictions: Vec<BatchItem>,
    /// Metrics over all persons with ground truth (`all`) and per mode that ran, counting every
    /// labelled keypoint, occluded or not (Waymo's convention).
    pub metrics: BTreeMap<String, MetricsReport>,
    /// `all` scored on the `visible` keypoints only and on the `occluded` ones only.
    #[serde(default)]
    pub breakdown: BTreeMap<String, MetricsReport>,
    /// Left/right swap rate and facing error (not Waymo metrics), `all` and per mode.
    #[serde(default)]
    pub diagnostics: BTreeMap<String, DiagnosticsReport>,
    /// Frames that failed (their persons are not scored).
    pub failed_frames: usize,
    /// Persons with ground truth that got no pose (listed in their frame's `skipped`; not scored).
    pub skipped_persons: usize,
}

/// Metrics over all persons and per mode that ran.
#[derive(Debug, Clone, Default)]
pub struct EvalAccumulator {
    all: MetricsAccumulator,
    by_mode: BTreeMap<Mode, MetricsAccumulator>,
    diagnostics: Diagnostics,
    diagnostics_by_mode: BTreeMap<Mode, Diagnostics>,
    visible_only: MetricsAccumulator,
    occluded_only: MetricsAccumulator,
    skipped: usize,
}

/// The masks of every labelled keypoint (the headline), the visible and the occluded ones.
fn masks(v: &[Visibility]) -> [Vec<bool>; 3] {
    [
        Visibility::labelled_mask(v),
        Visibility::select(v, Visibility::Visible),
        Visibility::select(v, Visibility::Occluded),
    ]
}

impl EvalAccumulator {
    /// Scores the persons of `frame` that carry ground truth against `resp` (same order, less
    /// the skipped ones, which are counted): 3D keypoints against the 3D box scale, and the
    /// projected 3D prediction (OKS@2D) against 2D keypoints with the request's 2D box (else the
    /// box the server derived).
    pub fn add(&mut self, frame: &Frame, resp: &PoseResponse) -> Result<()> {
        let skipped: Vec<usize> = resp.skipped.iter().map(|s| s.index).collect();
        if frame.persons.len() != resp.persons.len() + skipped.len() {
            return Err(Error::Runtime("response and request disagree on the number of persons".into()));
        }
        let answered = frame.persons.iter().enumerate().filter(|(i, _)| !skipped.contains(i));
        self.skipped +=
            frame.persons.iter().enumerate().filter(|(i, p)| skipped.contains(i) && p.ground_truth.is_some()).count();
        for ((_, person), pose) in answered.zip(&resp.persons) {
            let Some(gt) = &person.ground_truth else { continue };
            let pred: Vec<[f64; 3]> = pose.keypoints.iter().map(|k| k.xyz).collect();
            // the headline counts every labelled keypoint (Waymo's mask); the breakdowns score
            // the visible and the occluded ones apart
            let mut one = [MetricsAccumulator::new(), MetricsAccumulator::new(), MetricsAccumulator::new()];
            if let Some(k3) = &gt.keypoints_3d {
                let v = k3.visibility();
                for (acc, mask) in one.iter_mut().zip(masks(&v)) {
                    acc.add_3d(&pred, &k3.xyz, &mask, &person.box_3d)?;
                }
                let mut d = Diagnostics::default();
                d.add(&pred, &k3.xyz, &Visibility::labelled_mask(&v));
                self.diagnostics.merge(&d);
                self.diagnostics_by_mode.entry(pose.mode).or_default().merge(&d);
            }
            // 2D labels are in the pixels of the person's camera: the single one, or the one of
            // `cameras` it names (without a name they belong to no camera in particular)
            let calibration = frame.calibration_of(person.camera.as_deref());
            if let (Some(k2), Some(b2), Some(c)) = (&gt.keypoints_2d, person.box_2d.or(pose.box_2d), calibration) {
                let camera = Camera::from_calibration(c)?;
                for (acc, mask) in one.iter_mut().zip(masks(&k2.visibility())) {
                    acc.add_projected(&camera, &pred, &k2.uv, &mask, &b2)?;
                }
            }
            let [labelled, visible, occluded] = one;
            self.all.merge(&labelled);
            self.by_mode.entry(pose.mode).or_default().merge(&labelled);
            self.visible_only.merge(&visible);
            self.occluded_only.merge(&occluded);
        }
        Ok(())
    }

    /// The visible-only and occluded-only breakdowns of `all` (never the headline).
    pub fn breakdown(&self) -> BTreeMap<String, MetricsReport> {
        BTreeMap::from([
            ("visible".to_string(), self.visible_only.report()),
            ("occluded".to_string(), self.occluded_only.report()),
        ])
    }

    /// Persons with ground truth that the server skipped (not scored).
    pub fn skipped(&self) -> usize {
        self.skipped
    }

    /// Facing and left/right diagnostics: `all` plus one per mode that ran.
    pub fn diagnostics(&self) -> BTreeMap<String, DiagnosticsReport> {
        let mut out = BTreeMap::new();
        out.insert("all".to_string(), self.diagnostics.report());
        for (mode, d) in &self.diagnostics_by_mode {
            out.insert(mode.as_str().to_string(), d.report());
        }
        out
    }

    /// `all` plus one report per mode that ran.
    pub fn reports(&self) -> BTreeMap<String, MetricsReport> {
        let mut out = BTreeMap::new();
        out.insert("all".to_string(), self.all.report());
        for (mode, acc) in &self.by_mode {
            out.insert(mode.as_str().to_string(), acc.report());
        }
        out
    }
}

/// `posefuse eval --json` output.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EvalReport {
    /// The data directory.
    pub data: PathBuf,
    /// Bundle name and version.
    pub model: ModelRef,
    /// The forced mode, if any.
    pub mode: Option<RequestedMode>,
    /// The heading error put on every request box, if any (`--heading-noise`).
    #[serde(default, skip_serializing_if = "Option::is_none", skip_deserializing)]
    pub heading_noise: Option<HeadingNoise>,
    pub frames: usize,
    pub failed_frames: usize,
    /// Persons with ground truth that got no pose (no LiDAR point in the box, ...); not scored.
    pub skipped_persons: usize,
    /// The first few failures (`file: message`).
    pub failures: Vec<String>,
    /// `all` and per mode, every labelled keypoint counted.
    pub metrics: BTreeMap<String, MetricsReport>,
    /// `all` on the `visible` keypoints only and on the `occluded` ones only.
    #[serde(default)]
    pub breakdown: BTreeMap<String, MetricsReport>,
    /// Left/right swaps and facing error, `all` and per mode.
    pub diagnostics: BTreeMap<String, DiagnosticsReport>,
}

impl EvalReport {
    /// Plain-text tables, one per mode.
    pub fn text(&self) -> String {
        let mut out = format!(
            "model {} {} on {} ({} frames, {} failed; {} persons skipped)\n",
            self.model.name,
            self.model.version,
            self.data.display(),
            self.frames,
            self.failed_frames,
            self.skipped_persons
        );
        for f in &self.failures {
            out.push_str(&format!("  failed: {f}\n"));
        }
        if let Some(n) = self.heading_noise {
            out.push_str(&format!("request box headings turned by: {n} (degrees)\n"));
        }
        for (name, report) in &self.metrics {
            out.push_str(&format!("\n== {name}\n{}", report.table()));
            if let Some(d) = self.diagnostics.get(name) {
                let pct = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{:.1} %", 100.0 * v));
                let deg = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{v:.1}°"));
                let by_view: Vec<String> = d
                    .swaps_by_view
                    .iter()
                    .map(|(view, v)| format!("{view} {} of {}", pct(Some(v.swap_rate)), v.judged))
                    .collect();
                out.push_str(&format!(
                    "left/right swapped {} of {} ({}) · facing error median {} of {}\n",
                    pct(d.left_right_swap_rate),
                    d.swap_judged,
                    by_view.join(", "),
                    deg(d.facing_error_median_deg),
                    d.facing_judged
                ));
            }
        }
        let line = |r: &MetricsReport| {
            let pct = r.oks_acc_3d.map_or_else(|| "-".to_string(), |v| format!("{:.2} %", 100.0 * v));
            let cm = r.mpjpe_3d_m.map_or_else(|| "-".to_string(), |v| format!("{:.2} cm", 100.0 * v));
            format!("OKS/ACC {pct}, MPJPE {cm} ({} persons)", r.count_3d)
        };
        for (name, r) in &self.breakdown {
            out.push_str(&format!("breakdown, {name} keypoints only (3D): {}\n", line(r)));
        }
        out
    }
}

/// The request fixtures of a simulator output directory: `DIR/requests/*.json`, each a frame or
/// an array of frames, in file-name order.
pub fn load_fixtures(data: &Path) -> Result<Vec<(String, Frame)>> {
    let dir = data.join("requests");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map_err(|e| Error::Io(format!("cannot list {}: {e}", dir.display())))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(Error::Io(format!("no *.json request fixtures in {}", dir.display())));
    }
    let mut frames = Vec::new();
    for f in files {
        let name = f.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let bytes = std::fs::read(&f).map_err(|e| Error::Io(format!("{}: {e}", f.display())))?;
        let value: serde_json::Value = parse_json(&bytes).map_err(|e| Error::Io(format!("{}: {e}", f.display())))?;
        let items = match value {
            serde_json::Value::Array(v) => v,
            other => vec![other],
        };
        let many = items.len() > 1;
        for (i, v) in items.into_iter().enumerate() {
            let frame: Frame = from_value(v).map_err(|e| Error::Io(format!("{}: {e}", f.display())))?;
            frames.push((if many { format!("{name}[{i}]") } else { name.clone() }, frame));
        }
    }
    Ok(frames)
}

/// Answers every frame (`concurrency` at a time, results in input order) and scores those that
/// carry ground truth. A frame that failed to parse or to predict is an error item, not scored.
pub async fn evaluate_frames(
    predictor: &Predictor,
    frames: Vec<Result<Frame>>,
    concurrency: usize,
    timeout: Duration,
) -> Result<EvaluateResponse> {
    let results: Vec<(Option<Frame>, BatchItem)> = futures::stream::iter(frames.into_iter().enumerate())
        .map(|(i, parsed)| async move {
            match parsed {
                Ok(frame) => {
                    let r = predictor.answer(frame.clone(), None, timeout).await;
                    (Some(frame), BatchItem::new(i, r))
                }
                Err(e) => (None, BatchItem::new(i, Err(e))),
            }
        })
        .buffered(concurrency.max(1))
        .collect()
        .await;
    let mut acc = EvalAccumulator::default();
    let mut failed = 0;
    for (frame, it) in &results {
        match (frame, &it.response) {
            (Some(f), Some(resp)) => acc.add(f, resp)?,
            _ => failed += 1,
        }
    }
    Ok(EvaluateResponse {
        predictions: results.into_iter().map(|(_, it)| it).collect(),
        metrics: acc.reports(),
        breakdown: acc.breakdown(),
        diagnostics: acc.diagnostics(),
        failed_frames: failed,
        skipped_persons: acc.skipped(),
    })
}

/// How `posefuse eval` runs a data set's fixtures.
#[derive(Debug, Clone)]
pub struct FixtureRun {
    /// Forced on every frame, when given.
    pub mode: Option<RequestedMode>,
    /// Put on every request box's heading, when given (seeded by `noise_seed`).
    pub heading_noise: Option<HeadingNoise>,
    pub noise_seed: u64,
    /// Frames answered at once (the results do not depend on it).
    pub concurrency: usize,
    pub timeout: Duration,
}

/// The `posefuse eval` report of a data set's fixtures.
pub async fn evaluate_fixtures(predictor: &Predictor, data: &Path, run: &FixtureRun) -> Result<EvalReport> {
    let (names, mut frames): (Vec<String>, Vec<Frame>) = load_fixtures(data)?.into_iter().unzip();
    if let Some(m) = run.mode {
        for f in &mut frames {
            f.mode = m;
        }
    }
    if let Some(noise) = run.heading_noise {
        perturb_headings(&mut frames, noise, run.noise_seed);
    }
    let (mode, concurrency, timeout) = (run.mode, run.concurrency, run.timeout);
    let n = frames.len();
    let ev = evaluate_frames(predictor, frames.into_iter().map(Ok).collect(), concurrency, timeout).await?;
    let failures = ev
        .predictions
        .iter()
        .filter_map(|it| it.error.as_ref().map(|e| format!("{}: {}", names[it.index], e.message)))
        .take(10)
        .collect();
    let m = &predictor.bundle().manifest;
    Ok(EvalReport {
        data: data.to_path_buf(),
        model: ModelRef { name: m.name.clone(), version: m.version.clone() },
        mode,
        frames: n,
        failed_frames: ev.failed_frames,
        skipped_persons: ev.skipped_persons,
        failures,
        metrics: ev.metrics,
        breakdown: ev.breakdown,
        diagnostics: ev.diagnostics,
        heading_noise: run.heading_noise,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use posefuse_core::frame::{Box3d, GroundTruth, Keypoints3d, Person, Points};
    use posefuse_core::keypoints::{K, NAMES};

    /// One person whose keypoints are all predicted 10 cm off, except keypoint 3 (occluded, 40 cm
    /// off) and keypoint 4 (missing from the labels, 2 m off).
    fn frame_and_answer() -> (Frame, PoseResponse) {
        let gt: Vec<[f64; 3]> = (0..K).map(|k| [10.0, 0.0, 0.1 * k as f64]).collect();
        let off = |k: usize| match k {
            3 => 0.4,
            4 => 2.0,
            _ => 0.1,
        };
        let person = Person {
            id: "p".into(),
            camera: None,
            box_2d: None,
            box_3d: Box3d {
                center_x: 10.0,
                center_y: 0.0,
                center_z: 0.9,
                length: 0.6,
                width: 0.6,
                height: 1.8,
                heading: 0.0,
            },
            ground_truth: Some(GroundTruth {
                keypoints_3d: Some(Keypoints3d {
                    xyz: gt.clone(),
                    visible: (0..K).map(|k| k != 3 && k != 4).collect(),
                    occluded: (0..K).map(|k| k == 3).collect(),
                }),
                keypoints_2d: None,
            }),
        };
        let frame = Frame {
            frame_id: None,
            image: None,
            image_rgb: None,
            calibration: None,
            cameras: Vec::new(),
            points: Points::Flat(vec![10.0, 0.0, 1.0]),
            persons: vec![person],
            mode: RequestedMode::Auto,
        };
        let keypoints: Vec<serde_json::Value> = (0..K)
            .map(|k| {
                let p = gt[k];
                serde_json::json!({"name": NAMES[k], "waymo_type": 1, "xyz": [p[0] + off(k), p[1], p[2]]})
            })
            .collect();
        let answer = serde_json::json!({
            "model": {"name": "m", "version": "1"},
            "persons": [{"id": "p", "mode": "lidar", "mode_reason": "test", "num_points": 1, "keypoints": keypoints}],
            "timings": {"decode_ms": 0.0, "preprocess_ms": 0.0, "queue_ms": 0.0, "inference_ms": 0.0, "total_ms": 0.0},
        });
        (frame, serde_json::from_value(answer).unwrap())
    }

    #[test]
    fn occluded_keypoints_count_in_the_headline_and_missing_ones_do_not() {
        let (frame, answer) = frame_and_answer();
        let mut acc = EvalAccumulator::default();
        acc.add(&frame, &answer).unwrap();
        let all = &acc.reports()["all"];
        // 11 visible keypoints at 0.1 m and one occluded at 0.4 m: (11·0.1 + 0.4) / 12 = 0.125
        assert!((all.mpjpe_3d_m.unwrap() - 0.125).abs() < 1e-12, "{all:?}");
        // PCK@0.2 m: 11 of 12
        assert!((all.pck_3d_20cm.unwrap() - 11.0 / 12.0).abs() < 1e-12);
        assert!(all.per_keypoint_oks_3d[3].oks.is_some() && all.per_keypoint_oks_3d[4].oks.is_none());
        let b = acc.breakdown();
        assert!((b["visible"].mpjpe_3d_m.unwrap() - 0.1).abs() < 1e-12);
        assert!((b["occluded"].mpjpe_3d_m.unwrap() - 0.4).abs() < 1e-12);
        assert_eq!((b["visible"].count_3d, b["occluded"].count_3d), (1, 1));
        assert_eq!(acc.reports()["lidar"], *all);
        let report = EvalReport {
            data: PathBuf::from("d"),
            model: ModelRef { name: "m".into(), version: "1".into() },
            mode: None,
            heading_noise: None,
            frames: 1,
            failed_frames: 0,
            skipped_persons: 0,
            failures: Vec::new(),
            metrics: acc.reports(),
            breakdown: b,
            diagnostics: acc.diagnostics(),
        };
        let text = report.text();
        assert!(text.contains("model m 1 on d (1 frames"), "{text}");
        assert!(text.contains("MPJPE                        0.1250 m"), "{text}");
        assert!(text.contains("breakdown, occluded keypoints only (3D): OKS/ACC"), "{text}");
        assert!(text.contains("MPJPE 40.00 cm (1 persons)"), "{text}");
    }
}
