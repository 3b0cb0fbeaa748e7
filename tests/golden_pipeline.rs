//! Golden vectors for the steps that also run inside the Python trainer: smoothing + sampling,
//! point normalization and lifting. The files are written from this implementation
//! (`POSEFUSE_WRITE_GOLDEN=1 cargo test --test golden_pipeline`) and both sides check against them
//! (models-export/tests: test_fusion.py, test_metrics.py). That run writes the files and fails, so a
//! stray variable never turns the checks into passes; it refuses to write at all where `CI` is set.

use std::path::PathBuf;

use posefuse::frame::Box3d;
use posefuse::geometry::BoxFrame;
use posefuse::pipeline::{
    gaussian_kernel, lift, model_frame, reliability, sample_bilinear, sample_features, smooth_heatmaps, to_local,
    PipelineConfig, PointFrame,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{json, Value};

fn golden(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden").join(name)
}

/// Checks `value` against the committed file; when regenerating, writes it and fails instead.
fn check(name: &str, value: Value) {
    let path = golden(name);
    if std::env::var_os("POSEFUSE_WRITE_GOLDEN").is_some() {
        assert!(std::env::var_os("CI").is_none(), "POSEFUSE_WRITE_GOLDEN is set in CI: {name} is not rewritten");
        let text = serde_json::to_string_pretty(&value).expect("serializable");
        std::fs::write(&path, text + "\n").expect("writable golden dir");
        panic!("wrote {}: review the diff, then run the tests again without POSEFUSE_WRITE_GOLDEN", path.display());
    }
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let want: Value = serde_json::from_str(&text).expect("golden JSON");
    assert_close(&want, &value, name);
}

fn assert_close(want: &Value, got: &Value, at: &str) {
    match (want, got) {
        (Value::Number(a), Value::Number(b)) => {
            let (a, b) = (a.as_f64().unwrap_or(f64::NAN), b.as_f64().unwrap_or(f64::NAN));
            assert!((a - b).abs() <= 1e-6 * (1.0 + a.abs()), "{at}: {a} != {b}");
        }
        (Value::Array(a), Value::Array(b)) => {
            assert_eq!(a.len(), b.len(), "{at}: length");
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert_close(x, y, &format!("{at}[{i}]"));
            }
        }
        (Value::Object(a), Value::Object(b)) => {
            assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>(), "{at}: keys");
            for (k, x) in a {
                assert_close(x, &b[k], &format!("{at}.{k}"));
            }
        }
        _ => assert_eq!(want, got, "{at}"),
    }
}

/// NaN has no JSON form: projections behind the camera are written as null.
fn uv_json(uv: &[[f32; 2]]) -> Value {
    uv.iter().map(|p| if p[0].is_nan() { Value::Null } else { json!([p[0], p[1]]) }).collect()
}

#[test]
fn fusion_smoothing_and_sampling() {
    let (k, h, w, s) = (3usize, 16usize, 16usize, 64u32);
    let cfg = PipelineConfig::with_image_size(s);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let heatmaps: Vec<f32> = (0..k * h * w).map(|_| rng.random::<f32>().powi(4)).collect();
    let mut uv: Vec<[f32; 2]> = (0..20).map(|_| [rng.random_range(-4.0..68.0), rng.random_range(-4.0..68.0)]).collect();
    // exact rounding boundaries and the clamp at both ends
    uv.extend([[2.0, 2.0], [1.99, 6.01], [63.9, 0.0], [-1.0, 70.0], [f32::NAN, f32::NAN]]);
    let smoothed = smooth_heatmaps(&heatmaps, k, h, w, &cfg);
    let features = sample_features(&smoothed, k, h, w, &uv, s);
    let bilinear = sample_bilinear(&smoothed, k, h, w, &uv, s);
    check(
        "fusion.json",
        json!({
            "k": k, "h": h, "w": w, "image_size": s,
            "kernel_size": cfg.smoothing_kernel, "sigma": cfg.smoothing_sigma,
            "heatmaps": heatmaps,
            "kernel": gaussian_kernel(cfg.smoothing_kernel, cfg.smoothing_sigma),
            "smoothed": smoothed,
            "uv": uv_json(&uv),
            "features": features,
            "bilinear_features": bilinear,
        }),
    );
}

#[test]
fn point_normalization() {
    let cfg = PipelineConfig::default();
    let b =
        Box3d { center_x: 12.0, center_y: -3.0, center_z: 0.85, length: 0.7, width: 0.9, height: 1.7, heading: 2.4 };
    let frame = BoxFrame::new(&b);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let vehicle: Vec<[f64; 3]> = (0..8)
        .map(|_| [12.0 + rng.random_range(-0.5..0.5), -3.0 + rng.random_range(-0.5..0.5), rng.random_range(0.0..1.7)])
        .collect();
    let in_frame = |cfg: &PipelineConfig| {
        let local: Vec<[f64; 3]> = vehicle.iter().map(|p| to_local(&frame, *p, cfg)).collect();
        json!({"local": local, "frame_yaw": model_frame(&frame, cfg).heading})
    };
    let view = cfg.clone().in_frame(PointFrame::View);
    check(
        "points.json",
        json!({
            "box3d": b, "vehicle": vehicle, "view_origin": view.view_origin,
            "box_heading": in_frame(&cfg), "view": in_frame(&view),
        }),
    );
}

#[test]
fn lifting_and_reliability() {
    let (s, t, t_r) = (64u32, 2000.0, 400.0);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let points_uv: Vec<[f32; 2]> =
        (0..30).map(|_| [rng.random_range(0.0..64.0), rng.random_range(0.0..64.0)]).collect();
    let points_xyz: Vec<[f32; 3]> = (0..30)
        .map(|_| [rng.random_range(-0.4..0.4), rng.random_range(-0.4..0.4), rng.random_range(-0.9..0.9)])
        .collect();
    let kp_uv: Vec<[f32; 2]> = (0..13).map(|_| [rng.random_range(0.0..64.0), rng.random_range(0.0..64.0)]).collect();
    let lifted = lift(&kp_uv, &points_uv, &points_xyz, s, t);
    check(
        "lift.json",
        json!({
            "image_size": s, "temperature": t, "t_r": t_r,
            "kp_uv": kp_uv, "points_uv": points_uv, "points_xyz": points_xyz,
            "lifted": lifted, "reliability": reliability(&kp_uv, &points_uv, s, t_r),
        }),
    );
}
