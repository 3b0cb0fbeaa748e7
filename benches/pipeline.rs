//! The whole per-person pipeline: crop + resize from a decoded 1920×1280 image, 2,000 in-box
//! points gathered, projected and reduced to N, K heatmaps smoothed and sampled.
//! `cargo bench --bench pipeline`; results in BENCHMARKS.md.

use criterion::{criterion_group, criterion_main, Criterion};
use image::RgbImage;
use posefuse::frame::{Box2d, Box3d, CameraCalibration};
use posefuse::geometry::Camera;
use posefuse::keypoints::K;
use posefuse::pipeline::{
    crop_rgb, fusion_input, gather_points, normalize, point_input, prepare_person, smoothed_features, PipelineConfig,
    Sampling,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;

fn camera() -> Camera {
    // forward-looking camera 1.5 m ahead of the vehicle origin, 2 m up
    let calib = CameraCalibration {
        intrinsic: vec![2000.0, 2000.0, 960.0, 640.0, 0.05, -0.01, 0.0, 0.0, 0.0],
        extrinsic: vec![1.0, 0.0, 0.0, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 0.0, 0.0, 0.0, 1.0],
        width: 1920,
        height: 1280,
    };
    Camera::from_calibration(&calib).expect("valid calibration")
}

fn bench_person(c: &mut Criterion, image_size: u32) {
    let cfg = PipelineConfig::with_image_size(image_size);
    let cam = camera();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut raw = vec![0u8; 1920 * 1280 * 3];
    rng.fill(&mut raw[..]);
    let image = RgbImage::from_raw(1920, 1280, raw).expect("buffer size");
    // a person 8 m ahead: 2,000 points in the box and 20,000 elsewhere in the sweep
    let box3d =
        Box3d { center_x: 9.5, center_y: 0.5, center_z: 0.9, length: 0.6, width: 0.7, height: 1.8, heading: 0.3 };
    let mut points: Vec<[f32; 3]> = (0..2000)
        .map(|_| [9.5 + rng.random_range(-0.25..0.25), 0.5 + rng.random_range(-0.3..0.3), rng.random_range(0.0..1.8)])
        .collect();
    points.extend(
        (0..20000).map(|_| [rng.random_range(-40.0..40.0), rng.random_range(-40.0..40.0), rng.random_range(0.0..3.0)]),
    );
    let box2d = Box2d { center_x: 900.0, center_y: 600.0, width: 180.0, height: 420.0 };
    let hw = cfg.heatmap_size as usize;
    let heatmaps: Vec<f32> = (0..K * hw * hw).map(|_| rng.random::<f32>()).collect();

    c.bench_function(&format!("person_pipeline_s{image_size}"), |b| {
        b.iter(|| {
            let p = prepare_person(Some(&image), Some(&cam), &points, &box3d, Some(&box2d), &cfg);
            let tensor = p.crop_rgb.as_ref().map(|crop| normalize(crop, &cfg));
            let input = p.input.as_ref().map(|i| i.uv.clone()).unwrap_or_default();
            let features = smoothed_features(&heatmaps, K, hw, hw, &input, &cfg);
            black_box((tensor, features))
        })
    });
    // the same work step by step, to see where the time goes
    let t = posefuse::pipeline::CropTransform::for_box(&box2d, &cfg);
    c.bench_function(&format!("crop_resize_s{image_size}"), |b| b.iter(|| black_box(crop_rgb(&image, &t))));
    let crop = crop_rgb(&image, &t);
    c.bench_function(&format!("normalize_s{image_size}"), |b| b.iter(|| black_box(normalize(&crop, &cfg))));
    let frame = posefuse::geometry::BoxFrame::new(&box3d);
    c.bench_function(&format!("points_s{image_size}"), |b| {
        b.iter(|| {
            let pp = gather_points(&points, &frame, &cfg);
            black_box(point_input(&pp, Some(&cam), Some(&t), &cfg))
        })
    });
    let uv = point_input(&gather_points(&points, &frame, &cfg), Some(&cam), Some(&t), &cfg)
        .map(|i| i.uv)
        .unwrap_or_default();
    c.bench_function(&format!("fusion_s{image_size}"), |b| {
        b.iter(|| black_box(smoothed_features(&heatmaps, K, hw, hw, &uv, &cfg)))
    });
    // the default bundle's fusion (models/default/manifest.json): every cell smoothed with a
    // 5-tap Gaussian, then sampled between the four cells around each point
    let bilinear =
        PipelineConfig { sampling: Sampling::Bilinear, smoothing_kernel: 5, smoothing_sigma: 1.5, ..cfg.clone() };
    let xyz = vec![[0.0f32; 3]; uv.len()];
    c.bench_function(&format!("fusion_bilinear_s{image_size}"), |b| {
        b.iter(|| black_box(fusion_input(&heatmaps, &xyz, &uv, &bilinear)))
    });
}

fn pipeline(c: &mut Criterion) {
    bench_person(c, 256);
    bench_person(c, 128);
    bench_person(c, 64);
}

criterion_group!(benches, pipeline);
criterion_main!(benches);
