//! Planning a validated frame for one bundle, in steps with one job each: each person's camera
//! ([`FrameCameras::choose`]), the used images' headers ([`FrameCameras::open_used`]), each
//! person's 2D box, points, mode and crop window ([`plan_person`]), then the crops cut and
//! normalized ([`cut_crops`]). The 3D boxes are passed in, so the heading stage plans the same
//! frame again with its estimated headings, reusing the opened images and the crops already cut.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use super::api::{ErrorDetail, Mode, SkippedPerson};
use super::cameras::FrameCameras;
use super::crop_cache::CropCache;
use super::limits::{CropBudget, FrameLimits};
use super::policy::choose_mode;
use super::valid_frame::ValidFrame;
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Box2d, Box3d, Frame, Person, RequestedMode};
use posefuse_core::geometry::{clip_to_image, overlaps_image, projected_box, BoxFrame, Camera};
use posefuse_core::image_decode::{self, CameraImage};
use posefuse_core::pipeline::{normalize, prepare_person, CropTransform, PipelineConfig, PointInput};

/// Everything decided before inference for one person.
pub(super) struct PersonPlan {
    pub id: String,
    /// Index of the camera the person uses (its `box_2d`, crop and keypoint pixels).
    pub camera: Option<usize>,
    pub mode: Mode,
    pub reason: String,
    pub box_frame: BoxFrame,
    pub box_2d: Option<Box2d>,
    pub num_points: usize,
    pub input: PointInput,
    /// The crop window, while the camera network is to run.
    crop: Option<CropTransform>,
    /// Normalized crop `[3, S, S]` when the camera network runs.
    pub image_input: Option<Vec<f32>>,
}

/// A frame planned for one bundle.
pub(super) struct FramePlan {
    pub persons: Vec<PersonPlan>,
    /// Persons no model can answer (their data, not the request, is lacking).
    pub skipped: Vec<SkippedPerson>,
    pub decode: Duration,
    pub preprocess: Duration,
}

/// What the service feeds the networks for one answered person of a frame.
pub struct PlannedInput {
    pub mode: Mode,
    /// Normalized crop `[3, S, S]` (fusion and camera-only).
    pub image: Option<Vec<f32>>,
    /// The N-point input: points in the model frame and their model-input pixels.
    pub points: PointInput,
}

/// The networks' inputs for each answered person of `frame`, planned for a bundle of `cfg`
/// exactly as the service plans a request (validation, cameras, modes, crops). Benchmarks feed
/// ONNX Runtime with these, so that "raw" runs the inputs the server builds.
pub fn planned_inputs(frame: Frame, cfg: &PipelineConfig) -> Result<Vec<PlannedInput>> {
    let mut valid = ValidFrame::new(frame, None, &FrameLimits::DEFAULT)?;
    let boxes = valid.boxes();
    let plan = plan_frame(&mut valid, &boxes, cfg, &mut CropCache::default(), &AtomicBool::new(false))?;
    Ok(plan.persons.into_iter().map(|p| PlannedInput { mode: p.mode, image: p.image_input, points: p.input }).collect())
}

/// Stops a frame's pre-processing once nobody waits for it. The error is `ClientGone`, not a
/// server failure: whoever reads it (a log, a caller that kept the result) must not count the
/// server as unavailable for a request that stopped being wanted.
pub(super) fn still_wanted(abandoned: &AtomicBool) -> Result<()> {
    if abandoned.load(Ordering::Relaxed) {
        metrics::counter!("posefuse_frames_abandoned_total").increment(1);
        return Err(Error::ClientGone("the request was abandoned (deadline passed or client gone)".into()));
    }
    Ok(())
}

/// Plans `frame` for a bundle of `cfg` with the persons' 3D boxes at `boxes` (one per person).
pub(super) fn plan_frame(
    frame: &mut ValidFrame,
    boxes: &[Box3d],
    cfg: &PipelineConfig,
    crops: &mut CropCache,
    abandoned: &AtomicBool,
) -> Result<FramePlan> {
    let t0 = Instant::now();
    still_wanted(abandoned)?;
    // each person's camera, then the headers of the images someone uses (their sizes checked
    // against the calibrations): the pixels are decoded once the crops are known
    let chosen: Vec<Option<usize>> = frame.persons.iter().zip(boxes).map(|(p, b)| frame.cameras.choose(p, b)).collect();
    frame.cameras.open_used(&chosen)?;
    let opened = t0.elapsed();
    let t1 = Instant::now();
    let mut budgets: Vec<CropBudget> =
        frame.cameras.cameras.iter().map(|c| CropBudget::for_image(c.width, c.height)).collect();
    let (mut persons, mut skipped) = (Vec::with_capacity(frame.persons.len()), Vec::new());
    for (i, ((person, box_3d), &cam)) in frame.persons.iter().zip(boxes).zip(&chosen).enumerate() {
        still_wanted(abandoned)?;
        let at = PersonAt { index: i, person, box_3d, camera: cam };
        match plan_person(&at, frame, cfg, &mut budgets)? {
            Ok(plan) => persons.push(plan),
            Err(e) => {
                metrics::counter!("posefuse_persons_skipped_total").increment(1);
                skipped.push(SkippedPerson { index: i, id: person.id.clone(), error: ErrorDetail::from(&e) });
            }
        }
    }
    let decode_pixels = cut_crops(&mut persons, &frame.cameras, frame.mode, cfg, crops, abandoned)?;
    Ok(FramePlan {
        persons,
        skipped,
        decode: opened + decode_pixels,
        preprocess: t1.elapsed().saturating_sub(decode_pixels),
    })
}

/// One person of the frame as planned: its index, its request, its 3D box and its camera.
struct PersonAt<'a> {
    index: usize,
    person: &'a Person,
    box_3d: &'a Box3d,
    camera: Option<usize>,
}

/// A person's plan; `Ok(Err(_))`: the person is skipped (its data is lacking), `Err(_)`: the
/// frame is refused.
fn plan_person(
    at: &PersonAt<'_>,
    frame: &ValidFrame,
    cfg: &PipelineConfig,
    budgets: &mut [CropBudget],
) -> Result<Result<PersonPlan>> {
    let field = format!("persons[{}]", at.index);
    let cams = &frame.cameras;
    let camera = at.camera.and_then(|c| cams.cameras.get(c));
    let box_2d = box_2d(at.person.box_2d.as_ref(), at.box_3d, camera, &field)?;
    let prepared = prepare_person(None, camera, &frame.points, at.box_3d, box_2d.as_ref(), cfg);
    let num_points = prepared.points.len();
    let Some(input) = prepared.input else {
        let why = format!("no LiDAR point lies inside the box (grown by {} m on every side)", cfg.box_margin);
        return Ok(Err(Error::InsufficientData { field: format!("{field}.box_3d"), message: why }));
    };
    let image = at.camera.map(|c| cams.image(c));
    let camera_problem: Option<(String, String)> = match (at.camera, image, box_2d) {
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
        return Ok(Err(Error::InsufficientData { field: format!("{field}.box_3d"), message: why.into() }));
    }
    let usable = image.is_some_and(CameraImage::usable);
    let crop = match (mode, usable, at.camera, prepared.crop) {
        (Mode::Fusion | Mode::Camera, true, Some(c), Some(t)) => {
            budgets[c].spend(t.side(), &field)?;
            Some(t)
        }
        (Mode::Fusion | Mode::Camera, _, _, _) => {
            return Err(Error::Runtime(format!("{field}: camera mode chosen without a crop")));
        }
        (Mode::Lidar, _, _, _) => None,
    };
    Ok(Ok(PersonPlan {
        id: at.person.id.clone(),
        camera: at.camera,
        mode,
        reason,
        box_frame: prepared.box_frame,
        box_2d,
        num_points,
        input,
        crop,
        image_input: None,
    }))
}

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

/// The person's 2D box in its camera: the one given (checked against the image), or the
/// projection of its 3D box (clipped when oversized); none without a camera.
fn box_2d(given: Option<&Box2d>, box_3d: &Box3d, camera: Option<&Camera>, field: &str) -> Result<Option<Box2d>> {
    let Some(camera) = camera else { return Ok(None) };
    let (w, h) = (camera.width, camera.height);
    match given {
        Some(b) => {
            if !overlaps_image(b, w, h) {
                return Err(Error::field(
                    format!("{field}.box_2d"),
                    format!("lies entirely outside the {w}x{h} image"),
                ));
            }
            check_box_size(b, &format!("{field}.box_2d"), w, h)?;
            Ok(Some(*b))
        }
        None => Ok(projected_box(camera, box_3d).map(|b| {
            if check_box_size(&b, "", w, h).is_ok() {
                b
            } else {
                clip_to_image(b, w, h)
            }
        })),
    }
}

/// Cuts and normalizes the crops the persons' modes need, per camera, each from the image at its
/// own DCT scale (`image_decode::decode_crops`; a person's crop does not depend on the others),
/// windows cut before taken from `crops`. A camera whose pixels do not decode turns its persons
/// to LiDAR-only under `auto`, and refuses the frame under a requested camera mode. Returns the
/// time spent decoding.
fn cut_crops(
    persons: &mut [PersonPlan],
    cams: &FrameCameras,
    mode: RequestedMode,
    cfg: &PipelineConfig,
    crops: &mut CropCache,
    abandoned: &AtomicBool,
) -> Result<Duration> {
    let mut decoding = Duration::ZERO;
    for (c, camera) in cams.cameras.iter().enumerate() {
        let here: Vec<usize> =
            (0..persons.len()).filter(|&i| persons[i].camera == Some(c) && persons[i].crop.is_some()).collect();
        if here.is_empty() {
            continue;
        }
        // persons with the same window (one box given twice) share its crop
        let mut missing: Vec<CropTransform> = Vec::new();
        for t in here.iter().filter_map(|&i| persons[i].crop) {
            if crops.get(c, &t).is_none() && !missing.contains(&t) {
                missing.push(t);
            }
        }
        let failed = match crops.failure(c) {
            Some(why) => Some(why.to_string()),
            None if missing.is_empty() => None,
            None => {
                let t0 = Instant::now();
                let cut = image_decode::decode_crops(cams.image(c), &missing, camera.width, camera.height, || {
                    still_wanted(abandoned)
                })?;
                decoding += t0.elapsed();
                match cut {
                    Ok(cut) => {
                        missing.into_iter().zip(cut).for_each(|(t, crop)| crops.insert(c, t, crop));
                        None
                    }
                    Err(why) => {
                        crops.fail(c, why.clone());
                        Some(why)
                    }
                }
            }
        };
        match failed {
            None => {
                for &i in &here {
                    still_wanted(abandoned)?;
                    let p = &mut persons[i];
                    let crop = p.crop.and_then(|t| crops.get(c, &t));
                    p.image_input = crop.map(|crop| normalize(crop, cfg));
                }
            }
            // the header was sound but the pixels are not
            Some(why) if mode == RequestedMode::Auto => {
                for &i in &here {
                    let p = &mut persons[i];
                    (p.mode, p.reason, p.crop) = (Mode::Lidar, format!("camera unusable: {why}"), None);
                }
            }
            Some(why) => {
                return Err(Error::field(cams.field(c, "image"), format!("mode {mode:?} needs the camera: {why}")));
            }
        }
    }
    Ok(decoding)
}

#[cfg(test)]
mod tests {
    use super::*;
    use base64::Engine;
    use posefuse_core::frame::Points;

    /// One 200×160 PNG camera looking down the x axis; two persons at 10 m, the first with its
    /// 2D box given, the second without (its box is the projection of its 3D box).
    fn frame() -> Frame {
        let image =
            image::RgbImage::from_fn(200, 160, |x, y| image::Rgb([(x * 5 % 251) as u8, (y * 7 % 253) as u8, 90]));
        let mut png = Vec::new();
        image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png).unwrap();
        let mut points = Vec::new();
        for y in [-1.0f32, 1.0] {
            for i in 0..100 {
                let t = i as f32 / 100.0;
                points.push([10.0 + 0.2 * (t * 7.0).sin(), y + 0.2 * (t * 5.0).cos(), 0.1 + 1.6 * t]);
            }
        }
        let person = |id: &str, y: f64, box_2d: serde_json::Value| {
            let b = serde_json::json!({"center_x": 10.0, "center_y": y, "center_z": 0.9,
                "length": 0.6, "width": 0.7, "height": 1.8, "heading": 0.3});
            let mut p = serde_json::json!({"id": id, "box_3d": b});
            if !box_2d.is_null() {
                p["box_2d"] = box_2d;
            }
            p
        };
        let given = serde_json::json!({"center_x": 90.0, "center_y": 71.0, "width": 9.0, "height": 19.0});
        serde_json::from_value(serde_json::json!({
            "image": base64::engine::general_purpose::STANDARD.encode(&png),
            "calibration": {"intrinsic": [100.0, 100.0, 100.0, 80.0, 0, 0, 0, 0, 0],
                "extrinsic": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "width": 200, "height": 160},
            "points": Points::encode(&points),
            "persons": [person("given", 1.0, given), person("projected", -1.0, serde_json::Value::Null)],
        }))
        .unwrap()
    }

    fn inputs(plan: &FramePlan) -> Vec<(Mode, Option<Vec<f32>>)> {
        plan.persons.iter().map(|p| (p.mode, p.image_input.clone())).collect()
    }

    #[test]
    fn a_second_pass_reuses_the_crops_it_can_and_equals_a_fresh_plan() {
        let (cfg, never) = (PipelineConfig::with_image_size(64), AtomicBool::new(false));
        let mut valid = ValidFrame::new(frame(), None, &FrameLimits::DEFAULT).unwrap();
        let mut crops = CropCache::default();
        let boxes = valid.boxes();
        let first = plan_frame(&mut valid, &boxes, &cfg, &mut crops, &never).unwrap();
        assert!(first.persons.iter().all(|p| p.mode == Mode::Fusion && p.image_input.is_some()));
        assert_eq!(crops.cut, 2);
        // the heading stage's second pass, at other headings: the given 2D box's crop is reused,
        // the projected box moved with its heading and its crop is cut anew
        let turned: Vec<Box3d> = boxes.iter().map(|b| Box3d { heading: b.heading + 1.0, ..*b }).collect();
        let second = plan_frame(&mut valid, &turned, &cfg, &mut crops, &never).unwrap();
        assert_eq!(crops.cut, 3);
        assert_eq!(first.persons[0].image_input, second.persons[0].image_input);
        assert_ne!(first.persons[1].box_2d, second.persons[1].box_2d);
        // exactly what a frame planned afresh at those headings gets
        let mut fresh = ValidFrame::new(frame(), None, &FrameLimits::DEFAULT).unwrap();
        let alone = plan_frame(&mut fresh, &turned, &cfg, &mut CropCache::default(), &never).unwrap();
        assert_eq!(inputs(&second), inputs(&alone));
        // the same boxes again: nothing is cut
        plan_frame(&mut valid, &turned, &cfg, &mut crops, &never).unwrap();
        assert_eq!(crops.cut, 3);
    }

    #[test]
    fn persons_with_the_same_window_share_one_crop() {
        let (cfg, never) = (PipelineConfig::with_image_size(64), AtomicBool::new(false));
        let mut f = frame();
        let twin = Person { id: "twin".into(), ..f.persons[0].clone() };
        f.persons.push(twin);
        let mut valid = ValidFrame::new(f, None, &FrameLimits::DEFAULT).unwrap();
        let mut crops = CropCache::default();
        let boxes = valid.boxes();
        let plan = plan_frame(&mut valid, &boxes, &cfg, &mut crops, &never).unwrap();
        assert_eq!(crops.cut, 2);
        assert!(plan.persons[2].image_input.is_some());
        assert_eq!(plan.persons[0].image_input, plan.persons[2].image_input);
    }

    #[test]
    fn pixels_that_do_not_decode_are_tried_once() {
        let (cfg, never) = (PipelineConfig::with_image_size(64), AtomicBool::new(false));
        let mut f = frame();
        // a sound PNG header (the size matches) over pixels cut short
        let png = base64::engine::general_purpose::STANDARD.decode(f.image.as_ref().unwrap()).unwrap();
        f.image = Some(base64::engine::general_purpose::STANDARD.encode(&png[..png.len() / 2]));
        let mut valid = ValidFrame::new(f, None, &FrameLimits::DEFAULT).unwrap();
        let mut crops = CropCache::default();
        let boxes = valid.boxes();
        for _ in 0..2 {
            let plan = plan_frame(&mut valid, &boxes, &cfg, &mut crops, &never).unwrap();
            assert!(plan.persons.iter().all(|p| p.mode == Mode::Lidar && p.reason.starts_with("camera unusable")));
        }
        assert_eq!(crops.cut, 0);
        assert!(crops.failure(0).is_some());
    }

    #[test]
    fn an_abandoned_frame_is_not_planned_and_is_not_a_server_failure() {
        let (cfg, gone) = (PipelineConfig::with_image_size(64), AtomicBool::new(true));
        let mut valid = ValidFrame::new(frame(), None, &FrameLimits::DEFAULT).unwrap();
        let mut crops = CropCache::default();
        let boxes = valid.boxes();
        let e = plan_frame(&mut valid, &boxes, &cfg, &mut crops, &gone).err().unwrap();
        assert!(matches!(e, Error::ClientGone(_)), "{e:?}");
        assert_eq!(crops.cut, 0);
    }

    #[test]
    fn oversized_boxes_are_refused() {
        let b = Box2d { center_x: 50.0, center_y: 40.0, width: 201.0, height: 10.0 };
        let e = check_box_size(&b, "persons[0].box_2d", 100, 80).unwrap_err();
        assert_eq!(e.field_name(), Some("persons[0].box_2d"));
        assert!(check_box_size(&Box2d { width: 200.0, ..b }, "f", 100, 80).is_ok());
        assert!(check_box_size(&Box2d { height: 161.0, ..b }, "f", 100, 80).is_err());
    }
}
