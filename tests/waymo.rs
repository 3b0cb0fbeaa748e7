//! The Waymo v2 layout end to end on simulated segments: the reader joins and casts both
//! physical-type variants, names what is missing, range images come back as the simulator's
//! points (with the TOP sweep's motion compensated), and `waymo convert` gives the prepared
//! samples the simulator makes directly from its own data.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use posefuse::pipeline::{PipelineConfig, PointFrame};
use posefuse::sample::Sample;
use posefuse::sim::street::Profile;
use posefuse::waymo::convert::{convert, frame_points, ConvertOptions};
use posefuse::waymo::range::{range_image_pixels, SweepPoses};
use posefuse::waymo::reader::Segment;
use posefuse::waymo::schema::{col, comp, LASER_TOP};
use posefuse::waymo::sim::{rig, segment_name, simulate, simulate_frame, WaymoSimOptions};

const FRAMES: usize = 3;

/// The segment of every test; the alternate-types one renders `posefuse waymo simulate`'s default
/// profile (street-hard), so that its effects are converted as well.
fn options(out: &Path, alt: bool) -> WaymoSimOptions {
    WaymoSimOptions {
        out: out.to_path_buf(),
        seed: 5,
        segments: 1,
        frames: FRAMES,
        top: [48, 1200],
        short: [24, 80],
        image_scale: 0.25,
        speed_mps: 15.0,
        keypoint_fraction: 1.0,
        alt_types: alt,
        profile: if alt { Profile::StreetHard } else { Profile::Clean },
        frames_per_row_group: 2,
        jobs: Some(2),
    }
}

struct Simulated {
    root: PathBuf,
    samples: Vec<Sample>,
}

fn simulated(alt: bool) -> &'static Simulated {
    static DECLARED: OnceLock<Simulated> = OnceLock::new();
    static ALTERNATE: OnceLock<Simulated> = OnceLock::new();
    let cell = if alt { &ALTERNATE } else { &DECLARED };
    cell.get_or_init(|| {
        let root = kept_dir();
        let samples = simulate(&options(&root, alt), true).unwrap().remove(0);
        Simulated { root, samples }
    })
}

/// A directory that outlives its test (shared datasets, conversions whose paths are returned): under
/// cargo's per-target scratch folder, so runs leave nothing behind in the system's temp folder.
fn kept_dir() -> PathBuf {
    tempfile::Builder::new().tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap().keep()
}

fn convert_to(root: &Path, image_size: u32) -> (PathBuf, posefuse::waymo::convert::ConvertSummary) {
    let out = kept_dir();
    let sum = convert(&ConvertOptions {
        dataset: root.to_path_buf(),
        out: out.clone(),
        segments: None,
        cameras: None,
        image_size,
        frame: PointFrame::BoxHeading,
        points_cap: 1024,
        requests: true,
        jobs: Some(2),
    })
    .unwrap();
    (out, sum)
}

/// Loads the converted shards back as (array name → flat f32 values) per sample.
fn shard_arrays(dir: &Path) -> std::collections::BTreeMap<String, ndarray::ArrayD<f32>> {
    use ndarray_npy::NpzReader;
    let mut npz = NpzReader::new(std::fs::File::open(dir.join("shards/shard-00000.npz")).unwrap()).unwrap();
    let mut out = std::collections::BTreeMap::new();
    for name in npz.names().unwrap() {
        let key = name.trim_end_matches(".npy").to_owned();
        if let Ok(a) = npz.by_name::<ndarray::OwnedRepr<f32>, ndarray::IxDyn>(&name) {
            out.insert(key, a);
        }
    }
    out
}

fn close(a: &[f32], b: &[f32], tol: f32, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tol, "{what}[{i}]: {x} vs {y}");
    }
}

fn round_trip(alt: bool) {
    let sim = simulated(alt);
    assert!(!sim.samples.is_empty(), "the simulated segment has labelled pedestrians");
    let cfg = PipelineConfig::default();
    let (out, sum) = convert_to(&sim.root, cfg.image_size);
    assert_eq!(sum.frames, FRAMES);
    assert_eq!(sum.samples, sim.samples.len(), "one sample per camera object with keypoints");
    let a = shard_arrays(&out);
    let p = a["points_xyz"].shape()[1];
    // persons with 3D labels; visible and occluded 3D and 2D keypoints over all samples
    let mut seen = (0, 0, 0, 0, 0);
    for (i, s) in sim.samples.iter().enumerate() {
        let pick = |name: &str| a[name].index_axis(ndarray::Axis(0), i).iter().copied().collect::<Vec<f32>>();
        close(&pick("box3d"), &s.box3d, 1e-5, "box3d");
        close(&pick("box2d"), &s.box2d, 1e-3, "box2d");
        close(&pick("kp2d"), &s.kp2d.concat(), 1e-3, "kp2d");
        close(&pick("kp3d_vehicle"), &s.kp3d_vehicle.concat(), 1e-5, "kp3d_vehicle");
        // Waymo's is_occluded comes through: the same visible and occluded keypoints, and every 3D
        // keypoint labelled, as the simulator labels them
        let flags = |name: &str| {
            let mut npz =
                ndarray_npy::NpzReader::new(std::fs::File::open(out.join("shards/shard-00000.npz")).unwrap()).unwrap();
            let arr: ndarray::ArrayD<u8> = npz.by_name(name).unwrap();
            arr.index_axis(ndarray::Axis(0), i).iter().copied().collect::<Vec<u8>>()
        };
        assert_eq!(flags("kp2d_visible"), s.kp2d_visible, "kp2d_visible of sample {i}");
        assert_eq!(flags("kp2d_occluded"), s.kp2d_occluded, "kp2d_occluded of sample {i}");
        assert_eq!(flags("kp3d_visible"), s.kp3d_visible, "kp3d_visible of sample {i}");
        assert_eq!(flags("kp3d_occluded"), s.kp3d_occluded, "kp3d_occluded of sample {i}");
        let labelled: Vec<u8> = s.kp3d_visible.iter().zip(&s.kp3d_occluded).map(|(v, o)| v + o).collect();
        assert!(labelled == [0; 13] || labelled == [1; 13], "all 13 or none: {labelled:?}");
        let count = |v: &[u8]| v.iter().map(|&x| x as usize).sum::<usize>();
        seen.0 += usize::from(labelled == [1; 13]);
        seen.1 += count(&s.kp3d_visible);
        seen.2 += count(&s.kp3d_occluded);
        seen.3 += count(&s.kp2d_visible);
        seen.4 += count(&s.kp2d_occluded);
        close(&pick("crop"), &s.crop, 1e-3, "crop");
        // Same crops: the same JPEG bytes went through the same crop.
        let img: Vec<u8> = {
            let mut npz =
                ndarray_npy::NpzReader::new(std::fs::File::open(out.join("shards/shard-00000.npz")).unwrap()).unwrap();
            let arr: ndarray::ArrayD<u8> = npz.by_name("image").unwrap();
            arr.index_axis(ndarray::Axis(0), i).iter().copied().collect()
        };
        assert_eq!(img, s.image, "crop pixels of sample {i}");
        // Points: the same set up to the range image's quantisation.
        let n = {
            let mut npz =
                ndarray_npy::NpzReader::new(std::fs::File::open(out.join("shards/shard-00000.npz")).unwrap()).unwrap();
            let arr: ndarray::ArrayD<i32> = npz.by_name("points_count").unwrap();
            arr[[i]] as usize
        };
        let got: Vec<[f32; 3]> = (0..n)
            .map(|j| {
                let v = &a["points_xyz"];
                [v[[i, j, 0]], v[[i, j, 1]], v[[i, j, 2]]]
            })
            .collect();
        assert!(n <= p);
        let want = &s.points_xyz;
        let diff = (got.len() as i64 - want.len() as i64).abs();
        assert!(
            diff <= 1 + want.len() as i64 / 100,
            "sample {i}: {} points vs the simulator's {}",
            got.len(),
            want.len()
        );
        for q in &got {
            let d = want
                .iter()
                .map(|w| ((q[0] - w[0]).powi(2) + (q[1] - w[1]).powi(2) + (q[2] - w[2]).powi(2)).sqrt())
                .fold(f32::INFINITY, f32::min);
            assert!(d < 0.005, "sample {i}: a converted point is {d} m from every simulated one");
        }
    }
    // the simulator's labels come through as labels: some persons labelled in 3D, with both
    // visible and occluded keypoints in 3D and in 2D
    assert!(seen.0 > 0 && seen.1 > 0 && seen.2 > 0 && seen.3 > 0 && seen.4 > 0, "{seen:?}");
    let fixtures = std::fs::read_dir(out.join("requests")).unwrap().count();
    assert_eq!(fixtures, sum.fixtures);
    assert!(fixtures >= FRAMES, "at least one fixture per frame");
}

#[test]
fn convert_gives_the_simulators_samples() {
    round_trip(false);
}

#[test]
fn convert_reads_the_alternate_physical_types() {
    round_trip(true);
}

#[test]
fn sparse_unordered_keypoints_as_real_labels() {
    let sim = simulated(false);
    let seg = Segment::open(&sim.root, &segment_name(5, 0), &None).unwrap();
    let mut with_extra = 0;
    let mut lengths = std::collections::BTreeSet::new();
    for ts in &seg.timestamps {
        for o in seg.labels(*ts).camera_objects {
            let k = o.keypoints.expect("keypoint_fraction 1: every camera object has keypoints");
            lengths.insert(k.len());
            with_extra += k.iter().filter(|k| k.kind == 19 || k.kind == 20).count();
            assert!(k.len() <= 15);
        }
    }
    assert!(with_extra > 0, "FOREHEAD / HEAD_CENTER are present");
    assert!(lengths.len() > 1, "keypoint lists vary in length: {lengths:?}");
    assert!(seg.has_lidar_hkp && seg.has_camera_hkp);
}

#[test]
fn missing_components_and_columns_are_named() {
    let sim = simulated(false);
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().to_path_buf();
    copy_dir(&sim.root, &root);
    let seg = segment_name(5, 0);
    // Optional components may go.
    std::fs::remove_dir_all(root.join(comp::LIDAR_HKP)).unwrap();
    let s = Segment::open(&root, &seg, &None).unwrap();
    assert!(!s.has_lidar_hkp);
    // Required ones may not.
    std::fs::remove_dir_all(root.join(comp::LIDAR_BOX)).unwrap();
    let err = Segment::open(&root, &seg, &None).err().unwrap().to_string();
    assert!(err.contains("lidar_box"), "{err}");
    copy_dir(&sim.root.join(comp::LIDAR_BOX), &root.join(comp::LIDAR_BOX));
    // A column that is not there.
    let mut c = posefuse::waymo::table::Columns::new(false);
    c.string(posefuse::waymo::schema::key::SEGMENT, std::slice::from_ref(&seg));
    c.int8(posefuse::waymo::schema::key::LASER, &[1]);
    let batch = c.finish().unwrap();
    std::fs::remove_file(root.join(comp::LIDAR_CALIBRATION).join(format!("{seg}.parquet"))).unwrap();
    let mut w = posefuse::waymo::table::ComponentWriter::new(&root, comp::LIDAR_CALIBRATION, &seg).unwrap();
    w.write(&batch).unwrap();
    w.finish().unwrap();
    let err = Segment::open(&root, &seg, &None).err().unwrap().to_string();
    assert!(err.contains("lidar_calibration") && err.contains(col::LASER_EXTRINSIC), "{err}");
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let t = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_dir(&p, &t);
        } else {
            std::fs::copy(&p, &t).unwrap();
        }
    }
}

#[test]
fn moving_sweep_is_compensated_with_pixel_poses() {
    // One frame at 15 m/s: the TOP laser's returns, converted with the per-pixel poses and the
    // frame's vehicle pose, land where the simulator's rays hit the static scene; without them
    // they are off by the distance driven between the column's time and the frame's.
    let dir = tempfile::tempdir().unwrap();
    let o = options(dir.path(), false);
    let rig = rig(&o).unwrap();
    let (f, _) = simulate_frame(&o, &rig, 0, 1, &PipelineConfig::default()).unwrap();
    let top = rig.lasers.iter().find(|l| l.name == LASER_TOP).unwrap();
    let cal = posefuse::waymo::range::LaserCalibration {
        name: LASER_TOP,
        extrinsic: std::array::from_fn(|i| top.extrinsic[i / 4][i % 4]),
        inclination_min: top.min,
        inclination_max: top.max,
        inclinations: top.stored.clone(),
    };
    let (_, ri, _, poses) = f.lasers.iter().find(|l| l.0 == LASER_TOP).unwrap();
    let poses = poses.as_ref().unwrap();
    let truth: std::collections::HashMap<(usize, usize), [f32; 3]> =
        f.top_truth.iter().map(|(r, c, p)| ((*r, *c), *p)).collect();
    let err = |pts: Vec<(usize, usize, [f32; 3])>| -> Vec<f32> {
        pts.iter()
            .map(|(r, c, p)| {
                let t = truth[&(*r, *c)];
                ((p[0] - t[0]).powi(2) + (p[1] - t[1]).powi(2) + (p[2] - t[2]).powi(2)).sqrt()
            })
            .collect()
    };
    let with = err(
        range_image_pixels(ri, &cal, Some(SweepPoses { pixel_poses: poses, frame_pose: &f.vehicle_pose })).unwrap()
    );
    let without = err(range_image_pixels(ri, &cal, None).unwrap());
    assert_eq!(with.len(), truth.len());
    let max_with = with.iter().copied().fold(0.0, f32::max);
    assert!(max_with < 0.02, "compensated points are within 2 cm (worst {max_with} m)");
    let max_without = without.iter().copied().fold(0.0, f32::max);
    let mean_without = without.iter().sum::<f32>() / without.len() as f32;
    // 15 m/s over half a 0.1 s sweep: up to 0.75 m.
    assert!(max_without > 0.6 && mean_without > 0.2, "uncompensated: worst {max_without} m, mean {mean_without} m");
}

#[test]
fn frame_points_cover_all_lasers_and_both_returns() {
    let sim = simulated(false);
    let mut seg = Segment::open(&sim.root, &segment_name(5, 0), &None).unwrap();
    let ts = seg.timestamps[0];
    let f = seg.frame(ts, &[]).unwrap();
    assert_eq!(f.lasers.iter().map(|l| l.name).collect::<Vec<_>>(), vec![1, 2, 3, 4, 5]);
    let second: usize =
        f.lasers.iter().map(|l| l.returns[1].values.iter().step_by(4).filter(|&&r| r > 0.0).count()).sum();
    assert!(second > 0, "second returns are read");
    let pts = frame_points(&seg.lasers, &f, true).unwrap();
    let first: usize =
        f.lasers.iter().map(|l| l.returns[0].values.iter().step_by(4).filter(|&&r| r > 0.0).count()).sum();
    assert_eq!(pts.len(), first + second);
    assert!(f.images.is_empty(), "no camera asked for, none kept");
}

fn posefuse(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(args)
        .env("ORT_DYLIB_PATH", std::env::var("ORT_DYLIB_PATH").unwrap_or_else(|_| ".ort/lib/libonnxruntime.so".into()))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap()
}

#[test]
fn eval_score_and_waymo_metrics_run_on_simulated_segments() {
    let sim = simulated(false);
    let (out, sum) = convert_to(&sim.root, 64);
    // `posefuse eval` scores the converted fixtures like the simulator's.
    let o = posefuse(&["eval", "--data", out.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["frames"], sum.fixtures);
    assert_eq!(r["failed_frames"], 0);
    assert!(r["metrics"]["all"]["count_3d"].as_u64().unwrap() > 0, "{r}");
    // occluded 3D keypoints are labelled, so they count: the headline pools visible and occluded
    let (all, vis, occ) = (&r["metrics"]["all"], &r["breakdown"]["visible"], &r["breakdown"]["occluded"]);
    assert!(occ["count_3d"].as_u64().unwrap() > 0, "{r}");
    let mpjpe = |m: &serde_json::Value| m["mpjpe_3d_m"].as_f64().unwrap();
    let (lo, hi) = (mpjpe(vis).min(mpjpe(occ)), mpjpe(vis).max(mpjpe(occ)));
    assert!(lo < mpjpe(all) && mpjpe(all) < hi, "the headline lies between its breakdowns: {r}");
    // Batch scoring writes lidar_hkp-shaped predictions that `waymo eval` scores.
    let pred = tempfile::tempdir().unwrap();
    let (root, pred_dir) = (sim.root.to_str().unwrap(), pred.path().to_str().unwrap());
    let o = posefuse(&["waymo", "score", "--dataset", root, "--out", pred_dir, "--shard", "0/1"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let file = pred.path().join(format!("{}.parquet", segment_name(5, 0)));
    assert!(file.is_file());
    let t = posefuse::waymo::table::read_columns(&file, "predictions", &[col::LHKP_TYPE, col::LHKP_X], None).unwrap();
    assert!(t.rows() > 0 && t.i64_lists(col::LHKP_TYPE).unwrap().iter().all(|k| k.len() == 13));
    let o = posefuse(&["waymo", "eval", "--dataset", root, "--predictions", pred_dir, "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["missing"], 0);
    assert_eq!(r["metrics"]["count_3d"].as_u64().unwrap() as usize, t.rows(), "{r}");
    assert!(r["metrics"]["pem_3d_m"].as_f64().unwrap() < 0.25);
    // A rerun resumes: the finished segment is skipped; another shard has nothing of it.
    let o = posefuse(&["waymo", "score", "--dataset", root, "--out", pred_dir]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("(1 already done)"), "{}", String::from_utf8_lossy(&o.stderr));
    let other = tempfile::tempdir().unwrap();
    let o = posefuse(&["waymo", "score", "--dataset", root, "--out", other.path().to_str().unwrap(), "--shard", "1/2"]);
    assert!(o.status.success());
    assert_eq!(std::fs::read_dir(other.path()).unwrap().count(), 0);
}

#[test]
fn score_through_a_server_gives_the_in_process_predictions() {
    let sim = simulated(false);
    let root = sim.root.to_str().unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let mut server = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(["serve", "--addr", &addr])
        .env("ORT_DYLIB_PATH", std::env::var("ORT_DYLIB_PATH").unwrap_or_else(|_| ".ort/lib/libonnxruntime.so".into()))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let ready = (0..240).any(|_| {
        std::thread::sleep(std::time::Duration::from_millis(500));
        posefuse(&["health", "--addr", &addr]).status.success()
    });
    let (remote, local) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let o = ready.then(|| {
        posefuse(&[
            "waymo",
            "score",
            "--dataset",
            root,
            "--out",
            remote.path().to_str().unwrap(),
            "--server",
            &format!("http://{addr}"),
        ])
    });
    let _ = server.kill();
    let _ = server.wait();
    assert!(ready, "the server did not become ready");
    let o = o.unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = posefuse(&["waymo", "score", "--dataset", root, "--out", local.path().to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let name = format!("{}.parquet", segment_name(5, 0));
    let read = |d: &Path| {
        let t = posefuse::waymo::table::read_columns(
            &d.join(&name),
            "predictions",
            &[posefuse::waymo::schema::key::TIMESTAMP, posefuse::waymo::schema::key::LASER_OBJECT, col::LHKP_X],
            None,
        )
        .unwrap();
        let mut rows: Vec<(i64, String, Vec<f64>)> = t
            .i64s(posefuse::waymo::schema::key::TIMESTAMP)
            .unwrap()
            .into_iter()
            .zip(t.strings(posefuse::waymo::schema::key::LASER_OBJECT).unwrap())
            .zip(t.f64_lists(col::LHKP_X).unwrap())
            .map(|((a, b), c)| (a, b, c))
            .collect();
        rows.sort_by(|a, b| (a.0, &a.1).cmp(&(b.0, &b.1)));
        rows
    };
    let (r, l) = (read(remote.path()), read(local.path()));
    assert!(!r.is_empty());
    assert_eq!(r.len(), l.len());
    for (a, b) in r.iter().zip(&l) {
        assert_eq!((a.0, &a.1), (b.0, &b.1));
        close(
            &a.2.iter().map(|&x| x as f32).collect::<Vec<_>>(),
            &b.2.iter().map(|&x| x as f32).collect::<Vec<_>>(),
            1e-4,
            "x",
        );
    }
}

#[test]
fn without_camera_keypoints_only_requests() {
    let sim = simulated(false);
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().to_path_buf();
    copy_dir(&sim.root, &root);
    std::fs::remove_dir_all(root.join(comp::CAMERA_HKP)).unwrap();
    std::fs::remove_dir_all(root.join(comp::LIDAR_POSE)).unwrap();
    let (out, sum) = convert_to(&root, 64);
    assert_eq!(sum.samples, 0, "no 2D labels, no training samples");
    assert!(sum.fixtures >= FRAMES);
    let f: posefuse::frame::Frame = serde_json::from_slice(
        &std::fs::read(std::fs::read_dir(out.join("requests")).unwrap().next().unwrap().unwrap().path()).unwrap(),
    )
    .unwrap();
    let gt = f.persons[0].ground_truth.as_ref().unwrap();
    assert!(gt.keypoints_3d.is_some() && gt.keypoints_2d.is_none());
}
