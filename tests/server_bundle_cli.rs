//! Start-up refuses inconsistent bundles with a precise message; the CLI (`predict`, `eval`)
//! runs the serving path without a server.

mod server_support;

use std::path::Path;
use std::process::Command;

use posefuse::runtime::{Bundle, Runtime, RuntimeConfig};
use serde_json::Value;
use server_support::*;

fn copy_bundle() -> tempfile::TempDir {
    let d = tempfile::tempdir().unwrap();
    for e in std::fs::read_dir(model_dir()).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, d.path().join(p.file_name().unwrap())).unwrap();
    }
    d
}

fn edit_manifest(dir: &Path, f: impl FnOnce(&mut Value)) {
    let p = dir.join("manifest.json");
    let mut m: Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    f(&mut m);
    std::fs::write(p, serde_json::to_string_pretty(&m).unwrap()).unwrap();
}

/// Loads and starts; returns the error text.
fn start_error(dir: &Path) -> String {
    let bundle = match Bundle::load(dir) {
        Ok(b) => b,
        Err(e) => return e.to_string(),
    };
    match Runtime::start(std::sync::Arc::new(bundle), &RuntimeConfig::default()) {
        Ok(_) => panic!("bundle in {} was accepted", dir.display()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn inconsistent_bundles_are_refused_precisely() {
    // The untouched copy loads.
    let d = copy_bundle();
    let rt = Runtime::start(std::sync::Arc::new(Bundle::load(d.path()).unwrap()), &RuntimeConfig::default()).unwrap();
    assert!(rt.wait_ready(std::time::Duration::from_secs(60)));
    drop(rt);

    let d = copy_bundle();
    std::fs::write(d.path().join("point_lidar.onnx"), b"not a model").unwrap();
    let e = start_error(d.path());
    assert!(e.contains("models.point_lidar.sha256"), "{e}");

    let d = copy_bundle();
    std::fs::remove_file(d.path().join("camera.onnx")).unwrap();
    let e = start_error(d.path());
    assert!(e.contains("models.camera.file"), "{e}");

    // Declared tensor name that the ONNX file does not have.
    let d = copy_bundle();
    edit_manifest(d.path(), |m| {
        let shape = m["models"]["camera"]["inputs"]["image"].take();
        m["models"]["camera"]["inputs"] = serde_json::json!({ "pixels": shape });
    });
    let e = start_error(d.path());
    assert!(e.contains("models.camera.inputs.pixels: the ONNX file has no such tensor"), "{e}");

    // A manifest (and config) for another point count than the ONNX files were exported with.
    let d = copy_bundle();
    edit_manifest(d.path(), |m| {
        m["preprocessing"]["num_points"] = 128.into();
        for key in ["point_fusion", "point_lidar"] {
            m["models"][key]["inputs"]["points"][1] = 128.into();
            m["models"][key]["outputs"]["segmentation"][1] = 128.into();
        }
    });
    let e = start_error(d.path());
    assert!(e.contains("models.point_fusion.inputs.points: the ONNX file says shape"), "{e}");

    // Manifest shapes that disagree with its own preprocessing: a crop twice the bundle's (still
    // a multiple of the heatmap grid, so only the camera's declared input can disagree).
    let d = copy_bundle();
    edit_manifest(d.path(), |m| {
        let size = 2 * m["preprocessing"]["image_size"].as_u64().unwrap();
        m["preprocessing"]["image_size"] = size.into();
    });
    let e = start_error(d.path());
    assert!(e.contains("models.camera.inputs.image"), "{e}");

    let d = copy_bundle();
    edit_manifest(d.path(), |m| drop(m["preprocessing"].as_object_mut().unwrap().remove("lift_temperature")));
    let e = start_error(d.path());
    assert!(e.contains("preprocessing") && e.contains("lift_temperature"), "{e}");
}

fn posefuse(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(args)
        .env("ORT_DYLIB_PATH", std::env::var("ORT_DYLIB_PATH").unwrap_or_else(|_| ".ort/lib/libonnxruntime.so".into()))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap()
}

#[test]
fn cli_predict_prints_the_response() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("frame.json");
    std::fs::write(&f, serde_json::to_vec(&three_mode_frame()).unwrap()).unwrap();
    let out = posefuse(&["predict", f.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: posefuse::service::api::PoseResponse = serde_json::from_slice(&out.stdout).unwrap();
    let modes: Vec<&str> = r.persons.iter().map(|p| p.mode.as_str()).collect();
    assert_eq!(modes, ["fusion", "lidar", "camera"]);

    let out = Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(["predict", f.to_str().unwrap()])
        .env("ORT_DYLIB_PATH", "/nonexistent/libonnxruntime.so")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bash scripts/setup.sh") && err.contains("/nonexistent/libonnxruntime.so"), "{err}");
}

#[test]
fn cli_eval_reports_metrics_per_mode() {
    let d = tempfile::tempdir().unwrap();
    std::fs::create_dir(d.path().join("requests")).unwrap();
    let mut f = three_mode_frame();
    for p in &mut f.persons {
        p.ground_truth = Some(ground_truth(&p.box_3d));
    }
    std::fs::write(d.path().join("requests/000.json"), serde_json::to_vec(&f).unwrap()).unwrap();
    std::fs::write(d.path().join("requests/001.json"), serde_json::to_vec(&vec![f.clone(), f.clone()]).unwrap())
        .unwrap();
    let data = d.path().to_str().unwrap();
    let out = posefuse(&["eval", "--data", data, "--json"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["frames"], 3);
    assert_eq!(r["failed_frames"], 0);
    assert_eq!(r["metrics"]["all"]["count_3d"], 9);
    for m in ["fusion", "lidar", "camera"] {
        assert_eq!(r["metrics"][m]["count_3d"], 3, "{m}");
    }
    // Forcing a mode runs only that mode.
    let out = posefuse(&["eval", "--data", data, "--json", "--mode", "lidar"]);
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["metrics"]["lidar"]["count_3d"], 9);
    assert!(r["metrics"].get("fusion").is_none());
    // The text report has one table per mode.
    let out = posefuse(&["eval", "--data", data]);
    let text = String::from_utf8_lossy(&out.stdout);
    for h in ["== all", "== camera", "== fusion", "== lidar", "OKS/ACC", "left_shoulder"] {
        assert!(text.contains(h), "{h} missing:\n{text}");
    }
}

#[test]
fn cli_eval_with_wrong_headings_reports_the_swaps_they_cause() {
    let d = tempfile::tempdir().unwrap();
    let data = d.path().join("sim");
    let data = data.to_str().unwrap();
    let s = bundle_image_size().to_string();
    let out = posefuse(&[
        "simulate",
        "--count",
        "12",
        "--seed",
        "5",
        "--image-size",
        &s,
        "--profile",
        "clean",
        "--out",
        data,
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let eval = |extra: &[&str]| -> Value {
        let out = posefuse(&[&["eval", "--data", data, "--json", "--mode", "lidar"], extra].concat());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let exact = eval(&[]);
    let turned = eval(&["--heading-noise", "180"]);
    assert!(exact.get("heading_noise").is_none());
    assert_eq!(turned["heading_noise"], "180");
    let (e, t) = (&exact["diagnostics"]["lidar"], &turned["diagnostics"]["lidar"]);
    assert!(e["swap_judged"].as_u64().unwrap() >= 8, "{e}");
    // The default bundle reads the facing from the box heading (docs/BUNDLE.md): turned round,
    // it reads persons backwards.
    let rate = |v: &Value| v["left_right_swap_rate"].as_f64().unwrap();
    assert!(rate(e) <= 0.25 && rate(t) >= 0.75, "swap rate exact {} vs turned {}", rate(e), rate(t));
    let median = |v: &Value| v["facing_error_median_deg"].as_f64().unwrap();
    assert!(median(e) < 30.0 && median(t) > 120.0, "facing error exact {} vs turned {}", median(e), median(t));
    // Same seed, same errors, same metrics.
    assert_eq!(
        eval(&["--heading-noise", "uniform", "--noise-seed", "3"])["metrics"],
        eval(&["--heading-noise", "uniform", "--noise-seed", "3"])["metrics"]
    );
}

fn bundle_image_size() -> u64 {
    let m: Value = serde_json::from_slice(&std::fs::read(model_dir().join("manifest.json")).unwrap()).unwrap();
    m["preprocessing"]["image_size"].as_u64().unwrap()
}
