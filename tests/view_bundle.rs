//! The view-frame bundle (`models/view`, docs/BUNDLE.md "Point frame") needs no box heading: a
//! box turned end for end (the same box, its heading off by 180°) gives the same answer, while the
//! default bundle, which reads the facing from the heading, answers with left and right exchanged.
//! As the default bundle's heading stage ("Heading stage") it repairs wrong headings, and the
//! refinement ("Heading refinement") moves a heading some tens of degrees off toward the body's.

mod server_support;

use std::path::PathBuf;
use std::time::Duration;

use posefuse::frame::Frame;
use posefuse::pipeline::yaw_difference;
use posefuse::runtime::{Runtime, RuntimeConfig};
use posefuse::service::api::{Mode, PersonPose};
use posefuse::service::heading_stage::{estimated_boxes, Refine, AGREE_DEG};
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
        let boxes = frame.persons.iter().map(|p| p.box_3d).collect();
        let mut repaired = frame.clone();
        for (p, b) in repaired.persons.iter_mut().zip(estimated_boxes(boxes, &first, AGREE_DEG)) {
            p.box_3d = b;
        }
        let want = answer(&default, repaired).await;
        let got = answer(&staged, frame).await;
        assert_eq!(got.len(), want.len());
        for ((kg, _), (kw, _)) in got.iter().zip(&want) {
            assert!(max_distance(kg, kw) < 1e-6, "staged answer off by {} m", max_distance(kg, kw));
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refinement_asks_the_point_network_again_unless_the_answer_has_settled() {
    let with =
        |passes, settle_deg| async move { predictor(model_dir()).await.with_refine(Refine { passes, settle_deg }) };
    let (plain, eager, refined, settled) =
        (with(0, 5.0).await, with(3, 0.0).await, with(3, 5.0).await, with(3, 180.0).await);
    let frame = three_mode_frame();
    let timeout = Duration::from_secs(30);
    let a = plain.answer(frame.clone(), None, timeout).await.unwrap();
    let [e, r, s] = [&eager, &refined, &settled].map(|p| p.answer(frame.clone(), None, timeout));
    let (e, r, s) = (e.await.unwrap(), r.await.unwrap(), s.await.unwrap());
    let modes: Vec<Mode> = a.persons.iter().map(|p| p.mode).collect();
    assert!(modes.contains(&Mode::Fusion) && modes.contains(&Mode::Lidar), "{modes:?}");
    let xyz = |p: &PersonPose| p.keypoints.iter().map(|k| k.xyz).collect::<Vec<_>>();
    for (i, pa) in a.persons.iter().enumerate() {
        let (pe, pr, ps) = (&e.persons[i], &r.persons[i], &s.persons[i]);
        // no facing is more than 180° from its heading: the settled predictor never asks again
        assert_eq!(xyz(pa), xyz(ps), "{}: a settled answer moved", pa.id);
        if pa.mode == Mode::Camera {
            assert!(xyz(pa) == xyz(pe) && xyz(pa) == xyz(pr), "{}: a camera-only answer was refined", pa.id);
            continue;
        }
        // settle_deg 0: every answer is asked again
        assert!(max_distance(&xyz(pa), &xyz(pe)) > 1e-4, "{}: not refined", pa.id);
        // 5°: asked again exactly when the first facing is more than 5° from the box heading
        let heading = frame.persons.iter().find(|p| p.id == pa.id).unwrap().box_3d.heading;
        let off = yaw_difference(pa.facing.unwrap().yaw, heading).to_degrees();
        let moved = max_distance(&xyz(pa), &xyz(pr));
        assert_eq!(moved > 0.0, off > 5.0, "{}: facing {off:.1}° off the heading, moved {moved} m", pa.id);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bundle_in_the_view_frame_is_not_refined() {
    let plain = predictor(view_dir()).await;
    let refined = predictor(view_dir()).await.with_refine(Refine { passes: 3, settle_deg: 0.0 });
    let frame = three_mode_frame();
    let (a, b) = (answer(&plain, frame.clone()).await, answer(&refined, frame).await);
    assert_eq!(a.len(), b.len());
    for ((ka, fa), (kb, fb)) in a.iter().zip(&b) {
        assert_eq!(ka, kb);
        assert_eq!(fa.to_bits(), fb.to_bits());
    }
}

/// Aggregate metric of `posefuse eval --json` output (headings flipped unless `extra` says).
fn eval_oks(data: &std::path::Path, extra: &[&str]) -> f64 {
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"));
    let noise = if extra.contains(&"--heading-noise") { &[][..] } else { &["--heading-noise", "180"][..] };
    cmd.args(["eval", "--mode", "fusion", "--json", "--data"]).arg(data).args(noise).args(extra);
    cmd.arg("--model-dir").arg(model_dir()).current_dir(env!("CARGO_MANIFEST_DIR"));
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    r["metrics"]["fusion"]["oks_acc_3d"].as_f64().unwrap()
}

/// 24 simulated street persons under `dir`.
fn simulated(dir: &std::path::Path) -> PathBuf {
    let data = dir.join("sim");
    let sim = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(["simulate", "--count", "24", "--seed", "31", "--image-size", "64", "--profile", "street", "--out"])
        .arg(&data)
        .output()
        .unwrap();
    assert!(sim.status.success(), "{}", String::from_utf8_lossy(&sim.stderr));
    data
}

#[test]
fn with_headings_45_degrees_off_refinement_recovers_the_default_bundles_accuracy() {
    let tmp = tempfile::tempdir().unwrap();
    let data = simulated(tmp.path());
    let exact = eval_oks(&data, &["--heading-noise", "0"]);
    let off = eval_oks(&data, &["--heading-noise", "45"]);
    let refined = eval_oks(&data, &["--heading-noise", "45", "--heading-refine", "3"]);
    assert!(off < exact - 0.15, "45° off: OKS@3D {off}, exact {exact}");
    assert!(refined > off + 0.1, "refined: OKS@3D {refined}, unrefined {off}");
}

#[test]
fn with_every_heading_flipped_the_heading_stage_keeps_the_default_bundle_accurate() {
    let tmp = tempfile::tempdir().unwrap();
    let data = simulated(tmp.path());
    let alone = eval_oks(&data, &[]);
    let view = view_dir();
    let staged = eval_oks(&data, &["--heading-model", view.to_str().unwrap()]);
    // Flipped headings: the default bundle reads every person backwards; the stage turns them back.
    assert!(alone < 0.1, "default bundle alone: OKS@3D {alone}");
    assert!(staged > 0.45, "with the heading stage: OKS@3D {staged}");
    // --precision names the main bundle's camera: the view bundle, which has no INT8 file, keeps its own.
    let int8 = eval_oks(&data, &["--heading-model", view.to_str().unwrap(), "--precision", "int8"]);
    assert!(int8 > 0.45, "with the heading stage, the main camera in INT8: OKS@3D {int8}");
}
