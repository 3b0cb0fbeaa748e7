//! No train/serve skew, mode by mode: the serving path (`POST /v1/evaluate` on an in-process
//! server, the evaluation `posefuse eval` runs) and the trainer's evaluation of the same bundle
//! (`models-export/tools/evaluate_bundle.py`: the simulator's prepared shards through ONNX Runtime
//! from Python) must agree on the same simulated persons, person by person: the same frames
//! refused, the same persons skipped, the same mode, and every keypoint within 1 mm.
//!
//! The fixtures are `posefuse simulate` output with the image dropped from every third frame, so
//! that `auto` takes all three paths: fusion, camera lifting (fewer than `min_points` points) and
//! LiDAR-only (no image). `auto` runs twice, on copies of the bundle whose `min_points` is one
//! chosen person's point count and that count plus one: the person is exactly at the threshold in
//! the first run and one below it in the second.

mod server_support;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use serde_json::{json, Value};

/// Largest allowed distance between a served and a trainer-evaluated keypoint (metres).
const TOLERANCE_M: f64 = 1e-3;
/// Fewest persons each mode's comparison must cover.
const MIN_PERSONS: usize = 10;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn run(cmd: &mut Command) -> Vec<u8> {
    let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    assert!(out.status.success(), "{cmd:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    out.stdout
}

fn read_json(path: &Path) -> Value {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A copy of the bundle at `src` with its manifest edited (the ONNX files are unchanged, so their
/// hashes still hold).
fn bundle_copy(src: &Path, dst: &Path, edit: impl Fn(&mut Value)) -> PathBuf {
    std::fs::create_dir_all(dst).expect("bundle dir");
    let mut manifest = read_json(&src.join("manifest.json"));
    for m in manifest["models"].as_object().expect("models").values() {
        let variants = m["variants"].as_object().into_iter().flat_map(|v| v.values());
        for file in std::iter::once(&m["file"]).chain(variants.map(|v| &v["file"])) {
            let file = file.as_str().expect("file");
            std::fs::copy(src.join(file), dst.join(file)).expect("copy model");
        }
    }
    edit(&mut manifest);
    std::fs::write(dst.join("manifest.json"), serde_json::to_vec_pretty(&manifest).expect("JSON")).expect("write");
    dst.to_path_buf()
}

/// One evaluation on both sides: what the server answered (the `/v1/evaluate` body, one item per
/// fixture in file order) and what the trainer's tool computed (its report and its per-person
/// predictions, keyed by fixture file and person id).
struct Run {
    serve: Value,
    trainer: Value,
    trainer_predictions: Value,
}

struct Setup {
    /// Fixture file names, in the order they were posted.
    files: Vec<String>,
    runs: BTreeMap<&'static str, Run>,
    /// The person whose point count sets `min_points` in the two auto runs: (file, id, count).
    boundary: (String, String, u64),
    /// Camera-mode predictions of the trainer's tool with the bundle's lifting temperature set to 1.
    camera_t1: Value,
}

fn python(bundle: &Path, data: &Path, modes: &str, out: &Path) -> (Value, Value) {
    let python = root().join(".venv/bin/python");
    assert!(python.exists(), "{} missing: run `bash scripts/setup.sh`", python.display());
    let stdout = run(Command::new(&python)
        .args(["-m", "tools.evaluate_bundle", "--fixtures-only", "--json", "--mode", modes, "--bundle"])
        .arg(bundle)
        .arg("--data")
        .arg(data)
        .arg("--predictions-out")
        .arg(out)
        .env("PYTHONPATH", root().join("models-export"))
        .current_dir(root().join("models-export")));
    (serde_json::from_slice(&stdout).expect("tool JSON"), read_json(out))
}

/// Posts every fixture with `mode` set to a fresh server on `bundle`, as one `/v1/evaluate` call.
fn serve(rt: &tokio::runtime::Runtime, bundle: &Path, frames: &[Value], modes: &[&str]) -> Vec<Value> {
    let mut config = posefuse::server::ServerConfig::new(bundle);
    config.body_limit = 256 * 1024 * 1024;
    rt.block_on(async {
        let server = server_support::start(config).await;
        let client = reqwest::Client::new();
        let mut out = Vec::new();
        for mode in modes {
            let body: Vec<Value> = frames
                .iter()
                .map(|f| {
                    let mut f = f.clone();
                    f["mode"] = json!(mode);
                    f
                })
                .collect();
            let resp = client.post(server.url("/v1/evaluate")).json(&body).send().await.expect("POST /v1/evaluate");
            assert_eq!(resp.status(), 200, "mode {mode}");
            out.push(resp.json::<Value>().await.expect("evaluate JSON"));
        }
        server.shutdown().await.expect("clean shutdown");
        out
    })
}

fn setup() -> Setup {
    let bundle = root().join("models/default");
    let manifest = read_json(&bundle.join("manifest.json"));
    let s = manifest["preprocessing"]["image_size"].as_u64().expect("image_size").to_string();
    let tmp = tempfile::tempdir().expect("temp dir");
    let dir = tmp.path().to_path_buf();
    let data = dir.join("sim");
    let bin = env!("CARGO_BIN_EXE_posefuse");
    run(Command::new(bin)
        .args(["simulate", "--count", "40", "--seed", "77", "--image-size", &s, "--profile", "clean", "--out"])
        .arg(&data));

    let requests = data.join("requests");
    let mut files: Vec<String> = std::fs::read_dir(&requests)
        .expect("requests dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("frame-") && n.ends_with(".json"))
        .collect();
    files.sort();
    let mut frames: Vec<Value> = files.iter().map(|f| read_json(&requests.join(f))).collect();
    let rt = tokio::runtime::Runtime::new().expect("tokio runtime");

    // Point counts (as the server counts them) pick the boundary person: the median count among
    // persons with points, so that auto finds persons on both sides of min_points.
    let lidar = serve(&rt, &bundle, &frames, &["lidar"]).remove(0);
    let mut counted: Vec<(u64, usize, String)> = Vec::new();
    for (i, item) in lidar["predictions"].as_array().expect("predictions").iter().enumerate() {
        for p in item["response"]["persons"].as_array().expect("persons") {
            counted.push((p["num_points"].as_u64().expect("num_points"), i, p["id"].as_str().expect("id").into()));
        }
    }
    counted.sort();
    let (count, boundary_frame, boundary_id) = counted[counted.len() / 2].clone();
    assert!(count >= 2, "boundary person has {count} points");

    // Every third frame loses its image (never the boundary person's): LiDAR-only in auto mode,
    // refused in fusion and camera mode.
    for (i, frame) in frames.iter_mut().enumerate() {
        if i % 3 == 1 && i != boundary_frame {
            frame.as_object_mut().expect("frame object").remove("image");
            std::fs::write(requests.join(&files[i]), serde_json::to_vec(frame).expect("JSON")).expect("write fixture");
        }
    }

    let mut runs = BTreeMap::new();
    let served = serve(&rt, &bundle, &frames, &["fusion", "lidar", "camera"]);
    let (reports, preds) = python(&bundle, &data, "fusion,lidar,camera", &dir.join("forced.json"));
    for (mode, serve) in ["fusion", "lidar", "camera"].into_iter().zip(served) {
        runs.insert(mode, Run { serve, trainer: reports[mode].clone(), trainer_predictions: preds[mode].clone() });
    }
    for (name, min_points) in [("auto_at_min_points", count), ("auto_below_min_points", count + 1)] {
        let copy = bundle_copy(&bundle, &dir.join(name), |m| m["preprocessing"]["min_points"] = json!(min_points));
        let serve = serve(&rt, &copy, &frames, &["auto"]).remove(0);
        let (reports, preds) = python(&copy, &data, "auto", &dir.join(format!("{name}.json")));
        runs.insert(name, Run { serve, trainer: reports["auto"].clone(), trainer_predictions: preds["auto"].clone() });
    }
    // the heatmap sampling the bundle does not use (nearest cell or bilinear): a copy whose
    // manifest asks for it (the networks are the same)
    let sampling = if manifest["preprocessing"]["sampling"] == "bilinear" { "nearest" } else { "bilinear" };
    let copy = bundle_copy(&bundle, &dir.join("other_sampling"), |m| m["preprocessing"]["sampling"] = json!(sampling));
    let served = serve(&rt, &copy, &frames, &["fusion"]).remove(0);
    let (reports, preds) = python(&copy, &data, "fusion", &dir.join("other_sampling.json"));
    runs.insert(
        "fusion_other_sampling",
        Run { serve: served, trainer: reports["fusion"].clone(), trainer_predictions: preds["fusion"].clone() },
    );
    // the camera network at the precision the bundle does not serve: a copy whose manifest makes
    // it its own, which both sides must then run without being told
    let other = if manifest["precision"] == "int8" { "fp32" } else { "int8" };
    let copy = bundle_copy(&bundle, &dir.join("other_precision"), |m| m["precision"] = json!(other));
    let serve = serve(&rt, &copy, &frames, &["fusion"]).remove(0);
    let (reports, preds) = python(&copy, &data, "fusion", &dir.join("other_precision.json"));
    runs.insert(
        "fusion_other_precision",
        Run { serve, trainer: reports["fusion"].clone(), trainer_predictions: preds["fusion"].clone() },
    );
    let t1 = bundle_copy(&bundle, &dir.join("t1"), |m| m["preprocessing"]["lift_temperature"] = json!(1.0));
    let (_, camera_t1) = python(&t1, &data, "camera", &dir.join("t1.json"));
    drop(tmp);
    let boundary = (files[boundary_frame].clone(), boundary_id, count);
    Setup { files, runs, boundary, camera_t1: camera_t1["camera"].clone() }
}

fn setup_once() -> &'static Setup {
    static SETUP: OnceLock<Setup> = OnceLock::new();
    SETUP.get_or_init(setup)
}

fn xyz(person: &Value) -> Vec<[f64; 3]> {
    let kps = person["keypoints"].as_array().map(|k| k.iter().map(|k| &k["xyz"]).collect::<Vec<_>>());
    let rows: Vec<&Value> = kps.unwrap_or_else(|| person["xyz"].as_array().expect("xyz").iter().collect());
    rows.iter().map(|v| std::array::from_fn(|c| v[c].as_f64().expect("coordinate"))).collect()
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// What one comparison covered.
#[derive(Debug, Default)]
struct Compared {
    persons: usize,
    by_mode: BTreeMap<String, usize>,
    refused_frames: usize,
    skipped: usize,
    worst_m: f64,
}

/// Compares a run person by person and returns what it covered; panics on the first difference.
fn compare(setup: &Setup, name: &str) -> Compared {
    let run = &setup.runs[name];
    let items = run.serve["predictions"].as_array().expect("predictions");
    assert_eq!(items.len(), setup.files.len(), "{name}: one answer per fixture");
    let mut c = Compared::default();
    for (file, item) in setup.files.iter().zip(items) {
        let want = &run.trainer_predictions[file.as_str()];
        assert!(want.is_object(), "{name}: the trainer's tool did not see {file}");
        if want["refused"].as_bool().expect("refused") {
            assert!(item["error"].is_object(), "{name}: {file} is served, the trainer refuses it: {item}");
            c.refused_frames += 1;
            continue;
        }
        let resp = &item["response"];
        assert!(resp.is_object(), "{name}: {file} is refused by the server: {item}");
        let skipped: BTreeSet<&str> = resp["skipped"]
            .as_array()
            .map_or_else(BTreeSet::new, |v| v.iter().map(|s| s["id"].as_str().expect("id")).collect());
        let want_skipped: BTreeSet<&str> =
            want["skipped"].as_array().expect("skipped").iter().map(|s| s.as_str().expect("id")).collect();
        assert_eq!(skipped, want_skipped, "{name}: {file}: skipped persons");
        c.skipped += skipped.len();
        let persons = resp["persons"].as_array().expect("persons");
        assert_eq!(persons.len(), want["persons"].as_object().expect("persons").len(), "{name}: {file}: persons");
        for p in persons {
            let id = p["id"].as_str().expect("id");
            let w = &want["persons"][id];
            assert!(w.is_object(), "{name}: {file}: person {id} is answered by the server only");
            let mode = p["mode"].as_str().expect("mode");
            assert_eq!(mode, w["mode"], "{name}: {file}: person {id} ({} points)", p["num_points"]);
            let (got, exp) = (xyz(p), xyz(w));
            assert_eq!((got.len(), exp.len()), (13, 13), "{name}: {file}: person {id}: keypoints");
            for (k, (g, e)) in got.iter().zip(&exp).enumerate() {
                let d = distance(g, e);
                assert!(
                    d <= TOLERANCE_M,
                    "{name}: {file}: person {id} ({mode} mode), keypoint {k}: served {g:?}, trainer {e:?} ({:.2} mm apart)",
                    d * 1e3
                );
                c.worst_m = c.worst_m.max(d);
            }
            c.persons += 1;
            *c.by_mode.entry(mode.to_string()).or_default() += 1;
        }
    }
    // The metrics of both sides are over the same persons.
    let (sm, tm) = (&run.serve["metrics"], &run.trainer["metrics"]);
    for (key, report) in sm.as_object().expect("metrics") {
        assert_eq!(report["count_3d"], tm[key.as_str()]["count_3d"], "{name}: metrics {key}: persons");
        let (a, b) = (report["mpjpe_3d_m"].as_f64(), tm[key.as_str()]["mpjpe_3d_m"].as_f64());
        let (a, b) = (a.expect("served mpjpe"), b.expect("trainer mpjpe"));
        assert!((a - b).abs() <= TOLERANCE_M, "{name}: metrics {key}: MPJPE {a} vs {b}");
    }
    assert_eq!(sm.as_object().map(|m| m.len()), tm.as_object().map(|m| m.len()), "{name}: the same modes ran");
    assert_eq!(run.serve["failed_frames"].as_u64(), Some(c.refused_frames as u64), "{name}: failed frames");
    assert_eq!(run.trainer["failed_frames"].as_u64(), Some(c.refused_frames as u64), "{name}: trainer's refusals");
    assert_eq!(run.serve["skipped_persons"].as_u64(), Some(c.skipped as u64), "{name}: skipped persons");
    eprintln!("{name}: {c:?}");
    c
}

fn forced(mode: &str) {
    let c = compare(setup_once(), mode);
    assert!(c.persons >= MIN_PERSONS, "{mode}: only {} persons compared", c.persons);
    assert_eq!(c.by_mode.keys().collect::<Vec<_>>(), [mode], "{mode}: every person in the requested mode");
    if mode != "lidar" {
        assert!(c.refused_frames > 0, "{mode}: frames without an image must be refused");
    }
}

#[test]
fn fusion_mode_serves_what_the_trainer_evaluates() {
    forced("fusion");
}

#[test]
fn lidar_mode_serves_what_the_trainer_evaluates() {
    forced("lidar");
}

#[test]
fn camera_mode_serves_what_the_trainer_evaluates() {
    forced("camera");
}

/// A fusion-mode variant `name` serves what the trainer evaluates with it, and it is not plain
/// fusion: returns how far its farthest keypoint moved from plain fusion's (metres).
fn fusion_variant(name: &str) -> f64 {
    let setup = setup_once();
    let c = compare(setup, name);
    assert!(c.persons >= MIN_PERSONS && c.by_mode.keys().collect::<Vec<_>>() == ["fusion"], "{c:?}");
    let answers = |name: &str| -> Vec<Vec<[f64; 3]>> {
        let items = setup.runs[name].serve["predictions"].as_array().expect("predictions").clone();
        items
            .iter()
            .flat_map(|it| it["response"]["persons"].as_array().cloned().unwrap_or_default())
            .map(|p| xyz(&p))
            .collect()
    };
    let (variant, plain) = (answers(name), answers("fusion"));
    assert_eq!(variant.len(), plain.len());
    variant.iter().zip(&plain).flat_map(|(a, b)| a.iter().zip(b)).map(|(a, b)| distance(a, b)).fold(0.0, f64::max)
}

/// The camera network at the precision the bundle does not serve (float32 for an INT8 bundle, and
/// the other way round), made the bundle's own by its manifest alone, serves what the trainer
/// evaluates with it, and it is not the other file: some fused keypoint moves.
#[test]
fn fusion_mode_at_the_other_precision_serves_what_the_trainer_evaluates() {
    let changed = fusion_variant("fusion_other_precision");
    assert!(changed > 1e-6, "the other camera file changed nothing: was it loaded?");
}

/// The heatmap sampling the bundle does not use (docs/BUNDLE.md, "Heatmap grid and sampling":
/// nearest cell or bilinear) serves what the trainer evaluates with it, and it is not the other.
#[test]
fn fusion_mode_with_the_other_sampling_serves_what_the_trainer_evaluates() {
    assert!(fusion_variant("fusion_other_sampling") > 1e-6, "the other sampling changed nothing: was it read?");
}

fn auto(name: &str, boundary_mode: &str) {
    let setup = setup_once();
    let c = compare(setup, name);
    assert!(c.persons >= MIN_PERSONS, "{name}: only {} persons compared", c.persons);
    for path in ["fusion", "camera", "lidar"] {
        assert!(c.by_mode.get(path).copied().unwrap_or(0) > 0, "{name}: no person took the {path} path: {c:?}");
    }
    let (file, id, count) = &setup.boundary;
    let served = setup.runs[name].serve["predictions"]
        .as_array()
        .and_then(|items| items.iter().zip(&setup.files).find(|(_, f)| *f == file))
        .map(|(item, _)| item["response"]["persons"].clone())
        .expect("boundary frame");
    let person = served.as_array().and_then(|ps| ps.iter().find(|p| p["id"] == id.as_str())).expect("boundary person");
    assert_eq!(person["num_points"].as_u64(), Some(*count), "{name}: boundary person's points");
    assert_eq!(person["mode"], boundary_mode, "{name}: person {id} of {file} with {count} points");
}

#[test]
fn auto_mode_with_a_person_exactly_at_min_points_serves_what_the_trainer_evaluates() {
    auto("auto_at_min_points", "fusion");
}

#[test]
fn auto_mode_with_a_person_one_below_min_points_serves_what_the_trainer_evaluates() {
    auto("auto_below_min_points", "camera");
}

/// The parity check can see the lifting temperature: with T = 1 instead of the bundle's, the
/// trainer's camera-mode keypoints move by more than the tolerance (so a server that ignored the
/// manifest's T would fail `camera_mode_serves_what_the_trainer_evaluates`).
#[test]
fn a_wrong_lift_temperature_moves_camera_keypoints_past_the_tolerance() {
    let setup = setup_once();
    let served = &setup.runs["camera"].serve["predictions"];
    let (mut moved, mut total) = (0, 0);
    for (file, item) in setup.files.iter().zip(served.as_array().expect("predictions")) {
        let Some(persons) = item["response"]["persons"].as_array() else { continue };
        for p in persons {
            let other = &setup.camera_t1[file.as_str()]["persons"][p["id"].as_str().expect("id")];
            let worst = xyz(p).iter().zip(xyz(other)).map(|(a, b)| distance(a, &b)).fold(0.0, f64::max);
            total += 1;
            moved += usize::from(worst > TOLERANCE_M);
        }
    }
    assert!(total >= MIN_PERSONS, "only {total} camera-mode persons");
    assert!(moved * 2 > total, "T = 1 moves only {moved} of {total} persons past {TOLERANCE_M} m");
}
