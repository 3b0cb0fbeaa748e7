//! `posefuse simulate --format waymo-v2`: simulated segments in the v2 layout, built on the
//! simulator's worlds (its persons, scene, renderer and labels). One segment is a sequence of
//! the simulator's frames (each an independent street scene) seen from a vehicle that drives
//! straight at a constant speed: five cameras (FRONT from the simulator, the others yawed
//! around it), five lasers as range images with two returns (the TOP laser non-uniform, its
//! sweep taken while the vehicle moves, with per-pixel poses), vehicle poses, pedestrian 3D and
//! 2D boxes with their associations, sparse `camera_hkp` labels and `lidar_hkp`.
//!
//! Rays are cast against the scene inside angular windows around the pedestrians and against
//! the ground elsewhere, which keeps Waymo-size range images cheap while every return is real.

use std::path::PathBuf;

use rand::seq::SliceRandom;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

use posefuse_core::frame::{Box2d, Box3d, CameraCalibration};
use posefuse_core::geometry::nominal_camera;
use posefuse_core::geometry::Camera;
use posefuse_core::keypoints::K;
use posefuse_core::pipeline::PipelineConfig;
use posefuse_core::pipeline::NOMINAL_LIDAR_ORIGIN as LIDAR_ORIGIN;
use posefuse_core::sample::{encode_jpeg, Sample};
use posefuse_data::error::Context;
use posefuse_data::sim::dataset::{frame_rng, persons_in_frame, render_frame_image};
use posefuse_data::sim::labels::label_person;
use posefuse_data::sim::math::{hash, madd, V3};
use posefuse_data::sim::street::Profile;
use posefuse_data::sim::world::{sample_world, World};
use posefuse_data::waymo::convert::{person_sample, Kp2dLabel, Kp3dLabel, PersonLabelsIn};
use posefuse_data::waymo::range::{matrix_pose, mul, pose_matrix, Mat4, RangeImage};
use posefuse_data::waymo::schema::{
    col, comp, key, CAMERA_NAMES, KEYPOINT_TYPES, KP_FOREHEAD, KP_HEAD_CENTER, LASER_NAMES,
};
use posefuse_data::waymo::segments::write_lidar_keypoints;
use posefuse_data::waymo::table::{Columns, ComponentWriter};

/// Frame period (µs): 10 Hz.
pub const FRAME_US: i64 = 100_000;
/// Duration of one TOP revolution (s).
pub const SWEEP_S: f64 = 0.1;
/// Range noise (m) and dropout probability of every return.
const RANGE_NOISE_M: f64 = 0.02;
const DROPOUT: f64 = 0.02;
const TOP_MAX_RANGE: f64 = 75.0;
const SHORT_MAX_RANGE: f64 = 20.0;

/// What to simulate.
#[derive(Debug, Clone)]
pub struct WaymoSimOptions {
    pub out: PathBuf,
    pub seed: u64,
    pub segments: usize,
    pub frames: usize,
    /// TOP range image rows × columns (Waymo: 64 × 2650).
    pub top: [usize; 2],
    /// The four short-range lasers' rows × columns (Waymo: 200 × 600).
    pub short: [usize; 2],
    /// Camera images are 1920×1280 times this.
    pub image_scale: f64,
    /// Vehicle speed (m/s), straight ahead.
    pub speed_mps: f64,
    /// Fraction of camera objects that carry keypoint labels.
    pub keypoint_fraction: f64,
    /// Write the alternate physical types (names as strings, int32 lists, float↔double).
    pub alt_types: bool,
    pub profile: Profile,
    /// Frames per row group of the large components.
    pub frames_per_row_group: usize,
    pub jobs: Option<usize>,
}

impl WaymoSimOptions {
    /// Waymo's sizes.
    pub fn full(out: PathBuf) -> WaymoSimOptions {
        WaymoSimOptions {
            out,
            seed: 0,
            segments: 1,
            frames: 20,
            top: [64, 2650],
            short: [200, 600],
            image_scale: 1.0,
            speed_mps: 15.0,
            keypoint_fraction: 0.35,
            alt_types: false,
            profile: Profile::default(),
            frames_per_row_group: 4,
            jobs: None,
        }
    }
}

/// One laser of the simulated vehicle.
#[derive(Debug, Clone)]
pub struct SimLaser {
    pub name: i64,
    pub extrinsic: Mat4,
    /// Row inclinations, row 0 highest.
    pub rows: Vec<f64>,
    pub cols: usize,
    /// Stored non-uniform inclinations (lowest first); empty for uniform lasers.
    pub stored: Vec<f64>,
    pub min: f64,
    pub max: f64,
    pub max_range: f64,
}

/// The fixed sensors of a segment.
#[derive(Debug, Clone)]
pub struct Rig {
    pub cameras: Vec<(i64, Camera)>,
    pub lasers: Vec<SimLaser>,
}

fn yawed(yaw: f64, t: V3) -> Mat4 {
    let mut m = pose_matrix([0.0, 0.0, yaw, t[0], t[1], t[2]]);
    m[3] = [0.0, 0.0, 0.0, 1.0];
    m
}

/// The rig at the given sizes.
pub fn rig(o: &WaymoSimOptions) -> posefuse_data::error::Result<Rig> {
    let front = nominal_camera()?.to_calibration();
    let s = o.image_scale;
    let mut cameras = Vec::new();
    for (i, yaw) in [0.0f64, 45.0, -45.0, 90.0, -90.0].iter().enumerate() {
        let mut c = front.clone();
        for v in c.intrinsic.iter_mut().take(4) {
            *v *= s;
        }
        c.width = (1920.0 * s).round() as u32;
        c.height = (1280.0 * s).round() as u32;
        let e = posefuse_data::waymo::range::mat4(&std::array::from_fn(|k| front.extrinsic[k]));
        let m = mul(&yawed(yaw.to_radians(), [0.0; 3]), &e);
        c.extrinsic = m.iter().flatten().copied().collect();
        cameras.push((i as i64 + 1, Camera::from_calibration(&c)?));
    }
    // TOP: the simulator's 64 inclinations, resampled to the requested rows.
    let sim = posefuse_data::sim::lidar::inclinations();
    let h = o.top[0].max(2);
    let top_rows: Vec<f64> = (0..h)
        .map(|r| {
            let x = r as f64 * (sim.len() - 1) as f64 / (h - 1) as f64;
            let i = (x.floor() as usize).min(sim.len() - 2);
            sim[i] + (sim[i + 1] - sim[i]) * (x - i as f64)
        })
        .collect();
    let mut lasers = vec![SimLaser {
        name: 1,
        extrinsic: yawed(0.0, LIDAR_ORIGIN),
        stored: top_rows.iter().rev().copied().collect(),
        min: top_rows[h - 1],
        max: top_rows[0],
        rows: top_rows,
        cols: o.top[1],
        max_range: TOP_MAX_RANGE,
    }];
    let (min, max) = ((-60f64).to_radians(), 30f64.to_radians());
    let hs = o.short[0];
    let uniform: Vec<f64> = (0..hs).rev().map(|i| min + (i as f64 + 0.5) / hs as f64 * (max - min)).collect();
    for (name, yaw, t) in [
        (2, 0.0f64, [4.0, 0.0, 0.75]),
        (3, 90.0, [1.6, 1.0, 0.95]),
        (4, -90.0, [1.6, -1.0, 0.95]),
        (5, 180.0, [-1.1, 0.0, 0.9]),
    ] {
        lasers.push(SimLaser {
            name,
            extrinsic: yawed(yaw.to_radians(), t),
            rows: uniform.clone(),
            cols: o.short[1],
            stored: Vec::new(),
            min,
            max,
            max_range: SHORT_MAX_RANGE,
        });
    }
    Ok(Rig { cameras, lasers })
}

/// World-from-vehicle at time `t` (s since the segment start): straight along a heading.
pub fn vehicle_pose(seed: u64, t: f64, speed: f64) -> Mat4 {
    let h = hash(&[seed, 77]);
    let heading = (h % 6283) as f64 / 1000.0;
    let p0 = [300.0 + (h >> 20) as f64 % 500.0, -200.0 + (h >> 30) as f64 % 300.0, 4.0];
    let d = speed * t;
    pose_matrix([0.0, 0.0, heading, p0[0] + d * heading.cos(), p0[1] + d * heading.sin(), p0[2]])
}

/// Time offset (s) from the frame's timestamp at which TOP column `c` of `w` is measured.
pub fn column_time(c: usize, w: usize) -> f64 {
    ((c as f64 + 0.5) / w as f64 - 0.5) * SWEEP_S
}

/// One laser's row of a frame: (name, return 1, return 2, TOP pixel poses).
pub type LaserRow = (i64, RangeImage, RangeImage, Option<RangeImage>);
/// One `camera_hkp` row: (camera, camera object id, keypoints).
pub type CameraHkpRow = (i64, String, Vec<Kp2dLabel>);

/// Everything one simulated frame writes, plus the simulator's own view of it.
pub struct SimFrame {
    pub timestamp: i64,
    pub vehicle_pose: Mat4,
    /// Per laser: (name, return 1, return 2, TOP pixel poses).
    pub lasers: Vec<LaserRow>,
    pub images: Vec<(i64, Vec<u8>)>,
    pub lidar_boxes: Vec<(String, Box3d)>,
    pub camera_boxes: Vec<(i64, String, Box2d)>,
    pub associations: Vec<(i64, String, String)>,
    pub camera_hkp: Vec<CameraHkpRow>,
    pub lidar_hkp: Vec<(String, Vec<Kp3dLabel>)>,
    /// Every return's true point in the vehicle frame at the frame's timestamp.
    pub points: Vec<[f32; 3]>,
    /// The TOP laser's first returns: (row, column, true point).
    pub top_truth: Vec<(usize, usize, [f32; 3])>,
}

/// A cone around a pedestrian (from a laser origin) inside which rays see the scene.
struct Window {
    dir: V3,
    cos_half: f64,
    candidates: Vec<u32>,
}

fn windows(world: &World, origin: V3, slack: f64) -> Vec<Window> {
    let scene = &world.scene;
    world
        .persons
        .iter()
        .map(|p| {
            let b = &p.box3d;
            let c = [b.center_x, b.center_y, b.center_z];
            let r = 0.5 * (b.length * b.length + b.width * b.width + b.height * b.height).sqrt() + 0.3 + slack;
            let v = posefuse_data::sim::math::sub(c, origin);
            let d = posefuse_data::sim::math::norm(v);
            let half = if d <= r { std::f64::consts::PI } else { (r / d).asin() };
            let dir = posefuse_data::sim::math::normalize(v);
            let candidates = (0..scene.prims.len() as u32)
                .filter(|&i| {
                    let q = &scene.prims[i as usize];
                    let u = posefuse_data::sim::math::sub(q.center, origin);
                    let du = posefuse_data::sim::math::norm(u);
                    if du <= q.radius + slack {
                        return true;
                    }
                    let ang = posefuse_data::sim::math::dot(posefuse_data::sim::math::normalize(u), dir)
                        .clamp(-1.0, 1.0)
                        .acos();
                    ang <= half + ((q.radius + slack) / du).min(1.0).asin()
                })
                .collect();
            Window { dir, cos_half: half.cos(), candidates }
        })
        .collect()
}

/// Scans one laser: range images of both returns (and the TOP's pixel poses), the true points
/// in the frame's vehicle frame and which object each return hit.
#[allow(clippy::too_many_arguments)]
fn scan_laser<R: Rng>(
    world: &World,
    laser: &SimLaser,
    frame_pose: &Mat4,
    speed: f64,
    rng: &mut R,
    points: &mut Vec<[f32; 3]>,
    hits: &mut Vec<(u32, V3)>,
    truth: &mut Vec<(usize, usize, [f32; 3])>,
) -> (RangeImage, RangeImage, Option<RangeImage>) {
    let (h, w) = (laser.rows.len(), laser.cols);
    let e = laser.extrinsic;
    let origin0 = [e[0][3], e[1][3], e[2][3]];
    let moving = laser.name == posefuse_data::waymo::schema::LASER_TOP;
    let slack = if moving { speed.abs() * SWEEP_S } else { 0.0 };
    let wins = windows(world, origin0, slack);
    let noise = Normal::new(0.0, RANGE_NOISE_M).ok();
    let mut ri1 = vec![0.0f32; h * w * 4];
    let mut ri2 = vec![0.0f32; h * w * 4];
    for px in ri1.chunks_exact_mut(4).chain(ri2.chunks_exact_mut(4)) {
        px[0] = -1.0;
    }
    let mut poses = moving.then(|| vec![0.0f32; h * w * 6]);
    let yaw = e[1][0].atan2(e[0][0]);
    for c in 0..w {
        let ratio = ((w - c) as f64 - 0.5) / w as f64;
        let az = (ratio * 2.0 - 1.0) * std::f64::consts::PI - yaw;
        let dt = if moving { column_time(c, w) } else { 0.0 };
        let o = [origin0[0] + speed * dt, origin0[1], origin0[2]];
        if let Some(p) = poses.as_mut() {
            let m = mul(frame_pose, &pose_matrix([0.0, 0.0, 0.0, speed * dt, 0.0, 0.0]));
            let v = matrix_pose(&m);
            for r in 0..h {
                for (i, x) in v.iter().enumerate() {
                    p[(r * w + c) * 6 + i] = *x as f32;
                }
            }
        }
        for (r, inc) in laser.rows.iter().enumerate() {
            let ds = [inc.cos() * az.cos(), inc.cos() * az.sin(), inc.sin()];
            let d = [
                e[0][0] * ds[0] + e[0][1] * ds[1] + e[0][2] * ds[2],
                e[1][0] * ds[0] + e[1][1] * ds[1] + e[1][2] * ds[2],
                e[2][0] * ds[0] + e[2][1] * ds[1] + e[2][2] * ds[2],
            ];
            let win = wins.iter().find(|wn| posefuse_data::sim::math::dot(wn.dir, d) >= wn.cos_half);
            let cands: &[u32] = win.map_or(&[], |wn| &wn.candidates);
            let Some(hit) = world.scene.cast(o, d, cands, laser.max_range) else {
                continue;
            };
            if rng.random_bool(DROPOUT) {
                continue;
            }
            let t = hit.t + noise.map_or(0.0, |n| n.sample(rng));
            let idx = (r * w + c) * 4;
            ri1[idx] = t as f32;
            ri1[idx + 1] = if hit.prim.is_some() { 0.3 } else { 0.1 };
            let x = madd(o, d, t as f32 as f64);
            points.push([x[0] as f32, x[1] as f32, x[2] as f32]);
            if moving {
                truth.push((r, c, [x[0] as f32, x[1] as f32, x[2] as f32]));
            }
            hits.push((world.scene.object_of(&hit), x));
            // A second return from what lies behind a thing the first one hit.
            if hit.prim.is_some() {
                let skip = hit.t + 0.3;
                if let Some(h2) = world.scene.cast(madd(o, d, skip), d, cands, laser.max_range - skip) {
                    let t2 = skip + h2.t;
                    ri2[idx] = t2 as f32;
                    ri2[idx + 1] = 0.05;
                    let x2 = madd(o, d, t2 as f32 as f64);
                    points.push([x2[0] as f32, x2[1] as f32, x2[2] as f32]);
                    hits.push((world.scene.object_of(&h2), x2));
                }
            }
        }
    }
    let shape = |ch: i64| [h as i64, w as i64, ch];
    let pose = poses.map(|p| RangeImage::new(p, &shape(6))).transpose().ok().flatten();
    (
        RangeImage::new(ri1, &shape(4)).unwrap_or(RangeImage { shape: [h, w, 4], values: vec![] }),
        RangeImage::new(ri2, &shape(4)).unwrap_or(RangeImage { shape: [h, w, 4], values: vec![] }),
        pose,
    )
}

/// The simulator's frame `index` of segment `seg` seen by the rig.
pub fn simulate_frame(
    o: &WaymoSimOptions,
    rig: &Rig,
    seg: usize,
    index: usize,
    cfg: &PipelineConfig,
) -> posefuse_data::error::Result<(SimFrame, Vec<Sample>)> {
    let seg_seed = hash(&[o.seed, seg as u64]);
    let mut rng = frame_rng(seg_seed, index);
    let n = persons_in_frame(&mut rng);
    let mut world = sample_world(&mut rng, n, o.profile)?;
    world.camera = rig.cameras[0].1.clone();
    let t = index as f64 * FRAME_US as f64 * 1e-6;
    let frame_pose = vehicle_pose(seg_seed, t, o.speed_mps);
    let mut points = Vec::new();
    let mut hits = Vec::new();
    let mut lasers = Vec::new();
    let mut top_truth = Vec::new();
    for l in &rig.lasers {
        let (a, b, p) =
            scan_laser(&world, l, &frame_pose, o.speed_mps, &mut rng, &mut points, &mut hits, &mut top_truth);
        lasers.push((l.name, a, b, p));
    }
    let mut f = SimFrame {
        timestamp: 1_600_000_000_000_000 + index as i64 * FRAME_US,
        vehicle_pose: frame_pose,
        lasers,
        images: Vec::new(),
        lidar_boxes: Vec::new(),
        camera_boxes: Vec::new(),
        associations: Vec::new(),
        camera_hkp: Vec::new(),
        lidar_hkp: Vec::new(),
        points: Vec::new(),
        top_truth,
    };
    // Labels per camera; persons are kept when the FRONT camera labels them.
    let mut samples = Vec::new();
    let mut kept = Vec::new();
    let sensor = LIDAR_ORIGIN;
    for (li, p) in world.persons.iter().enumerate() {
        let on_person: Vec<V3> = hits.iter().filter(|h| h.0 == p.object).map(|h| h.1).collect();
        let Some(front) = label_person(&world, p, &on_person, &mut rng) else {
            continue;
        };
        let id = format!("ped{index:04}{li}");
        // the simulator's own 3D labels: every keypoint of a person with one seen, those neither
        // seen nor hit marked occluded
        let mut kps: Vec<Kp3dLabel> = (0..K)
            .filter(|&k| front.visible_3d[k] || front.occluded_3d[k])
            .map(|k| Kp3dLabel { kind: KEYPOINT_TYPES[k], xyz: p.keypoints[k], occluded: front.occluded_3d[k] })
            .collect();
        let head = head_center(p.keypoints[0], p.heading);
        kps.push(Kp3dLabel { kind: KP_HEAD_CENTER, xyz: head, occluded: false });
        kps.shuffle(&mut rng);
        f.lidar_boxes.push((id.clone(), p.box3d));
        f.lidar_hkp.push((id.clone(), kps));
        kept.push((li, id, on_person));
    }
    for (cam_name, cam) in &rig.cameras {
        let mut cw = world.clone();
        cw.camera = cam.clone();
        let mut labelled = Vec::new();
        for (li, id, on_person) in &kept {
            let p = &world.persons[*li];
            let Some(l) = label_person(&cw, p, on_person, &mut rng) else {
                continue;
            };
            let cid = format!("{id}-{}", CAMERA_NAMES[*cam_name as usize - 1]);
            f.camera_boxes.push((*cam_name, cid.clone(), l.box2d));
            f.associations.push((*cam_name, cid.clone(), id.clone()));
            if rng.random_bool(o.keypoint_fraction.clamp(0.0, 1.0)) {
                let kps = camera_keypoints(&l, p, cam, &mut rng);
                f.camera_hkp.push((*cam_name, cid, kps));
            }
            labelled.push(l);
        }
        let img = if labelled.is_empty() {
            let coarse = posefuse_data::sim::render::render(
                &cw,
                posefuse_data::sim::render::Region {
                    x0: 0,
                    y0: 0,
                    w: cam.width.div_ceil(16),
                    h: cam.height.div_ceil(16),
                    step: 16,
                },
            )
            .image;
            image::imageops::resize(&coarse, cam.width, cam.height, image::imageops::FilterType::Triangle)
        } else {
            let wins: Vec<_> =
                labelled.iter().map(|l| posefuse_core::pipeline::CropTransform::for_box(&l.box2d, cfg)).collect();
            render_frame_image(&cw, &wins)
        };
        f.images.push((*cam_name, encode_jpeg(&img)?));
    }
    // The simulator's direct prepared samples: the same labels, its own points.
    for (cam_name, cid, kps) in &f.camera_hkp {
        let cam = &rig.cameras[*cam_name as usize - 1].1;
        let Some(jpeg) = f.images.iter().find(|i| i.0 == *cam_name) else { continue };
        let Some(b2) = f.camera_boxes.iter().find(|b| &b.1 == cid) else { continue };
        let Some(a) = f.associations.iter().find(|a| &a.1 == cid) else { continue };
        let Some(b3) = f.lidar_boxes.iter().find(|b| b.0 == a.2) else { continue };
        let k3 = f.lidar_hkp.iter().find(|k| k.0 == a.2).map(|k| k.1.as_slice()).unwrap_or(&[]);
        let labels = PersonLabelsIn::new(b3.1, b2.2, kps, k3);
        if !labels.trainable() {
            continue;
        }
        samples.push(person_sample(&jpeg.1, cam, &points, sensor, &labels, cfg, 1024, index as i32)?);
    }
    f.points = points;
    Ok((f, samples))
}

/// The head centre: behind the nose along the heading.
fn head_center(nose: V3, heading: f64) -> V3 {
    [nose[0] - 0.08 * heading.cos(), nose[1] - 0.08 * heading.sin(), nose[2] + 0.02]
}

/// Camera keypoints as annotators leave them: visible keypoints (the nose skipped for 40 % of
/// persons), some occluded ones marked occluded, FOREHEAD and HEAD_CENTER, in random order.
fn camera_keypoints<R: Rng>(
    l: &posefuse_data::sim::labels::PersonLabels,
    p: &posefuse_data::sim::world::PlacedPerson,
    cam: &Camera,
    rng: &mut R,
) -> Vec<Kp2dLabel> {
    let inside = |u: [f64; 2]| {
        u[0].is_finite() && u[0] >= 0.0 && u[1] >= 0.0 && u[0] < cam.width as f64 && u[1] < cam.height as f64
    };
    let skip_nose = rng.random_bool(0.4);
    let mut out = Vec::new();
    for (k, &kind) in KEYPOINT_TYPES.iter().enumerate() {
        if l.visible_2d[k] {
            if k == 0 && skip_nose {
                continue;
            }
            out.push(Kp2dLabel { kind, uv: l.uv_label[k], occluded: false });
        } else if inside(l.uv_true[k]) && rng.random_bool(0.5) {
            out.push(Kp2dLabel { kind, uv: l.uv_label[k], occluded: true });
        }
    }
    let head = head_center(p.keypoints[0], p.heading);
    for (kind, q) in
        [(KP_FOREHEAD, [p.keypoints[0][0], p.keypoints[0][1], p.keypoints[0][2] + 0.06]), (KP_HEAD_CENTER, head)]
    {
        let pr = cam.project(q);
        if pr.in_image {
            out.push(Kp2dLabel { kind, uv: pr.uv, occluded: false });
        }
    }
    out.shuffle(rng);
    out
}

/// The name of simulated segment `seg`.
pub fn segment_name(seed: u64, seg: usize) -> String {
    format!("sim{seed}_{seg:04}_0000_000_0000")
}

fn key_cols(c: &mut Columns, segment: &str, n: usize) {
    c.string(key::SEGMENT, &vec![segment.to_owned(); n]);
}

fn flat(m: &Mat4) -> Vec<f64> {
    m.iter().flatten().copied().collect()
}

fn calibration_batches(
    rig: &Rig,
    segment: &str,
    alt: bool,
) -> posefuse_data::error::Result<(arrow_array::RecordBatch, arrow_array::RecordBatch)> {
    let mut c = Columns::new(alt);
    let n = rig.cameras.len();
    key_cols(&mut c, segment, n);
    c.enum8(key::CAMERA, &rig.cameras.iter().map(|x| x.0).collect::<Vec<_>>(), &CAMERA_NAMES);
    let cals: Vec<CameraCalibration> = rig.cameras.iter().map(|x| x.1.to_calibration()).collect();
    for (i, name) in col::CAM_INTRINSIC.iter().enumerate() {
        c.double(name, &cals.iter().map(|k| k.intrinsic[i]).collect::<Vec<_>>());
    }
    c.fixed_f64(col::CAM_EXTRINSIC, &cals.iter().map(|k| k.extrinsic.clone()).collect::<Vec<_>>(), 16);
    c.int32(col::CAM_WIDTH, &cals.iter().map(|k| k.width as i64).collect::<Vec<_>>());
    c.int32(col::CAM_HEIGHT, &cals.iter().map(|k| k.height as i64).collect::<Vec<_>>());
    let cams = c.finish()?;
    let mut l = Columns::new(alt);
    key_cols(&mut l, segment, rig.lasers.len());
    l.enum8(key::LASER, &rig.lasers.iter().map(|x| x.name).collect::<Vec<_>>(), &LASER_NAMES);
    l.fixed_f64(col::LASER_EXTRINSIC, &rig.lasers.iter().map(|x| flat(&x.extrinsic)).collect::<Vec<_>>(), 16);
    l.double(col::INCL_MIN, &rig.lasers.iter().map(|x| x.min).collect::<Vec<_>>());
    l.double(col::INCL_MAX, &rig.lasers.iter().map(|x| x.max).collect::<Vec<_>>());
    // The stored inclinations stay double in every release we know.
    let mut lc = l;
    let alt_saved = lc.alt;
    lc.alt = false;
    lc.list_f64(col::INCL_VALUES, &rig.lasers.iter().map(|x| x.stored.clone()).collect::<Vec<_>>());
    lc.alt = alt_saved;
    Ok((cams, lc.finish()?))
}

/// The writers of one segment's components.
struct SegmentWriters {
    w: Vec<(&'static str, ComponentWriter)>,
}

impl SegmentWriters {
    fn get(&mut self, name: &str) -> posefuse_data::error::Result<&mut ComponentWriter> {
        self.w
            .iter_mut()
            .find(|x| x.0 == name)
            .map(|x| &mut x.1)
            .ok_or_else(|| posefuse_data::invalid!("writer {name}"))
    }
}

/// Writes a chunk of frames (one row group per component).
fn write_frames(
    w: &mut SegmentWriters,
    frames: &[SimFrame],
    segment: &str,
    alt: bool,
) -> posefuse_data::error::Result<()> {
    // camera_image
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, i64, &Vec<u8>)> =
        frames.iter().flat_map(|f| f.images.iter().map(move |i| (f.timestamp, i.0, &i.1))).collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.enum8(key::CAMERA, &rows.iter().map(|r| r.1).collect::<Vec<_>>(), &CAMERA_NAMES);
    c.binary(col::IMAGE, &rows.iter().map(|r| r.2.clone()).collect::<Vec<_>>());
    w.get(comp::CAMERA_IMAGE)?.write(&c.finish()?)?;
    // lidar and lidar_pose
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, &LaserRow)> =
        frames.iter().flat_map(|f| f.lasers.iter().map(move |l| (f.timestamp, l))).collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.enum8(key::LASER, &rows.iter().map(|r| r.1 .0).collect::<Vec<_>>(), &LASER_NAMES);
    let shape = |ri: &RangeImage| ri.shape.iter().map(|&s| s as i64).collect::<Vec<_>>();
    c.list_f32(col::RI1_VALUES, &rows.iter().map(|r| r.1 .1.values.clone()).collect::<Vec<_>>());
    c.fixed_i32(col::RI1_SHAPE, &rows.iter().map(|r| shape(&r.1 .1)).collect::<Vec<_>>(), 3);
    c.list_f32(col::RI2_VALUES, &rows.iter().map(|r| r.1 .2.values.clone()).collect::<Vec<_>>());
    c.fixed_i32(col::RI2_SHAPE, &rows.iter().map(|r| shape(&r.1 .2)).collect::<Vec<_>>(), 3);
    w.get(comp::LIDAR)?.write(&c.finish()?)?;
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, i64, &RangeImage)> = frames
        .iter()
        .flat_map(|f| f.lasers.iter().filter_map(move |l| l.3.as_ref().map(|p| (f.timestamp, l.0, p))))
        .collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.enum8(key::LASER, &rows.iter().map(|r| r.1).collect::<Vec<_>>(), &LASER_NAMES);
    c.list_f32(col::POSE_VALUES, &rows.iter().map(|r| r.2.values.clone()).collect::<Vec<_>>());
    c.fixed_i32(col::POSE_SHAPE, &rows.iter().map(|r| shape(r.2)).collect::<Vec<_>>(), 3);
    w.get(comp::LIDAR_POSE)?.write(&c.finish()?)?;
    // vehicle_pose
    let mut c = Columns::new(alt);
    key_cols(&mut c, segment, frames.len());
    c.int64(key::TIMESTAMP, &frames.iter().map(|f| f.timestamp).collect::<Vec<_>>());
    c.fixed_f64(col::VEHICLE_POSE, &frames.iter().map(|f| flat(&f.vehicle_pose)).collect::<Vec<_>>(), 16);
    w.get(comp::VEHICLE_POSE)?.write(&c.finish()?)?;
    // lidar_box
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, &String, &Box3d)> =
        frames.iter().flat_map(|f| f.lidar_boxes.iter().map(move |b| (f.timestamp, &b.0, &b.1))).collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.string(key::LASER_OBJECT, &rows.iter().map(|r| r.1.clone()).collect::<Vec<_>>());
    let g = |f: fn(&Box3d) -> f64| rows.iter().map(|r| f(r.2)).collect::<Vec<_>>();
    c.double(col::LBOX_CX, &g(|b| b.center_x));
    c.double(col::LBOX_CY, &g(|b| b.center_y));
    c.double(col::LBOX_CZ, &g(|b| b.center_z));
    c.double(col::LBOX_SX, &g(|b| b.length));
    c.double(col::LBOX_SY, &g(|b| b.width));
    c.double(col::LBOX_SZ, &g(|b| b.height));
    c.double(col::LBOX_HEADING, &g(|b| b.heading));
    c.int8(col::LBOX_TYPE, &vec![2; rows.len()]);
    w.get(comp::LIDAR_BOX)?.write(&c.finish()?)?;
    // camera_box and the association
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, i64, &String, &Box2d)> =
        frames.iter().flat_map(|f| f.camera_boxes.iter().map(move |b| (f.timestamp, b.0, &b.1, &b.2))).collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.enum8(key::CAMERA, &rows.iter().map(|r| r.1).collect::<Vec<_>>(), &CAMERA_NAMES);
    c.string(key::CAMERA_OBJECT, &rows.iter().map(|r| r.2.clone()).collect::<Vec<_>>());
    let g = |f: fn(&Box2d) -> f64| rows.iter().map(|r| f(r.3)).collect::<Vec<_>>();
    c.double(col::CBOX_CX, &g(|b| b.center_x));
    c.double(col::CBOX_CY, &g(|b| b.center_y));
    c.double(col::CBOX_SX, &g(|b| b.width));
    c.double(col::CBOX_SY, &g(|b| b.height));
    c.int8(col::CBOX_TYPE, &vec![2; rows.len()]);
    w.get(comp::CAMERA_BOX)?.write(&c.finish()?)?;
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, &(i64, String, String))> =
        frames.iter().flat_map(|f| f.associations.iter().map(move |a| (f.timestamp, a))).collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.enum8(key::CAMERA, &rows.iter().map(|r| r.1 .0).collect::<Vec<_>>(), &CAMERA_NAMES);
    c.string(key::CAMERA_OBJECT, &rows.iter().map(|r| r.1 .1.clone()).collect::<Vec<_>>());
    c.string(key::LASER_OBJECT, &rows.iter().map(|r| r.1 .2.clone()).collect::<Vec<_>>());
    w.get(comp::ASSOCIATION)?.write(&c.finish()?)?;
    // camera_hkp
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, &CameraHkpRow)> =
        frames.iter().flat_map(|f| f.camera_hkp.iter().map(move |a| (f.timestamp, a))).collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.enum8(key::CAMERA, &rows.iter().map(|r| r.1 .0).collect::<Vec<_>>(), &CAMERA_NAMES);
    c.string(key::CAMERA_OBJECT, &rows.iter().map(|r| r.1 .1.clone()).collect::<Vec<_>>());
    let l = |f: fn(&Kp2dLabel) -> f64| rows.iter().map(|r| r.1 .2.iter().map(f).collect()).collect::<Vec<Vec<f64>>>();
    c.list_i8(col::CHKP_TYPE, &rows.iter().map(|r| r.1 .2.iter().map(|k| k.kind).collect()).collect::<Vec<_>>());
    c.list_f64(col::CHKP_X, &l(|k| k.uv[0]));
    c.list_f64(col::CHKP_Y, &l(|k| k.uv[1]));
    c.list_bool(
        col::CHKP_OCCLUDED,
        &rows.iter().map(|r| r.1 .2.iter().map(|k| k.occluded).collect()).collect::<Vec<_>>(),
    );
    w.get(comp::CAMERA_HKP)?.write(&c.finish()?)?;
    // lidar_hkp
    let mut c = Columns::new(alt);
    let rows: Vec<(i64, &(String, Vec<Kp3dLabel>))> =
        frames.iter().flat_map(|f| f.lidar_hkp.iter().map(move |a| (f.timestamp, a))).collect();
    key_cols(&mut c, segment, rows.len());
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.string(key::LASER_OBJECT, &rows.iter().map(|r| r.1 .0.clone()).collect::<Vec<_>>());
    write_lidar_keypoints(&mut c, &rows.iter().map(|r| r.1 .1.as_slice()).collect::<Vec<_>>());
    w.get(comp::LIDAR_HKP)?.write(&c.finish()?)?;
    Ok(())
}

/// Writes the segments; returns the simulator's direct prepared samples of each segment (for
/// the round trip) when `keep_samples`.
pub fn simulate(o: &WaymoSimOptions, keep_samples: bool) -> posefuse_data::error::Result<Vec<Vec<Sample>>> {
    posefuse_data::ensure!(o.frames > 0 && o.segments > 0, "--frames and --segments must be positive");
    posefuse_data::ensure!(
        o.top[0] >= 2 && o.top[1] >= 2 && o.short[0] >= 2 && o.short[1] >= 2,
        "range images need at least 2×2 pixels"
    );
    posefuse_data::ensure!(o.image_scale > 0.0 && o.image_scale <= 2.0, "--image-scale must be in (0, 2]");
    let cfg = PipelineConfig::default();
    let rig = rig(o)?;
    let pool =
        rayon::ThreadPoolBuilder::new().num_threads(o.jobs.unwrap_or(0)).build().context("the worker threads")?;
    let bar = indicatif::ProgressBar::new((o.segments * o.frames) as u64);
    let mut all = Vec::new();
    for seg in 0..o.segments {
        let segment = segment_name(o.seed, seg);
        let mut w = SegmentWriters { w: Vec::new() };
        for name in [
            comp::CAMERA_IMAGE,
            comp::CAMERA_CALIBRATION,
            comp::LIDAR,
            comp::LIDAR_CALIBRATION,
            comp::LIDAR_POSE,
            comp::VEHICLE_POSE,
            comp::LIDAR_BOX,
            comp::CAMERA_BOX,
            comp::ASSOCIATION,
            comp::CAMERA_HKP,
            comp::LIDAR_HKP,
        ] {
            w.w.push((name, ComponentWriter::new(&o.out, name, &segment)?));
        }
        let (cams, lasers) = calibration_batches(&rig, &segment, o.alt_types)?;
        w.get(comp::CAMERA_CALIBRATION)?.write(&cams)?;
        w.get(comp::LIDAR_CALIBRATION)?.write(&lasers)?;
        let mut samples = Vec::new();
        let chunk = o.frames_per_row_group.max(1);
        for start in (0..o.frames).step_by(chunk) {
            let end = (start + chunk).min(o.frames);
            let done: Vec<posefuse_data::error::Result<(SimFrame, Vec<Sample>)>> =
                pool.install(|| (start..end).into_par_iter().map(|i| simulate_frame(o, &rig, seg, i, &cfg)).collect());
            let mut frames = Vec::new();
            for d in done {
                let (f, s) = d?;
                if keep_samples {
                    samples.extend(s);
                }
                frames.push(f);
            }
            write_frames(&mut w, &frames, &segment, o.alt_types)?;
            bar.inc((end - start) as u64);
        }
        for (_, cw) in w.w {
            cw.finish()?;
        }
        all.push(samples);
    }
    bar.finish_and_clear();
    Ok(all)
}

/// Writes the segments (the `posefuse simulate --format waymo-v2` entry point).
pub fn run(o: &WaymoSimOptions) -> posefuse_data::error::Result<()> {
    let started = std::time::Instant::now();
    simulate(o, false)?;
    eprintln!(
        "wrote {} segment(s) of {} frames in the Waymo v2 layout into {} in {:.1} s",
        o.segments,
        o.frames,
        o.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}
