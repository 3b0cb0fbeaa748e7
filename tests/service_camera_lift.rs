//! Camera mode, recomputed by hand from the pipeline's steps: the service's answer must be the
//! paper's eq. 1 with the bundle's lifting temperature, and that temperature must matter.

mod server_support;

use std::time::Duration;

use posefuse::frame::RequestedMode;
use posefuse::geometry::Camera;
use posefuse::keypoints::K;
use posefuse::pipeline::{crop_rgb, decode_heatmaps, keypoints_to_vehicle, lift, normalize, prepare_person};
use posefuse::runtime::{ModelKind, Runtime, RuntimeConfig};
use posefuse::service::api::Mode;
use posefuse::service::Predictor;
use server_support::*;

fn max_distance(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt())
        .fold(0.0, f64::max)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn camera_mode_lifts_with_the_bundles_temperature() {
    let dir = model_dir();
    let runtime =
        tokio::task::spawn_blocking(move || Runtime::load(&dir, &RuntimeConfig::DEFAULT)).await.unwrap().unwrap();
    assert!(runtime.wait_ready(Duration::from_secs(60)));
    let predictor = Predictor::new(runtime.clone());
    let mut frame = fusion_frame();
    frame.mode = RequestedMode::Camera;
    let resp = predictor.answer(frame.clone(), None, Duration::from_secs(30)).await.unwrap();
    assert_eq!(resp.persons[0].mode, Mode::Camera);
    let served: Vec<[f64; 3]> = resp.persons[0].keypoints.iter().map(|k| k.xyz).collect();

    // The same person through the pipeline's steps, one by one.
    let cfg = runtime.bundle().config().clone();
    let camera = Camera::from_calibration(frame.calibration.as_ref().unwrap()).unwrap();
    let points = frame.points.decode().unwrap();
    let p = &frame.persons[0];
    let prepared = prepare_person(None, Some(&camera), &points, &p.box_3d, p.box_2d.as_ref(), &cfg);
    let image = image::load_from_memory(&image_png(&[p.box_2d.unwrap()])).unwrap().to_rgb8();
    let x = normalize(&crop_rgb(&image, prepared.crop.as_ref().unwrap()), &cfg);
    let heatmaps = runtime.infer(ModelKind::Camera, x).await.unwrap().data;
    let hm = cfg.heatmap_size as usize;
    let kp_uv: Vec<[f32; 2]> =
        decode_heatmaps(&heatmaps, K, hm, hm, cfg.image_size).into_iter().map(|(uv, _)| uv).collect();
    let input = prepared.input.unwrap();
    let by_hand = |t: f64| {
        keypoints_to_vehicle(&lift(&kp_uv, &input.uv, &input.xyz, cfg.image_size, t), &prepared.box_frame, &cfg)
    };

    let expected = by_hand(cfg.lift_temperature);
    assert!(max_distance(&served, &expected) < 1e-4, "served {served:?}\nexpected {expected:?}");
    // A temperature of 1 (no sharpening) gives another pose: the test would notice a wrong one.
    assert_ne!(cfg.lift_temperature, 1.0);
    let flat = by_hand(1.0);
    assert!(max_distance(&served, &flat) > 1e-3, "the temperature does not matter on this frame");
}
