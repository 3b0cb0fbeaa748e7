//! Several cameras per frame (`cameras`) against a real in-process server, over HTTP and gRPC:
//! each person uses the camera it names or the one that sees it, answers as the same person sent
//! with that camera alone, and camera errors name their field.

mod server_support;

use base64::Engine;
use posefuse::frame::{Box2d, CameraCalibration, Frame, FrameCamera, Person, Points};
use posefuse::geometry::{projected_box, Camera};
use posefuse::server::grpc::frame_to_proto;
use posefuse::server::grpc::proto::{self, posefuse_client::PosefuseClient};
use posefuse::service::api::{Mode, PersonPose, PoseResponse};
use serde_json::{json, Value};
use server_support::*;

/// The support scene's camera turned to look left (+y): yawed 90° about z, 1.5 m up.
fn left_calibration() -> CameraCalibration {
    #[rustfmt::skip]
    let extrinsic = vec![
        0.0, -1.0, 0.0, 0.0,
        1.0, 0.0, 0.0, 0.0,
        0.0, 0.0, 1.0, 1.5,
        0.0, 0.0, 0.0, 1.0,
    ];
    CameraCalibration { extrinsic, ..calibration() }
}

fn left_camera() -> Camera {
    Camera::from_calibration(&left_calibration()).unwrap()
}

/// Two persons beside the vehicle on the left, which only the left camera sees.
fn left_boxes() -> [posefuse::frame::Box3d; 2] {
    [person_box(0.5, 8.0), person_box(-1.5, 11.0)]
}

fn left_persons() -> Vec<Person> {
    left_boxes().iter().enumerate().map(|(i, b)| person(&format!("left-{i}"), *b, false)).collect()
}

/// The left camera's image: the figures drawn in the persons' boxes as it sees them.
fn left_image() -> String {
    let boxes: Vec<_> = left_boxes().iter().map(|b| projected_box(&left_camera(), b).unwrap()).collect();
    image_b64(&boxes)
}

fn points() -> Points {
    let mut pts: Vec<[f32; 3]> = left_boxes().iter().flat_map(|b| points_in(b, 300)).collect();
    pts.extend(points_in(&person_box(-9.0, -2.0), 200));
    Points::encode(&pts)
}

/// `front` (an empty street) and `left` (the persons), the persons naming no camera.
fn two_camera_frame() -> Frame {
    let grey = image_b64(&[]);
    Frame {
        frame_id: Some("two".into()),
        image: None,
        image_rgb: None,
        calibration: None,
        cameras: vec![
            FrameCamera { name: "front".into(), image: Some(grey), image_rgb: None, calibration: calibration() },
            FrameCamera {
                name: "left".into(),
                image: Some(left_image()),
                image_rgb: None,
                calibration: left_calibration(),
            },
        ],
        points: points(),
        persons: left_persons(),
        mode: Default::default(),
    }
}

/// The same persons sent with the left camera alone.
fn left_only_frame() -> Frame {
    Frame {
        image: Some(left_image()),
        calibration: Some(left_calibration()),
        cameras: Vec::new(),
        ..two_camera_frame()
    }
}

async fn post(s: &TestServer, body: &Value) -> (u16, Value) {
    let r = reqwest::Client::new().post(s.url("/v1/poses")).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

async fn answer(s: &TestServer, frame: &Frame) -> PoseResponse {
    let (status, body) = post(s, &serde_json::to_value(frame).unwrap()).await;
    assert_eq!(status, 200, "{body}");
    serde_json::from_value(body).unwrap()
}

fn assert_same_keypoints(a: &PersonPose, b: &PersonPose) {
    assert_eq!(a.mode, b.mode, "{}", a.id);
    assert_same_box(a.box_2d, b.box_2d);
    for (ka, kb) in a.keypoints.iter().zip(&b.keypoints) {
        for i in 0..3 {
            assert!((ka.xyz[i] - kb.xyz[i]).abs() < 1e-5, "{} {}: {:?} vs {:?}", a.id, ka.name, ka.xyz, kb.xyz);
        }
        match (ka.uv, kb.uv) {
            (Some(u), Some(v)) => assert!((u[0] - v[0]).abs() < 1e-3 && (u[1] - v[1]).abs() < 1e-3),
            (u, v) => assert_eq!(u, v),
        }
    }
}

/// Equal boxes, up to the last digit JSON's decimal form keeps.
fn assert_same_box(a: Option<Box2d>, b: Option<Box2d>) {
    let (Some(a), Some(b)) = (a, b) else { return assert_eq!(a, b) };
    let d = [a.center_x - b.center_x, a.center_y - b.center_y, a.width - b.width, a.height - b.height];
    assert!(d.iter().all(|d| d.abs() < 1e-9), "{a:?} vs {b:?}");
}

fn field(body: &Value) -> &str {
    body["error"]["field"].as_str().unwrap_or("")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn persons_seen_by_the_second_camera_use_it_and_answer_as_with_that_camera_alone() {
    let s = start(config()).await;
    let mut frame = two_camera_frame();
    // a third person behind every camera: LiDAR only, and no camera named
    frame.persons.push(person("behind", person_box(-9.0, -2.0), false));
    let multi = answer(&s, &frame).await;
    let single = answer(&s, &left_only_frame()).await;
    let cam = left_camera();
    for (i, b) in left_boxes().iter().enumerate() {
        let p = &multi.persons[i];
        assert_eq!(p.camera.as_deref(), Some("left"), "{}", p.id);
        assert_eq!(p.mode, Mode::Fusion, "{}: {}", p.id, p.mode_reason);
        assert_same_box(p.box_2d, projected_box(&cam, b));
        // the keypoints' pixels are the left camera's
        let kp = &p.keypoints[0];
        let uv = cam.project(kp.xyz).uv;
        assert!((kp.uv.unwrap()[0] - uv[0]).abs() < 1e-9 && (kp.uv.unwrap()[1] - uv[1]).abs() < 1e-9);
        assert_eq!(single.persons[i].camera, None, "a single-camera answer names no camera");
        assert_same_keypoints(p, &single.persons[i]);
    }
    let behind = &multi.persons[2];
    assert_eq!((behind.camera.as_deref(), behind.mode), (None, Mode::Lidar));
    assert!(behind.mode_reason.contains("every camera"), "{}", behind.mode_reason);
    assert!(behind.keypoints.iter().all(|k| k.uv.is_none()) && behind.box_2d.is_none());
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_named_camera_is_used_and_camera_errors_name_their_field() {
    let s = start(config()).await;
    // Named: the front camera, which does not see the person (LiDAR only, said why) ...
    let mut frame = two_camera_frame();
    frame.persons[0].camera = Some("front".into());
    // ... and the left camera with the caller's own 2D box, used as given.
    let given = Box2d { width: 60.0, ..projected_box(&left_camera(), &left_boxes()[1]).unwrap() };
    frame.persons[1].camera = Some("left".into());
    frame.persons[1].box_2d = Some(given);
    let r = answer(&s, &frame).await;
    assert_eq!((r.persons[0].camera.as_deref(), r.persons[0].mode), (Some("front"), Mode::Lidar));
    assert!(r.persons[0].mode_reason.contains("outside the camera view"), "{}", r.persons[0].mode_reason);
    assert_eq!(r.persons[1].camera.as_deref(), Some("left"));
    assert_same_box(r.persons[1].box_2d, Some(given));
    assert_eq!(r.persons[1].mode, Mode::Fusion);

    let frame = serde_json::to_value(two_camera_frame()).unwrap();
    let mut v = frame.clone();
    v["persons"][1]["camera"] = json!("rear");
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "persons[1].camera"), "{body}");
    assert!(body["error"]["message"].as_str().unwrap().contains("`rear`"), "{body}");
    // both forms at once
    let mut v = frame.clone();
    v["calibration"] = serde_json::to_value(calibration()).unwrap();
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "cameras"), "{body}");
    // a camera without an image, and one with two
    let mut v = frame.clone();
    v["cameras"][1].as_object_mut().unwrap().remove("image");
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "cameras[1].image"), "{body}");
    let mut v = frame.clone();
    v["cameras"][0]["image_rgb"] = json!({"width": 1, "height": 1, "b64": "AAAA"});
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "cameras[0].image_rgb"), "{body}");
    // duplicate names; a bad calibration is named within its camera
    let mut v = frame.clone();
    v["cameras"][1]["name"] = json!("front");
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "cameras[1].name"), "{body}");
    let mut v = frame.clone();
    v["cameras"][1]["calibration"]["extrinsic"][15] = json!(2.0);
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "cameras[1].calibration.extrinsic"), "{body}");
    // more cameras than a frame may have
    let mut v = frame.clone();
    let one = v["cameras"][0].clone();
    v["cameras"] = (0..=posefuse::service::limits::MAX_CAMERAS)
        .map(|i| {
            let mut c = one.clone();
            c["name"] = json!(format!("c{i}"));
            c
        })
        .collect();
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "cameras"), "{body}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_image_no_person_uses_is_not_even_opened() {
    let s = start(config()).await;
    // The front image's header disagrees with its calibration: refused had it been read.
    let mut v = serde_json::to_value(two_camera_frame()).unwrap();
    v["cameras"][0]["calibration"]["width"] = json!(WIDTH * 2);
    let (status, body) = post(&s, &v).await;
    assert_eq!(status, 200, "{body}");
    assert!(body["persons"].as_array().unwrap().iter().all(|p| p["camera"] == "left"), "{body}");
    // ... and it is, once a person uses that camera.
    v["persons"][0]["camera"] = json!("front");
    let (status, body) = post(&s, &v).await;
    assert_eq!((status, field(&body)), (422, "cameras[0].image"), "{body}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_cameras_answer_as_http_and_errors_name_their_field() {
    let s = start(config()).await;
    let mut c = PosefuseClient::connect(s.url("")).await.unwrap();
    let frame = two_camera_frame();
    let request = frame_to_proto(&frame, Vec::new()).unwrap();
    assert_eq!(request.cameras.len(), 2);
    assert!(request.calibration.is_none() && request.image.is_empty());
    let r = c.predict(request.clone()).await.unwrap().into_inner();
    let single = answer(&s, &left_only_frame()).await;
    for (g, h) in r.persons.iter().zip(&single.persons) {
        assert_eq!((g.camera.as_str(), g.mode), ("left", proto::Mode::Fusion as i32), "{}", g.mode_reason);
        for (a, b) in g.keypoints.iter().zip(&h.keypoints) {
            let d = [(a.x - b.xyz[0]).abs(), (a.y - b.xyz[1]).abs(), (a.z - b.xyz[2]).abs()];
            assert!(d.iter().all(|d| *d < 1e-5), "{}: {d:?}", a.name);
        }
    }
    // naming a camera
    let mut named = request.clone();
    named.persons[0].camera = "front".into();
    let r = c.predict(named).await.unwrap().into_inner();
    assert_eq!((r.persons[0].camera.as_str(), r.persons[0].mode), ("front", proto::Mode::Lidar as i32));
    let mut unknown = request.clone();
    unknown.persons[0].camera = "rear".into();
    let e = c.predict(unknown).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(e.message().contains("persons[0].camera"), "{}", e.message());
    // both forms: the single camera's image bytes beside `cameras`
    let png = base64::engine::general_purpose::STANDARD.decode(left_image()).unwrap();
    let both = proto::PredictRequest { image: png.clone(), ..request.clone() };
    let e = c.predict(both).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(e.message().contains("`cameras`"), "{}", e.message());
    let mut both = request.clone();
    both.calibration =
        Some(proto::Calibration { intrinsic: vec![1.0; 9], extrinsic: vec![0.0; 16], width: 1, height: 1 });
    assert!(c.predict(both).await.unwrap_err().message().contains("`cameras`"));
    // a camera without an image
    let mut empty = request.clone();
    empty.cameras[1].image.clear();
    let e = c.predict(empty).await.unwrap_err();
    assert!(e.message().contains("cameras[1].image"), "{}", e.message());
    s.shutdown().await.unwrap();
}

/// A Waymo-like 1920×1280 camera 1.5 m up, yawed `deg` degrees left, with strong barrel
/// distortion (k2 = −0.33, as real Waymo cameras have): half field of view about 24.9°.
fn barrel_calibration(deg: f64) -> CameraCalibration {
    let (s, c) = deg.to_radians().sin_cos();
    #[rustfmt::skip]
    let extrinsic = vec![
        c, -s, 0.0, 0.0,
        s, c, 0.0, 0.0,
        0.0, 0.0, 1.0, 1.5,
        0.0, 0.0, 0.0, 1.0,
    ];
    CameraCalibration {
        intrinsic: vec![2055.0, 2055.0, 960.0, 640.0, 0.0, -0.33, 0.0, 0.0, 0.0],
        extrinsic,
        width: 1920,
        height: 1280,
    }
}

/// A grey 1920×1280 JPEG (base64).
fn grey_jpeg() -> String {
    let img = image::RgbImage::from_pixel(1920, 1280, image::Rgb([110, 115, 120]));
    base64::engine::general_purpose::STANDARD.encode(posefuse::sample::encode_jpeg(&img).unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_box_outside_a_distorted_cameras_view_is_never_answered_with_it() {
    let s = start(config()).await;
    // pedestrians 10 m away at 5°, 50° and 57° left of the FRONT camera's axis
    let at = |deg: f64| {
        let (y, x) = deg.to_radians().sin_cos();
        person_box(10.0 * x, 10.0 * y)
    };
    let boxes = [at(5.0), at(50.0), at(57.0)];
    let pts: Vec<[f32; 3]> = boxes.iter().flat_map(|b| points_in(b, 300)).collect();
    let persons: Vec<Person> = boxes.iter().enumerate().map(|(i, b)| person(&format!("p{i}"), *b, false)).collect();
    let camera = |name: &str, deg: f64| FrameCamera {
        name: name.into(),
        image: Some(grey_jpeg()),
        image_rgb: None,
        calibration: barrel_calibration(deg),
    };
    let frame = Frame {
        frame_id: Some("distorted".into()),
        image: None,
        image_rgb: None,
        calibration: None,
        cameras: vec![camera("FRONT", 0.0), camera("FRONT_LEFT", 45.0)],
        points: Points::encode(&pts),
        persons: persons.clone(),
        mode: Default::default(),
    };
    // with both cameras each person is answered in the one that really sees it
    let r = answer(&s, &frame).await;
    let cams: Vec<Option<&str>> = r.persons.iter().map(|p| p.camera.as_deref()).collect();
    assert_eq!(cams, vec![Some("FRONT"), Some("FRONT_LEFT"), Some("FRONT_LEFT")], "{r:?}");
    for p in &r.persons {
        let b = p.box_2d.unwrap();
        assert!(b.width < 400.0 && b.height > 250.0, "{}: not a folded box: {b:?}", p.id);
    }
    // with FRONT alone, the two off its view get no camera: LiDAR-only, saying why
    let front_only = Frame { cameras: vec![camera("FRONT", 0.0)], ..frame };
    let r = answer(&s, &front_only).await;
    let modes: Vec<Mode> = r.persons.iter().map(|p| p.mode).collect();
    assert_eq!(modes, vec![Mode::Fusion, Mode::Lidar, Mode::Lidar], "{r:?}");
    for p in &r.persons[1..] {
        assert!(p.camera.is_none() && p.box_2d.is_none(), "{p:?}");
        assert!(p.mode_reason.contains("outside the view of every camera"), "{}", p.mode_reason);
        assert!(p.keypoints.iter().all(|k| k.uv.is_none()), "{}: keypoints folded into FRONT", p.id);
    }
    s.shutdown().await.unwrap();
}
