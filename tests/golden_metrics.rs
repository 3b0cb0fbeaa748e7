//! Golden vectors for the metrics, shared with the trainer's Python copy.
//!
//! `tests/golden/metrics.json` is written by this implementation: after an intended change of a
//! metric, regenerate it with `POSEFUSE_WRITE_GOLDEN=1 cargo test --test golden_metrics`. That run
//! writes the file and fails (so a stray variable never turns the checks into passes); it refuses
//! to write at all where `CI` is set. Review the diff, then run the tests again without it.

use std::path::PathBuf;

use posefuse::keypoints::{K, OKS_SCALES};
use posefuse::metrics::{evaluate_person, oks_acc, PersonEval};
use serde_json::{json, Value};

const TOL: f64 = 1e-9;

fn golden_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden/metrics.json")
}

/// A standing person 12 m ahead, in the project's keypoint order (vehicle frame, metres).
fn skeleton_3d() -> Vec<[f64; 3]> {
    let (x, y) = (12.0, 1.0);
    let sides = |dy: f64, z: f64| [[x, y + dy, z], [x, y - dy, z]];
    let mut out = vec![[x, y, 1.62]];
    for (dy, z) in [(0.2, 1.45), (0.25, 1.15), (0.27, 0.9), (0.1, 0.95), (0.1, 0.5), (0.1, 0.08)] {
        out.extend(sides(dy, z));
    }
    out
}

/// The same person in pixels, roughly as a 2000 px focal length camera sees it.
fn skeleton_2d() -> Vec<[f64; 2]> {
    skeleton_3d().iter().map(|p| [960.0 - 2000.0 * (p[1] - 1.0) / p[0], 900.0 - 2000.0 * p[2] / p[0]]).collect()
}

/// A case; `labelled` gives Waymo's visibility codes (2 visible, 0 missing) unless `occluded`
/// marks a labelled keypoint 1.
fn case<const D: usize>(name: &str, pred: &[[f64; D]], gt: &[[f64; D]], labelled: &[bool], box_scale: f64) -> Value {
    case_occluded(name, pred, gt, labelled, &[], box_scale)
}

fn case_occluded<const D: usize>(
    name: &str,
    pred: &[[f64; D]],
    gt: &[[f64; D]],
    labelled: &[bool],
    occluded: &[usize],
    box_scale: f64,
) -> Value {
    let rows = |v: &[[f64; D]]| v.iter().map(|p| p.to_vec()).collect::<Vec<_>>();
    let visibility: Vec<u8> = labelled
        .iter()
        .enumerate()
        .map(|(k, &l)| match (l, occluded.contains(&k)) {
            (false, _) => 0,
            (true, true) => 1,
            (true, false) => 2,
        })
        .collect();
    json!({"name": name, "dim": D, "pred": rows(pred), "gt": rows(gt), "visibility": visibility, "box_scale": box_scale})
}

/// The inputs: hand-checkable cases (perfect, exactly one or two OKS scales off, far off, nothing
/// visible) and general ones with invisible keypoints.
fn inputs() -> Vec<Value> {
    let g3 = skeleton_3d();
    let g2 = skeleton_2d();
    let s3 = (0.6f64 * 0.5 * 1.75).cbrt();
    let s2 = (70.0f64 * 300.0).sqrt();
    let all = [true; K];
    let some: Vec<bool> = (0..K).map(|k| ![0, 5, 6].contains(&k)).collect();

    let one_sigma: Vec<[f64; 3]> = (0..K)
        .map(|k| if some[k] { [g3[k][0], g3[k][1] + OKS_SCALES[k] * s3, g3[k][2]] } else { [0.0, 0.0, 0.0] })
        .collect();
    let far: Vec<[f64; 3]> = g3.iter().map(|p| [p[0] + 1.2, p[1] - 1.6, p[2]]).collect();
    let mixed_3d: Vec<[f64; 3]> = g3
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let e = 0.02 * (k as f64 + 1.0);
            [p[0] + e, p[1] - 0.5 * e * (k % 3) as f64, p[2] + 0.3 * e * (k % 2) as f64]
        })
        .collect();
    let vis_mixed: Vec<bool> = (0..K).map(|k| k % 4 != 2).collect();
    let two_sigma: Vec<[f64; 2]> = (0..K).map(|k| [g2[k][0], g2[k][1] - 2.0 * OKS_SCALES[k] * s2]).collect();
    let mixed_2d: Vec<[f64; 2]> =
        g2.iter().enumerate().map(|(k, p)| [p[0] + 1.5 * k as f64, p[1] - 3.0 + 0.7 * (k % 5) as f64]).collect();

    // keypoint 5 occluded and one scale off, keypoint 6 missing from the labels and far off
    let occluded_pred: Vec<[f64; 3]> = (0..K)
        .map(|k| match k {
            5 => [g3[k][0], g3[k][1] + OKS_SCALES[k] * s3, g3[k][2]],
            6 => [g3[k][0] + 3.0, g3[k][1], g3[k][2]],
            _ => g3[k],
        })
        .collect();
    let but_6: Vec<bool> = (0..K).map(|k| k != 6).collect();

    vec![
        case("perfect_3d", &g3, &g3, &all, s3),
        case_occluded("occluded_counts_missing_does_not_3d", &occluded_pred, &g3, &but_6, &[5], s3),
        case("one_scale_off_3d_three_invisible", &one_sigma, &g3, &some, s3),
        case("far_off_3d", &far, &g3, &all, s3),
        case("mixed_3d", &mixed_3d, &g3, &vis_mixed, s3),
        case("two_scales_off_2d", &two_sigma, &g2, &all, s2),
        case("mixed_2d_three_invisible", &mixed_2d, &g2, &some, s2),
        case("nothing_visible_2d", &mixed_2d, &g2, &[false; K], s2),
    ]
}

/// 1.0 and 0.95 pass all 10 thresholds, 0.75 passes 6, 0.7499999999 passes 5, 0.55 passes 2,
/// 0.5 passes 1, 0.4999999 and 0.0 none, 0.9 passes 9, 0.6 passes 3: 46 passes of 100.
const OKS_LIST: [f64; 10] = [0.5, 0.75, 0.95, 1.0, 0.0, 0.4999999, 0.55, 0.7499999999, 0.9, 0.6];
const OKS_ACC_BY_HAND: f64 = 0.46;

fn points<const D: usize>(v: &Value) -> Vec<[f64; D]> {
    v.as_array()
        .expect("array of points")
        .iter()
        .map(|p| std::array::from_fn(|a| p[a].as_f64().expect("number")))
        .collect()
}

fn evaluate(c: &Value) -> PersonEval {
    // Waymo's mask: labelled, occluded (1) or visible (2)
    let visible: Vec<bool> = c["visibility"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap() > 0).collect();
    let s = c["box_scale"].as_f64().unwrap();
    match c["dim"].as_u64() {
        Some(2) => evaluate_person(&points::<2>(&c["pred"]), &points::<2>(&c["gt"]), &visible, s),
        Some(3) => evaluate_person(&points::<3>(&c["pred"]), &points::<3>(&c["gt"]), &visible, s),
        other => panic!("dim must be 2 or 3, got {other:?}"),
    }
    .unwrap()
}

fn with_outputs(mut c: Value) -> Value {
    let e = evaluate(&c);
    c["oks"] = json!(e.oks);
    c["per_keypoint_oks"] = json!(e.per_keypoint_oks);
    c["mpjpe"] = json!(e.mpjpe());
    c
}

fn generate() -> Value {
    json!({
        "cases": inputs().into_iter().map(with_outputs).collect::<Vec<_>>(),
        "oks_acc": {"oks": OKS_LIST, "value": oks_acc(&OKS_LIST)},
    })
}

fn assert_close(got: &Value, want: &Value, what: &str) {
    match (got.as_f64(), want.as_f64()) {
        (Some(g), Some(w)) => assert!((g - w).abs() <= TOL, "{what}: got {g}, golden {w}"),
        _ => assert!(got.is_null() && want.is_null(), "{what}: got {got}, golden {want}"),
    }
}

/// The golden file. With `POSEFUSE_WRITE_GOLDEN` set it is rewritten from the implementation
/// (once per run: the tests run in parallel and must not read a half-written file) and the test
/// fails; in CI it is never rewritten.
fn read_golden() -> Value {
    if std::env::var_os("POSEFUSE_WRITE_GOLDEN").is_some() {
        assert!(
            std::env::var_os("CI").is_none(),
            "POSEFUSE_WRITE_GOLDEN is set in CI: the golden file is not rewritten"
        );
        static WRITE: std::sync::Once = std::sync::Once::new();
        WRITE.call_once(|| {
            let text = serde_json::to_string_pretty(&generate()).unwrap() + "\n";
            std::fs::write(golden_path(), text).unwrap();
        });
        panic!(
            "wrote {}: review the diff, then run the tests again without POSEFUSE_WRITE_GOLDEN",
            golden_path().display()
        );
    }
    let text = std::fs::read_to_string(golden_path()).expect("tests/golden/metrics.json (see module docs to write it)");
    serde_json::from_str(&text).expect("golden file is JSON")
}

#[test]
fn implementation_reproduces_the_golden_file() {
    let golden = read_golden();
    let cases = golden["cases"].as_array().unwrap();
    assert_eq!(cases.len(), inputs().len(), "golden file is stale: regenerate it");
    for c in cases {
        let name = c["name"].as_str().unwrap();
        let fresh = with_outputs(c.clone());
        assert_close(&fresh["oks"], &c["oks"], &format!("{name} oks"));
        assert_close(&fresh["mpjpe"], &c["mpjpe"], &format!("{name} mpjpe"));
        for k in 0..K {
            assert_close(&fresh["per_keypoint_oks"][k], &c["per_keypoint_oks"][k], &format!("{name} keypoint {k}"));
        }
    }
    let list: Vec<f64> = golden["oks_acc"]["oks"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_close(&json!(oks_acc(&list)), &golden["oks_acc"]["value"], "oks_acc");
}

#[test]
fn golden_file_matches_its_generator_and_hand_values() {
    let golden = read_golden();
    let fresh = generate();
    for (g, f) in golden["cases"].as_array().unwrap().iter().zip(fresh["cases"].as_array().unwrap()) {
        let name = f["name"].as_str().unwrap();
        assert_eq!(g["name"], f["name"], "golden file is stale: regenerate it");
        assert_eq!(g["visibility"], f["visibility"], "{name}: stale visibility");
        assert_close(&g["oks"], &f["oks"], name);
    }
    let by_name = |n: &str| golden["cases"].as_array().unwrap().iter().find(|c| c["name"] == n).unwrap().clone();
    assert_eq!(by_name("perfect_3d")["oks"], json!(1.0));
    assert_eq!(by_name("perfect_3d")["mpjpe"], json!(0.0));
    assert_close(&by_name("one_scale_off_3d_three_invisible")["oks"], &json!((-0.5f64).exp()), "one scale");
    assert!(by_name("one_scale_off_3d_three_invisible")["per_keypoint_oks"][5].is_null());
    // by hand: 11 exact keypoints and the occluded one at one scale (OKS e^-½) over 12 labelled;
    // its error alone over 12 for MPJPE; the missing keypoint's 3 m count nowhere
    let occ = by_name("occluded_counts_missing_does_not_3d");
    assert_close(&occ["oks"], &json!((11.0 + (-0.5f64).exp()) / 12.0), "occluded oks");
    assert_close(&occ["mpjpe"], &json!(OKS_SCALES[5] * (0.6f64 * 0.5 * 1.75).cbrt() / 12.0), "occluded mpjpe");
    assert_close(&occ["per_keypoint_oks"][5], &json!((-0.5f64).exp()), "occluded keypoint");
    assert!(occ["per_keypoint_oks"][6].is_null());
    assert_close(&by_name("two_scales_off_2d")["oks"], &json!((-2.0f64).exp()), "two scales");
    assert_close(&by_name("far_off_3d")["mpjpe"], &json!(2.0), "far mpjpe");
    assert!(by_name("far_off_3d")["oks"].as_f64().unwrap() < 1e-10);
    assert!(by_name("nothing_visible_2d")["oks"].is_null());
    assert!(by_name("nothing_visible_2d")["mpjpe"].is_null());
    assert_close(&golden["oks_acc"]["value"], &json!(OKS_ACC_BY_HAND), "oks_acc by hand");
}
