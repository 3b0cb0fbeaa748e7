//! JPEG decoders on request-size frames: the `image` crate (zune-jpeg) whole at full resolution,
//! libjpeg-turbo whole at each DCT scale, one plan for all of a frame's crop windows (one scale
//! and region, not read to the end: what the server ran before, over today's crop scales), and
//! the server's `decode_crops` (each window at its own scale, one pass per scale, the last read
//! to the end). Frames: `POSEFUSE_BENCH_DATA` (a simulator output directory, e.g.
//! `posefuse simulate --profile street`), each as written (4:4:4) and re-encoded 4:2:0 at the same
//! quality; without it, one synthetic 1920×1280 frame. `cargo bench --bench decode`; results in
//! BENCHMARKS.md.

use std::time::{Duration, Instant};

use base64::Engine;
use posefuse::image_decode::{decode_crops, decode_planned, CameraImage};
use posefuse::pipeline::{plan_decode, plan_passes, CropTransform, DecodePlan, PipelineConfig};
use posefuse::runtime::Bundle;

struct Case {
    jpeg444: Vec<u8>,
    jpeg420: Vec<u8>,
    windows: Vec<CropTransform>,
    size: (u32, u32),
}

fn encode(img: &image::RgbImage, sampling: jpeg_encoder::SamplingFactor) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = jpeg_encoder::Encoder::new(&mut out, posefuse::sample::JPEG_QUALITY);
    enc.set_sampling_factor(sampling);
    enc.encode(img.as_raw(), img.width() as u16, img.height() as u16, jpeg_encoder::ColorType::Rgb).unwrap();
    out
}

fn cases(limit: usize) -> Vec<Case> {
    // the default bundle's crop size S and crop scale
    let cfg: PipelineConfig = Bundle::load(std::path::Path::new("models/default")).unwrap().config().clone();
    let Some(dir) = std::env::var_os("POSEFUSE_BENCH_DATA") else {
        let img = image::RgbImage::from_fn(1920, 1280, |x, y| {
            image::Rgb([(x % 251) as u8, (y % 241) as u8, ((x ^ y) % 256) as u8])
        });
        let window = CropTransform { x0: 800.0, y0: 400.0, scale: cfg.image_size as f64 / 300.0, size: cfg.image_size };
        return vec![Case {
            jpeg444: posefuse::sample::encode_jpeg(&img).unwrap(),
            jpeg420: encode(&img, jpeg_encoder::SamplingFactor::R_4_2_0),
            windows: vec![window],
            size: (1920, 1280),
        }];
    };
    let frames = posefuse::eval::load_fixtures(std::path::Path::new(&dir)).unwrap();
    frames
        .into_iter()
        .take(limit)
        .map(|(_, f)| {
            let jpeg = base64::engine::general_purpose::STANDARD.decode(f.image.as_ref().unwrap()).unwrap();
            let img = image::load_from_memory(&jpeg).unwrap().into_rgb8();
            let windows = f.persons.iter().filter_map(|p| p.box_2d.map(|b| CropTransform::for_box(&b, &cfg))).collect();
            Case {
                jpeg420: encode(&img, jpeg_encoder::SamplingFactor::R_4_2_0),
                jpeg444: jpeg,
                windows,
                size: f.calibration.as_ref().map(|c| (c.width, c.height)).unwrap(),
            }
        })
        .collect()
}

fn median(mut v: Vec<Duration>) -> f64 {
    v.sort();
    v[v.len() / 2].as_secs_f64() * 1e3
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let rounds = if full { 5 } else { 1 };
    let cases = cases(if full { 40 } else { 2 });
    let mut plans = [0usize; 9];
    let mut passes = 0;
    for c in &cases {
        plans[plan_decode(&c.windows, c.size.0, c.size.1).denominator as usize] += 1;
        passes += plan_passes(&c.windows, c.size.0, c.size.1).len();
    }
    println!(
        "{} frames, {} rounds | frame-wide scale: 1/1 {} · 1/2 {} · 1/4 {} · 1/8 {} | per-window passes per frame {:.2}",
        cases.len(),
        rounds,
        plans[1],
        plans[2],
        plans[4],
        plans[8],
        passes as f64 / cases.len().max(1) as f64
    );
    println!("| decoder | 4:4:4 median ms | 4:2:0 median ms |");
    println!("|---|---|---|");
    type Run = Box<dyn Fn(&Case, &[u8])>;
    let whole = |d: u32| -> Run {
        Box::new(move |c: &Case, j: &[u8]| {
            drop(
                decode_planned(j, &DecodePlan { denominator: d, ..DecodePlan::full(c.size.0, c.size.1) }, true)
                    .unwrap(),
            )
        })
    };
    let variants: Vec<(&str, Run)> = vec![
        (
            "image (zune-jpeg), full",
            Box::new(|_, j| {
                drop(image::load_from_memory_with_format(j, image::ImageFormat::Jpeg).unwrap().into_rgb8());
            }),
        ),
        ("libjpeg-turbo 1/1, whole", whole(1)),
        ("libjpeg-turbo 1/2, whole", whole(2)),
        ("libjpeg-turbo 1/4, whole", whole(4)),
        ("libjpeg-turbo 1/8, whole", whole(8)),
        (
            "libjpeg-turbo, one scale and region for all of a frame's windows",
            Box::new(|c, j| drop(decode_planned(j, &plan_decode(&c.windows, c.size.0, c.size.1), false).unwrap())),
        ),
        (
            "libjpeg-turbo, each window at its own scale, no pass read to the end",
            Box::new(|c, j| {
                for pass in plan_passes(&c.windows, c.size.0, c.size.1) {
                    drop(decode_planned(j, &pass.plan, false).unwrap());
                }
            }),
        ),
        (
            "libjpeg-turbo, each window at its own scale (the server's)",
            Box::new(|c, j| {
                let crops = decode_crops(&CameraImage::Jpeg(j.to_vec()), &c.windows, c.size.0, c.size.1, || Ok(()));
                drop(crops.unwrap().unwrap())
            }),
        ),
    ];
    for (name, run) in &variants {
        let mut t444 = Vec::new();
        let mut t420 = Vec::new();
        for _ in 0..rounds {
            for c in &cases {
                let t = Instant::now();
                run(c, &c.jpeg444);
                t444.push(t.elapsed());
                let t = Instant::now();
                run(c, &c.jpeg420);
                t420.push(t.elapsed());
            }
        }
        println!("| {name} | {:.2} | {:.2} |", median(t444), median(t420));
    }
}
