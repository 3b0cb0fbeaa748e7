//! `posefuse waymo convert`: a v2 dataset root → the simulator's outputs (docs/DATA.md):
//! prepared training samples in shards, built by the same pipeline call the simulator makes,
//! with 2D labels from `camera_hkp` and 3D labels from `lidar_hkp`, and request fixtures (one
//! per frame and camera that shows pedestrians, plus one LiDAR-only fixture per frame for the
//! pedestrians no camera box is associated with) with `lidar_hkp` as the 3D truth.

use std::collections::BTreeMap;
use std::path::PathBuf;

use crate::error::Context;
use rayon::prelude::*;

use super::range::{range_image_points, LaserCalibration, SweepPoses};
use super::reader::{FrameData, FrameLabels, Segment};
use super::schema::{keypoint_index, LASER_TOP};
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Box2d, Box3d, Frame, GroundTruth, Keypoints2d, Keypoints3d, Person, Points, RequestedMode};
use posefuse_core::geometry::{BoxFrame, Camera};
use posefuse_core::keypoints::K;
use posefuse_core::pipeline::NOMINAL_LIDAR_ORIGIN as LIDAR_ORIGIN;
use posefuse_core::pipeline::{model_frame, prepare_person, to_local, CropTransform, PipelineConfig, PointFrame};
use posefuse_core::sample::{sample_points, Sample, SamplePoints, ShardWriter};

/// Version written to the output's `dataset.json`.
pub const CONVERT_VERSION: &str = "posefuse-waymo-1";
/// Fixtures carry the points within this distance (m) of a pedestrian's box: all the server
/// looks at, without a whole sweep per fixture.
pub const FIXTURE_POINTS_MARGIN_M: f64 = 1.0;

/// A labelled 2D keypoint (`camera_hkp`).
#[derive(Debug, Clone, PartialEq)]
pub struct Kp2dLabel {
    pub kind: i64,
    pub uv: [f64; 2],
    pub occluded: bool,
}

/// A labelled 3D keypoint (`lidar_hkp`, vehicle frame).
#[derive(Debug, Clone, PartialEq)]
pub struct Kp3dLabel {
    pub kind: i64,
    pub xyz: [f64; 3],
    pub occluded: bool,
}

/// A labelled keypoint: where it is, and whether Waymo marks it occluded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Labelled<const D: usize> {
    pub at: [f64; D],
    pub occluded: bool,
}

impl<const D: usize> Labelled<D> {
    /// Labelled and not occluded.
    pub fn visible(&self) -> bool {
        !self.occluded
    }
}

/// A pedestrian's labels in posefuse's keypoint order; `None` where not labelled.
#[derive(Debug, Clone)]
pub struct PersonLabelsIn {
    pub box3d: Box3d,
    pub box2d: Box2d,
    /// Every labelled 2D keypoint (the visible ones are the training target; occluded labels are
    /// scored, not trained on, as the simulator's `kp2d_occluded`).
    pub kp2d: [Option<Labelled<2>>; K],
    /// Every labelled 3D keypoint.
    pub kp3d: [Option<Labelled<3>>; K],
}

/// The 13 keypoints of a label list (other types ignored; the last of a repeated type wins).
pub fn kp2d_of(kps: &[Kp2dLabel]) -> [Option<Labelled<2>>; K] {
    let mut out = [None; K];
    for k in kps {
        if let Some(i) = keypoint_index(k.kind) {
            out[i] = k.uv.iter().all(|v| v.is_finite()).then_some(Labelled { at: k.uv, occluded: k.occluded });
        }
    }
    out
}

pub fn kp3d_of(kps: &[Kp3dLabel]) -> [Option<Labelled<3>>; K] {
    let mut out = [None; K];
    for k in kps {
        if let Some(i) = keypoint_index(k.kind) {
            out[i] = k.xyz.iter().all(|v| v.is_finite()).then_some(Labelled { at: k.xyz, occluded: k.occluded });
        }
    }
    out
}

/// Waymo's flags as the shards' `*_visible` / `*_occluded` arrays.
fn flags<const D: usize>(kps: &[Option<Labelled<D>>; K]) -> ([u8; K], [u8; K]) {
    (kps.map(|k| u8::from(k.is_some_and(|k| k.visible()))), kps.map(|k| u8::from(k.is_some_and(|k| k.occluded))))
}

impl PersonLabelsIn {
    /// Whether the person has a visible 2D label to train on.
    pub fn trainable(&self) -> bool {
        self.kp2d.iter().any(|k| k.is_some_and(|k| k.visible()))
    }

    pub fn new(box3d: Box3d, box2d: Box2d, kp2d: &[Kp2dLabel], kp3d: &[Kp3dLabel]) -> PersonLabelsIn {
        PersonLabelsIn { box3d, box2d, kp2d: kp2d_of(kp2d), kp3d: kp3d_of(kp3d) }
    }
}

fn f32x<const N: usize>(v: [f64; N]) -> [f32; N] {
    v.map(|x| x as f32)
}

/// One prepared training sample, through the pipeline's `prepare_person` as the simulator's, its
/// crop cut from the camera's JPEG as the server cuts it (`image_decode::decode_crops`).
/// `kp2d_image_true` holds the labels (real data has no exact projections).
#[allow(clippy::too_many_arguments)]
pub fn person_sample(
    jpeg: &[u8],
    cam: &Camera,
    points: &[[f32; 3]],
    sensor: [f64; 3],
    l: &PersonLabelsIn,
    cfg: &PipelineConfig,
    points_cap: usize,
    frame_index: i32,
) -> Result<Sample> {
    let prepared = prepare_person(None, Some(cam), points, &l.box3d, Some(&l.box2d), cfg);
    let t = CropTransform::for_box(&l.box2d, cfg);
    let crop = posefuse_core::sample::planned_crops(jpeg, &[t], cam.width, cam.height)?
        .pop()
        .ok_or_else(|| Error::Io("jpeg decode: no crop".into()))?;
    let points_uv = prepared.points.model_uv(Some(cam), Some(&t));
    let bf = &prepared.box_frame;
    let SamplePoints { points_xyz, points_uv, serve_xyz, serve_uv } =
        sample_points(&prepared, &points_uv, cfg, points_cap);
    let b = &l.box3d;
    let calib = cam.to_calibration();
    let v = [b.center_x - sensor[0], b.center_y - sensor[1]];
    let ((kp2d_visible, kp2d_occluded), (kp3d_visible, kp3d_occluded)) = (flags(&l.kp2d), flags(&l.kp3d));
    Ok(Sample {
        image: crop.into_raw(),
        points_xyz,
        points_uv,
        serve_xyz,
        serve_uv,
        kp2d: l.kp2d.map(|u| u.map_or([0.0; 2], |u| f32x(t.to_model(u.at)))),
        kp2d_visible,
        kp2d_occluded,
        kp2d_image_true: l.kp2d.map(|u| u.map_or([0.0; 2], |u| f32x(u.at))),
        kp3d: l.kp3d.map(|k| k.map_or([0.0; 3], |k| f32x(to_local(bf, k.at, cfg)))),
        kp3d_vehicle: l.kp3d.map(|k| k.map_or([0.0; 3], |k| f32x(k.at))),
        kp3d_visible,
        kp3d_occluded,
        box3d: f32x(b.to_row()),
        box2d: f32x([l.box2d.center_x, l.box2d.center_y, l.box2d.width, l.box2d.height]),
        crop: f32x([t.x0, t.y0, t.scale]),
        intrinsic: std::array::from_fn(|i| calib.intrinsic[i] as f32),
        extrinsic: std::array::from_fn(|i| calib.extrinsic[i] as f32),
        image_size_wh: [cam.width as i32, cam.height as i32],
        sensor_xyz: f32x(to_local(bf, sensor, cfg)),
        frame_yaw: model_frame(bf, cfg).heading as f32,
        range_m: (v[0] * v[0] + v[1] * v[1]).sqrt() as f32,
        frame_index,
    })
}

/// All returns of a frame (every laser, both returns) in the vehicle frame at the frame's
/// timestamp; the TOP laser's per-pixel poses are used when `compensate` and present.
pub fn frame_points(
    lasers: &BTreeMap<i64, LaserCalibration>,
    f: &FrameData,
    compensate: bool,
) -> crate::error::Result<Vec<[f32; 3]>> {
    let mut out = Vec::new();
    for l in &f.lasers {
        let cal = lasers
            .get(&l.name)
            .ok_or_else(|| crate::invalid!("component `lidar_calibration`: no row for laser {}", l.name))?;
        for ri in &l.returns {
            let poses = match (compensate && l.name == LASER_TOP, &l.pixel_poses, &f.vehicle_pose) {
                (true, Some(p), Some(v)) => Some(SweepPoses { pixel_poses: p, frame_pose: v }),
                _ => None,
            };
            out.extend(range_image_points(ri, cal, poses)?);
        }
    }
    Ok(out)
}

/// The TOP laser's position in the vehicle frame (the simulator's when there is no TOP).
pub fn sensor_position(lasers: &BTreeMap<i64, LaserCalibration>) -> [f64; 3] {
    lasers.get(&LASER_TOP).map_or(LIDAR_ORIGIN, |c| [c.extrinsic[3], c.extrinsic[7], c.extrinsic[11]])
}

/// What to convert.
#[derive(Debug, Clone)]
pub struct ConvertOptions {
    pub dataset: PathBuf,
    pub out: PathBuf,
    /// At most this many segments (in name order).
    pub segments: Option<usize>,
    /// Only these cameras (enum values); `None`: all.
    pub cameras: Option<Vec<i64>>,
    pub image_size: u32,
    /// The point networks' frame the samples are prepared in.
    pub frame: PointFrame,
    pub points_cap: usize,
    /// Write request fixtures.
    pub requests: bool,
    pub jobs: Option<usize>,
}

/// What frame processing needs of its segment.
struct SegmentInfo<'a> {
    name: &'a str,
    lasers: &'a BTreeMap<i64, LaserCalibration>,
}

/// What a frame produced.
struct FrameOut {
    samples: Vec<Sample>,
    fixtures: Vec<(String, Frame)>,
}

fn ground_truth(kp3d: Option<&Vec<super::convert::Kp3dLabel>>, kp2d: Option<&Vec<Kp2dLabel>>) -> Option<GroundTruth> {
    let k3 = kp3d.map(|k| {
        let a = kp3d_of(k);
        Keypoints3d {
            xyz: a.iter().map(|x| x.map_or([0.0; 3], |x| x.at)).collect(),
            visible: a.iter().map(|x| x.is_some_and(|x| x.visible())).collect(),
            occluded: a.iter().map(|x| x.is_some_and(|x| x.occluded)).collect(),
        }
    });
    let k2 = kp2d.map(|k| {
        let a = kp2d_of(k);
        Keypoints2d {
            uv: a.iter().map(|x| x.map_or([0.0; 2], |x| x.at)).collect(),
            visible: a.iter().map(|x| x.is_some_and(|x| x.visible())).collect(),
            occluded: a.iter().map(|x| x.is_some_and(|x| x.occluded)).collect(),
        }
    });
    (k3.is_some() || k2.is_some()).then_some(GroundTruth { keypoints_3d: k3, keypoints_2d: k2 })
}

/// The points within [`FIXTURE_POINTS_MARGIN_M`] of any of the boxes.
pub fn near_boxes(points: &[[f32; 3]], boxes: &[Box3d]) -> Vec<[f32; 3]> {
    let frames: Vec<BoxFrame> = boxes.iter().map(BoxFrame::new).collect();
    points
        .iter()
        .filter(|p| {
            let q = [p[0] as f64, p[1] as f64, p[2] as f64];
            frames.iter().any(|b| b.contains(q, FIXTURE_POINTS_MARGIN_M))
        })
        .copied()
        .collect()
}

#[allow(clippy::too_many_arguments)]
fn process_frame(
    seg: &SegmentInfo,
    cameras: &BTreeMap<i64, Camera>,
    f: &FrameData,
    labels: &FrameLabels,
    index: usize,
    o: &ConvertOptions,
    cfg: &PipelineConfig,
) -> crate::error::Result<FrameOut> {
    let points = frame_points(seg.lasers, f, true)?;
    let sensor = sensor_position(seg.lasers);
    let mut out = FrameOut { samples: Vec::new(), fixtures: Vec::new() };
    let ped = |id: &str| labels.pedestrians.iter().find(|p| p.id == id);
    let mut seen = std::collections::HashSet::new();
    for (cam_name, cam) in cameras {
        let objs: Vec<_> = labels
            .camera_objects
            .iter()
            .filter(|c| c.camera == *cam_name)
            .filter_map(|c| c.laser_object.as_deref().and_then(ped).map(|p| (c, p)))
            .collect();
        if objs.is_empty() {
            continue;
        }
        let Some(jpeg) = f.images.get(cam_name) else {
            continue;
        };
        let mut persons = Vec::new();
        for (c, p) in &objs {
            seen.insert(p.id.clone());
            let k3 = labels.lidar_keypoints.get(&p.id);
            if let Some(k2) = &c.keypoints {
                let l = PersonLabelsIn::new(p.box3d, c.box2d, k2, k3.map_or(&[][..], |v| v.as_slice()));
                if l.trainable() {
                    let sample = person_sample(jpeg, cam, &points, sensor, &l, cfg, o.points_cap, index as i32)
                        .with_context(|| {
                            format!("segment {}: image of camera {cam_name} at {}", seg.name, f.timestamp)
                        })?;
                    out.samples.push(sample);
                }
            }
            persons.push(Person {
                id: p.id.clone(),
                camera: None,
                box_2d: Some(c.box2d),
                box_3d: p.box3d,
                ground_truth: ground_truth(k3, c.keypoints.as_ref()),
            });
        }
        if o.requests {
            use base64::Engine;
            let boxes: Vec<Box3d> = persons.iter().map(|p| p.box_3d).collect();
            out.fixtures.push((
                format!("{}-{}-{}.json", seg.name, f.timestamp, super::schema::CAMERA_NAMES[*cam_name as usize - 1]),
                Frame {
                    frame_id: Some(format!("{}/{}/{cam_name}", seg.name, f.timestamp)),
                    image: Some(base64::engine::general_purpose::STANDARD.encode(jpeg)),
                    image_rgb: None,
                    calibration: Some(cam.to_calibration()),
                    cameras: Vec::new(),
                    points: Points::encode(&near_boxes(&points, &boxes)),
                    persons,
                    mode: RequestedMode::Auto,
                },
            ));
        }
    }
    // Pedestrians no camera shows: a LiDAR-only fixture.
    let rest: Vec<_> = labels.pedestrians.iter().filter(|p| !seen.contains(&p.id)).collect();
    if o.requests && !rest.is_empty() {
        let calibration = cameras
            .values()
            .next()
            .map(Camera::to_calibration)
            .map_or_else(|| posefuse_core::geometry::nominal_camera().map(|c| c.to_calibration()), Ok)?;
        let boxes: Vec<Box3d> = rest.iter().map(|p| p.box3d).collect();
        out.fixtures.push((
            format!("{}-{}-LIDAR.json", seg.name, f.timestamp),
            Frame {
                frame_id: Some(format!("{}/{}/lidar", seg.name, f.timestamp)),
                image: None,
                image_rgb: None,
                calibration: Some(calibration),
                cameras: Vec::new(),
                points: Points::encode(&near_boxes(&points, &boxes)),
                persons: rest
                    .iter()
                    .map(|p| Person {
                        id: p.id.clone(),
                        camera: None,
                        box_2d: None,
                        box_3d: p.box3d,
                        ground_truth: ground_truth(labels.lidar_keypoints.get(&p.id), None),
                    })
                    .collect(),
                mode: RequestedMode::Auto,
            },
        ));
    }
    Ok(out)
}

/// What a conversion wrote.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ConvertSummary {
    pub segments: usize,
    pub frames: usize,
    pub samples: usize,
    pub fixtures: usize,
    pub seconds: f64,
}

/// Frames read before they are processed in parallel.
const CHUNK_FRAMES: usize = 4;

/// Runs `posefuse waymo convert`.
pub fn convert(o: &ConvertOptions) -> crate::error::Result<ConvertSummary> {
    let started = std::time::Instant::now();
    let cfg = PipelineConfig::with_image_size(o.image_size).in_frame(o.frame);
    cfg.validate().map_err(|e| crate::invalid!("--image-size {}: {e}", o.image_size))?;
    let mut names = super::segments::segments_in(&o.dataset)?;
    crate::ensure!(!names.is_empty(), "{}: no segments (no lidar/*.parquet)", o.dataset.display());
    if let Some(n) = o.segments {
        names.truncate(n);
    }
    std::fs::create_dir_all(o.out.join("shards")).with_context(|| format!("creating {}", o.out.display()))?;
    if o.requests {
        std::fs::create_dir_all(o.out.join("requests"))?;
    }
    let pool =
        rayon::ThreadPoolBuilder::new().num_threads(o.jobs.unwrap_or(0)).build().context("the worker threads")?;
    let mut shards = ShardWriter::new(&o.out.join("shards"), &cfg, o.points_cap);
    let mut sum = ConvertSummary { segments: names.len(), ..Default::default() };
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} frames ({per_sec}, eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut frame_index = 0usize;
    for name in &names {
        let mut seg = Segment::open(&o.dataset, name, &o.cameras)?;
        let cameras: BTreeMap<i64, Camera> = seg
            .cameras
            .iter()
            .map(|(n, c)| Camera::from_calibration(c).map(|cam| (*n, cam)))
            .collect::<posefuse_core::Result<_>>()
            .map_err(|e| crate::invalid!("segment {name}: component `camera_calibration`: {e}"))?;
        bar.inc_length(seg.timestamps.len() as u64);
        bar.set_message(name.clone());
        let timestamps = seg.timestamps.clone();
        for chunk in timestamps.chunks(CHUNK_FRAMES) {
            let mut batch = Vec::new();
            for &ts in chunk {
                let labels = seg.labels(ts);
                let mut wanted: Vec<i64> = labels.camera_objects.iter().map(|c| c.camera).collect();
                wanted.sort_unstable();
                wanted.dedup();
                let data = seg.frame(ts, &wanted)?;
                batch.push((data, labels, frame_index));
                frame_index += 1;
            }
            let segr = SegmentInfo { name, lasers: &seg.lasers };
            let segr = &segr;
            let outs: Vec<crate::error::Result<FrameOut>> = pool.install(|| {
                batch.par_iter().map(|(d, l, i)| process_frame(segr, &cameras, d, l, *i, o, &cfg)).collect()
            });
            for r in outs {
                let r = r?;
                sum.samples += r.samples.len();
                for s in r.samples {
                    shards.push(s)?;
                }
                for (file, frame) in r.fixtures {
                    let path = o.out.join("requests").join(file);
                    std::fs::write(&path, serde_json::to_vec(&frame)?)
                        .with_context(|| format!("writing {}", path.display()))?;
                    sum.fixtures += 1;
                }
            }
            sum.frames += chunk.len();
            bar.inc(chunk.len() as u64);
        }
    }
    shards.flush()?;
    bar.finish_and_clear();
    sum.seconds = started.elapsed().as_secs_f64();
    let doc = serde_json::json!({
        "version": CONVERT_VERSION,
        "source": o.dataset,
        "segments": names,
        "count": sum.samples,
        "image_size": cfg.image_size,
        "points_cap": o.points_cap,
        "frames": sum.frames,
        "request_fixtures": sum.fixtures,
        "shards": shards.written.iter().map(|(f, n)| serde_json::json!({"file": f, "samples": n})).collect::<Vec<_>>(),
        "preprocessing": cfg,
    });
    let path = o.out.join("dataset.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&doc)?).with_context(|| format!("writing {}", path.display()))?;
    Ok(sum)
}
