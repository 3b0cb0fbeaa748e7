//! Frame → poses: the one path shared by HTTP, gRPC, `posefuse predict` and `posefuse eval`.
//! Pre-processing is exactly the pipeline's (`prepare_person`, `crop_rgb`, `normalize`,
//! `smoothed_features` (smoothing + sampling), `fused_points`, `decode_heatmaps`, `lift`,
//! `keypoints_to_vehicle`, `Camera::project_points`); this file only decides the mode and moves data.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use super::admission::{Admission, Ticket};
use super::api::{
    BatchItem, ErrorDetail, KeypointPose, Mode, ModelRef, PersonPose, PoseResponse, SkippedPerson, Timings,
};
use super::cameras::FrameCameras;
use super::heading_stage::Refine;
use super::policy::choose_mode;
use crate::runtime::{Bundle, ChainStep, JobOutput, ModelKind, Runtime};
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Box2d, Frame, RgbPixels};
use posefuse_core::geometry::{clip_to_image, overlaps_image, projected_box, BoxFrame, Camera};
use posefuse_core::image_decode::{self, CameraImage, RawImages};
use posefuse_core::keypoints::{K, NAMES, WAYMO_TYPES};
use posefuse_core::pipeline::{
    decode_heatmaps, facing, fused_points, keypoints_to_vehicle, lidar_points, lift, normalize, prepare_person,
    smoothed_features, turn_points, yaw_difference, CropTransform, PipelineConfig, PointFrame, PointInput,
};

/// Runs frames through the pipeline and the runtime. The runtime can be swapped while serving
/// ([`Predictor::swap`]); a request keeps the runtime it started on.
#[derive(Clone)]
pub struct Predictor {
    runtime: Arc<RwLock<Arc<Runtime>>>,
    admission: Arc<Admission>,
    limits: super::limits::FrameLimits,
    /// A bundle that needs no heading, asked first for the persons' facing (docs/BUNDLE.md,
    /// "Heading stage"), and how far (degrees) a box heading may be from its facing to be kept.
    heading_stage: Option<(Arc<Runtime>, f64)>,
    /// Passes asking the point network again at the facing it predicted.
    refine: Refine,
}

/// Everything decided before inference for one person.
struct PersonPlan {
    id: String,
    /// Index of the camera the person uses (its `box_2d`, crop and keypoint pixels).
    camera: Option<usize>,
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
    cameras: Vec<Camera>,
    /// The cameras' names as responses give them (`None`: the single-camera form).
    names: Vec<Option<String>>,
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
    /// A predictor over a started runtime, with unbounded admission.
    pub fn new(runtime: Arc<Runtime>) -> Predictor {
        Predictor::with_admission(runtime, Admission::unbounded())
    }

    /// A predictor whose pre-processing is admitted through `admission`.
    pub fn with_admission(runtime: Arc<Runtime>, admission: Arc<Admission>) -> Predictor {
        Predictor {
            runtime: Arc::new(RwLock::new(runtime)),
            admission,
            limits: Default::default(),
            heading_stage: None,
            refine: Refine::OFF,
        }
    }

    /// The same predictor with `stage` answering first; its facings replace the box headings that
    /// disagree with them by more than `agree_deg` ([`super::heading_stage::with_estimated_headings`]).
    pub fn with_heading_stage(mut self, stage: Arc<Runtime>, agree_deg: f64) -> Predictor {
        self.heading_stage = Some((stage, agree_deg));
        self
    }

    /// The same predictor refining each box-frame answer's heading as `refine` says
    /// ([`Refine`]; bundles whose point frame does not turn with the box ignore it).
    pub fn with_refine(mut self, refine: Refine) -> Predictor {
        self.refine = refine;
        self
    }

    /// The heading stage's runtime, when there is one.
    pub fn heading_stage(&self) -> Option<&Arc<Runtime>> {
        self.heading_stage.as_ref().map(|(s, _)| s)
    }

    /// The same predictor with other per-frame limits.
    pub fn with_limits(mut self, limits: super::limits::FrameLimits) -> Predictor {
        self.limits = limits;
        self
    }

    /// The bundle the runtime serves now.
    pub fn bundle(&self) -> Arc<Bundle> {
        self.runtime().bundle().clone()
    }

    /// The runtime serving now (readiness, pausing).
    pub fn runtime(&self) -> Arc<Runtime> {
        self.runtime.read().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Serves new requests on `runtime` from now on and returns the previous one (requests that
    /// started on it finish on it).
    pub fn swap(&self, runtime: Arc<Runtime>) -> Arc<Runtime> {
        std::mem::replace(&mut *self.runtime.write().unwrap_or_else(|p| p.into_inner()), runtime)
    }

    /// The admission gate in front of pre-processing.
    pub fn admission(&self) -> &Arc<Admission> {
        &self.admission
    }

    /// Poses for every person of `frame`. `raw_images` (JPEG/PNG bytes, as gRPC sends them, in
    /// camera order) replace the frame's base64 images when given. Dropping the future (deadline,
    /// client gone) stops the frame's pre-processing at its next step and queues nothing more.
    pub async fn predict(&self, frame: Frame, raw_images: Option<RawImages>) -> Result<PoseResponse> {
        let ticket = self.admission.admit()?;
        self.predict_admitted(&ticket, frame, raw_images).await
    }

    /// [`Predictor::predict`] for a frame admitted before its body was read.
    pub async fn predict_admitted(
        &self,
        ticket: &Ticket,
        frame: Frame,
        raw_images: Option<RawImages>,
    ) -> Result<PoseResponse> {
        let runtime = self.runtime();
        let frame = match &self.heading_stage {
            Some((stage, agree_deg)) => {
                let first = self.predict_on(stage.clone(), ticket, frame.clone(), raw_images.clone()).await?;
                super::heading_stage::with_estimated_headings(frame, &first, *agree_deg)
            }
            None => frame,
        };
        self.predict_on(runtime, ticket, frame, raw_images).await
    }

    /// One pass of a frame through `runtime`'s bundle.
    async fn predict_on(
        &self,
        runtime: Arc<Runtime>,
        ticket: &Ticket,
        frame: Frame,
        raw_images: Option<RawImages>,
    ) -> Result<PoseResponse> {
        let started = Instant::now();
        if !runtime.is_ready() {
            return Err(Error::Unavailable("the models are warming up".into()));
        }
        let bundle = runtime.bundle().clone();
        // A decode permit before any decoding (admission bounds how many wait for one).
        let permit = self.admission.enter(ticket).await?;
        let abandoned = Arc::new(AtomicBool::new(false));
        let _abandon_on_drop = AbandonOnDrop(abandoned.clone());
        let limits = self.limits;
        // Decoding and cropping are CPU work; keep them off the async executor.
        let plan = tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let cfg = bundle.config();
            limits.check(&frame)?;
            let mut frame = frame;
            let pixels = frame.take_pixels();
            plan_frame(&frame, raw_images, pixels, cfg, &abandoned).map(|p| (p, frame.frame_id))
        })
        .await
        .map_err(|e| Error::Runtime(format!("pre-processing task failed: {e}")))?;
        let (plan, frame_id) = plan?;
        let refine =
            if runtime.bundle().config().point_frame() == PointFrame::BoxHeading { self.refine } else { Refine::OFF };
        let on = OnRuntime { runtime: &runtime, cameras: &plan.cameras, names: &plan.names, refine };
        let results = futures::future::try_join_all(plan.persons.into_iter().map(|p| on.run_person(p))).await?;
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
        let m = &runtime.bundle().manifest;
        Ok(PoseResponse {
            frame_id,
            model: ModelRef { name: m.name.clone(), version: m.version.clone() },
            persons,
            skipped: plan.skipped,
            timings,
        })
    }

    /// Admits the frame, then [`Predictor::answer_admitted`]: for callers that hold the frame
    /// already (the command line, tools, tests). The server admits before it reads a body.
    pub async fn answer(&self, frame: Frame, raw_images: Option<RawImages>, timeout: Duration) -> Result<PoseResponse> {
        let ticket = self.admission.admit()?;
        self.answer_admitted(&ticket, frame, raw_images, timeout).await
    }

    /// The ticket a request was admitted with before its body was read (the server's early
    /// admission), or one taken now: every transport calls this before it parses a frame.
    pub fn admitted(&self, early: Option<Arc<Ticket>>) -> Result<Arc<Ticket>> {
        match early {
            Some(ticket) => Ok(ticket),
            None => self.admission.admit().map(Arc::new),
        }
    }

    /// [`Predictor::predict_admitted`] with a deadline, counted in the metrics.
    pub async fn answer_admitted(
        &self,
        ticket: &Ticket,
        frame: Frame,
        raw_images: Option<RawImages>,
        timeout: Duration,
    ) -> Result<PoseResponse> {
        let t0 = Instant::now();
        let r = match tokio::time::timeout(timeout, self.predict_admitted(ticket, frame, raw_images)).await {
            Ok(r) => r,
            Err(_) => Err(Error::Timeout(timeout.as_millis() as u64)),
        };
        let outcome = r.as_ref().map_or_else(Error::code, |_| "ok");
        metrics::counter!("posefuse_frames_total", "outcome" => outcome).increment(1);
        metrics::histogram!("posefuse_request_seconds").record(t0.elapsed().as_secs_f64());
        r
    }

    /// One item of a batch or stream: admitted, then `parse`d (nothing is parsed for a frame the
    /// server has no room for), then answered.
    pub async fn answer_item(
        &self,
        index: usize,
        parse: impl std::future::Future<Output = Result<Frame>>,
        timeout: Duration,
    ) -> BatchItem {
        let answer = async {
            let ticket = self.admission.admit()?;
            let frame = parse.await?;
            self.answer_admitted(&ticket, frame, None, timeout).await
        };
        BatchItem::new(index, answer.await)
    }
}

/// Marks a frame's pre-processing abandoned when its request future is dropped.
struct AbandonOnDrop(Arc<AtomicBool>);

impl Drop for AbandonOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

/// Stops a frame's pre-processing once nobody waits for it.
fn still_wanted(abandoned: &AtomicBool) -> Result<()> {
    if abandoned.load(Ordering::Relaxed) {
        metrics::counter!("posefuse_frames_abandoned_total").increment(1);
        return Err(Error::Unavailable("the request was abandoned (deadline passed or client gone)".into()));
    }
    Ok(())
}

/// A request's view of the runtime it started on.
struct OnRuntime<'a> {
    runtime: &'a Runtime,
    cameras: &'a [Camera],
    names: &'a [Option<String>],
    refine: Refine,
}

impl OnRuntime<'_> {
    async fn run_person(&self, p: PersonPlan) -> Result<(PersonPose, PersonTimes)> {
        let cfg = self.runtime.bundle().config();
        let (s, hm) = (cfg.image_size, cfg.heatmap_size as usize);
        let mut times = PersonTimes::default();
        let PersonPlan { id, camera, mode, reason, mut box_frame, box_2d, num_points, input, image_input } = p;
        let need_crop = || Error::Runtime(format!("{id}: camera input missing"));
        let (local, scores): (Vec<[f32; 3]>, Option<Vec<f32>>) = match mode {
            Mode::Fusion => {
                let x = image_input.ok_or_else(need_crop)?;
                let chain_cfg = cfg.clone();
                let kept = (self.refine.passes > 0).then(|| (input.xyz.clone(), input.uv.clone()));
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
                let mut local = triples(&out.data);
                if let Some((xyz, uv)) = &kept {
                    let ask = Ask { xyz, camera: Some((h, uv)), given: box_frame.heading, cfg };
                    (local, box_frame) = self.refine_heading(&ask, local, box_frame, &mut times).await?;
                }
                (local, Some(scores))
            }
            Mode::Lidar => {
                let out = self.runtime.infer(ModelKind::PointLidar, lidar_points(&input.xyz)).await?;
                times.add(&out);
                let ask = Ask { xyz: &input.xyz, camera: None, given: box_frame.heading, cfg };
                let local = triples(&out.data);
                let (local, frame) = self.refine_heading(&ask, local, box_frame, &mut times).await?;
                box_frame = frame;
                (local, None)
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
        let pixels = match camera.and_then(|c| self.cameras.get(c)) {
            Some(cam) => cam.project_points(&vehicle),
            None => vec![None; K],
        };
        let camera = camera.and_then(|c| self.names.get(c).cloned().flatten());
        let keypoints = (0..K)
            .map(|k| KeypointPose {
                name: NAMES[k].to_string(),
                waymo_type: WAYMO_TYPES[k],
                xyz: vehicle[k],
                uv: pixels[k],
                score: scores.as_ref().map(|s| s[k]),
            })
            .collect();
        let facing = facing(&vehicle);
        let pose = PersonPose { id, camera, mode, mode_reason: reason, num_points, box_2d, keypoints, facing };
        Ok((pose, times))
    }
}

/// A person's points as the point network was first asked about them.
struct Ask<'a> {
    /// Model-input points in the frame of the box as given.
    xyz: &'a [[f32; 3]],
    /// The camera's heatmaps and the points' model-input pixels (fusion), or none (LiDAR-only).
    camera: Option<(&'a [f32], &'a [[f32; 2]])>,
    /// The heading the box was given with.
    given: f64,
    cfg: &'a PipelineConfig,
}

impl OnRuntime<'_> {
    /// `local` (the answer in `frame`) refined as [`Refine`] says: while the facing it predicts is
    /// more than `settle_deg` from the heading it was asked at, ask again at that facing.
    async fn refine_heading(
        &self,
        ask: &Ask<'_>,
        mut local: Vec<[f32; 3]>,
        mut frame: BoxFrame,
        times: &mut PersonTimes,
    ) -> Result<(Vec<[f32; 3]>, BoxFrame)> {
        // the points' camera features, sampled again only once a second pass is needed
        let mut features: Option<Vec<f32>> = None;
        for _ in 0..self.refine.passes {
            let Some(f) = facing(&keypoints_to_vehicle(&local, &frame, ask.cfg)) else { break };
            if yaw_difference(f.yaw, frame.heading).to_degrees() <= self.refine.settle_deg {
                break;
            }
            let turned = turn_points(ask.xyz, ask.given, f.yaw);
            let (kind, input) = match ask.camera {
                Some((heatmaps, uv)) => {
                    let hm = ask.cfg.heatmap_size as usize;
                    let f = features.get_or_insert_with(|| smoothed_features(heatmaps, K, hm, hm, uv, ask.cfg));
                    (ModelKind::PointFusion, fused_points(&turned, f, K))
                }
                None => (ModelKind::PointLidar, lidar_points(&turned)),
            };
            let out = self.runtime.infer(kind, input).await?;
            times.add(&out);
            local = triples(&out.data);
            frame = frame.turned_to(f.yaw);
        }
        Ok((local, frame))
    }
}

fn triples(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Persons per frame by default: each one scans every point of the frame, so the work is
/// bounded here (`--max-persons`).
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

fn plan_frame(
    frame: &Frame,
    raw_images: Option<RawImages>,
    pixels: Vec<Option<RgbPixels>>,
    cfg: &PipelineConfig,
    abandoned: &AtomicBool,
) -> Result<FramePlan> {
    frame.validate()?;
    super::limits::check_declared_sizes(frame)?;
    let mut cams = FrameCameras::new(frame, raw_images, pixels)?;
    let t0 = Instant::now();
    let points = frame.points.decode()?;
    if points.is_empty() {
        return Err(Error::field("points", "no LiDAR points: every mode needs the points of the persons' boxes"));
    }
    still_wanted(abandoned)?;
    // each person's camera, then the headers of the images someone uses (their sizes checked
    // against the calibrations): the pixels are decoded once the crops are known
    let chosen: Vec<Option<usize>> = frame.persons.iter().map(|p| cams.choose(p)).collect();
    let mut images = cams.open_used(&chosen)?;
    let mut decode = t0.elapsed();
    let t1 = Instant::now();
    let mut persons = Vec::with_capacity(frame.persons.len());
    let mut crops: Vec<Option<CropTransform>> = Vec::with_capacity(frame.persons.len());
    let mut crop_budgets: Vec<_> =
        cams.cameras.iter().map(|c| super::limits::CropBudget::for_image(c.width, c.height)).collect();
    let mut skipped = Vec::new();
    let mut skip = |index: usize, id: &str, e: Error| {
        metrics::counter!("posefuse_persons_skipped_total").increment(1);
        skipped.push(SkippedPerson { index, id: id.to_string(), error: ErrorDetail::from(&e) });
    };
    for (i, (person, &cam)) in frame.persons.iter().zip(&chosen).enumerate() {
        still_wanted(abandoned)?;
        let field = format!("persons[{i}]");
        let camera = cam.and_then(|c| cams.cameras.get(c));
        let box_2d = match (&person.box_2d, camera) {
            (Some(b), Some(camera)) => {
                if !overlaps_image(b, camera.width, camera.height) {
                    return Err(Error::field(
                        format!("{field}.box_2d"),
                        format!("lies entirely outside the {}x{} image", camera.width, camera.height),
                    ));
                }
                check_box_size(b, &format!("{field}.box_2d"), camera.width, camera.height)?;
                Some(*b)
            }
            (None, Some(camera)) => projected_box(camera, &person.box_3d).map(|b| {
                let (w, h) = (camera.width, camera.height);
                if check_box_size(&b, "", w, h).is_ok() {
                    b
                } else {
                    clip_to_image(b, w, h)
                }
            }),
            // a box of a camera the person does not name (validation refuses it)
            (_, None) => None,
        };
        let prepared = prepare_person(None, camera, &points, &person.box_3d, box_2d.as_ref(), cfg);
        let num_points = prepared.points.len();
        let Some(input) = prepared.input else {
            let why = format!("no LiDAR point lies inside the box (grown by {} m on every side)", cfg.box_margin);
            skip(i, &person.id, Error::InsufficientData { field: format!("{field}.box_3d"), message: why });
            continue;
        };
        let image = cam.and_then(|c| images.get(c));
        let camera_problem: Option<(String, String)> = match (cam, image, box_2d) {
            (Some(c), Some(CameraImage::Absent), _) => Some((cams.field(c, "image"), "no image in the request".into())),
            (Some(c), Some(CameraImage::Undecodable(m)), _) => Some((cams.field(c, "image"), m.clone())),
            (None, _, _) => Some((
                format!("{field}.box_2d"),
                "no 2D box given and the projected 3D box is outside the view of every camera".into(),
            )),
            (_, _, None) => Some((
                format!("{field}.box_2d"),
                "no 2D box given and the projected 3D box is outside the camera view".into(),
            )),
            (_, _, Some(_)) => None,
        };
        let (mode, reason) = choose_mode(frame.mode, camera_problem, num_points, cfg.min_points as usize)?;
        if mode == Mode::Camera && !input.uv.iter().any(|uv| uv[0].is_finite() && uv[1].is_finite()) {
            let why = "camera-only lifting needs points in front of the camera; none of the box's points are";
            skip(i, &person.id, Error::InsufficientData { field: format!("{field}.box_3d"), message: why.into() });
            continue;
        }
        let usable = image.is_some_and(CameraImage::usable);
        let crop = match (mode, usable, cam, prepared.crop) {
            (Mode::Fusion | Mode::Camera, true, Some(c), Some(t)) => {
                crop_budgets[c].spend(t.side(), &field)?;
                Some(t)
            }
            (Mode::Fusion | Mode::Camera, _, _, _) => {
                return Err(Error::Runtime(format!("{field}: camera mode chosen without a crop")));
            }
            (Mode::Lidar, _, _, _) => None,
        };
        crops.push(crop);
        persons.push(PersonPlan {
            id: person.id.clone(),
            camera: cam,
            mode,
            reason,
            box_frame: prepared.box_frame,
            box_2d,
            num_points,
            input,
            image_input: None,
        });
    }
    // Per camera, each crop cut from the image decoded at its own DCT scale
    // (`image_decode::decode_crops`): a person's crop does not depend on the others.
    let mut decode_pixels = Duration::ZERO;
    for (c, camera) in cams.cameras.iter().enumerate() {
        let here: Vec<usize> =
            (0..persons.len()).filter(|&i| persons[i].camera == Some(c) && crops[i].is_some()).collect();
        if here.is_empty() {
            continue;
        }
        let windows: Vec<CropTransform> = here.iter().filter_map(|&i| crops[i]).collect();
        let image = std::mem::replace(&mut images[c], CameraImage::Absent);
        let t2 = Instant::now();
        let decoded =
            image_decode::decode_crops(image, &windows, camera.width, camera.height, || still_wanted(abandoned))?;
        decode_pixels += t2.elapsed();
        match decoded {
            Ok(cut) => {
                for (&i, crop) in here.iter().zip(&cut) {
                    still_wanted(abandoned)?;
                    persons[i].image_input = Some(normalize(crop, cfg));
                }
            }
            // the header was sound but the pixels are not
            Err(why) if frame.mode == posefuse_core::frame::RequestedMode::Auto => {
                for &i in &here {
                    (persons[i].mode, persons[i].reason) = (Mode::Lidar, format!("camera unusable: {why}"));
                }
            }
            Err(why) => {
                let field = cams.field(c, "image");
                return Err(Error::field(field, format!("mode {:?} needs the camera: {why}", frame.mode)));
            }
        }
    }
    decode += decode_pixels;
    let FrameCameras { cameras, names, .. } = cams;
    Ok(FramePlan { cameras, names, persons, skipped, decode, preprocess: t1.elapsed().saturating_sub(decode_pixels) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn oversized_boxes_are_refused() {
        let b = Box2d { center_x: 50.0, center_y: 40.0, width: 201.0, height: 10.0 };
        let e = check_box_size(&b, "persons[0].box_2d", 100, 80).unwrap_err();
        assert_eq!(e.field_name(), Some("persons[0].box_2d"));
        assert!(check_box_size(&Box2d { width: 200.0, ..b }, "f", 100, 80).is_ok());
        assert!(check_box_size(&Box2d { height: 161.0, ..b }, "f", 100, 80).is_err());
    }
}
