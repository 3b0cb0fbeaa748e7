//! `posefuse mcap record`: a Waymo Open Dataset v2 root (real, or written by `posefuse waymo
//! simulate`) as the ROS 2 log a vehicle would have recorded (docs/ROS.md, "Test logs"): per
//! frame, each camera's JPEG (`CompressedImage`) and `CameraInfo`, all returns of every laser as
//! one `PointCloud2` in the TOP laser's frame, and the pedestrian boxes as a
//! `Detection3DArray` in `base_link`; the sensors' mounting on `/tf_static` at each segment's
//! start. Each camera's stamp is a few milliseconds after the sweep's, as on a real vehicle.

use std::path::PathBuf;

use crate::error::Context;

use super::build::WAYMO_TO_OPTICAL;
use super::log_writer::LogWriter;
use super::msgs::{
    encode_tf, schema, CameraInfo, CompressedImage, Detection3D, Detection3DArray, Header, PointCloud2, PointField,
    Pose, TransformStamped, FLOAT32,
};
use super::tf::matrix_quaternion;
use crate::waymo::convert::frame_points;
use crate::waymo::reader::Segment;
use crate::waymo::schema::{CAMERA_NAMES, LASER_NAMES};
use posefuse_core::geometry::rigid::{apply, mat4, mul, rigid_inverse, Mat4, IDENTITY};
use posefuse_core::geometry::Camera;

/// The body frame of the log.
pub const BASE_FRAME: &str = "base_link";
/// The class the boxes are labelled with.
pub const PEDESTRIAN_CLASS: &str = "pedestrian";
/// A camera's stamp after the sweep's, per camera in Waymo's order.
const CAMERA_DELAY_NS: i64 = 7_000_000;
const LASER_TOP: i64 = 1;

/// What to record.
#[derive(Debug, Clone)]
pub struct RecordOptions {
    pub dataset: PathBuf,
    pub out: PathBuf,
    /// Frames at most (all when `None`).
    pub max_frames: Option<usize>,
}

/// What was written.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RecordSummary {
    pub segments: usize,
    pub frames: usize,
    pub images: usize,
    pub pedestrians: usize,
    pub out: String,
}

fn camera_slug(cam: i64) -> String {
    usize::try_from(cam - 1)
        .ok()
        .and_then(|i| CAMERA_NAMES.get(i))
        .map_or_else(|| format!("camera{cam}"), |n| n.to_ascii_lowercase())
}

/// Topics of a camera: image, info, and its optical frame.
pub fn camera_topics(cam: i64) -> (String, String, String) {
    let s = camera_slug(cam);
    (format!("/camera/{s}/image/compressed"), format!("/camera/{s}/camera_info"), format!("camera_{s}_optical"))
}

pub const LIDAR_TOPIC: &str = "/lidar/points";
pub const BOXES_TOPIC: &str = "/detections";
pub const TF_STATIC: &str = "/tf_static";

fn lidar_frame() -> String {
    format!("lidar_{}", LASER_NAMES.first().map_or("top".into(), |n| n.to_ascii_lowercase()))
}

fn link(stamp_ns: i64, child: String, m: &Mat4) -> TransformStamped {
    TransformStamped {
        header: Header { stamp_ns, frame_id: BASE_FRAME.into() },
        child_frame_id: child,
        transform: Pose { translation: [m[0][3], m[1][3], m[2][3]], rotation: matrix_quaternion(m) },
    }
}

fn header(stamp_ns: i64, frame_id: &str) -> Header {
    Header { stamp_ns, frame_id: frame_id.to_owned() }
}

/// Points as a cloud with x, y, z and an intensity channel (16 bytes a point).
fn cloud(h: Header, points: &[[f32; 3]]) -> PointCloud2 {
    let mut data = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in [p[0], p[1], p[2], 0.0] {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    let field = |name: &str, offset| PointField { name: name.into(), offset, datatype: FLOAT32, count: 1 };
    PointCloud2 {
        header: h,
        height: 1,
        width: points.len() as u32,
        fields: vec![field("x", 0), field("y", 4), field("z", 8), field("intensity", 12)],
        is_bigendian: false,
        point_step: 16,
        row_step: 16 * points.len() as u32,
        data,
    }
}

/// Runs `posefuse mcap record`.
pub fn record(o: &RecordOptions) -> crate::error::Result<RecordSummary> {
    let names = crate::waymo::segments::segments_in(&o.dataset)?;
    crate::ensure!(!names.is_empty(), "{}: no segments", o.dataset.display());
    let mut log = LogWriter::create(&o.out, "ros2")?;
    let mut sum = RecordSummary::default();
    let bar = indicatif::ProgressBar::new(names.len() as u64);
    'segments: for name in &names {
        let mut seg = Segment::open(&o.dataset, name, &None)?;
        let cameras: Vec<(i64, Camera)> = seg
            .cameras
            .iter()
            .map(|(n, c)| Camera::from_calibration(c).map(|cam| (*n, cam)))
            .collect::<posefuse_core::Result<_>>()
            .map_err(|e| crate::invalid!("segment {name}: component `camera_calibration`: {e}"))?;
        let lidar_in_base = seg.lasers.get(&LASER_TOP).map_or(IDENTITY, |l| mat4(&l.extrinsic));
        let base_to_lidar = rigid_inverse(&lidar_in_base);
        let start = seg.timestamps.first().copied().unwrap_or(0) * 1000;
        let mut links = vec![link(start, lidar_frame(), &lidar_in_base)];
        for (cam, c) in &cameras {
            let e: [f64; 16] =
                c.to_calibration().extrinsic.as_slice().try_into().context("a camera extrinsic of 16 numbers")?;
            let optical_in_base = mul(&mat4(&e), &rigid_inverse(&WAYMO_TO_OPTICAL));
            links.push(link(start, camera_topics(*cam).2, &optical_in_base));
        }
        log.ros(TF_STATIC, schema::TF_MESSAGE, start, &encode_tf(&links))?;
        sum.segments += 1;
        for ts in seg.timestamps.clone() {
            if o.max_frames.is_some_and(|m| sum.frames >= m) {
                break 'segments;
            }
            let wanted: Vec<i64> = cameras.iter().map(|(n, _)| *n).collect();
            let f = seg.frame(ts, &wanted).with_context(|| format!("segment {name}, frame {ts}"))?;
            let stamp = ts * 1000;
            let points: Vec<[f32; 3]> = frame_points(&seg.lasers, &f, true)?
                .iter()
                .map(|p| apply(&base_to_lidar, [p[0] as f64, p[1] as f64, p[2] as f64]).map(|v| v as f32))
                .collect();
            log.ros(LIDAR_TOPIC, schema::POINT_CLOUD2, stamp, &cloud(header(stamp, &lidar_frame()), &points).encode())?;
            for (i, (cam, c)) in cameras.iter().enumerate() {
                let Some(jpeg) = f.images.get(cam) else { continue };
                let t = stamp + CAMERA_DELAY_NS * (i as i64 + 1);
                let (image_topic, info_topic, frame) = camera_topics(*cam);
                let cal = c.to_calibration();
                let k = &cal.intrinsic;
                let info = CameraInfo {
                    header: header(t, &frame),
                    height: cal.height,
                    width: cal.width,
                    distortion_model: "plumb_bob".into(),
                    d: k[4..9].to_vec(),
                    k: [k[0], 0.0, k[2], 0.0, k[1], k[3], 0.0, 0.0, 1.0],
                    binning: [0, 0],
                    roi: [0; 4],
                };
                log.ros(&info_topic, schema::CAMERA_INFO, t, &info.encode())?;
                let msg = CompressedImage { header: header(t, &frame), format: "jpeg".into(), data: jpeg.clone() };
                log.ros(&image_topic, schema::COMPRESSED_IMAGE, t, &msg.encode())?;
                sum.images += 1;
            }
            let labels = seg.labels(ts);
            let detections: Vec<Detection3D> = labels
                .pedestrians
                .iter()
                .map(|p| {
                    let b = p.box3d;
                    let h = b.heading / 2.0;
                    Detection3D {
                        classes: vec![(PEDESTRIAN_CLASS.into(), 1.0)],
                        center: Pose {
                            translation: [b.center_x, b.center_y, b.center_z],
                            rotation: [0.0, 0.0, h.sin(), h.cos()],
                        },
                        size: [b.length, b.width, b.height],
                        id: p.id.clone(),
                    }
                })
                .collect();
            sum.pedestrians += detections.len();
            let boxes = Detection3DArray { header: header(stamp, BASE_FRAME), detections };
            log.ros(BOXES_TOPIC, schema::DETECTION3D_ARRAY, stamp, &boxes.encode())?;
            sum.frames += 1;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    sum.out = log.finish()?.display().to_string();
    Ok(sum)
}
