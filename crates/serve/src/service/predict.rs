//! Frame → poses: the one path shared by HTTP, gRPC, KServe, `posefuse predict` and `posefuse
//! eval`. The frame is validated once (`valid_frame`) and planned (`plan`); this file runs the
//! plan's persons through the runtime with the pipeline's own functions (`fusion_input`,
//! `decode_heatmaps`, `lift`, `keypoints_to_vehicle`, `Camera::project_points`) and assembles the
//! response.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use tracing::Instrument;

use super::admission::{Admission, Ticket};
use super::api::{BatchItem, KeypointPose, Mode, ModelRef, PersonPose, PoseResponse, Timings};
use super::crop_cache::CropCache;
use super::heading_stage::Refine;
use super::plan::{plan_frame, FramePlan, PersonPlan};
use super::valid_frame::ValidFrame;
use crate::runtime::{Bundle, ChainStep, JobOutput, ModelKind, Runtime};
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::Frame;
use posefuse_core::geometry::{BoxFrame, Camera};
use posefuse_core::image_decode::RawImages;
use posefuse_core::keypoints::{K, NAMES, WAYMO_TYPES};
use posefuse_core::pipeline::{
    decode_heatmaps, facing, fused_points, fusion_features, fusion_input, keypoints_to_vehicle, lidar_points, lift,
    turn_points, yaw_difference, PipelineConfig, PointFrame, PointInput,
};

/// Makes a frame and its images on the blocking pool, under the pre-processing permit: inputs
/// whose reading is work of its own (tensors in shared memory) are read there, in the same step
/// as the crops, rather than in a step of their own before admission.
pub type FrameBuilder = Box<dyn FnOnce() -> Result<(Frame, Option<RawImages>)> + Send>;

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
    /// disagree with them by more than `agree_deg` ([`super::heading_stage::estimated_boxes`]).
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

    /// [`Predictor::predict`] for a frame admitted before its body was read. The frame is
    /// validated once ([`ValidFrame`]); with a heading stage it is planned twice (the stage's
    /// bundle, then the served one at the headings the stage estimated), the second time on the
    /// images already opened and the crops already cut.
    pub async fn predict_admitted(
        &self,
        ticket: &Ticket,
        frame: Frame,
        raw_images: Option<RawImages>,
    ) -> Result<PoseResponse> {
        self.predict_built(ticket, Box::new(move || Ok((frame, raw_images)))).await
    }

    /// [`Predictor::predict_admitted`] for a frame that `build` makes in the pre-processing step
    /// (on the blocking pool, under its permit), where reading the inputs costs work of its own.
    async fn predict_built(&self, ticket: &Ticket, build: FrameBuilder) -> Result<PoseResponse> {
        let started = Instant::now();
        let runtime = self.runtime();
        let stage = self.heading_stage.clone();
        if !runtime.is_ready() || stage.as_ref().is_some_and(|(s, _)| !s.is_ready()) {
            return Err(Error::Unavailable("the models are warming up".into()));
        }
        let abandoned = Arc::new(AtomicBool::new(false));
        let _abandon_on_drop = AbandonOnDrop(abandoned.clone());
        let limits = self.limits;
        let first = stage.as_ref().map_or(&runtime, |(s, _)| s).clone();
        let prepared = self
            .off_executor(ticket, &abandoned, move |abandoned| {
                let t0 = Instant::now();
                let (frame, raw_images) = build()?;
                let mut valid = ValidFrame::new(frame, raw_images, &limits)?;
                let validated = t0.elapsed();
                let mut crops = CropCache::default();
                let boxes = valid.boxes();
                let mut plan = plan_frame(&mut valid, &boxes, first.bundle().config(), &mut crops, abandoned)?;
                plan.decode += validated;
                record_plan(&plan);
                Ok((valid, crops, plan))
            })
            .await?;
        let (mut valid, mut crops, plan) = prepared;
        let Some((stage, agree_deg)) = stage else {
            return self.respond(&runtime, &valid, plan, Timings::default(), started).await;
        };
        let estimate = self.respond(&stage, &valid, plan, Timings::default(), started).await?;
        let boxes = super::heading_stage::estimated_boxes(valid.boxes(), &estimate, agree_deg);
        let cfg = runtime.bundle().config().clone();
        let (valid, plan) = self
            .off_executor(ticket, &abandoned, move |abandoned| {
                let plan = plan_frame(&mut valid, &boxes, &cfg, &mut crops, abandoned)?;
                record_plan(&plan);
                Ok((valid, plan))
            })
            .await?;
        self.respond(&runtime, &valid, plan, estimate.timings, started).await
    }

    /// Runs CPU work on the blocking pool, holding a decode permit (admission bounds how many
    /// wait for one); `work` is told through the flag when nobody waits for it any more.
    async fn off_executor<T: Send + 'static>(
        &self,
        ticket: &Ticket,
        abandoned: &Arc<AtomicBool>,
        work: impl FnOnce(&AtomicBool) -> Result<T> + Send + 'static,
    ) -> Result<T> {
        let permit = self.admission.enter(ticket).instrument(tracing::info_span!("admission")).await?;
        let abandoned = abandoned.clone();
        // decode and pre-processing are one step (crops are decoded as they are cut); the span
        // carries the split
        let span =
            tracing::info_span!("preprocess", decode_ms = tracing::field::Empty, preprocess_ms = tracing::field::Empty);
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let _in = span.enter();
            work(&abandoned)
        })
        .await
        .map_err(|e| Error::Runtime(format!("pre-processing task failed: {e}")))?
    }

    /// Runs a planned frame's persons on `runtime` and assembles the response; `before` holds
    /// the times of an earlier pass over the same frame (the heading stage's), added in.
    async fn respond(
        &self,
        runtime: &Arc<Runtime>,
        frame: &ValidFrame,
        plan: FramePlan,
        before: Timings,
        started: Instant,
    ) -> Result<PoseResponse> {
        let refine =
            if runtime.bundle().config().point_frame() == PointFrame::BoxHeading { self.refine } else { Refine::OFF };
        let on = OnRuntime { runtime, cameras: &frame.cameras.cameras, names: &frame.cameras.names, refine };
        let results = futures::future::try_join_all(plan.persons.into_iter().map(|p| on.run_person(p))).await?;
        let _response = tracing::info_span!("response").entered();
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
        let timings = Timings {
            decode_ms: before.decode_ms + ms(plan.decode),
            preprocess_ms: before.preprocess_ms + ms(plan.preprocess) + ms(post),
            queue_ms: before.queue_ms + ms(queue),
            inference_ms: before.inference_ms + ms(inference),
            total_ms: ms(started.elapsed()),
        };
        metrics::histogram!("posefuse_preprocess_seconds").record(plan.preprocess.as_secs_f64() + post.as_secs_f64());
        metrics::histogram!("posefuse_decode_seconds").record(plan.decode.as_secs_f64());
        let m = &runtime.bundle().manifest;
        Ok(PoseResponse {
            frame_id: frame.frame_id.clone(),
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
        self.answer_built(ticket, Box::new(move || Ok((frame, raw_images))), timeout).await
    }

    /// [`Predictor::answer_admitted`] for a frame that `build` makes in the pre-processing step
    /// ([`FrameBuilder`]); its errors are the request's.
    pub async fn answer_built(&self, ticket: &Ticket, build: FrameBuilder, timeout: Duration) -> Result<PoseResponse> {
        let t0 = Instant::now();
        let r = match tokio::time::timeout(timeout, self.predict_built(ticket, build)).await {
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
        let PersonPlan { id, camera, mode, reason, mut box_frame, box_2d, num_points, input, image_input, .. } = p;
        let need_crop = || Error::Runtime(format!("{id}: camera input missing"));
        let (local, scores): (Vec<[f32; 3]>, Option<Vec<f32>>) = match mode {
            Mode::Fusion => {
                let x = image_input.ok_or_else(need_crop)?;
                let chain_cfg = cfg.clone();
                let kept = (self.refine.passes > 0).then(|| (input.xyz.clone(), input.uv.clone()));
                let PointInput { xyz, uv, .. } = input;
                // runs on the inference worker, between the two networks
                let then: ChainStep = Box::new(move |h: &[f32]| fusion_input(h, &xyz, &uv, &chain_cfg));
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
                    let f = features.get_or_insert_with(|| fusion_features(heatmaps, uv, ask.cfg));
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

/// The decode and pre-processing times of a planned frame, on the `preprocess` span it was
/// planned in.
fn record_plan(plan: &FramePlan) {
    let span = tracing::Span::current();
    span.record("decode_ms", ms(plan.decode));
    span.record("preprocess_ms", ms(plan.preprocess));
}
