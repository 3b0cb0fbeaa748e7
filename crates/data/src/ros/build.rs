//! A posefuse request out of one frame's ROS 2 messages (docs/ROS.md, "Frames").
//!
//! ROS (REP 103) and Waymo agree on the body frame: x forward, y left, z up, metres. They differ
//! on cameras: a ROS image's frame is its optical frame (z along the optical axis, x right,
//! y down); Waymo's camera frame has x along the axis, y left, z up. Both project with the same
//! pinhole and plumb_bob (k1 k2 p1 p2 k3) model once in their own frames.

use std::collections::BTreeMap;

use super::msgs::{CameraInfo, PointCloud2, FLOAT32};
use super::sync::{Assembled, CameraImage, ImagePayload};
use super::tf::{yaw, TfTree};
use posefuse_core::frame::{Box3d, CameraCalibration, Frame, FrameCamera, Person, Points, RequestedMode, RgbPixels};
use posefuse_core::geometry::rigid::{apply, mul, Mat4};

/// Waymo camera coordinates to optical ones: `x_o = -y`, `y_o = -z`, `z_o = x`.
pub const WAYMO_TO_OPTICAL: Mat4 =
    [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

/// What a frame is built with.
#[derive(Debug, Clone)]
pub struct BuildOptions {
    /// A detection is a pedestrian when one of its hypotheses has one of these classes.
    pub pedestrian_classes: Vec<String>,
}

/// A frame's request, the cameras it carries, and what was left out of it and why.
#[derive(Debug, Clone)]
pub struct Built {
    pub frame: Frame,
    /// The images of `frame.cameras`, in order.
    pub images: Vec<std::sync::Arc<CameraImage>>,
    pub left_out: Vec<String>,
}

/// Why a whole frame could not be built.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skip(pub String);

/// The points of a cloud, in its own frame: float32 `x`, `y`, `z` at any offsets and steps;
/// non-finite points (no return) are dropped.
pub fn cloud_points(c: &PointCloud2) -> Result<Vec<[f32; 3]>, String> {
    let field = |name: &str| {
        c.fields.iter().find(|f| f.name == name && f.datatype == FLOAT32 && f.count >= 1).map(|f| f.offset as usize)
    };
    let (Some(x), Some(y), Some(z)) = (field("x"), field("y"), field("z")) else {
        let names: Vec<String> = c.fields.iter().map(|f| format!("{}(type {})", f.name, f.datatype)).collect();
        return Err(format!("PointCloud2 without float32 x, y and z fields (fields: {})", names.join(", ")));
    };
    let step = c.point_step as usize;
    let (w, h) = (c.width as usize, c.height as usize);
    let row = c.row_step as usize;
    if step < 4 || x.max(y).max(z) + 4 > step || row < w.saturating_mul(step) {
        return Err(format!("PointCloud2 fields at x={x} y={y} z={z} do not fit point_step {step}, row_step {row}"));
    }
    if h.saturating_mul(row) > c.data.len() {
        return Err(format!(
            "PointCloud2 of {h}×{w} points with row_step {row} needs more than its {} bytes",
            c.data.len()
        ));
    }
    let read = |at: usize| {
        let b = [c.data[at], c.data[at + 1], c.data[at + 2], c.data[at + 3]];
        if c.is_bigendian {
            f32::from_be_bytes(b)
        } else {
            f32::from_le_bytes(b)
        }
    };
    let mut out = Vec::with_capacity(w * h);
    for r in 0..h {
        for i in 0..w {
            let at = r * row + i * step;
            let p = [read(at + x), read(at + y), read(at + z)];
            if p.iter().all(|v| v.is_finite()) {
                out.push(p);
            }
        }
    }
    Ok(out)
}

/// Waymo's camera calibration of a camera whose optical frame sits at `optical_in_base`.
pub fn calibration(info: &CameraInfo, optical_in_base: &Mat4) -> Result<CameraCalibration, String> {
    let plumb_bob = matches!(info.distortion_model.as_str(), "plumb_bob" | "" if info.d.len() <= 5);
    if !plumb_bob {
        return Err(format!(
            "distortion model `{}` with {} coefficients (plumb_bob is read)",
            info.distortion_model,
            info.d.len()
        ));
    }
    if info.binning.iter().any(|b| *b > 1) || info.roi.iter().any(|v| *v != 0) {
        return Err("CameraInfo with binning or a region of interest".into());
    }
    let k = info.k;
    if k[0] <= 0.0 || k[4] <= 0.0 {
        return Err(format!("CameraInfo with focal lengths {} and {}", k[0], k[4]));
    }
    let d = |i: usize| info.d.get(i).copied().unwrap_or(0.0);
    let e = mul(optical_in_base, &WAYMO_TO_OPTICAL);
    Ok(CameraCalibration {
        intrinsic: vec![k[0], k[4], k[2], k[5], d(0), d(1), d(2), d(3), d(4)],
        extrinsic: e.iter().flatten().copied().collect(),
        width: info.width,
        height: info.height,
    })
}

/// Raw images as packed RGB (rgb8, bgr8, rgba8, bgra8, mono8), rows of `step` bytes.
pub fn raw_rgb(encoding: &str, width: u32, height: u32, step: u32, data: &[u8]) -> Result<ImagePayload, String> {
    let (channels, order): (usize, [usize; 3]) = match encoding {
        "rgb8" => (3, [0, 1, 2]),
        "bgr8" => (3, [2, 1, 0]),
        "rgba8" => (4, [0, 1, 2]),
        "bgra8" => (4, [2, 1, 0]),
        "mono8" => (1, [0, 0, 0]),
        other => return Err(format!("image encoding `{other}` (rgb8, bgr8, rgba8, bgra8 and mono8 are read)")),
    };
    let (w, h, step) = (width as usize, height as usize, step as usize);
    if w == 0 || h == 0 || step < w * channels || h.saturating_mul(step) > data.len() {
        return Err(format!("a {width}×{height} {encoding} image with step {step} in {} bytes", data.len()));
    }
    let mut pixels = Vec::with_capacity(w * h * 3);
    for row in data.chunks(step).take(h) {
        for px in row[..w * channels].chunks_exact(channels) {
            pixels.extend(order.iter().map(|&c| px[c]));
        }
    }
    Ok(ImagePayload::Rgb { width, height, pixels })
}

fn is_pedestrian(classes: &[(String, f64)], wanted: &[String]) -> bool {
    classes.iter().any(|(c, _)| wanted.iter().any(|w| w.eq_ignore_ascii_case(c)))
}

/// The request of one frame (module docs). Points and cameras are expressed in the boxes' frame.
pub fn build_frame(
    a: &Assembled,
    tf: &TfTree,
    infos: &BTreeMap<String, CameraInfo>,
    o: &BuildOptions,
) -> Result<Built, Skip> {
    let base = &a.boxes.header.frame_id;
    let mut persons: Vec<Person> = Vec::new();
    for (i, d) in a.boxes.detections.iter().enumerate() {
        if !is_pedestrian(&d.classes, &o.pedestrian_classes) {
            continue;
        }
        let mut id = if d.id.is_empty() { format!("detection-{i}") } else { d.id.clone() };
        if persons.iter().any(|p| p.id == id) {
            id = format!("{id}#{i}");
        }
        let [cx, cy, cz] = d.center.translation;
        let [length, width, height] = d.size;
        persons.push(Person {
            id,
            camera: None,
            box_2d: None,
            box_3d: Box3d {
                center_x: cx,
                center_y: cy,
                center_z: cz,
                length,
                width,
                height,
                heading: yaw(d.center.rotation),
            },
            ground_truth: None,
        });
    }
    if persons.is_empty() {
        return Err(Skip("no pedestrian among the detections".into()));
    }
    let (topic, cloud) = a.cloud.as_ref().ok_or_else(|| Skip("no LiDAR cloud within the sync window".into()))?;
    let to_base = tf.lookup(base, &cloud.header.frame_id).map_err(|e| Skip(format!("{topic}: {e}")))?;
    let points: Vec<[f32; 3]> = cloud_points(cloud)
        .map_err(|e| Skip(format!("{topic}: {e}")))?
        .into_iter()
        .map(|p| apply(&to_base, [p[0] as f64, p[1] as f64, p[2] as f64]).map(|v| v as f32))
        .collect();
    let boxes: Vec<Box3d> = persons.iter().map(|p| p.box_3d).collect();
    let points = crate::waymo::convert::near_boxes(&points, &boxes);

    let mut left_out = Vec::new();
    let mut cameras = Vec::new();
    let mut images = Vec::new();
    for img in &a.images {
        let frame_id = &img.header.frame_id;
        let calib = infos
            .get(frame_id)
            .ok_or_else(|| format!("no CameraInfo for frame `{frame_id}`"))
            .and_then(|info| tf.lookup(base, frame_id).and_then(|m| calibration(info, &m)));
        let calibration = match calib {
            Ok(c) => c,
            Err(e) => {
                left_out.push(format!("camera {}: {e}", img.topic));
                continue;
            }
        };
        let (image, image_rgb) = match &img.payload {
            ImagePayload::Encoded(bytes) => {
                use base64::Engine;
                (Some(base64::engine::general_purpose::STANDARD.encode(bytes)), None)
            }
            ImagePayload::Rgb { width, height, pixels } => {
                (None, Some(RgbPixels { width: *width, height: *height, pixels: pixels.clone() }))
            }
        };
        cameras.push(FrameCamera { name: img.topic.clone(), image, image_rgb, calibration });
        images.push(img.clone());
    }
    let calibration = match cameras.is_empty() {
        // LiDAR-only frames still name a camera, for the keypoints' pixels
        true => Some(posefuse_core::geometry::nominal_camera().map_err(|e| Skip(e.to_string()))?.to_calibration()),
        false => None,
    };
    Ok(Built {
        frame: Frame {
            frame_id: Some(a.boxes.header.stamp_ns.to_string()),
            image: None,
            image_rgb: None,
            calibration,
            cameras,
            points: Points::encode(&points),
            persons,
            mode: RequestedMode::Auto,
        },
        images,
        left_out,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::msgs::{Header, PointField};
    use posefuse_core::geometry::Camera;

    fn field(name: &str, offset: u32, datatype: u8) -> PointField {
        PointField { name: name.into(), offset, datatype, count: 1 }
    }

    fn cloud(fields: Vec<PointField>, step: u32, points: &[[f32; 3]], big: bool) -> PointCloud2 {
        let (x, y, z) = (fields[0].offset as usize, fields[1].offset as usize, fields[2].offset as usize);
        let mut data = vec![0xAAu8; step as usize * points.len()];
        for (i, p) in points.iter().enumerate() {
            for (off, v) in [(x, p[0]), (y, p[1]), (z, p[2])] {
                let b = if big { v.to_be_bytes() } else { v.to_le_bytes() };
                data[i * step as usize + off..][..4].copy_from_slice(&b);
            }
        }
        PointCloud2 {
            header: Header { stamp_ns: 0, frame_id: "lidar".into() },
            height: 1,
            width: points.len() as u32,
            fields,
            is_bigendian: big,
            point_step: step,
            row_step: step * points.len() as u32,
            data,
        }
    }

    #[test]
    fn points_are_read_at_any_offset_step_and_byte_order() {
        let pts = [[1.0, 2.0, 3.0], [-4.5, 0.25, 9.0]];
        // intensity first, z before y, padding after
        let fields =
            vec![field("x", 4, FLOAT32), field("y", 12, FLOAT32), field("z", 8, FLOAT32), field("i", 0, FLOAT32)];
        assert_eq!(cloud_points(&cloud(fields.clone(), 20, &pts, false)).unwrap(), pts);
        assert_eq!(cloud_points(&cloud(fields, 20, &pts, true)).unwrap(), pts);
        let mut c =
            cloud(vec![field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)], 12, &pts, false);
        c.data[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(cloud_points(&c).unwrap(), vec![pts[1]]);
    }

    #[test]
    fn clouds_without_float_xyz_or_with_short_data_are_named() {
        let pts = [[1.0, 2.0, 3.0]];
        let c = cloud(vec![field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, 8)], 16, &pts, false);
        let e = cloud_points(&c).unwrap_err();
        assert!(e.contains("without float32 x, y and z") && e.contains("z(type 8)"), "{e}");
        let mut c =
            cloud(vec![field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)], 12, &pts, false);
        c.width = 2;
        c.row_step = 24;
        assert!(cloud_points(&c).unwrap_err().contains("needs more than"));
        c.width = 1;
        c.point_step = 8;
        assert!(cloud_points(&c).unwrap_err().contains("do not fit"));
    }

    #[test]
    fn an_optical_frame_becomes_waymos_camera_frame() {
        // a camera 1.5 m up looking forward along base_link's x: its optical frame is
        // z forward, x right (-y), y down (-z)
        let optical_in_base: Mat4 =
            [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]];
        let info = CameraInfo {
            header: Header { stamp_ns: 0, frame_id: "cam".into() },
            height: 480,
            width: 640,
            distortion_model: "plumb_bob".into(),
            d: vec![0.0; 5],
            k: [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0],
            binning: [0, 0],
            roi: [0; 4],
        };
        let c = calibration(&info, &optical_in_base).unwrap();
        // Waymo's camera→vehicle extrinsic of a forward camera is the identity rotation
        let e: Vec<f64> = c.extrinsic.iter().map(|v| v + 0.0).collect();
        assert_eq!(e, vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.5, 0.0, 0.0, 0.0, 1.0]);
        let cam = Camera::from_calibration(&c).unwrap();
        // 10 m ahead, 1 m left and at camera height: left of the centre (u < 320), on its row
        let p = cam.project([10.0, 1.0, 1.5]);
        assert!(p.valid);
        assert!((p.uv[0] - (320.0 - 50.0)).abs() < 1e-9 && (p.uv[1] - 240.0).abs() < 1e-9, "{:?}", p.uv);
        let mut fisheye = info.clone();
        fisheye.distortion_model = "equidistant".into();
        assert!(calibration(&fisheye, &optical_in_base).unwrap_err().contains("equidistant"));
        let mut roi = info;
        roi.roi[3] = 100;
        assert!(calibration(&roi, &optical_in_base).is_err());
    }

    #[test]
    fn raw_images_become_packed_rgb() {
        // 2×1 bgr8 with 2 bytes of row padding
        let ImagePayload::Rgb { pixels, .. } = raw_rgb("bgr8", 2, 1, 8, &[1, 2, 3, 4, 5, 6, 0, 0]).unwrap() else {
            panic!("not rgb");
        };
        assert_eq!(pixels, vec![3, 2, 1, 6, 5, 4]);
        let ImagePayload::Rgb { pixels, .. } = raw_rgb("mono8", 2, 2, 2, &[7, 8, 9, 10]).unwrap() else {
            panic!("not rgb");
        };
        assert_eq!(pixels, vec![7, 7, 7, 8, 8, 8, 9, 9, 9, 10, 10, 10]);
        assert!(raw_rgb("rgb8", 2, 2, 6, &[0; 11]).is_err());
        assert!(raw_rgb("rgb8", 0, 2, 0, &[]).is_err());
        assert!(raw_rgb("yuv422", 2, 2, 4, &[0; 8]).unwrap_err().contains("yuv422"));
    }
}
