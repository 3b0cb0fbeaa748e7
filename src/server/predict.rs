//! Frame → poses: the one path shared by HTTP, gRPC, `posefuse predict` and `posefuse eval`.
//! Pre-processing is exactly the pipeline's (`prepare_person`, `crop_rgb`, `normalize`,
//! `smoothed_features` (smoothing + sampling), `fused_points`, `decode_heatmaps`, `lift`,
//! `keypoints_to_vehicle`, `keypoints_to_pixels`); this file only decides the mode and moves data.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::api::{KeypointPose, Mode, ModelRef, PersonPose, PoseResponse, SkippedPerson, Timings};
use crate::error::{Error, Result};
use crate::frame::{Box2d, Box3d, Frame, RequestedMode, RgbPixels};
use crate::geometry::{box2d_from_points, BoxFrame, Camera};
use crate::image_decode::{self, CameraImage};
use crate::keypoints::{K, NAMES, WAYMO_TYPES};
use crate::pipeline::{
    decode_heatmaps, fused_points, keypoints_to_pixels, keypoints_to_vehicle, lidar_points, lift, normalize,
    plan_decode, prepare_person, smoothed_features, CropTransform, PipelineConfig, PointInput,
};
use crate::runtime::{Bundle, ChainStep, JobOutput, ModelKind, Runtime};

/// Runs frames through the pipeline and the runtime.
#[derive(Clone)]
pub struct Predictor {
    runtime: Arc<Runtime>,
}

/// Everything decided before inference for one person.
struct PersonPlan {
    id: String,
    mode: Mode,
    reason: String,
    box_frame: BoxFrame,
    box_2d: Option<Box2d>,
    num_points: usize,
    input: PointInput,
    /// Normalized crop `[3, S, S]` when the camera network runs.
    image_input: Option<Vec<f32>>,
}

struct FramePlan {
    camera: Camera,
    persons: Vec<PersonPlan>,
    /// Persons no model can answer (their data, not the request, is lacking).
    skipped: Vec<SkippedPerson>,
    decode: Duration,
    preprocess: Duration,
}

#[derive(Default)]
struct PersonTimes {
    queue: Duration,
    inference: Duration,
    preprocess: Duration,
}

impl PersonTimes {
    fn add(&mut self, out: &JobOutput) {
        self.queue += out.queue;
        self.inference += out.inference;
        self.preprocess += out.between;
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

impl Predictor {
    /// A predictor over a started runtime.
    pub fn new(runtime: Arc<Runtime>) -> Predictor {
        Predictor { runtime }
    }

    /// The bundle the runtime serves.
    pub fn bundle(&self) -> &Bundle {
        self.runtime.bundle()
    }

    /// The runtime (readiness, pausing).
    pub fn runtime(&self) -> &Arc<Runtime> {
        &self.runtime
    }

    /// Poses for every person of `frame`. `raw_image` (JPEG/PNG bytes, as gRPC sends them)
    /// replaces `frame.image` (base64) when given.
    pub async fn predict(&self, frame: Frame, raw_image: Option<Vec<u8>>) -> Result<PoseResponse> {
        let started = Instant::now();
        if !self.runtime.is_ready() {
            return Err(Error::Unavailable("the models are warming up".into()));
        }
        let bundle = self.runtime.bundle().clone();
        // Decoding and cropping are CPU work; keep them off the async executor.
        let plan = tokio::task::spawn_blocking(move || {
            let cfg = bundle.config();
            let mut frame = frame;
            let pixels = frame.image_rgb.take();
            plan_frame(&frame, raw_image, pixels, cfg).map(|p| (p, frame.frame_id))
        })
        .await
        .map_err(|e| Error::Runtime(format!("pre-processing task failed: {e}")))?;
        let (plan, frame_id) = plan?;
        let camera = &plan.camera;
        let results =
            futures::future::try_join_all(plan.persons.into_iter().map(|p| self.run_person(p, camera))).await?;
        let mut timings =
            Timings { decode_ms: ms(plan.decode), preprocess_ms: ms(plan.preprocess), ..Timings::default() };
        let mut persons = Vec::with_capacity(results.len());
        let (mut queue, mut inference, mut post) = (Duration::ZERO, Duration::ZERO, Duration::ZERO);
        for (pose, t) in results {
            // Persons run concurrently: the slowest one is the request's time.
            queue = queue.max(t.queue);
            inference = inference.max(t.inference);
            post = post.max(t.preprocess);
            metrics::counter!("posefuse_persons_total", "mode" => pose.mode.as_str()).increment(1);
            persons.push(pose);
        }
        timings.queue_ms = ms(queue);
        timings.inference_ms = ms(inference);
        timings.preprocess_ms += ms(post);
        timings.total_ms = ms(started.elapsed());
        metrics::histogram!("posefuse_preprocess_seconds").record(plan.preprocess.as_secs_f64() + post.as_secs_f64());
        metrics::histogram!("posefuse_decode_seconds").record(plan.decode.as_secs_f64());
        let m = &self.runtime.bundle().manifest;
        Ok(PoseResponse {
            frame_id,
            model: ModelRef { name: m.name.clone(), version: m.version.clone() },
            persons,
            skipped: plan.skipped,
            timings,
        })
    }

    /// [`Predictor::predict`] with a deadline.
    pub async fn predict_within(
        &self,
        frame: Frame,
        raw_image: Option<Vec<u8>>,
        timeout: Duration,
    ) -> Result<PoseResponse> {
        match tokio::time::timeout(timeout, self.predict(frame, raw_image)).await {
            Ok(r) => r,
            Err(_) => Err(Error::Timeout(timeout.as_millis() as u64)),
        }
    }

    async fn run_person(&self, p: PersonPlan, camera: &Camera) -> Result<(PersonPose, PersonTimes)> {
        let cfg = self.runtime.bundle().config();
        let (s, hm) = (cfg.image_size, cfg.heatmap_size as usize);
        let mut times = PersonTimes::default();
        let PersonPlan { id, mode, reason, box_frame, box_2d, num_points, input, image_input } = p;
        let need_crop = || Error::Runtime(format!("{id}: camera input missing"));
        let (local, scores): (Vec<[f32; 3]>, Option<Vec<f32>>) = match mode {
            Mode::Fusion => {
                let x = image_input.ok_or_else(need_crop)?;
                let chain_cfg = cfg.clone();
                let PointInput { xyz, uv, .. } = input;
                // runs on the inference worker, between the two networks
                let then: ChainStep =
                    Box::new(move |h: &[f32]| fused_points(&xyz, &smoothed_features(h, K, hm, hm, &uv, &chain_cfg), K));
                let out = self.runtime.infer_chain(x, ModelKind::PointFusion, then).await?;
                times.add(&out);
                let h = out.camera.as_deref().ok_or_else(|| Error::Runtime(format!("{id}: heatmaps missing")))?;
                let t0 = Instant::now();
                let scores = decode_heatmaps(h, K, hm, hm, s).into_iter().map(|(_, v)| v).collect();
                times.preprocess += t0.elapsed();
                (triples(&out.data), Some(scores))
            }
            Mode::Lidar => {
                let out = self.runtime.infer(ModelKind::PointLidar, lidar_points(&input.xyz)).await?;
                times.add(&out);
                (triples(&out.data), None)
            }
            Mode::Camera => {
                let x = image_input.ok_or_else(need_crop)?;
                let out = self.runtime.infer(ModelKind::Camera, x).await?;
                times.add(&out);
                let t0 = Instant::now();
                let decoded = decode_heatmaps(&out.data, K, hm, hm, s);
                let kp_uv: Vec<[f32; 2]> = decoded.iter().map(|d| d.0).collect();
                let lifted = lift(&kp_uv, &input.uv, &input.xyz, s, cfg.lift_temperature);
                times.preprocess += t0.elapsed();
                (lifted, Some(decoded.into_iter().map(|d| d.1).collect()))
            }
        };
        if let Some(k) = local.iter().position(|q| q.iter().any(|v| !v.is_finite())) {
            return Err(Error::Runtime(format!("{id}: keypoint {} is not finite", NAMES[k])));
        }
        let vehicle = keypoints_to_vehicle(&local, &box_frame, cfg);
        let pixels = keypoints_to_pixels(&vehicle, camera);
        let keypoints = (0..K)
            .map(|k| KeypointPose {
                name: NAMES[k].to_string(),
                waymo_type: WAYMO_TYPES[k],
                xyz: vehicle[k],
                uv: pixels[k],
                score: scores.as_ref().map(|s| s[k]),
            })
            .collect();
        let pose = PersonPose { id, mode, mode_reason: reason, num_points, box_2d, keypoints };
        Ok((pose, times))
    }
}

fn triples(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Whether a 2D box overlaps the image at all.
fn overlaps_image(b: &Box2d, width: u32, height: u32) -> bool {
    let (x0, x1) = (b.center_x - b.width / 2.0, b.center_x + b.width / 2.0);
    let (y0, y1) = (b.center_y - b.height / 2.0, b.center_y + b.height / 2.0);
    x1 > 0.0 && y1 > 0.0 && x0 < width as f64 && y0 < height as f64
}

/// The 2D box of the projected 3D box corners, when the whole box is in front of the camera and
/// overlaps the image.
pub fn projected_box(camera: &Camera, b: &Box3d) -> Option<Box2d> {
    let mut uv = Vec::with_capacity(8);
    for c in BoxFrame::new(b).corners() {
        let p = camera.project(c);
        if !p.in_front {
            return None;
        }
        uv.push(p.uv);
    }
    box2d_from_points(uv)
        .filter(|bb| bb.width > 0.0 && bb.height > 0.0 && overlaps_image(bb, camera.width, camera.height))
}

/// Persons per frame: each one scans every point of the frame, so the work is bounded here.
pub const MAX_PERSONS: usize = 256;

/// A 2D box may extend past the image (a person close to the camera) but not without bound: the
/// crop allocates its full side.
const MAX_BOX_IMAGE_RATIO: f64 = 2.0;

fn check_box_size(b: &Box2d, field: &str, width: u32, height: u32) -> Result<()> {
    if b.width > MAX_BOX_IMAGE_RATIO * width as f64 || b.height > MAX_BOX_IMAGE_RATIO * height as f64 {
        return Err(Error::field(
            field,
            format!("{}x{} px is more than {MAX_BOX_IMAGE_RATIO} times the {width}x{height} image", b.width, b.height),
        ));
    }
    Ok(())
}

/// The part of a box inside the image (for derived boxes of persons close to the camera).
fn clip_to_image(b: Box2d, width: u32, height: u32) -> Box2d {
    let x0 = (b.center_x - b.width / 2.0).max(0.0);
    let x1 = (b.center_x + b.width / 2.0).min(width as f64);
    let y0 = (b.center_y - b.height / 2.0).max(0.0);
    let y1 = (b.center_y + b.height / 2.0).min(height as f64);
    Box2d { center_x: (x0 + x1) / 2.0, center_y: (y0 + y1) / 2.0, width: x1 - x0, height: y1 - y0 }
}

fn plan_frame(
    frame: &Frame,
    raw_image: Option<Vec<u8>>,
    pixels: Option<RgbPixels>,
    cfg: &PipelineConfig,
) -> Result<FramePlan> {
    frame.validate()?;
    if frame.persons.len() > MAX_PERSONS {
        return Err(Error::field(
            "persons",
            format!("{} persons; at most {MAX_PERSONS} per frame", frame.persons.len()),
        ));
    }
    let camera = Camera::from_calibration(&frame.calibration)?;
    let t0 = Instant::now();
    let points = frame.points.decode()?;
    if points.is_empty() {
        return Err(Error::field("points", "no LiDAR points: every mode needs the points of the persons' boxes"));
    }
    // the header only: the pixels are decoded once the crops are known
    let image = image_decode::open(frame, raw_image, pixels)?;
    let mut decode = t0.elapsed();
    let t1 = Instant::now();
    let mut persons = Vec::with_capacity(frame.persons.len());
    let mut crops: Vec<Option<CropTransform>> = Vec::with_capacity(frame.persons.len());
    // every person's window, whatever its mode: the simulator plans its fixtures' decodes from
    // all of them, so a crop is cut from the same decode in training and in serving
    let mut windows = Vec::with_capacity(frame.persons.len());
    let mut skipped = Vec::new();
    let mut skip = |index: usize, id: &str, e: Error| {
        metrics::counter!("posefuse_persons_skipped_total").increment(1);
        skipped.push(SkippedPerson { index, id: id.to_string(), error: super::errors::detail(&e) });
    };
    for (i, person) in frame.persons.iter().enumerate() {
        let field = format!("persons[{i}]");
        let box_2d = match &person.box_2d {
            Some(b) => {
                if !overlaps_image(b, camera.width, camera.height) {
                    return Err(Error::field(
                        format!("{field}.box_2d"),
                        format!("lies entirely outside the {}x{} image", camera.width, camera.height),
                    ));
                }
                check_box_size(b, &format!("{field}.box_2d"), camera.width, camera.height)?;
                Some(*b)
            }
            None => projected_box(&camera, &person.box_3d).map(|b| {
                let (w, h) = (camera.width, camera.height);
                if check_box_size(&b, "", w, h).is_ok() {
                    b
                } else {
                    clip_to_image(b, w, h)
                }
            }),
        };
        let prepared = prepare_person(None, Some(&camera), &points, &person.box_3d, box_2d.as_ref(), cfg);
        windows.extend(prepared.crop);
        let num_points = prepared.points.len();
        let Some(input) = prepared.input else {
            let why = format!("no LiDAR point lies inside the box (grown by {} m on every side)", cfg.box_margin);
            skip(i, &person.id, Error::InsufficientData { field: format!("{field}.box_3d"), message: why });
            continue;
        };
        let camera_problem: Option<(String, String)> = match (&image, box_2d) {
            (CameraImage::Absent, _) => Some(("image".into(), "no image in the request".into())),
            (CameraImage::Undecodable(m), _) => Some(("image".into(), m.clone())),
            (_, None) => Some((
                format!("{field}.box_2d"),
                "no 2D box given and the projected 3D box is outside the camera view".into(),
            )),
            (_, Some(_)) => None,
        };
        let min = cfg.min_points as usize;
        let (mode, reason) = match (frame.mode, &camera_problem) {
            (RequestedMode::Auto, None) if num_points >= min => {
                (Mode::Fusion, format!("camera and LiDAR usable ({num_points} points in the box)"))
            }
            (RequestedMode::Auto, None) => (
                Mode::Camera,
                format!("only {num_points} points in the box (fewer than {min}): camera keypoints lifted onto them"),
            ),
            (RequestedMode::Auto, Some((_, why))) => (Mode::Lidar, format!("camera unusable: {why}")),
            (RequestedMode::Lidar, _) => (Mode::Lidar, "requested".into()),
            (RequestedMode::Fusion | RequestedMode::Camera, Some((f, why))) => {
                return Err(Error::field(f.clone(), format!("mode {:?} needs the camera: {why}", frame.mode)));
            }
            (RequestedMode::Fusion, None) => (Mode::Fusion, "requested".into()),
            (RequestedMode::Camera, None) => (Mode::Camera, "requested".into()),
        };
        if mode == Mode::Camera && !input.uv.iter().any(|uv| uv[0].is_finite() && uv[1].is_finite()) {
            let why = "camera-only lifting needs points in front of the camera; none of the box's points are";
            skip(i, &person.id, Error::InsufficientData { field: format!("{field}.box_3d"), message: why.into() });
            continue;
        }
        let crop = match (mode, image.usable(), prepared.crop) {
            (Mode::Fusion | Mode::Camera, true, Some(t)) => Some(t),
            (Mode::Fusion | Mode::Camera, _, _) => {
                return Err(Error::Runtime(format!("{field}: camera mode chosen without a crop")));
            }
            (Mode::Lidar, _, _) => None,
        };
        crops.push(crop);
        persons.push(PersonPlan {
            id: person.id.clone(),
            mode,
            reason,
            box_frame: prepared.box_frame,
            box_2d,
            num_points,
            input,
            image_input: None,
        });
    }
    // Decode only what the crops need (`pipeline::plan_decode`), then cut them.
    let mut decode_pixels = Duration::ZERO;
    if crops.iter().any(Option::is_some) {
        let t2 = Instant::now();
        let decoded = image_decode::decode(image, &plan_decode(&windows, camera.width, camera.height));
        decode_pixels = t2.elapsed();
        match decoded {
            Ok(img) => {
                for (p, t) in persons.iter_mut().zip(&crops) {
                    p.image_input = t.map(|t| normalize(&img.crop(&t), cfg));
                }
            }
            // the header was sound but the pixels are not
            Err(why) if frame.mode == RequestedMode::Auto => {
                for (p, t) in persons.iter_mut().zip(&crops) {
                    if t.is_some() {
                        (p.mode, p.reason) = (Mode::Lidar, format!("camera unusable: {why}"));
                    }
                }
            }
            Err(why) => {
                return Err(Error::field("image", format!("mode {:?} needs the camera: {why}", frame.mode)));
            }
        }
    }
    decode += decode_pixels;
    Ok(FramePlan { camera, persons, skipped, decode, preprocess: t1.elapsed().saturating_sub(decode_pixels) })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::CameraCalibration;

    /// A forward-looking camera at the origin: camera frame = vehicle frame.
    fn camera() -> Camera {
        let mut ext = vec![0.0; 16];
        for i in 0..4 {
            ext[i * 5] = 1.0;
        }
        Camera::from_calibration(&CameraCalibration {
            intrinsic: vec![100.0, 100.0, 50.0, 40.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            extrinsic: ext,
            width: 100,
            height: 80,
        })
        .unwrap()
    }

    fn b3(x: f64, y: f64) -> Box3d {
        Box3d { center_x: x, center_y: y, center_z: 0.0, length: 1.0, width: 1.0, height: 2.0, heading: 0.0 }
    }

    #[test]
    fn projected_box_of_a_box_straight_ahead() {
        // Corners at x = 9.5 (near face) project to u = 50 ± 100·0.5/9.5, v = 40 ± 100·1/9.5.
        let b = projected_box(&camera(), &b3(10.0, 0.0)).unwrap();
        assert!((b.center_x - 50.0).abs() < 1e-9 && (b.center_y - 40.0).abs() < 1e-9);
        assert!((b.width - 100.0 / 9.5).abs() < 1e-9 && (b.height - 200.0 / 9.5).abs() < 1e-9);
    }

    #[test]
    fn boxes_behind_or_beside_the_camera_have_no_projection() {
        assert!(projected_box(&camera(), &b3(-10.0, 0.0)).is_none());
        // Far to the left: u = 50 - 100·20/10 < 0 for every corner.
        assert!(projected_box(&camera(), &b3(10.0, 20.0)).is_none());
        // Straddling the image plane (a corner behind the camera).
        assert!(projected_box(&camera(), &b3(0.2, 0.0)).is_none());
    }

    #[test]
    fn oversized_boxes_are_refused_or_clipped() {
        let b = Box2d { center_x: 50.0, center_y: 40.0, width: 201.0, height: 10.0 };
        let e = check_box_size(&b, "persons[0].box_2d", 100, 80).unwrap_err();
        assert_eq!(e.field_name(), Some("persons[0].box_2d"));
        assert!(check_box_size(&Box2d { width: 200.0, ..b }, "f", 100, 80).is_ok());
        let c = clip_to_image(Box2d { center_x: 90.0, center_y: 40.0, width: 40.0, height: 200.0 }, 100, 80);
        assert_eq!((c.center_x, c.center_y, c.width, c.height), (85.0, 40.0, 30.0, 80.0));
    }

    #[test]
    fn overlap_with_the_image() {
        let b = |cx, cy| Box2d { center_x: cx, center_y: cy, width: 10.0, height: 10.0 };
        assert!(overlaps_image(&b(50.0, 40.0), 100, 80));
        assert!(overlaps_image(&b(-4.0, 40.0), 100, 80));
        assert!(!overlaps_image(&b(-5.0, 40.0), 100, 80));
        assert!(!overlaps_image(&b(50.0, 85.0), 100, 80));
    }
}
