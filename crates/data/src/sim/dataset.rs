//! One frame from world to outputs: LiDAR scan, labels, the pipeline's crops and point inputs
//! (prepared samples), and the request fixture. The sample schema and its shard writer are
//! `posefuse_core::sample`.
//!
//! Frames with a fixture render the full image (at image resolution inside the labelled persons'
//! crop windows, at quarter resolution elsewhere), go through JPEG (quality 92) and crop from the
//! image decoded exactly as the server decodes it (`image_decode::decode_crops`: each crop at its
//! own window's DCT scale). Training-only frames render just the crop
//! window: at image resolution when the window is at most 2·S pixels wide (then through the same
//! JPEG codec and planned decode), otherwise one ray per step×step block with
//! step = ceil(side / 2S), i.e. at least 2×2 supersampling of the S×S crop; the crop is then cut
//! by the same `crop_rgb`.

use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::labels::{label_person, PersonLabels};
use super::lidar::{scan, Return};
use super::math::{hash, V3};
use super::realism::{Effect, Realism};
use super::render::{render, Region};
use super::world::{lidar_range, sample_world, World, LIDAR_ORIGIN};
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Frame, GroundTruth, Keypoints2d, Keypoints3d, Person, Points, RequestedMode};
use posefuse_core::keypoints::K;
use posefuse_core::pipeline::{crop_rgb, model_frame, prepare_person, to_local, CropTransform, PipelineConfig};
use posefuse_core::sample::{encode_jpeg, planned_crops, sample_points, Sample, SamplePoints};

/// Per-sample numbers for the realism statistics.
#[derive(Debug, Clone)]
pub struct SampleStats {
    pub range_m: f64,
    pub activity: &'static str,
    /// Points in the 3D box (grown by the pipeline's margin), before the cap.
    pub in_box_points: usize,
    /// LiDAR returns on the person's body or carried objects.
    pub person_points: usize,
    pub in_image: [bool; K],
    pub visible_2d: [bool; K],
    /// A point of the box projects within `near_px` model pixels of the exact keypoint.
    pub near_point: [bool; K],
}

/// Everything a frame produced.
pub struct FrameResult {
    pub index: usize,
    pub samples: Vec<Sample>,
    pub stats: Vec<SampleStats>,
    pub fixture: Option<Frame>,
}

/// The frame's random generator: a function of (seed, index) only.
pub fn frame_rng(seed: u64, index: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(hash(&[seed, index as u64]))
}

/// The frame's own stream for the 3D labels' noise, apart from the scene's, so the effect moves
/// nothing but the 3D labels.
fn label_noise_rng(seed: u64, index: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(hash(&[seed, index as u64, 3]))
}

pub fn persons_in_frame<R: Rng>(rng: &mut R) -> usize {
    match rng.random_range(0..100) {
        0..=39 => 1,
        40..=74 => 2,
        _ => 3,
    }
}

/// Renders only the crop window of `t` and cuts the S×S crop from it (training-only frames).
pub fn render_crop(world: &World, t: &CropTransform) -> Result<RgbImage> {
    let cam = &world.camera;
    let side = t.side();
    let step = ((side / (2.0 * t.size as f64)).ceil() as i64).max(1);
    let (wx0, wy0) = (t.x0.floor().max(0.0) as i64, t.y0.floor().max(0.0) as i64);
    let wx1 = ((t.x0 + side).ceil() as i64).min(cam.width as i64);
    let wy1 = ((t.y0 + side).ceil() as i64).min(cam.height as i64);
    if wx1 <= wx0 || wy1 <= wy0 {
        return Ok(RgbImage::new(t.size, t.size));
    }
    let region = Region {
        x0: wx0,
        y0: wy0,
        w: ((wx1 - wx0 + step - 1) / step) as u32,
        h: ((wy1 - wy0 + step - 1) / step) as u32,
        step: step as u32,
    };
    let patch = render(world, region).image;
    let s = step as f64;
    let local =
        CropTransform { x0: (t.x0 - wx0 as f64) / s, y0: (t.y0 - wy0 as f64) / s, scale: t.scale * s, size: t.size };
    if step == 1 {
        let jpeg = encode_jpeg(&patch)?;
        let mut crops = planned_crops(&jpeg, &[local], patch.width(), patch.height())?;
        return crops.pop().ok_or_else(|| Error::Io("jpeg decode: no crop".into()));
    }
    Ok(crop_rgb(&patch, &local))
}

/// Bilinear ×4 upsampling (pixel centres aligned) to `w`×`h`.
fn upsample4(src: &RgbImage, w: u32, h: u32) -> RgbImage {
    let (sw, sh) = (src.width() as i64, src.height() as i64);
    let raw = src.as_raw();
    // Source coordinate of output pixel x: (x + 0.5) / 4 − 0.5, in quarters: x − 1.5 → (x·2 − 3) / 8.
    let taps = |x: i64, n: i64| {
        let q = 2 * x - 3;
        let i0 = q.div_euclid(8);
        let f = q.rem_euclid(8) as u32;
        (i0.clamp(0, n - 1) as usize, (i0 + 1).clamp(0, n - 1) as usize, f)
    };
    let cols: Vec<(usize, usize, u32)> = (0..w as i64).map(|x| taps(x, sw)).collect();
    let mut out = RgbImage::new(w, h);
    for (y, row) in out.as_mut().chunks_exact_mut(w as usize * 3).enumerate() {
        let (r0, r1, fy) = taps(y as i64, sh);
        for (x, px) in row.chunks_exact_mut(3).enumerate() {
            let (c0, c1, fx) = cols[x];
            for c in 0..3 {
                let at = |r: usize, col: usize| raw[(r * sw as usize + col) * 3 + c] as u32;
                let top = at(r0, c0) * (8 - fx) + at(r0, c1) * fx;
                let bot = at(r1, c0) * (8 - fx) + at(r1, c1) * fx;
                px[c] = ((top * (8 - fy) + bot * fy + 32) / 64) as u8;
            }
        }
    }
    out
}

/// The full request image: at image resolution inside the crop windows of the labelled persons
/// (all the server will look at), elsewhere rendered at quarter resolution and upsampled.
pub fn render_frame_image(world: &World, windows: &[CropTransform]) -> RgbImage {
    let cam = &world.camera;
    let (w, h) = (cam.width, cam.height);
    let coarse = render(world, Region { x0: 0, y0: 0, w: w.div_ceil(4), h: h.div_ceil(4), step: 4 }).image;
    let mut img = upsample4(&coarse, w, h);
    for t in windows {
        let side = t.side();
        let (x0, y0) = (t.x0.floor().max(0.0) as i64, t.y0.floor().max(0.0) as i64);
        let x1 = ((t.x0 + side).ceil() as i64 + 1).min(w as i64);
        let y1 = ((t.y0 + side).ceil() as i64 + 1).min(h as i64);
        if x1 > x0 && y1 > y0 {
            let r = render(world, Region { x0, y0, w: (x1 - x0) as u32, h: (y1 - y0) as u32, step: 1 });
            image::imageops::replace(&mut img, &r.image, x0, y0);
        }
    }
    img
}

fn f32x<const N: usize>(v: [f64; N]) -> [f32; N] {
    v.map(|x| x as f32)
}

/// Simulates frame `index`: samples for its labelled persons and, when asked, its request fixture.
pub fn simulate_frame(
    seed: u64,
    index: usize,
    with_fixture: bool,
    cfg: &PipelineConfig,
    points_cap: usize,
    near_px: f64,
    realism: impl Into<Realism>,
) -> Result<FrameResult> {
    let realism = realism.into();
    let mut rng = frame_rng(seed, index);
    let n = persons_in_frame(&mut rng);
    let world = sample_world(&mut rng, n, realism)?;
    let returns: Vec<Return> = scan(&world, realism, &mut rng);
    let mut noise_rng = label_noise_rng(seed, index);
    let points: Vec<[f32; 3]> = returns.iter().map(|r| r.xyz).collect();
    let cam = &world.camera;
    let calib = cam.to_calibration();
    let mut labelled = Vec::new();
    for (li, p) in world.persons.iter().enumerate() {
        let on_person: Vec<V3> = returns
            .iter()
            .filter(|r| r.object == p.object)
            .map(|r| [r.xyz[0] as f64, r.xyz[1] as f64, r.xyz[2] as f64])
            .collect();
        if let Some(mut labels) = label_person(&world, p, &on_person, &mut rng) {
            if realism.has(Effect::LabelNoise) {
                labels = labels.with_3d_noise(p.model.anthro.height, &mut noise_rng);
            }
            labelled.push((li, p, labels, on_person.len()));
        }
    }
    let full = if with_fixture {
        let windows: Vec<CropTransform> = labelled.iter().map(|l| CropTransform::for_box(&l.2.box2d, cfg)).collect();
        let jpeg = encode_jpeg(&render_frame_image(&world, &windows))?;
        Some((planned_crops(&jpeg, &windows, cam.width, cam.height)?, jpeg))
    } else {
        None
    };
    let mut out = FrameResult { index, samples: Vec::new(), stats: Vec::new(), fixture: None };
    let mut fixture_persons = Vec::new();
    for (n, (li, p, labels, on_person)) in labelled.into_iter().enumerate() {
        let prepared = prepare_person(None, Some(cam), &points, &p.box3d, Some(&labels.box2d), cfg);
        let t = CropTransform::for_box(&labels.box2d, cfg);
        let crop = match &full {
            Some((crops, _)) => crops[n].clone(),
            None => render_crop(&world, &t)?,
        };
        let points_uv = prepared.points.model_uv(Some(cam), Some(&t));
        let sample = make_sample(&world, p, &labels, &prepared, &points_uv, &t, crop, cfg, points_cap, index, &calib);
        out.stats.push(sample_stats(&sample, p, &labels, &points_uv, on_person, &t, near_px));
        out.samples.push(sample);
        if with_fixture {
            fixture_persons.push(Person {
                id: format!("p{li}"),
                camera: None,
                box_2d: Some(labels.box2d),
                box_3d: p.box3d,
                ground_truth: Some(GroundTruth {
                    keypoints_3d: Some(Keypoints3d {
                        xyz: labels.xyz_3d.to_vec(),
                        visible: labels.visible_3d.to_vec(),
                        occluded: labels.occluded_3d.to_vec(),
                    }),
                    keypoints_2d: Some(Keypoints2d {
                        uv: labels.uv_true.iter().map(|u| if u[0].is_finite() { *u } else { [0.0, 0.0] }).collect(),
                        visible: labels.visible_2d.to_vec(),
                        occluded: labels.occluded_2d.to_vec(),
                    }),
                }),
            });
        }
    }
    if let Some((_, jpeg)) = full {
        use base64::Engine;
        out.fixture = Some(Frame {
            frame_id: Some(format!("sim-{seed}-{index:06}")),
            image: Some(base64::engine::general_purpose::STANDARD.encode(jpeg)),
            image_rgb: None,
            calibration: Some(calib),
            cameras: Vec::new(),
            points: Points::encode(&points),
            persons: fixture_persons,
            mode: RequestedMode::Auto,
        });
    }
    Ok(out)
}

#[allow(clippy::too_many_arguments)]
fn make_sample(
    world: &World,
    p: &super::world::PlacedPerson,
    labels: &PersonLabels,
    prepared: &posefuse_core::pipeline::PreparedPerson,
    points_uv: &[[f32; 2]],
    t: &CropTransform,
    crop: RgbImage,
    cfg: &PipelineConfig,
    points_cap: usize,
    index: usize,
    calib: &posefuse_core::frame::CameraCalibration,
) -> Sample {
    let bf = &prepared.box_frame;
    let SamplePoints { points_xyz, points_uv, serve_xyz, serve_uv } =
        sample_points(prepared, points_uv, cfg, points_cap);
    let b = &p.box3d;
    Sample {
        image: crop.into_raw(),
        points_xyz,
        points_uv,
        serve_xyz,
        serve_uv,
        kp2d: labels.uv_label.map(|u| f32x(t.to_model(u))),
        kp2d_visible: labels.visible_2d.map(u8::from),
        kp2d_occluded: labels.occluded_2d.map(u8::from),
        kp2d_image_true: labels.uv_true.map(f32x),
        kp3d: labels.xyz_3d.map(|k| f32x(to_local(bf, k, cfg))),
        kp3d_vehicle: labels.xyz_3d.map(f32x),
        kp3d_visible: labels.visible_3d.map(u8::from),
        kp3d_occluded: labels.occluded_3d.map(u8::from),
        box3d: f32x(b.to_row()),
        box2d: f32x([labels.box2d.center_x, labels.box2d.center_y, labels.box2d.width, labels.box2d.height]),
        crop: f32x([t.x0, t.y0, t.scale]),
        intrinsic: std::array::from_fn(|i| calib.intrinsic[i] as f32),
        extrinsic: std::array::from_fn(|i| calib.extrinsic[i] as f32),
        image_size_wh: [world.camera.width as i32, world.camera.height as i32],
        sensor_xyz: f32x(to_local(bf, LIDAR_ORIGIN, cfg)),
        frame_yaw: model_frame(bf, cfg).heading as f32,
        range_m: lidar_range([b.center_x, b.center_y, b.center_z]) as f32,
        frame_index: index as i32,
    }
}

fn sample_stats(
    s: &Sample,
    p: &super::world::PlacedPerson,
    labels: &PersonLabels,
    model_uv: &[[f32; 2]],
    person_points: usize,
    t: &CropTransform,
    near_px: f64,
) -> SampleStats {
    let mut in_image = [false; K];
    let mut near_point = [false; K];
    let (w, h) = (s.image_size_wh[0] as f64, s.image_size_wh[1] as f64);
    for k in 0..K {
        let u = labels.uv_true[k];
        in_image[k] = u[0].is_finite() && u[0] >= 0.0 && u[1] >= 0.0 && u[0] < w && u[1] < h;
        let m = t.to_model(u);
        near_point[k] = model_uv.iter().any(|q| {
            let (dx, dy) = (q[0] as f64 - m[0], q[1] as f64 - m[1]);
            dx * dx + dy * dy <= near_px * near_px
        });
    }
    SampleStats {
        range_m: s.range_m as f64,
        activity: p.model.activity.name(),
        in_box_points: model_uv.len(),
        person_points,
        in_image,
        visible_2d: labels.visible_2d,
        near_point,
    }
}
