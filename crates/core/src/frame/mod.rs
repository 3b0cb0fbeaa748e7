//! The frame model: what a perception stack sends for one camera frame, shared by the server,
//! the simulator (request fixtures) and evaluation. Serde types plus validation that names the
//! offending field.

use base64::Engine;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::keypoints::K;

mod cameras;
mod points;

pub use cameras::FrameCamera;

/// One frame: one LiDAR sweep, the persons to estimate and either one camera (`image` or
/// `image_rgb` with `calibration`) or several (`cameras`), never both.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Frame {
    /// Caller's identifier, echoed in the response.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_id: Option<String>,
    /// Camera image, base64 of a JPEG or PNG file. Absent: LiDAR-only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<String>,
    /// Decoded camera pixels instead of an encoded `image` (never both).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_rgb: Option<RgbPixels>,
    /// Calibration of the camera that took `image`; required unless `cameras` is given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CameraCalibration>,
    /// Several cameras of the same instant instead of `image`/`image_rgb`/`calibration`; each
    /// person uses the one it names, else the one that sees its 3D box best.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<FrameCamera>,
    /// LiDAR points in the vehicle frame (x forward, y left, z up; metres).
    pub points: Points,
    /// Persons to estimate.
    pub persons: Vec<Person>,
    /// Requested mode; `auto` picks per person.
    #[serde(default)]
    pub mode: RequestedMode,
}

/// Decoded RGB8 pixels, row-major without padding: `width·height·3` bytes, base64 in JSON (gRPC
/// sends the bytes themselves). The size must match the calibration's.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RgbPixels {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Base64 of the R, G, B bytes of each pixel, row by row from the top-left.
    #[serde(rename = "b64", with = "base64_bytes")]
    #[schema(value_type = String, format = Byte)]
    pub pixels: Vec<u8>,
}

impl RgbPixels {
    /// The pixels as an image, checked against their declared size and the calibration's.
    pub fn into_image(self, calib_width: u32, calib_height: u32) -> Result<image::RgbImage> {
        let (w, h) = (self.width, self.height);
        if (w, h) != (calib_width, calib_height) {
            return Err(Error::field(
                "image_rgb.width/height",
                format!("{w}x{h} but calibration.width/height say {calib_width}x{calib_height}"),
            ));
        }
        let expected = w as u64 * h as u64 * 3;
        if self.pixels.len() as u64 != expected {
            return Err(Error::field(
                "image_rgb.b64",
                format!("{} bytes, but {w}x{h} RGB8 pixels are {expected} bytes", self.pixels.len()),
            ));
        }
        image::RgbImage::from_raw(w, h, self.pixels)
            .ok_or_else(|| Error::field("image_rgb.b64", "pixel buffer does not fit the size"))
    }
}

/// Bytes as base64 text in JSON.
mod base64_bytes {
    use base64::Engine;
    use serde::{Deserializer, Serializer};

    pub fn serialize<S: Serializer>(bytes: &[u8], s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(&base64::engine::general_purpose::STANDARD.encode(bytes))
    }

    /// Decodes the text where the parser holds it (the request body itself when the string has
    /// no escapes): raw frames are megabytes, and an owned copy of the text would double them.
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> std::result::Result<Vec<u8>, D::Error> {
        d.deserialize_str(Base64Visitor)
    }

    struct Base64Visitor;

    impl serde::de::Visitor<'_> for Base64Visitor {
        type Value = Vec<u8>;

        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a base64 string")
        }

        fn visit_str<E: serde::de::Error>(self, text: &str) -> std::result::Result<Vec<u8>, E> {
            base64::engine::general_purpose::STANDARD
                .decode(text.as_bytes())
                .map_err(|e| E::custom(format!("not valid base64: {e}")))
        }
    }
}

/// Waymo-style camera calibration.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CameraCalibration {
    /// `[f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3]`.
    pub intrinsic: Vec<f64>,
    /// 4×4 camera→vehicle transform, row-major (16 numbers).
    pub extrinsic: Vec<f64>,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

/// LiDAR points: a flat JSON array `[x0,y0,z0,x1,...]`, or `{"b64": ...}` with base64 of a
/// little-endian f32 buffer of the same layout (the compact form perception stacks should send).
#[derive(Debug, Clone, Serialize, PartialEq, utoipa::ToSchema)]
// Deserialize: frame/points.rs (no buffering, unknown keys refused).
#[serde(untagged)]
pub enum Points {
    /// Flat array of x, y, z triples.
    Flat(Vec<f32>),
    /// Base64 of little-endian f32 x, y, z triples.
    Encoded {
        /// The base64 text.
        b64: String,
    },
}

/// Which model path to run.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq, Hash, utoipa::ToSchema)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum RequestedMode {
    /// Fusion when both modalities are usable, else the best available.
    #[default]
    Auto,
    /// Camera heatmaps fused into the point network.
    Fusion,
    /// Point network on LiDAR points only.
    Lidar,
    /// Camera heatmaps lifted to 3D with the paper's eq. 1.
    Camera,
}

/// One person to estimate.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Person {
    /// Caller's identifier, echoed in the response.
    pub id: String,
    /// The `cameras` entry (by name) to use for this person. Absent: the camera that sees the
    /// projected 3D box best. Required with `box_2d` when the frame has `cameras`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<String>,
    /// 2D box in image pixels (of the person's camera). Absent: derived from the projected 3D box.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub box_2d: Option<Box2d>,
    /// 3D box in the vehicle frame.
    pub box_3d: Box3d,
    /// Labels, for evaluation and fixtures; ignored by prediction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ground_truth: Option<GroundTruth>,
}

/// Axis-aligned 2D box: centre and size in pixels.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Box2d {
    pub center_x: f64,
    pub center_y: f64,
    pub width: f64,
    pub height: f64,
}

/// 3D box: centre (m, vehicle frame), size (length along heading, width, height) and yaw.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Box3d {
    pub center_x: f64,
    pub center_y: f64,
    pub center_z: f64,
    pub length: f64,
    pub width: f64,
    pub height: f64,
    /// Yaw about +z, radians.
    pub heading: f64,
}

/// Ground-truth keypoints of a person.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GroundTruth {
    /// 3D keypoints in the vehicle frame (13, in the project's order).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keypoints_3d: Option<Keypoints3d>,
    /// 2D keypoints in image pixels (13, in the project's order).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keypoints_2d: Option<Keypoints2d>,
}

/// 13 3D keypoints with Waymo's visibility: a keypoint is labelled when it is `visible` or
/// `occluded` (never both), and every labelled keypoint counts in the metrics (docs/DATA.md).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Keypoints3d {
    pub xyz: Vec<[f64; 3]>,
    /// Labelled and not occluded.
    pub visible: Vec<bool>,
    /// Labelled but occluded (Waymo's `is_occluded`); empty: no occluded label.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub occluded: Vec<bool>,
}

/// 13 2D keypoints with Waymo's visibility, as [`Keypoints3d`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Keypoints2d {
    pub uv: Vec<[f64; 2]>,
    /// Labelled and not occluded.
    pub visible: Vec<bool>,
    /// Labelled but occluded (Waymo's `is_occluded`); empty: no occluded label.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub occluded: Vec<bool>,
}

impl Keypoints3d {
    /// Per-keypoint visibility in Waymo's terms.
    pub fn visibility(&self) -> Vec<Visibility> {
        Visibility::of(&self.visible, &self.occluded)
    }
}

impl Keypoints2d {
    /// Per-keypoint visibility in Waymo's terms.
    pub fn visibility(&self) -> Vec<Visibility> {
        Visibility::of(&self.visible, &self.occluded)
    }
}

/// A ground-truth keypoint's label, coded as Waymo's toolkit codes it (`keypoint_data.py`:
/// 0 missing, 1 occluded, 2 visible).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Visibility {
    Missing = 0,
    Occluded = 1,
    Visible = 2,
}

impl Visibility {
    /// From the `visible` and `occluded` flags (`occluded` may be empty: none occluded).
    pub fn of(visible: &[bool], occluded: &[bool]) -> Vec<Visibility> {
        visible
            .iter()
            .enumerate()
            .map(|(k, &v)| match (v, occluded.get(k).copied().unwrap_or(false)) {
                (true, _) => Visibility::Visible,
                (false, true) => Visibility::Occluded,
                (false, false) => Visibility::Missing,
            })
            .collect()
    }

    /// Whether the keypoint counts in the metrics: labelled, occluded or not (Waymo's `mask`).
    pub fn labelled(self) -> bool {
        self != Visibility::Missing
    }

    /// Waymo's code.
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The mask of the keypoints with exactly this visibility.
    pub fn select(all: &[Visibility], which: Visibility) -> Vec<bool> {
        all.iter().map(|&v| v == which).collect()
    }

    /// The metrics' mask: every labelled keypoint.
    pub fn labelled_mask(all: &[Visibility]) -> Vec<bool> {
        all.iter().map(|v| v.labelled()).collect()
    }
}

impl Points {
    /// The points as xyz triples, checked for length and finiteness.
    pub fn decode(&self) -> Result<Vec<[f32; 3]>> {
        let flat: Vec<f32> = match self {
            Points::Flat(v) => v.clone(),
            Points::Encoded { b64 } => {
                let bytes = base64::engine::general_purpose::STANDARD
                    .decode(b64.as_bytes())
                    .map_err(|e| Error::field("points.b64", format!("not valid base64: {e}")))?;
                if bytes.len() % 12 != 0 {
                    return Err(Error::field(
                        "points.b64",
                        format!("{} bytes is not a whole number of f32 xyz triples (12 bytes each)", bytes.len()),
                    ));
                }
                f32_from_le_bytes(&bytes)
            }
        };
        if !flat.len().is_multiple_of(3) {
            return Err(Error::field(
                "points",
                format!("{} numbers is not a multiple of 3 (x, y, z per point)", flat.len()),
            ));
        }
        if let Some(i) = flat.iter().position(|v| !v.is_finite()) {
            return Err(Error::field(format!("points[{}]", i / 3), "coordinate is NaN or infinite"));
        }
        Ok(flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }

    /// Encodes points in the compact base64 form.
    pub fn encode(points: &[[f32; 3]]) -> Points {
        Points::Encoded { b64: base64::engine::general_purpose::STANDARD.encode(f32_to_le_bytes(points)) }
    }
}

/// Little-endian f32s (the compact point encoding of JSON and gRPC); a trailing partial value is
/// dropped, so callers check the length first.
pub fn f32_from_le_bytes(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

/// Little-endian f32 bytes of xyz triples.
pub fn f32_to_le_bytes(points: &[[f32; 3]]) -> Vec<u8> {
    points.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
}

fn finite(field: &str, v: f64) -> Result<()> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(Error::field(field, "is NaN or infinite"))
    }
}

/// `occluded` is empty or one flag per keypoint, and no keypoint is both visible and occluded.
fn check_occluded(field: &str, visible: &[bool], occluded: &[bool]) -> Result<()> {
    if !occluded.is_empty() && occluded.len() != K {
        return Err(Error::field(format!("{field}.occluded"), format!("needs {K} flags or none")));
    }
    match visible.iter().zip(occluded).position(|(&v, &o)| v && o) {
        Some(k) => Err(Error::field(format!("{field}.occluded[{k}]"), "a keypoint is either visible or occluded")),
        None => Ok(()),
    }
}

fn positive(field: &str, v: f64) -> Result<()> {
    finite(field, v)?;
    if v > 0.0 {
        Ok(())
    } else {
        Err(Error::field(field, format!("must be positive, got {v}")))
    }
}

impl CameraCalibration {
    /// Checks shape and values; the rigid-transform check lives in `geometry::Camera`.
    pub fn validate(&self) -> Result<()> {
        if self.intrinsic.len() != 9 {
            return Err(Error::field(
                "calibration.intrinsic",
                format!("needs 9 numbers [f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3], got {}", self.intrinsic.len()),
            ));
        }
        if self.extrinsic.len() != 16 {
            return Err(Error::field(
                "calibration.extrinsic",
                format!("needs 16 numbers (4x4 row-major), got {}", self.extrinsic.len()),
            ));
        }
        for (i, v) in self.intrinsic.iter().enumerate() {
            finite(&format!("calibration.intrinsic[{i}]"), *v)?;
        }
        for (i, v) in self.extrinsic.iter().enumerate() {
            finite(&format!("calibration.extrinsic[{i}]"), *v)?;
        }
        positive("calibration.intrinsic[0] (f_u)", self.intrinsic[0])?;
        positive("calibration.intrinsic[1] (f_v)", self.intrinsic[1])?;
        if self.width == 0 || self.height == 0 {
            return Err(Error::field(
                "calibration.width/height",
                format!("image size must be positive, got {}x{}", self.width, self.height),
            ));
        }
        Ok(())
    }
}

impl Box2d {
    /// Checks the box is finite with positive size.
    pub fn validate(&self, field: &str) -> Result<()> {
        finite(&format!("{field}.center_x"), self.center_x)?;
        finite(&format!("{field}.center_y"), self.center_y)?;
        positive(&format!("{field}.width"), self.width)?;
        positive(&format!("{field}.height"), self.height)
    }
}

impl Box3d {
    /// The box as the row `center_x, center_y, center_z, length, width, height, heading` (the
    /// Open Inference Protocol's `boxes_3d`, the shards' `box3d`).
    pub fn to_row(&self) -> [f64; 7] {
        [self.center_x, self.center_y, self.center_z, self.length, self.width, self.height, self.heading]
    }

    /// Checks the box is finite with positive size.
    pub fn validate(&self, field: &str) -> Result<()> {
        finite(&format!("{field}.center_x"), self.center_x)?;
        finite(&format!("{field}.center_y"), self.center_y)?;
        finite(&format!("{field}.center_z"), self.center_z)?;
        finite(&format!("{field}.heading"), self.heading)?;
        positive(&format!("{field}.length"), self.length)?;
        positive(&format!("{field}.width"), self.width)?;
        positive(&format!("{field}.height"), self.height)
    }
}

impl GroundTruth {
    /// Checks keypoint counts and finiteness.
    pub fn validate(&self, field: &str) -> Result<()> {
        if let Some(k3) = &self.keypoints_3d {
            if k3.xyz.len() != K || k3.visible.len() != K {
                return Err(Error::field(
                    format!("{field}.keypoints_3d"),
                    format!("needs {K} keypoints and {K} visibility flags"),
                ));
            }
            check_occluded(&format!("{field}.keypoints_3d"), &k3.visible, &k3.occluded)?;
            for (i, p) in k3.xyz.iter().enumerate() {
                for v in p {
                    finite(&format!("{field}.keypoints_3d.xyz[{i}]"), *v)?;
                }
            }
        }
        if let Some(k2) = &self.keypoints_2d {
            if k2.uv.len() != K || k2.visible.len() != K {
                return Err(Error::field(
                    format!("{field}.keypoints_2d"),
                    format!("needs {K} keypoints and {K} visibility flags"),
                ));
            }
            check_occluded(&format!("{field}.keypoints_2d"), &k2.visible, &k2.occluded)?;
            for (i, p) in k2.uv.iter().enumerate() {
                for v in p {
                    finite(&format!("{field}.keypoints_2d.uv[{i}]"), *v)?;
                }
            }
        }
        Ok(())
    }
}

impl Frame {
    /// Validates everything that can be checked without decoding the image or the points.
    pub fn validate(&self) -> Result<()> {
        self.validate_cameras()?;
        if self.persons.is_empty() {
            return Err(Error::field("persons", "at least one person is required"));
        }
        let mut ids = std::collections::HashSet::new();
        for (i, p) in self.persons.iter().enumerate() {
            let f = format!("persons[{i}]");
            if !ids.insert(p.id.as_str()) {
                return Err(Error::field(format!("{f}.id"), format!("duplicate person id `{}`", p.id)));
            }
            self.validate_person_camera(p, &f)?;
            if let Some(b) = &p.box_2d {
                b.validate(&format!("{f}.box_2d"))?;
            }
            p.box_3d.validate(&format!("{f}.box_3d"))?;
            if let Some(gt) = &p.ground_truth {
                gt.validate(&format!("{f}.ground_truth"))?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn calib() -> CameraCalibration {
        let mut ext = vec![0.0; 16];
        for i in 0..4 {
            ext[i * 5] = 1.0;
        }
        CameraCalibration {
            intrinsic: vec![1000.0, 1000.0, 960.0, 640.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            extrinsic: ext,
            width: 1920,
            height: 1280,
        }
    }

    fn frame() -> Frame {
        Frame {
            frame_id: None,
            image: None,
            image_rgb: None,
            calibration: Some(calib()),
            cameras: Vec::new(),
            points: Points::Flat(vec![10.0, 0.0, 1.0]),
            persons: vec![Person {
                id: "p".into(),
                camera: None,
                box_2d: Some(Box2d { center_x: 960.0, center_y: 640.0, width: 50.0, height: 150.0 }),
                box_3d: Box3d {
                    center_x: 10.0,
                    center_y: 0.0,
                    center_z: 1.0,
                    length: 0.6,
                    width: 0.6,
                    height: 1.8,
                    heading: 0.0,
                },
                ground_truth: None,
            }],
            mode: RequestedMode::Auto,
        }
    }

    fn field_of(r: Result<()>) -> String {
        match r {
            Err(Error::InvalidField { field, .. }) => field,
            other => panic!("expected an invalid-field error, got {other:?}"),
        }
    }

    #[test]
    fn both_point_encodings_decode_to_the_same_points() {
        let pts = vec![[1.0f32, 2.0, 3.0], [-4.5, 0.25, 1e3]];
        let flat = Points::Flat(pts.iter().flatten().copied().collect());
        assert_eq!(flat.decode().unwrap(), pts);
        assert_eq!(Points::encode(&pts).decode().unwrap(), pts);
        let json = serde_json::to_string(&Points::encode(&pts)).unwrap();
        let back: Points = serde_json::from_str(&json).unwrap();
        assert_eq!(back.decode().unwrap(), pts);
    }

    #[test]
    fn point_errors_name_the_problem() {
        let e = Points::Flat(vec![1.0, 2.0]).decode().unwrap_err();
        assert!(e.to_string().contains("multiple of 3"), "{e}");
        let e = Points::Flat(vec![1.0, f32::NAN, 2.0, 0.0, 0.0, 0.0]).decode().unwrap_err();
        assert!(matches!(&e, Error::InvalidField { field, .. } if field == "points[0]"), "{e}");
        let e = Points::Encoded { b64: "AAAA".into() }.decode().unwrap_err();
        assert!(e.to_string().contains("12 bytes"), "{e}");
        let e = Points::Encoded { b64: "!!".into() }.decode().unwrap_err();
        assert!(e.to_string().contains("base64"), "{e}");
        let inf = Points::encode(&[[f32::INFINITY, 0.0, 0.0]]).decode().unwrap_err();
        assert!(inf.to_string().contains("NaN or infinite"));
    }

    #[test]
    fn valid_frame_passes_and_round_trips_json() {
        let f = frame();
        f.validate().unwrap();
        let back: Frame = serde_json::from_str(&serde_json::to_string(&f).unwrap()).unwrap();
        assert_eq!(back, f);
    }

    #[test]
    fn each_validation_error_names_its_field() {
        let mut f = frame();
        f.calibration.as_mut().unwrap().intrinsic.pop();
        assert_eq!(field_of(f.validate()), "calibration.intrinsic");
        let mut f = frame();
        f.calibration.as_mut().unwrap().extrinsic.push(0.0);
        assert_eq!(field_of(f.validate()), "calibration.extrinsic");
        let mut f = frame();
        f.calibration.as_mut().unwrap().intrinsic[0] = 0.0;
        assert_eq!(field_of(f.validate()), "calibration.intrinsic[0] (f_u)");
        let mut f = frame();
        f.calibration.as_mut().unwrap().intrinsic[3] = f64::NAN;
        assert_eq!(field_of(f.validate()), "calibration.intrinsic[3]");
        let mut f = frame();
        f.calibration.as_mut().unwrap().width = 0;
        assert_eq!(field_of(f.validate()), "calibration.width/height");
        let mut f = frame();
        f.persons.clear();
        assert_eq!(field_of(f.validate()), "persons");
        let mut f = frame();
        f.persons[0].box_3d.height = -1.0;
        assert_eq!(field_of(f.validate()), "persons[0].box_3d.height");
        let mut f = frame();
        f.persons[0].box_2d.as_mut().unwrap().width = 0.0;
        assert_eq!(field_of(f.validate()), "persons[0].box_2d.width");
        let mut f = frame();
        f.persons[0].box_3d.center_x = f64::INFINITY;
        assert_eq!(field_of(f.validate()), "persons[0].box_3d.center_x");
        let mut f = frame();
        f.persons.push(f.persons[0].clone());
        assert_eq!(field_of(f.validate()), "persons[1].id");
        let mut f = frame();
        f.persons[0].ground_truth = Some(GroundTruth {
            keypoints_3d: Some(Keypoints3d { xyz: vec![[0.0; 3]; 12], visible: vec![true; 12], occluded: vec![] }),
            keypoints_2d: None,
        });
        assert_eq!(field_of(f.validate()), "persons[0].ground_truth.keypoints_3d");
        let gt = |visible: Vec<bool>, occluded: Vec<bool>| GroundTruth {
            keypoints_3d: None,
            keypoints_2d: Some(Keypoints2d { uv: vec![[1.0; 2]; K], visible, occluded }),
        };
        let mut f = frame();
        f.persons[0].ground_truth = Some(gt(vec![true; K], vec![false; K - 1]));
        assert_eq!(field_of(f.validate()), "persons[0].ground_truth.keypoints_2d.occluded");
        let mut both = vec![false; K];
        both[4] = true;
        f.persons[0].ground_truth = Some(gt(both.clone(), both));
        assert_eq!(field_of(f.validate()), "persons[0].ground_truth.keypoints_2d.occluded[4]");
        let mut occluded = vec![false; K];
        occluded[4] = true;
        let visible: Vec<bool> = (0..K).map(|k| k != 4 && k != 5).collect();
        f.persons[0].ground_truth = Some(gt(visible, occluded));
        assert!(f.validate().is_ok());
    }

    #[test]
    fn visibility_codes_are_waymos_and_occluded_keypoints_are_labelled() {
        let v = Visibility::of(&[true, false, false, false], &[false, true, false]);
        assert_eq!(v, [Visibility::Visible, Visibility::Occluded, Visibility::Missing, Visibility::Missing]);
        assert_eq!(v.iter().map(|x| x.code()).collect::<Vec<_>>(), [2, 1, 0, 0]);
        assert_eq!(Visibility::labelled_mask(&v), [true, true, false, false]);
        assert_eq!(Visibility::select(&v, Visibility::Occluded), [false, true, false, false]);
        assert_eq!(Visibility::select(&v, Visibility::Visible), [true, false, false, false]);
        // frames written before occlusion flags existed: every labelled keypoint was visible
        assert_eq!(Visibility::of(&[true, false], &[]), [Visibility::Visible, Visibility::Missing]);
        let k3 = Keypoints3d { xyz: vec![[0.0; 3]; 2], visible: vec![false, true], occluded: vec![true, false] };
        assert_eq!(k3.visibility(), [Visibility::Occluded, Visibility::Visible]);
        let k2 = Keypoints2d { uv: vec![[0.0; 2]; 2], visible: vec![true, false], occluded: vec![] };
        assert_eq!(k2.visibility(), [Visibility::Visible, Visibility::Missing]);
    }

    #[test]
    fn unknown_fields_and_modes_are_rejected_by_the_parser() {
        let mut v = serde_json::to_value(frame()).unwrap();
        v["mode"] = "fusion".into();
        assert_eq!(serde_json::from_value::<Frame>(v.clone()).unwrap().mode, RequestedMode::Fusion);
        v["mode"] = "telepathy".into();
        assert!(serde_json::from_value::<Frame>(v.clone()).is_err());
        v["mode"] = "auto".into();
        v["extra"] = 1.into();
        assert!(serde_json::from_value::<Frame>(v).is_err());
    }

    #[test]
    fn raw_pixels_decode_from_the_body_with_or_without_escapes() {
        let parse = |b64: &str| {
            let json = format!(r#"{{"width": 1, "height": 1, "b64": "{b64}"}}"#);
            crate::json::parse_json::<RgbPixels>(json.as_bytes())
        };
        assert_eq!(parse("AQID").unwrap().pixels, vec![1, 2, 3]);
        // an escaped character makes the parser copy the text first: the same bytes
        assert_eq!(parse(r"AQID").unwrap().pixels, vec![1, 2, 3]);
        let e = parse("not base64!").unwrap_err();
        assert_eq!(e.field_name(), Some("b64"));
        assert!(e.to_string().contains("not valid base64"), "{e}");
        assert!(parse("").unwrap().pixels.is_empty());
        let e = crate::json::parse_json::<RgbPixels>(br#"{"width": 1, "height": 1, "b64": 7}"#).unwrap_err();
        assert!(e.to_string().contains("expected a base64 string"), "{e}");
    }
}
