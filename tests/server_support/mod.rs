//! Shared by the server integration tests: a synthetic scene (camera, LiDAR box of points, an
//! image with a drawn figure) and an in-process server on a loopback port.
#![allow(dead_code)]

pub mod process;

use std::io::Cursor;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use base64::Engine;
use image::{Rgb, RgbImage};
use posefuse::frame::{
    Box2d, Box3d, CameraCalibration, Frame, GroundTruth, Keypoints2d, Keypoints3d, Person, Points, RequestedMode,
};
use posefuse::geometry::Camera;
use posefuse::server::{App, ServerConfig};
use tokio::sync::oneshot;

pub const WIDTH: u32 = 640;
pub const HEIGHT: u32 = 480;

/// The bundle the tests serve (`models/default`, exported by the trainer).
pub fn model_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/default")
}

/// A forward-looking camera 1.5 m above the vehicle origin (camera frame = vehicle axes).
pub fn calibration() -> CameraCalibration {
    let mut ext = vec![0.0; 16];
    for i in 0..4 {
        ext[i * 5] = 1.0;
    }
    ext[11] = 1.5;
    CameraCalibration {
        intrinsic: vec![500.0, 500.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        extrinsic: ext,
        width: WIDTH,
        height: HEIGHT,
    }
}

pub fn camera() -> Camera {
    Camera::from_calibration(&calibration()).unwrap()
}

/// A standing pedestrian's box centred at (x, y) on the ground.
pub fn person_box(x: f64, y: f64) -> Box3d {
    Box3d { center_x: x, center_y: y, center_z: 0.9, length: 0.5, width: 0.7, height: 1.8, heading: 0.3 }
}

/// `n` points spread through a box (a deterministic lattice walk), vehicle frame.
pub fn points_in(b: &Box3d, n: usize) -> Vec<[f32; 3]> {
    let frame = posefuse::geometry::BoxFrame::new(b);
    (0..n)
        .map(|i| {
            let f = |k: f64| ((i as f64 * k).fract() - 0.5) * 0.9;
            let q = [f(0.618_034) * b.length, f(0.414_214) * b.width, f(0.732_051) * b.height];
            let p = frame.to_vehicle(q);
            [p[0] as f32, p[1] as f32, p[2] as f32]
        })
        .collect()
}

/// The projection of the box corners (the test's "detector" 2D box).
pub fn box_2d(b: &Box3d) -> Box2d {
    posefuse::geometry::projected_box(&camera(), b).unwrap()
}

/// A grey image with a figure (head, torso, legs) drawn inside each 2D box; PNG, base64.
pub fn image_b64(boxes: &[Box2d]) -> String {
    base64::engine::general_purpose::STANDARD.encode(image_png(boxes))
}

pub fn image_png(boxes: &[Box2d]) -> Vec<u8> {
    let mut img = RgbImage::from_pixel(WIDTH, HEIGHT, Rgb([110, 115, 120]));
    for b in boxes {
        let (x0, y0) = (b.center_x - b.width / 2.0, b.center_y - b.height / 2.0);
        let mut fill = |fx0: f64, fy0: f64, fx1: f64, fy1: f64, c: [u8; 3]| {
            for y in (y0 + fy0 * b.height) as i64..(y0 + fy1 * b.height) as i64 {
                for x in (x0 + fx0 * b.width) as i64..(x0 + fx1 * b.width) as i64 {
                    if x >= 0 && y >= 0 && (x as u32) < WIDTH && (y as u32) < HEIGHT {
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
    let mut out = Vec::new();
    image::DynamicImage::ImageRgb8(img).write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
    out
}

/// Plausible ground truth for a person in box `b` (a standing figure), with its projection.
pub fn ground_truth(b: &Box3d) -> GroundTruth {
    let frame = posefuse::geometry::BoxFrame::new(b);
    // (forward, left, up) offsets from the box centre for the 13 keypoints.
    let local: [[f64; 3]; 13] = [
        [0.1, 0.0, 0.8],
        [0.0, 0.2, 0.5],
        [0.0, -0.2, 0.5],
        [0.0, 0.25, 0.2],
        [0.0, -0.25, 0.2],
        [0.05, 0.25, -0.05],
        [0.05, -0.25, -0.05],
        [0.0, 0.12, 0.0],
        [0.0, -0.12, 0.0],
        [0.05, 0.12, -0.45],
        [0.05, -0.12, -0.45],
        [0.0, 0.12, -0.85],
        [0.0, -0.12, -0.85],
    ];
    let xyz: Vec<[f64; 3]> = local.iter().map(|q| frame.to_vehicle(*q)).collect();
    let cam = camera();
    let proj: Vec<_> = xyz.iter().map(|p| cam.project(*p)).collect();
    let keypoints_2d = proj.iter().all(|p| p.in_front).then(|| Keypoints2d {
        uv: proj.iter().map(|p| p.uv).collect(),
        visible: vec![true; 13],
        occluded: vec![],
    });
    GroundTruth { keypoints_3d: Some(Keypoints3d { xyz, visible: vec![true; 13], occluded: vec![] }), keypoints_2d }
}

/// A person in view with plenty of points (fusion), given the box.
pub fn person(id: &str, b: Box3d, with_box_2d: bool) -> Person {
    Person { id: id.into(), camera: None, box_2d: with_box_2d.then(|| box_2d(&b)), box_3d: b, ground_truth: None }
}

/// One frame with one person in front of the camera, image and 300 points: fusion in auto mode.
pub fn fusion_frame() -> Frame {
    let b = person_box(8.0, 0.5);
    Frame {
        frame_id: Some("f-1".into()),
        image: Some(image_b64(&[box_2d(&b)])),
        image_rgb: None,
        calibration: Some(calibration()),
        cameras: Vec::new(),
        points: Points::encode(&points_in(&b, 300)),
        persons: vec![person("ped-1", b, true)],
        mode: RequestedMode::Auto,
    }
}

/// Three persons: in view with many points (fusion), behind the vehicle (lidar), in view with
/// only three points (camera).
pub fn three_mode_frame() -> Frame {
    let (a, b, c) = (person_box(8.0, 0.5), person_box(-9.0, 2.0), person_box(12.0, -1.5));
    let mut pts = points_in(&a, 300);
    pts.extend(points_in(&b, 200));
    pts.extend(points_in(&c, 3));
    // Clutter outside every box.
    pts.extend((0..50).map(|i| [20.0 + i as f32 * 0.1, 5.0, 0.1]));
    Frame {
        frame_id: Some("f-3".into()),
        image: Some(image_b64(&[box_2d(&a), box_2d(&c)])),
        image_rgb: None,
        calibration: Some(calibration()),
        cameras: Vec::new(),
        points: Points::encode(&pts),
        persons: vec![person("near", a, true), person("behind", b, false), person("sparse", c, false)],
        mode: RequestedMode::Auto,
    }
}

/// A running in-process server.
pub struct TestServer {
    pub addr: SocketAddr,
    pub predictor: posefuse::service::Predictor,
    stop: Option<oneshot::Sender<()>>,
    pub task: Option<tokio::task::JoinHandle<posefuse::Result<()>>>,
}

impl TestServer {
    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    /// Signals shutdown and waits for the server to finish.
    pub async fn shutdown(mut self) -> posefuse::Result<()> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        match self.task.take() {
            Some(t) => t.await.unwrap(),
            None => Ok(()),
        }
    }

    /// Signals shutdown without waiting.
    pub fn signal_shutdown(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
    }
}

impl TestServer {
    /// POSTs NDJSON lines to the batch endpoint.
    pub async fn post_ndjson(&self, body: String) -> reqwest::Response {
        reqwest::Client::new()
            .post(self.url("/v1/poses:batch"))
            .header("content-type", "application/x-ndjson")
            .body(body)
            .send()
            .await
            .unwrap()
    }
}

pub fn config() -> ServerConfig {
    ServerConfig::new(model_dir())
}

/// Starts a server with `config` and waits until /readyz says ready.
pub async fn start(config: ServerConfig) -> TestServer {
    start_with_admin(config, false).await.0
}

/// As [`start`], and with `admin` an admin listener on a loopback port (`--admin-addr`), whose
/// base URL comes back too.
pub async fn start_with_admin(config: ServerConfig, admin: bool) -> (TestServer, Option<String>) {
    let app = tokio::task::spawn_blocking(move || App::start(&config)).await.unwrap().unwrap();
    let admin_url = if admin {
        let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", l.local_addr().unwrap());
        app.serve_admin(l);
        Some(url)
    } else {
        None
    };
    let predictor = app.predictor().clone();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (tx, rx) = oneshot::channel::<()>();
    let task = tokio::spawn(app.serve(listener, async move {
        let _ = rx.await;
    }));
    let server = TestServer { addr, predictor, stop: Some(tx), task: Some(task) };
    let client = reqwest::Client::new();
    for _ in 0..1000 {
        if let Ok(r) = client.get(server.url("/readyz")).send().await {
            if r.status() == 200 {
                return (server, admin_url);
            }
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    panic!("server did not become ready");
}

/// A job input of `len` floats, different for each `seed`.
pub fn input(len: usize, seed: f32) -> Vec<f32> {
    (0..len).map(|i| ((i as f32 * 0.37 + seed).sin()) * 0.5).collect()
}

/// A warmed-up runtime on the test bundle that batches up to 8 jobs.
pub async fn started_runtime() -> std::sync::Arc<posefuse::runtime::Runtime> {
    use posefuse::runtime::{Bundle, Runtime, RuntimeConfig};
    let bundle = std::sync::Arc::new(Bundle::load(&model_dir()).unwrap());
    let cfg = RuntimeConfig { max_batch: 8, ..RuntimeConfig::default() };
    let rt = tokio::task::spawn_blocking(move || Runtime::start(bundle, &cfg)).await.unwrap().unwrap();
    assert!(rt.wait_ready(Duration::from_secs(60)));
    std::sync::Arc::new(rt)
}

/// A frame whose pre-processing is long: many persons, each scanning many points and each with
/// its own crop (boxes a few millimetres apart: identical windows would share one).
pub fn heavy_frame(persons: usize, points: usize) -> Frame {
    let b = person_box(8.0, 0.5);
    let mut pts = points_in(&b, 300);
    pts.extend((0..points).map(|i| [30.0 + (i % 1000) as f32 * 0.01, 5.0 + (i / 1000) as f32 * 0.01, 0.5]));
    Frame {
        frame_id: Some("heavy".into()),
        image: Some(image_b64(&[box_2d(&b)])),
        image_rgb: None,
        calibration: Some(calibration()),
        cameras: Vec::new(),
        points: Points::encode(&pts),
        persons: (0..persons)
            .map(|i| Person { id: format!("p{i}"), ..person("p", person_box(8.0, 0.5 + i as f64 * 0.002), true) })
            .collect(),
        mode: RequestedMode::Auto,
    }
}
