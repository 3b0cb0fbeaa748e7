//! `posefuse simulate` output: byte-identical reruns, shard keys and shapes as docs/DATA.md
//! documents them, shard crops and point inputs identical to what the pipeline makes from the
//! request fixtures, and 2D labels that are projections of the 3D keypoints up to the label noise.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ndarray::ArrayD;
use ndarray_npy::NpzReader;
use posefuse::frame::{Box3d, CameraCalibration, Frame};
use posefuse::geometry::{BoxFrame, Camera};
use posefuse::pipeline::PointFrame;
use posefuse::pipeline::{from_local, prepare_person, CropTransform, PipelineConfig};
use posefuse::sim::realism::Effect;
use posefuse::sim::street::Profile;
use posefuse::sim::{simulate, SimulateOptions};

const S: u32 = 64;
const COUNT: usize = 7;

fn args(out: &Path) -> SimulateOptions {
    SimulateOptions {
        count: COUNT,
        seed: 11,
        out: out.to_path_buf(),
        image_size: S,
        frame: PointFrame::BoxHeading,
        preview: true,
        requests: Some(1),
        points_cap: 300,
        profile: Profile::Clean,
        effects: Vec::new(),
        jobs: Some(2),
    }
}

fn run_once() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        // Under cargo's per-target scratch folder: shared by the tests, so it is kept.
        let dir = tempfile::Builder::new().tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap().keep();
        simulate(args(&dir)).unwrap();
        dir
    })
}

fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(p.strip_prefix(dir).unwrap().display().to_string(), std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

#[test]
fn two_runs_are_byte_identical() {
    let a = run_once();
    let b = tempfile::tempdir().unwrap();
    simulate(args(b.path())).unwrap();
    let (fa, fb) = (files(a), files(b.path()));
    assert!(fa.contains_key("dataset.json") && fa.contains_key("shards/shard-00000.npz"));
    assert!(fa.contains_key("requests/frame-000000.json") && fa.contains_key("preview/sheet-000.png"));
    assert_eq!(fa.keys().collect::<Vec<_>>(), fb.keys().collect::<Vec<_>>());
    for (name, bytes) in &fa {
        assert!(bytes == &fb[name], "{name} differs between runs");
    }
}

/// The keys of the shard table in docs/DATA.md with their dtypes and shapes.
#[test]
fn the_street_profile_is_recorded_reproducible_and_different() {
    let street = |dir: &Path| SimulateOptions { profile: Profile::Street, ..args(dir) };
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    simulate(street(a.path())).unwrap();
    simulate(street(b.path())).unwrap();
    let (fa, fb) = (files(a.path()), files(b.path()));
    assert_eq!(fa, fb, "street runs differ");
    let doc: serde_json::Value = serde_json::from_slice(&fa["dataset.json"]).unwrap();
    assert_eq!(doc["profile"], "street");
    let clean = files(run_once());
    let clean_doc: serde_json::Value = serde_json::from_slice(&clean["dataset.json"]).unwrap();
    assert_eq!(clean_doc["profile"], "clean");
    assert_ne!(fa["shards/shard-00000.npz"], clean["shards/shard-00000.npz"]);
}

/// `street` of one seed without and with `effect`; the second set records it as `name`.
fn street_without_and_with(count: usize, effect: Effect, name: &str) -> (tempfile::TempDir, tempfile::TempDir) {
    let with = |dir: &Path, effects: Vec<Effect>| SimulateOptions {
        profile: Profile::Street,
        count,
        preview: false,
        effects,
        ..args(dir)
    };
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    simulate(with(a.path(), vec![])).unwrap();
    simulate(with(b.path(), vec![effect])).unwrap();
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(b.path().join("dataset.json")).unwrap()).unwrap();
    assert_eq!(doc["effects"], serde_json::json!(["dress", "mixed-pixels", name]));
    (a, b)
}

#[test]
fn label_noise_moves_the_3d_labels_and_nothing_else() {
    let (a, b) = street_without_and_with(60, Effect::LabelNoise, "label-noise");
    let (mut sa, mut sb) = (open_shard(a.path()), open_shard(b.path()));
    for k in ["image", "kp3d_visible", "kp3d_occluded", "kp2d_visible"] {
        assert_eq!(sa.u8(k), sb.u8(k), "{k}");
    }
    for k in ["points_xyz", "kp2d", "kp2d_image_true"] {
        assert_eq!(sa.f32(k), sb.f32(k), "{k}");
    }
    let (ta, tb) = (sa.f32("kp3d_vehicle"), sb.f32("kp3d_vehicle"));
    let d: Vec<f64> = ta.iter().zip(tb.iter()).map(|(x, y)| (y - x) as f64).collect();
    let rms = (d.iter().map(|e| e * e).sum::<f64>() / d.len() as f64).sqrt();
    // σ = 1.5 % of heights between 1.0 and 2.0 m: 1.5 to 3 cm per axis.
    assert!(rms > 0.015 && rms < 0.032, "label error RMS {rms} m");
    assert!(d.iter().all(|e| e.abs() < 0.15), "no label moves more than five σ");
}

/// Points of each person within `r` of its keypoints `ks` (model-input coordinates).
fn points_near(sh: &mut Shard, ks: &[usize], r: f32) -> usize {
    let (pts, kp, count) = (sh.f32("points_xyz"), sh.f32("kp3d"), sh.i32("points_count"));
    let mut n = 0;
    for (m, &c) in count.iter().enumerate() {
        for p in 0..c as usize {
            let near =
                ks.iter().any(|&k| (0..3).map(|a| (pts[[m, p, a]] - kp[[m, k, a]]).powi(2)).sum::<f32>() < r * r);
            n += usize::from(near);
        }
    }
    n
}

#[test]
fn slim_hands_thins_the_wrists_and_keeps_the_persons() {
    let (a, b) = street_without_and_with(120, Effect::SlimHands, "slim-hands");
    let (mut sa, mut sb) = (open_shard(a.path()), open_shard(b.path()));
    // The boxes are fitted to the body's shapes, so only the keypoints stay to the bit.
    assert_eq!(sa.f32("kp3d_vehicle"), sb.f32("kp3d_vehicle"), "the same persons in the same poses");
    assert_ne!(sa.u8("image"), sb.u8("image"));
    let (wa, wb) = (points_near(&mut sa, &[5, 6], 0.05), points_near(&mut sb, &[5, 6], 0.05));
    let (ha, hb) = (points_near(&mut sa, &[7, 8], 0.1), points_near(&mut sb, &[7, 8], 0.1));
    // The hands are about as large as before, only flatter, and the wrists thinner: a few per cent
    // fewer returns near the wrists (docs/DATA.md), none fewer near the hips.
    assert!(wa > 100, "enough wrist points to compare: {wa}");
    assert!(wb < wa, "points within 5 cm of the wrists {wa} -> {wb}");
    assert!((hb as f64 - ha as f64).abs() < 0.03 * ha as f64, "points within 10 cm of the hips {ha} -> {hb}");
}

fn documented_keys() -> Vec<(String, String, String)> {
    let doc = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/DATA.md")).unwrap();
    let table = doc.split("## Shard keys").nth(1).unwrap();
    table
        .lines()
        .filter(|l| l.starts_with("| `"))
        .map(|l| {
            let cols: Vec<&str> = l.split('|').map(str::trim).collect();
            (cols[1].trim_matches('`').to_string(), cols[2].to_string(), cols[3].to_string())
        })
        .collect()
}

struct Shard {
    npz: NpzReader<std::fs::File>,
}

impl Shard {
    fn f32(&mut self, k: &str) -> ArrayD<f32> {
        self.npz.by_name(&format!("{k}.npy")).unwrap()
    }
    fn u8(&mut self, k: &str) -> ArrayD<u8> {
        self.npz.by_name(&format!("{k}.npy")).unwrap()
    }
    fn i32(&mut self, k: &str) -> ArrayD<i32> {
        self.npz.by_name(&format!("{k}.npy")).unwrap()
    }
}

fn open_shard(dir: &Path) -> Shard {
    Shard { npz: NpzReader::new(std::fs::File::open(dir.join("shards/shard-00000.npz")).unwrap()).unwrap() }
}

#[test]
fn shards_have_the_documented_keys_dtypes_and_shapes() {
    let dir = run_once();
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("dataset.json")).unwrap()).unwrap();
    let cfg: PipelineConfig = serde_json::from_value(meta["preprocessing"].clone()).unwrap();
    assert_eq!(cfg, PipelineConfig::with_image_size(S));
    assert_eq!(meta["count"], COUNT);
    assert_eq!(meta["seed"], 11);
    let cap = meta["points_cap"].as_u64().unwrap() as usize;
    assert_eq!(cap, 300);
    let mut sh = open_shard(dir);
    let mut names = sh.npz.names().unwrap();
    names.sort();
    let docs = documented_keys();
    let mut want: Vec<String> = docs.iter().map(|d| d.0.clone()).collect();
    want.sort();
    assert_eq!(names, want);
    let (m, s, n, k) = (COUNT, S as usize, cfg.num_points as usize, 13usize);
    for (key, dtype, shape) in &docs {
        let dims: Vec<usize> = shape
            .trim_matches(|c| c == '[' || c == ']')
            .split(',')
            .map(|d| match d.trim() {
                "M" => m,
                "S" => s,
                "P" => cap,
                "N" => n,
                "K" => k,
                other => other.parse().unwrap(),
            })
            .collect();
        let got = match dtype.as_str() {
            "uint8" => sh.u8(key).shape().to_vec(),
            "int32" => sh.i32(key).shape().to_vec(),
            "float32" => sh.f32(key).shape().to_vec(),
            other => panic!("undocumented dtype {other}"),
        };
        assert_eq!(got, dims, "{key}");
    }
    // Rows past points_count are zero; counts respect the cap.
    let count = sh.i32("points_count");
    let xyz = sh.f32("points_xyz");
    for i in 0..m {
        let c = count[[i]] as usize;
        assert!(c <= cap);
        assert!((c..cap).all(|r| (0..3).all(|a| xyz[[i, r, a]] == 0.0)));
    }
    assert!(count.iter().any(|&c| c > 0));
}

fn camera_of(sh: &mut Shard, i: usize) -> Camera {
    let (intr, extr, wh) = (sh.f32("intrinsic"), sh.f32("extrinsic"), sh.i32("image_size_wh"));
    Camera::from_calibration(&CameraCalibration {
        intrinsic: (0..9).map(|j| intr[[i, j]] as f64).collect(),
        extrinsic: (0..16).map(|j| extr[[i, j]] as f64).collect(),
        width: wh[[i, 0]] as u32,
        height: wh[[i, 1]] as u32,
    })
    .unwrap()
}

#[test]
fn labels_are_projections_of_the_3d_keypoints_up_to_the_label_noise() {
    let dir = run_once();
    let cfg = PipelineConfig::with_image_size(S);
    let mut sh = open_shard(dir);
    let (kp2d, true2d, kp3d, kpv, box2d, box3d, crop) = (
        sh.f32("kp2d"),
        sh.f32("kp2d_image_true"),
        sh.f32("kp3d"),
        sh.f32("kp3d_vehicle"),
        sh.f32("box2d"),
        sh.f32("box3d"),
        sh.f32("crop"),
    );
    let mut max_noise: f64 = 0.0;
    for i in 0..COUNT {
        let cam = camera_of(&mut sh, i);
        let t = CropTransform { x0: crop[[i, 0]] as f64, y0: crop[[i, 1]] as f64, scale: crop[[i, 2]] as f64, size: S };
        let sigma = (0.015 * box2d[[i, 3]] as f64).min(4.0);
        let b = BoxFrame::new(&Box3d {
            center_x: box3d[[i, 0]] as f64,
            center_y: box3d[[i, 1]] as f64,
            center_z: box3d[[i, 2]] as f64,
            length: box3d[[i, 3]] as f64,
            width: box3d[[i, 4]] as f64,
            height: box3d[[i, 5]] as f64,
            heading: box3d[[i, 6]] as f64,
        });
        for k in 0..13 {
            let v = [kpv[[i, k, 0]] as f64, kpv[[i, k, 1]] as f64, kpv[[i, k, 2]] as f64];
            let back = from_local(&b, [kp3d[[i, k, 0]] as f64, kp3d[[i, k, 1]] as f64, kp3d[[i, k, 2]] as f64], &cfg);
            assert!((0..3).all(|a| (back[a] - v[a]).abs() < 1e-3), "kp3d is not kp3d_vehicle in the box frame");
            // The keypoint is inside the 3D box.
            assert!(b.contains(v, 1e-3), "sample {i} keypoint {k} outside its 3D box");
            let pr = cam.project(v);
            assert!(pr.in_front);
            let tr = [true2d[[i, k, 0]] as f64, true2d[[i, k, 1]] as f64];
            assert!((pr.uv[0] - tr[0]).abs() < 0.05 && (pr.uv[1] - tr[1]).abs() < 0.05, "{:?} vs {tr:?}", pr.uv);
            let lab = t.to_image([kp2d[[i, k, 0]] as f64, kp2d[[i, k, 1]] as f64]);
            let d = ((lab[0] - tr[0]).powi(2) + (lab[1] - tr[1]).powi(2)).sqrt();
            assert!(d <= 5.0 * sigma + 0.01, "sample {i} kp {k}: label {d:.2} px off with sigma {sigma:.2}");
            max_noise = max_noise.max(d);
        }
    }
    assert!(max_noise > 0.1, "labels carry no annotation noise");
}

#[test]
fn fixture_frames_give_the_server_the_same_crops_and_points_as_the_shards() {
    let dir = run_once();
    let cfg = PipelineConfig::with_image_size(S);
    let frame: Frame = serde_json::from_slice(&std::fs::read(dir.join("requests/frame-000000.json")).unwrap()).unwrap();
    frame.validate().unwrap();
    use base64::Engine;
    let jpeg = base64::engine::general_purpose::STANDARD.decode(frame.image.as_ref().unwrap()).unwrap();
    let image = image::load_from_memory(&jpeg).unwrap().to_rgb8();
    assert_eq!((image.width(), image.height()), (1920, 1280));
    let cam = Camera::from_calibration(frame.calibration.as_ref().unwrap()).unwrap();
    let points = frame.points.decode().unwrap();
    let mut sh = open_shard(dir);
    let (img, fidx, serve_xyz, serve_uv) =
        (sh.u8("image"), sh.i32("frame_index"), sh.f32("serve_xyz"), sh.f32("serve_uv"));
    let rows: Vec<usize> = (0..COUNT).filter(|&i| fidx[[i]] == 0).collect();
    let mut with_points = 0;
    assert_eq!(rows.len(), frame.persons.len());
    // the server's decode: header, then each crop at its own window's DCT scale
    let windows: Vec<CropTransform> =
        frame.persons.iter().map(|p| CropTransform::for_box(&p.box_2d.unwrap(), &cfg)).collect();
    let opened = posefuse::image_decode::open(&frame, None, None).unwrap();
    let crops = posefuse::image_decode::decode_crops(&opened, &windows, 1920, 1280, || Ok(())).unwrap().unwrap();
    for ((row, person), crop) in rows.into_iter().zip(&frame.persons).zip(&crops) {
        let b2 = person.box_2d.unwrap();
        let shard_crop: Vec<u8> = img.slice(ndarray::s![row, .., .., ..]).iter().copied().collect();
        assert!(crop.as_raw() == &shard_crop, "shard crop of person {} differs from the server's", person.id);
        let prep = prepare_person(Some(&image), Some(&cam), &points, &person.box_3d, Some(&b2), &cfg);
        let count = sh.i32("points_count")[[row]] as usize;
        assert_eq!(count, prep.points.len().min(300));
        let Some(input) = prep.input else {
            assert!(serve_xyz.slice(ndarray::s![row, .., ..]).iter().all(|v| *v == 0.0));
            continue;
        };
        with_points += 1;
        for (r, (x, u)) in input.xyz.iter().zip(&input.uv).enumerate() {
            for a in 0..3 {
                assert_eq!(serve_xyz[[row, r, a]].to_bits(), x[a].to_bits());
            }
            for a in 0..2 {
                assert_eq!(serve_uv[[row, r, a]].to_bits(), u[a].to_bits());
            }
        }
        let gt = person.ground_truth.as_ref().unwrap();
        assert_eq!(gt.keypoints_3d.as_ref().unwrap().xyz.len(), 13);
    }
    assert!(with_points > 0, "no fixture person with points to compare");
}

#[test]
fn unusable_arguments_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut a = args(dir.path());
    a.image_size = 30;
    assert!(simulate(a).unwrap_err().to_string().contains("--image-size"));
    let mut a = args(dir.path());
    a.count = 0;
    assert!(simulate(a).is_err());
}

#[test]
fn a_seen_person_has_every_3d_keypoint_and_every_2d_keypoint_in_the_image_labelled() {
    let dir = run_once();
    let mut sh = open_shard(dir);
    let (v2, o2, v3, o3, true2d, wh) = (
        sh.u8("kp2d_visible"),
        sh.u8("kp2d_occluded"),
        sh.u8("kp3d_visible"),
        sh.u8("kp3d_occluded"),
        sh.f32("kp2d_image_true"),
        sh.i32("image_size_wh"),
    );
    let (mut occluded_3d, mut occluded_2d) = (0, 0);
    for i in 0..COUNT {
        let seen_3d = (0..13).any(|k| v3[[i, k]] == 1);
        let seen_2d = (0..13).any(|k| v2[[i, k]] == 1);
        for k in 0..13 {
            // labelled once (visible or occluded) when anything of the person is seen, else not at all
            assert_eq!(v3[[i, k]] + o3[[i, k]], u8::from(seen_3d), "sample {i} kp {k}: 3D labels");
            let (u, v) = (true2d[[i, k, 0]], true2d[[i, k, 1]]);
            let inside = u >= 0.0 && v >= 0.0 && u < wh[[i, 0]] as f32 && v < wh[[i, 1]] as f32;
            assert_eq!(v2[[i, k]] + o2[[i, k]], u8::from(inside && seen_2d), "sample {i} kp {k}: 2D labels");
            // the camera's visibility implies the 3D one
            assert!(v2[[i, k]] <= v3[[i, k]]);
            occluded_3d += o3[[i, k]] as usize;
            occluded_2d += o2[[i, k]] as usize;
        }
    }
    assert!(occluded_3d > 0 && occluded_2d > occluded_3d, "{occluded_3d} occluded in 3D, {occluded_2d} in 2D");
    // request fixtures carry the same flags
    let frame: Frame = serde_json::from_slice(&std::fs::read(dir.join("requests/frame-000000.json")).unwrap()).unwrap();
    for p in &frame.persons {
        let gt = p.ground_truth.as_ref().unwrap();
        let k3 = gt.keypoints_3d.as_ref().unwrap();
        let labelled = k3.visibility().iter().filter(|v| v.labelled()).count();
        assert!(labelled == 0 || labelled == 13, "{}: all 3D keypoints labelled or none", p.id);
        assert_eq!(k3.occluded.len(), 13);
        assert_eq!(gt.keypoints_2d.as_ref().unwrap().occluded.len(), 13);
    }
}

#[test]
fn street_hard_is_street_with_its_three_effects() {
    let run = |dir: &Path, profile: Profile, effects: Vec<Effect>| {
        simulate(SimulateOptions { profile, count: 40, preview: false, effects, ..args(dir) }).unwrap();
        files(dir)
    };
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let hard = run(a.path(), Profile::StreetHard, vec![]);
    let composed = run(b.path(), Profile::Street, vec![Effect::LabelNoise, Effect::ArmsIn, Effect::Reflectivity]);
    let doc: serde_json::Value = serde_json::from_slice(&hard["dataset.json"]).unwrap();
    assert_eq!(doc["profile"], "street-hard");
    assert_eq!(doc["effects"], serde_json::json!(["dress", "mixed-pixels", "reflectivity", "arms-in", "label-noise"]));
    assert_eq!(hard["shards/shard-00000.npz"], composed["shards/shard-00000.npz"]);
}
