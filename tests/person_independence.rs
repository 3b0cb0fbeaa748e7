//! A person's answer is a function of its own data: the same keypoints alone, among 1 to 9
//! persons, with one camera or two, and under the planned or the full decode (docs/ARCHITECTURE.md,
//! "A person's answer is its own"). The frames are 1920×1280 JPEGs with persons from 2.6 to 40 m,
//! so their crops need different DCT scales.

mod server_support;

use std::time::Duration;

use base64::Engine;
use image::{Rgb, RgbImage};
use posefuse::frame::{Box2d, CameraCalibration, Frame, FrameCamera, Person, Points, RequestedMode};
use posefuse::geometry::{projected_box, Camera};
use posefuse::pipeline::{window_denominator, CropTransform};
use posefuse::runtime::{Runtime, RuntimeConfig};
use posefuse::service::api::{PersonPose, PoseResponse};
use posefuse::service::Predictor;
use server_support::{model_dir, person_box, points_in};

/// A Waymo-size front camera 1.5 m up, looking along +x, with mild distortion.
fn front() -> CameraCalibration {
    #[rustfmt::skip]
    let extrinsic = vec![
        1.0, 0.0, 0.0, 0.0,
        0.0, 1.0, 0.0, 0.0,
        0.0, 0.0, 1.0, 1.5,
        0.0, 0.0, 0.0, 1.0,
    ];
    CameraCalibration {
        intrinsic: vec![2050.0, 2050.0, 960.0, 640.0, 0.05, -0.005, 0.0, 0.0, 0.0],
        extrinsic,
        width: 1920,
        height: 1280,
    }
}

/// The same camera turned to look left (+y): it sees none of the persons.
fn left() -> CameraCalibration {
    #[rustfmt::skip]
    let extrinsic = vec![
        0.0, -1.0, 0.0, 0.0,
        1.0, 0.0, 0.0, 0.0,
        0.0, 0.0, 1.0, 1.5,
        0.0, 0.0, 0.0, 1.0,
    ];
    CameraCalibration { extrinsic, ..front() }
}

/// Nine pedestrians from 2.6 to 40 m, spread across the view (the nearest needs the 1/8 DCT scale
/// at 128 px crops).
fn boxes() -> Vec<posefuse::frame::Box3d> {
    [
        (5.5, 0.8),
        (9.0, -2.0),
        (14.0, 3.5),
        (20.0, -4.0),
        (27.0, 1.0),
        (33.0, -7.0),
        (38.0, 6.0),
        (7.0, 2.6),
        (2.6, -0.3),
    ]
    .iter()
    .map(|&(x, y)| person_box(x, y))
    .collect()
}

/// A textured street with a figure drawn in each projected box, as a JPEG (base64).
fn image_b64(calibration: &CameraCalibration, boxes: &[Box2d]) -> String {
    let mut img = RgbImage::from_fn(1920, 1280, |x, y| {
        let v = 100 + ((x / 7 + y / 5) % 23) as u8 + if y > 700 { 30 } else { 0 };
        Rgb([v, v + 4, v + 9])
    });
    for b in boxes {
        let (x0, y0) = (b.center_x - b.width / 2.0, b.center_y - b.height / 2.0);
        let mut fill = |fx0: f64, fy0: f64, fx1: f64, fy1: f64, c: [u8; 3]| {
            for y in (y0 + fy0 * b.height) as i64..(y0 + fy1 * b.height) as i64 {
                for x in (x0 + fx0 * b.width) as i64..(x0 + fx1 * b.width) as i64 {
                    if x >= 0 && y >= 0 && (x as u32) < calibration.width && (y as u32) < calibration.height {
                        img.put_pixel(x as u32, y as u32, Rgb(c));
                    }
                }
            }
        };
        fill(0.4, 0.0, 0.6, 0.15, [220, 180, 150]);
        fill(0.25, 0.15, 0.75, 0.55, [200, 40, 40]);
        fill(0.3, 0.55, 0.48, 1.0, [30, 30, 120]);
        fill(0.52, 0.55, 0.7, 1.0, [30, 30, 120]);
    }
    let jpeg = posefuse::sample::encode_jpeg(&img).unwrap();
    base64::engine::general_purpose::STANDARD.encode(jpeg)
}

fn person(i: usize, b: posefuse::frame::Box3d) -> Person {
    Person { id: format!("p{i}"), camera: None, box_2d: None, box_3d: b, ground_truth: None }
}

/// The frame with the persons `which` (indices into [`boxes`]), the whole street's image and
/// every person's points; with `two_cameras` as `cameras` [front, left].
fn frame(which: &[usize], two_cameras: bool) -> Frame {
    let all = boxes();
    let cam = Camera::from_calibration(&front()).unwrap();
    let drawn: Vec<Box2d> = all.iter().filter_map(|b| projected_box(&cam, b)).collect();
    let image = image_b64(&front(), &drawn);
    let points: Vec<[f32; 3]> = all.iter().flat_map(|b| points_in(b, 300)).collect();
    let persons = which.iter().map(|&i| person(i, all[i])).collect();
    let mut f = Frame {
        frame_id: None,
        image: Some(image.clone()),
        image_rgb: None,
        calibration: Some(front()),
        cameras: Vec::new(),
        points: Points::encode(&points),
        persons,
        mode: RequestedMode::Auto,
    };
    if two_cameras {
        let grey = image_b64(&left(), &[]);
        f.image = None;
        f.calibration = None;
        f.cameras = vec![
            FrameCamera { name: "front".into(), image: Some(image), image_rgb: None, calibration: front() },
            FrameCamera { name: "left".into(), image: Some(grey), image_rgb: None, calibration: left() },
        ];
    }
    f
}

/// Largest 3D (m) and 2D (px) distance between two answers for the same person.
fn difference(a: &PersonPose, b: &PersonPose) -> (f64, f64) {
    let (mut d3, mut d2) = (0.0f64, 0.0f64);
    for (p, q) in a.keypoints.iter().zip(&b.keypoints) {
        let d = (0..3).map(|k| (p.xyz[k] - q.xyz[k]).powi(2)).sum::<f64>().sqrt();
        d3 = d3.max(d);
        if let (Some(u), Some(v)) = (p.uv, q.uv) {
            d2 = d2.max(((u[0] - v[0]).powi(2) + (u[1] - v[1]).powi(2)).sqrt());
        }
        assert_eq!(p.uv.is_some(), q.uv.is_some(), "{}: a keypoint projects in one answer only", a.id);
    }
    assert_eq!((a.mode, a.num_points), (b.mode, b.num_points), "{}", a.id);
    (d3, d2)
}

fn pose<'r>(r: &'r PoseResponse, id: &str) -> &'r PersonPose {
    r.persons.iter().find(|p| p.id == id).unwrap_or_else(|| panic!("{id} got no pose"))
}

async fn predictor() -> Predictor {
    let dir = model_dir();
    let runtime =
        tokio::task::spawn_blocking(move || Runtime::load(&dir, &RuntimeConfig::DEFAULT)).await.unwrap().unwrap();
    assert!(runtime.wait_ready(Duration::from_secs(120)));
    Predictor::new(runtime)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_persons_answer_does_not_depend_on_the_crowd_or_the_cameras() {
    // the persons' crops really need different DCT scales (else this would show nothing)
    let cam = Camera::from_calibration(&front()).unwrap();
    let cfg = posefuse::runtime::Bundle::load(&model_dir()).unwrap().config().clone();
    let scales: std::collections::BTreeSet<u32> = boxes()
        .iter()
        .map(|b| window_denominator(&CropTransform::for_box(&projected_box(&cam, b).unwrap(), &cfg)))
        .collect();
    assert!(scales.len() >= 3, "scales {scales:?} at crop size {}", cfg.image_size);

    let p = predictor().await;
    let t = Duration::from_secs(60);
    let mut alone = Vec::new();
    for i in 0..boxes().len() {
        let r = p.answer(frame(&[i], false), None, t).await.unwrap();
        assert_eq!(r.persons.len(), 1, "{i}: {:?}", r.skipped);
        alone.push(r.persons[0].clone());
    }
    assert!(alone.iter().all(|a| a.mode == posefuse::service::api::Mode::Fusion));
    let (mut worst3, mut worst2) = (0.0f64, 0.0f64);
    // 1 to 9 persons, in several orders, with one camera and with two
    let crowds: Vec<Vec<usize>> = vec![
        vec![0],
        vec![1, 0],
        vec![6, 2, 4],
        vec![3, 5, 7, 1],
        vec![0, 1, 2, 3, 4],
        vec![7, 6, 5, 4, 3, 2],
        vec![2, 4, 6, 0, 1, 3, 5],
        vec![8, 0, 7, 1, 6, 2, 5, 3],
        (0..boxes().len()).collect(),
        (0..boxes().len()).rev().collect(),
    ];
    for crowd in &crowds {
        for two in [false, true] {
            let r = p.answer(frame(crowd, two), None, t).await.unwrap();
            for &i in crowd {
                let got = pose(&r, &format!("p{i}"));
                assert_eq!(got.camera.as_deref(), two.then_some("front"));
                let (d3, d2) = difference(got, &alone[i]);
                worst3 = worst3.max(d3);
                worst2 = worst2.max(d2);
            }
        }
    }
    println!("largest difference from the person alone: {:.6} mm, {:.6} px", worst3 * 1e3, worst2);
    assert!(worst3 <= 1e-3 && worst2 <= 1.0, "{worst3} m, {worst2} px");
}

/// `posefuse predict` on a frame, with `POSEFUSE_DECODE` set as given.
fn predict_process(frame: &Frame, decode: Option<&str>) -> PoseResponse {
    let (ok, stdout, stderr) = predict_outcome(frame, decode);
    assert!(ok, "{stderr}");
    serde_json::from_str(&stdout).unwrap()
}

#[test]
fn the_planned_and_the_full_decode_give_the_same_answers() {
    let mut f = frame(&(0..boxes().len()).collect::<Vec<_>>(), false);
    let planned = predict_process(&f, None);
    let full = predict_process(&f, Some("full"));
    f.mode = RequestedMode::Camera;
    let (planned_cam, full_cam) = (predict_process(&f, None), predict_process(&f, Some("full")));
    for (a, b) in [(&planned, &full), (&planned_cam, &full_cam)] {
        assert_eq!(a.persons.len(), boxes().len());
        for pa in &a.persons {
            let (d3, d2) = difference(pa, pose(b, &pa.id));
            assert!(d3 <= 1e-3 && d2 <= 1.0, "{}: {d3} m, {d2} px", pa.id);
        }
    }
}

/// `posefuse predict`'s exit status, standard output and error, with `POSEFUSE_DECODE` as given.
fn predict_outcome(frame: &Frame, decode: Option<&str>) -> (bool, String, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("frame.json");
    std::fs::write(&path, serde_json::to_vec(frame).unwrap()).unwrap();
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"));
    cmd.args(["predict", "--model-dir"]).arg(model_dir()).arg(&path);
    match decode {
        Some(v) => cmd.env("POSEFUSE_DECODE", v),
        None => cmd.env_remove("POSEFUSE_DECODE"),
    };
    let out = cmd.output().unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (out.status.success(), text(&out.stdout), text(&out.stderr))
}

#[test]
fn a_cut_short_or_padded_jpeg_is_refused_in_both_decode_modes() {
    let f = frame(&[0, 1], false);
    let jpeg = base64::engine::general_purpose::STANDARD.decode(f.image.as_ref().unwrap()).unwrap();
    for bad in [jpeg[..jpeg.len() / 2].to_vec(), [&jpeg[..], b"trailing bytes"].concat()] {
        let mut g = f.clone();
        g.image = Some(base64::engine::general_purpose::STANDARD.encode(&bad));
        g.mode = RequestedMode::Fusion;
        for decode in [None, Some("full")] {
            let (ok, _, err) = predict_outcome(&g, decode);
            assert!(!ok && err.contains("end-of-image marker"), "{decode:?}: {err}");
        }
        // in auto mode the persons are answered LiDAR-only, saying why, in both modes
        g.mode = RequestedMode::Auto;
        for decode in [None, Some("full")] {
            let r = predict_process(&g, decode);
            assert!(r.persons.iter().all(|p| p.mode == posefuse::service::api::Mode::Lidar), "{decode:?}");
            assert!(r.persons[0].mode_reason.contains("end-of-image marker"), "{}", r.persons[0].mode_reason);
        }
    }
}
