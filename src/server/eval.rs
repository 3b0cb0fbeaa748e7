//! Scoring predictions against ground truth with `crate::metrics` (the same accumulator the
//! trainer's numbers are checked against), overall and per mode; and `posefuse eval`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::api::{Mode, PoseResponse};
use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::geometry::Camera;
use crate::metrics::{MetricsAccumulator, MetricsReport};

/// Metrics over all persons and per mode that ran.
#[derive(Debug, Clone, Default)]
pub struct EvalAccumulator {
    all: MetricsAccumulator,
    by_mode: BTreeMap<Mode, MetricsAccumulator>,
    skipped: usize,
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
        let camera = Camera::from_calibration(&frame.calibration)?;
        let answered = frame.persons.iter().enumerate().filter(|(i, _)| !skipped.contains(i));
        self.skipped +=
            frame.persons.iter().enumerate().filter(|(i, p)| skipped.contains(i) && p.ground_truth.is_some()).count();
        for ((_, person), pose) in answered.zip(&resp.persons) {
            let Some(gt) = &person.ground_truth else { continue };
            let pred: Vec<[f64; 3]> = pose.keypoints.iter().map(|k| k.xyz).collect();
            let mut one = MetricsAccumulator::new();
            if let Some(k3) = &gt.keypoints_3d {
                one.add_3d(&pred, &k3.xyz, &k3.visible, &person.box_3d)?;
            }
            if let (Some(k2), Some(b2)) = (&gt.keypoints_2d, person.box_2d.or(pose.box_2d)) {
                one.add_projected(&camera, &pred, &k2.uv, &k2.visible, &b2)?;
            }
            self.all.merge(&one);
            self.by_mode.entry(pose.mode).or_default().merge(&one);
        }
        Ok(())
    }

    /// Persons with ground truth that the server skipped (not scored).
    pub fn skipped(&self) -> usize {
        self.skipped
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
    pub model: super::api::ModelRef,
    /// The forced mode, if any.
    pub mode: Option<crate::frame::RequestedMode>,
    pub frames: usize,
    pub failed_frames: usize,
    /// Persons with ground truth that got no pose (no LiDAR point in the box, ...); not scored.
    pub skipped_persons: usize,
    /// The first few failures (`file: message`).
    pub failures: Vec<String>,
    /// `all` and per mode.
    pub metrics: BTreeMap<String, MetricsReport>,
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
        for (name, report) in &self.metrics {
            out.push_str(&format!("\n== {name}\n{}", report.table()));
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
        let value: serde_json::Value =
            super::http::parse_json(&bytes).map_err(|e| Error::Io(format!("{}: {e}", f.display())))?;
        let items = match value {
            serde_json::Value::Array(v) => v,
            other => vec![other],
        };
        let many = items.len() > 1;
        for (i, v) in items.into_iter().enumerate() {
            let frame: Frame = super::http::from_value(v).map_err(|e| Error::Io(format!("{}: {e}", f.display())))?;
            frames.push((if many { format!("{name}[{i}]") } else { name.clone() }, frame));
        }
    }
    Ok(frames)
}

/// Predicts every fixture (sequentially, like the trainer's evaluation) and scores it.
pub async fn evaluate_frames(
    predictor: &super::Predictor,
    data: &Path,
    mode: Option<crate::frame::RequestedMode>,
    frames: Vec<(String, Frame)>,
) -> Result<EvalReport> {
    let mut acc = EvalAccumulator::default();
    let (mut failed, mut failures) = (0, Vec::new());
    let n = frames.len();
    for (name, frame) in frames {
        match predictor.predict(frame.clone(), None).await {
            Ok(resp) => acc.add(&frame, &resp)?,
            Err(e) => {
                failed += 1;
                if failures.len() < 10 {
                    failures.push(format!("{name}: {e}"));
                }
            }
        }
    }
    let m = &predictor.bundle().manifest;
    Ok(EvalReport {
        data: data.to_path_buf(),
        model: super::api::ModelRef { name: m.name.clone(), version: m.version.clone() },
        mode,
        frames: n,
        failed_frames: failed,
        skipped_persons: acc.skipped(),
        failures,
        metrics: acc.reports(),
    })
}
