//! No train/serve skew: `posefuse eval` (the serving pipeline over request fixtures) and the
//! trainer's evaluation of the same bundle on the same simulated persons (prepared shards, ONNX
//! Runtime from Python) must agree: MPJPE within 1 mm, OKS/ACC within 0.5 points.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn run(cmd: &mut Command) -> Vec<u8> {
    let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    assert!(out.status.success(), "{cmd:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    out.stdout
}

fn bundle_image_size(bundle: &Path) -> u64 {
    let manifest: Value =
        serde_json::from_slice(&std::fs::read(bundle.join("manifest.json")).expect("bundle manifest")).expect("JSON");
    manifest["preprocessing"]["image_size"].as_u64().expect("image_size")
}

#[test]
fn posefuse_eval_reproduces_the_trainers_metrics() {
    let bundle = root().join("models/default");
    let python = root().join(".venv/bin/python");
    assert!(python.exists(), "{} missing: run `bash scripts/setup.sh`", python.display());
    let dir = tempfile::tempdir().expect("temp dir");
    let data = dir.path().join("sim");
    let s = bundle_image_size(&bundle).to_string();
    let bin = env!("CARGO_BIN_EXE_posefuse");
    run(Command::new(bin).args(["simulate", "--count", "16", "--seed", "77", "--image-size", &s, "--out"]).arg(&data));

    let rust: Value = serde_json::from_slice(&run(Command::new(bin)
        .args(["eval", "--json", "--data"])
        .arg(&data)
        .arg("--model-dir")
        .arg(&bundle)))
    .expect("eval JSON");
    let py: Value = serde_json::from_slice(&run(Command::new(&python)
        .args(["-m", "posefuse_train.evaluate_bundle", "--fixtures-only", "--json", "--bundle"])
        .arg(&bundle)
        .arg("--data")
        .arg(&data)
        .current_dir(root().join("models-export"))))
    .expect("python JSON");

    assert_eq!(rust["failed_frames"], 0, "{rust}");
    assert_eq!(rust["skipped_persons"], py["skipped_persons"], "the same persons are skipped: {rust}\n{py}");
    let (r, p) = (&rust["metrics"]["all"], &py["metrics"]["all"]);
    assert_eq!(r["count_3d"], p["count_3d"], "the same persons are scored: {rust}\n{py}");
    assert!(r["count_3d"].as_u64().unwrap_or(0) >= 10, "too few persons scored: {rust}");
    assert_eq!(r["count_2d"], p["count_2d"]);
    let num = |v: &Value, k: &str| v[k].as_f64().unwrap_or_else(|| panic!("{k} missing in {v}"));
    assert!((num(r, "mpjpe_3d_m") - num(p, "mpjpe_3d_m")).abs() <= 1e-3, "MPJPE {r} vs {p}");
    for k in ["oks_acc_3d", "oks_acc_2d"] {
        assert!((num(r, k) - num(p, k)).abs() <= 0.005, "{k}: {} vs {}", num(r, k), num(p, k));
    }
    for mode in ["fusion", "camera"] {
        assert_eq!(rust["metrics"][mode]["count_3d"], py["metrics"][mode]["count_3d"], "persons in {mode} mode");
    }
}
