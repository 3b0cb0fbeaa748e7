//! The view-frame bundle (`models/view`, docs/BUNDLE.md "Point frame") needs no box heading: a
//! box turned end for end (the same box, its heading off by 180°) gives the same answer, while the
//! default bundle, which reads the facing from the heading, answers with left and right exchanged.
//! As the default bundle's heading stage ("Heading stage") it repairs wrong headings.

mod server_support;

use std::path::PathBuf;
use std::time::Duration;

use posefuse::frame::Frame;
use posefuse::runtime::{Runtime, RuntimeConfig};
use posefuse::service::heading_stage::{with_estimated_headings, AGREE_DEG};
use posefuse::service::Predictor;
use server_support::*;

async fn runtime(dir: PathBuf) -> std::sync::Arc<Runtime> {
    let runtime =
        tokio::task::spawn_blocking(move || Runtime::load(&dir, &RuntimeConfig::DEFAULT)).await.unwrap().unwrap();
    assert!(runtime.wait_ready(Duration::from_secs(60)));
    runtime
}

async fn predictor(dir: PathBuf) -> Predictor {
    Predictor::new(runtime(dir).await)
}

fn view_dir() -> PathBuf {
    model_dir().with_file_name("view")
}

/// Keypoints and facing yaw of the frame's persons.
async fn answer(p: &Predictor, frame: Frame) -> Vec<(Vec<[f64; 3]>, f64)> {
    let resp = p.answer(frame, None, Duration::from_secs(30)).await.unwrap();
    resp.persons
        .iter()
        .map(|q| (q.keypoints.iter().map(|k| k.xyz).collect(), q.facing.as_ref().map_or(f64::NAN, |f| f.yaw)))
        .collect()
}

fn turned_end_for_end(mut frame: Frame) -> Frame {
    for p in &mut frame.persons {
        p.box_3d.heading += std::f64::consts::PI;
    }
    frame
}

fn max_distance(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt())
        .fold(0.0, f64::max)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_view_bundle_answers_the_same_whatever_the_heading() {
    let view = predictor(view_dir()).await;
    let default = predictor(model_dir()).await;
    for frame in [fusion_frame(), three_mode_frame()] {
        let (a, b) = (answer(&view, frame.clone()).await, answer(&view, turned_end_for_end(frame.clone())).await);
        assert_eq!(a.len(), b.len());
        for ((ka, fa), (kb, fb)) in a.iter().zip(&b) {
            assert!(max_distance(ka, kb) < 1e-4, "view bundle moved by {} m", max_distance(ka, kb));
            assert!((fa - fb).abs() < 1e-6 || (fa.is_nan() && fb.is_nan()));
        }
    }
    // The default bundle turns its answer with the box: far from its first answer.
    let frame = fusion_frame();
    let (a, b) = (answer(&default, frame.clone()).await, answer(&default, turned_end_for_end(frame)).await);
    assert!(max_distance(&a[0].0, &b[0].0) > 0.1, "the default bundle ignored the heading");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_heading_stage_answers_with_the_facings_it_predicted() {
    let view = predictor(view_dir()).await;
    let default = predictor(model_dir()).await;
    let staged = Predictor::new(runtime(model_dir()).await).with_heading_stage(runtime(view_dir()).await, AGREE_DEG);
    for frame in [three_mode_frame(), turned_end_for_end(three_mode_frame())] {
        let first = view.answer(frame.clone(), None, Duration::from_secs(30)).await.unwrap();
        let repaired = with_estimated_headings(frame.clone(), &first, AGREE_DEG);
        let want = answer(&default, repaired).await;
        let got = answer(&staged, frame).await;
        assert_eq!(got.len(), want.len());
        for ((kg, _), (kw, _)) in got.iter().zip(&want) {
            assert!(max_distance(kg, kw) < 1e-6, "staged answer off by {} m", max_distance(kg, kw));
        }
    }
}

/// Aggregate metric of `posefuse eval --json` output.
fn eval_oks(data: &std::path::Path, extra: &[&str]) -> f64 {
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"));
    cmd.args(["eval", "--mode", "fusion", "--json", "--heading-noise", "180", "--data"]).arg(data).args(extra);
    cmd.arg("--model-dir").arg(model_dir()).current_dir(env!("CARGO_MANIFEST_DIR"));
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    r["metrics"]["fusion"]["oks_acc_3d"].as_f64().unwrap()
}

#[test]
fn with_every_heading_flipped_the_heading_stage_keeps_the_default_bundle_accurate() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("sim");
    let sim = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(["simulate", "--count", "24", "--seed", "31", "--image-size", "64", "--profile", "street", "--out"])
        .arg(&data)
        .output()
        .unwrap();
    assert!(sim.status.success(), "{}", String::from_utf8_lossy(&sim.stderr));
    let alone = eval_oks(&data, &[]);
    let view = view_dir();
    let staged = eval_oks(&data, &["--heading-model", view.to_str().unwrap()]);
    // Flipped headings: the default bundle reads every person backwards; the stage turns them back.
    assert!(alone < 0.1, "default bundle alone: OKS@3D {alone}");
    assert!(staged > 0.45, "with the heading stage: OKS@3D {staged}");
}
