//! `posefuse mcap score` on malformed and incomplete ROS 2 logs: a clear error naming the topic
//! where a flag names it, a counted and explained skip where a frame or a camera cannot be
//! built, never a panic. The logs are written here with the library's own writer; the official
//! readers check that writer in tests/ros_logs.

use std::path::{Path, PathBuf};

use posefuse::ros::log_writer::LogWriter;
use posefuse::ros::msgs::{
    encode_tf, schema, CameraInfo, CompressedImage, Detection3D, Detection3DArray, Header, PointCloud2, PointField,
    Pose, TransformStamped, FLOAT32,
};
use posefuse::ros::tf::matrix_quaternion;
use serde_json::Value;

const FRAMES: i64 = 3;
const STEP_NS: i64 = 100_000_000;

fn model_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default")
}

/// What to break in a log.
#[derive(Default, Clone, Copy)]
struct Faults {
    no_camera_info: bool,
    cloud_without_z: bool,
    cloud_as_json: bool,
    truncated_boxes_message: bool,
}

fn header(t: i64, frame: &str) -> Header {
    Header { stamp_ns: t, frame_id: frame.into() }
}

/// 400 points inside a pedestrian-sized box 8 m ahead, in the LiDAR's frame (2 m above
/// base_link), with x, y, z (unless `without_z`) and an intensity first.
fn cloud(t: i64, without_z: bool) -> PointCloud2 {
    let mut data = Vec::new();
    for i in 0..400 {
        let f = i as f32;
        let p = [8.0 + (f * 0.37).sin() * 0.2, (f * 0.71).cos() * 0.25, -2.0 + 0.05 + (f * 0.013) % 1.6];
        data.extend_from_slice(&1.0f32.to_le_bytes());
        for v in p {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    let field = |name: &str, offset| PointField { name: name.into(), offset, datatype: FLOAT32, count: 1 };
    let mut fields = vec![field("intensity", 0), field("x", 4), field("y", 8), field("z", 12)];
    if without_z {
        fields.pop();
    }
    PointCloud2 {
        header: header(t, "lidar"),
        height: 1,
        width: 400,
        fields,
        is_bigendian: false,
        point_step: 16,
        row_step: 16 * 400,
        data,
    }
}

fn jpeg() -> Vec<u8> {
    let img = image::RgbImage::from_fn(320, 240, |x, y| image::Rgb([(x % 256) as u8, (y % 256) as u8, 90]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Jpeg).unwrap();
    out.into_inner()
}

/// The rotation of a forward camera's optical frame in base_link.
const OPTICAL_IN_BASE: [[f64; 4]; 4] =
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

fn write_log(path: &Path, f: Faults) {
    let mut log = LogWriter::create(path, "ros2").unwrap();
    let half = std::f64::consts::FRAC_1_SQRT_2;
    let links = [
        TransformStamped {
            header: header(0, "base_link"),
            child_frame_id: "lidar".into(),
            transform: Pose { translation: [0.0, 0.0, 2.0], rotation: [0.0, 0.0, 0.0, 1.0] },
        },
        // optical frame of a forward camera: z forward, x right, y down
        TransformStamped {
            header: header(0, "base_link"),
            child_frame_id: "cam_optical".into(),
            transform: Pose { translation: [0.0, 0.0, 1.5], rotation: matrix_quaternion(&OPTICAL_IN_BASE) },
        },
    ];
    log.ros("/tf_static", schema::TF_MESSAGE, 0, &encode_tf(&links)).unwrap();
    let image = jpeg();
    for i in 0..FRAMES {
        let t = 1_000_000_000 + i * STEP_NS;
        let c = cloud(t, f.cloud_without_z).encode();
        if f.cloud_as_json {
            let def = posefuse::ros::msgs::ros2msg(schema::POINT_CLOUD2).unwrap();
            let id = log.channel("/lidar/points", (schema::POINT_CLOUD2, "ros2msg", def.as_bytes()), "json").unwrap();
            log.write(id, t, b"{}").unwrap();
        } else {
            log.ros("/lidar/points", schema::POINT_CLOUD2, t, &c).unwrap();
        }
        if !f.no_camera_info {
            let info = CameraInfo {
                header: header(t + 5_000_000, "cam_optical"),
                height: 240,
                width: 320,
                distortion_model: "plumb_bob".into(),
                d: vec![0.0; 5],
                k: [300.0, 0.0, 160.0, 0.0, 300.0, 120.0, 0.0, 0.0, 1.0],
                binning: [0, 0],
                roi: [0; 4],
            };
            log.ros("/cam/camera_info", schema::CAMERA_INFO, t + 5_000_000, &info.encode()).unwrap();
        }
        let img = CompressedImage {
            header: header(t + 5_000_000, "cam_optical"),
            format: "jpeg".into(),
            data: image.clone(),
        };
        log.ros("/cam/image/compressed", schema::COMPRESSED_IMAGE, t + 5_000_000, &img.encode()).unwrap();
        let boxes = Detection3DArray {
            header: header(t, "base_link"),
            detections: vec![
                Detection3D {
                    classes: vec![("PEDESTRIAN".into(), 0.9)],
                    center: Pose { translation: [8.0, 0.0, 0.85], rotation: [0.0, 0.0, half, half] },
                    size: [0.6, 0.7, 1.7],
                    id: "walker".into(),
                },
                Detection3D {
                    classes: vec![("car".into(), 0.9)],
                    center: Pose { translation: [20.0, 5.0, 0.8], rotation: [0.0, 0.0, 0.0, 1.0] },
                    size: [4.0, 2.0, 1.5],
                    id: "car".into(),
                },
            ],
        }
        .encode();
        let boxes = if f.truncated_boxes_message && i == 1 { boxes[..boxes.len() - 9].to_vec() } else { boxes };
        log.ros("/detections", schema::DETECTION3D_ARRAY, t, &boxes).unwrap();
    }
    log.finish().unwrap();
}

/// Exit status, the summary printed, standard error.
fn score(input: &Path, extra: &[&str]) -> (bool, Option<Value>, String) {
    let out = input.with_extension("poses.mcap");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(["mcap", "score", "--workers", "1", "--model-dir"])
        .arg(model_dir())
        .arg("--in")
        .arg(input)
        .arg("--out")
        .arg(&out)
        .args(extra)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "{stderr}");
    (o.status.success(), serde_json::from_slice(&o.stdout).ok(), stderr)
}

fn scored(f: Faults, extra: &[&str]) -> Value {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("drive.mcap");
    write_log(&path, f);
    let (ok, summary, stderr) = score(&path, extra);
    assert!(ok, "{stderr}");
    summary.unwrap()
}

#[test]
fn a_whole_log_is_answered_frame_by_frame_with_the_camera() {
    let s = scored(Faults::default(), &[]);
    assert_eq!(s["frames"], FRAMES);
    assert_eq!(s["frames_answered"], FRAMES);
    // the car is not a pedestrian; the class matched in any case
    assert_eq!(s["persons"], FRAMES);
    assert_eq!(s["topics"]["images"][0], "/cam/image/compressed");
    assert_eq!(s["modes"]["fusion"], FRAMES, "{s}");
    assert!(s["cameras_left_out"].as_object().unwrap().is_empty(), "{s}");
}

#[test]
fn a_camera_without_its_camera_info_is_left_out_and_named() {
    let s = scored(Faults { no_camera_info: true, ..Faults::default() }, &[]);
    assert_eq!(s["frames_answered"], FRAMES);
    assert_eq!(s["modes"]["lidar"], FRAMES, "{s}");
    let left = &s["cameras_left_out"]["camera /cam/image/compressed"];
    assert_eq!(left["count"], FRAMES, "{s}");
    assert!(left["first"].as_str().unwrap().contains("no CameraInfo for frame `cam_optical`"), "{s}");
}

#[test]
fn a_cloud_without_xyz_skips_its_frames_with_the_topic_named() {
    let s = scored(Faults { cloud_without_z: true, ..Faults::default() }, &[]);
    assert_eq!(s["frames_answered"], 0);
    let skipped = s["frames_skipped"].as_object().unwrap();
    let (reason, c) = skipped.iter().next().unwrap();
    assert!(reason.starts_with("/lidar/points: PointCloud2 without float32 x, y and z"), "{reason}");
    assert_eq!(c["count"], FRAMES);
}

#[test]
fn an_unknown_encoding_is_an_error_on_a_named_topic_and_ignored_otherwise() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("drive.mcap");
    write_log(&path, Faults { cloud_as_json: true, ..Faults::default() });
    let (ok, _, stderr) = score(&path, &["--lidar-topic", "/lidar/points"]);
    assert!(!ok);
    assert!(stderr.contains("topic /lidar/points: message encoding `json` is not ROS 2's cdr"), "{stderr}");
    let (ok, s, stderr) = score(&path, &[]);
    assert!(ok, "{stderr}");
    let s = s.unwrap();
    assert_eq!(s["topics_ignored"][0], "/lidar/points");
    assert_eq!(s["frames_skipped"]["no LiDAR cloud within the sync window"]["count"], FRAMES);
}

#[test]
fn a_malformed_message_is_counted_and_its_frame_is_missing() {
    let s = scored(Faults { truncated_boxes_message: true, ..Faults::default() }, &[]);
    assert_eq!(s["frames"], FRAMES - 1);
    let m = &s["messages_skipped"]["/detections: vision_msgs/msg/Detection3DArray"];
    assert_eq!(m["count"], 1, "{s}");
    assert!(m["first"].as_str().unwrap().contains("more bytes"), "{s}");
}

#[test]
fn a_file_that_is_not_a_log_fails_with_its_name() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("notes.mcap");
    std::fs::write(&path, b"these are not the bytes of an MCAP file").unwrap();
    let (ok, s, stderr) = score(&path, &[]);
    assert!(!ok);
    assert!(stderr.contains("notes.mcap: the log cannot be read past message 0"), "{stderr}");
    assert_eq!(s.unwrap()["frames"], 0);
}

#[test]
fn a_short_sync_window_leaves_the_camera_out_and_a_bad_one_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("drive.mcap");
    write_log(&path, Faults::default());
    let (ok, _, stderr) = score(&path, &["--sync-ms=-1"]);
    assert!(!ok && stderr.contains("--sync-ms"), "{stderr}");
    // a window shorter than the camera's 5 ms lag leaves every frame LiDAR-only
    let s = scored(Faults::default(), &["--sync-ms", "2"]);
    assert_eq!(s["frames_answered"], FRAMES, "{s}");
    assert_eq!(s["modes"]["lidar"], FRAMES, "{s}");
}
