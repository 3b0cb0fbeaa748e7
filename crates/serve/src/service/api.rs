//! Response types of the HTTP API (JSON) and of the CLI; the gRPC messages mirror them.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use posefuse_core::error::{Error, Result};
use posefuse_core::frame::Box2d;
pub use posefuse_core::pipeline::Facing;

/// The model path that produced a person's pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Camera heatmaps fused into the point network.
    Fusion,
    /// Point network on LiDAR points only.
    Lidar,
    /// Camera heatmaps lifted onto the LiDAR points with the paper's eq. 1.
    Camera,
}

impl Mode {
    /// Lower-case name, as in JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Fusion => "fusion",
            Mode::Lidar => "lidar",
            Mode::Camera => "camera",
        }
    }
}

/// Poses of every person of one frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct PoseResponse {
    /// The request's `frame_id`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_id: Option<String>,
    /// The bundle that answered.
    pub model: ModelRef,
    /// One entry per answered person, in request order.
    pub persons: Vec<PersonPose>,
    /// Requested persons without a pose (e.g. no LiDAR point in their box), in request order;
    /// one person's missing data does not fail the frame. Omitted when empty.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub skipped: Vec<SkippedPerson>,
    /// Where the time went.
    pub timings: Timings,
}

/// Bundle name and version (manifest `name`, `version`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct ModelRef {
    pub name: String,
    pub version: String,
}

/// One person's pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct PersonPose {
    /// The request's person id.
    pub id: String,
    /// The `cameras` entry the person was seen with (its `box_2d`, crop and keypoint `uv` are in
    /// that camera's pixels); absent for single-camera frames and when no camera sees the person.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<String>,
    /// The model path that ran.
    pub mode: Mode,
    /// Why this mode ran.
    pub mode_reason: String,
    /// LiDAR points found inside the (margin-grown) 3D box.
    pub num_points: usize,
    /// The person's 2D box: the request's, or the projection of the 3D box (the camera crop is
    /// taken from it when the camera runs); absent when the person is outside the camera view.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub box_2d: Option<Box2d>,
    /// The 13 keypoints in the project's order.
    pub keypoints: Vec<KeypointPose>,
    /// Which way the body faces in the vehicle frame, from the predicted shoulders and hips;
    /// absent when they give no direction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub facing: Option<Facing>,
}

/// A requested person that got no pose, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct SkippedPerson {
    /// Position of the person in the request's `persons`, from 0.
    pub index: usize,
    /// The request's person id.
    pub id: String,
    /// Why no model could run (`code`, `message`, `field` as in error bodies).
    pub error: ErrorDetail,
}

/// One keypoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct KeypointPose {
    /// Keypoint name (`nose`, `left_shoulder`, ...).
    pub name: String,
    /// Waymo Open Dataset `KeypointType` id.
    pub waymo_type: u32,
    /// Position in the vehicle frame, metres (x forward, y left, z up).
    pub xyz: [f64; 3],
    /// Position in the image, pixels; null when it is behind the camera.
    pub uv: Option<[f64; 2]>,
    /// Heatmap peak (0..1) when the camera ran; null for LiDAR-only poses.
    pub score: Option<f32>,
}

/// Wall-clock time of each stage, milliseconds.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Timings {
    /// Image and points decoding.
    pub decode_ms: f64,
    /// Crops, point selection, heatmap smoothing and sampling, lifting.
    pub preprocess_ms: f64,
    /// Waiting in the inference queue (camera and point stages).
    pub queue_ms: f64,
    /// ONNX Runtime (camera and point stages; a batch's time counts fully for each member).
    pub inference_ms: f64,
    /// Whole request.
    pub total_ms: f64,
}

/// `{"error": {...}}`, the body of every error response.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

/// What went wrong.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ErrorDetail {
    /// Stable machine-readable code (`invalid_field`, `malformed_request`, `overloaded`, ...).
    pub code: String,
    /// Human-readable message naming the field when there is one.
    pub message: String,
    /// The offending field (JSON path), when there is one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
}

impl From<&Error> for ErrorDetail {
    fn from(e: &Error) -> ErrorDetail {
        ErrorDetail { code: e.code().to_string(), message: e.to_string(), field: e.field_name().map(str::to_string) }
    }
}

/// One result of a batch: a response or an error, never both.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct BatchItem {
    /// Position of the frame in the batch (NDJSON: line number among non-empty lines), from 0.
    pub index: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub response: Option<PoseResponse>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<ErrorDetail>,
}

impl BatchItem {
    /// The item at `index` for a frame's outcome.
    pub fn new(index: usize, r: Result<PoseResponse>) -> BatchItem {
        match r {
            Ok(resp) => BatchItem { index, response: Some(resp), error: None },
            Err(e) => BatchItem { index, response: None, error: Some(ErrorDetail::from(&e)) },
        }
    }
}

/// `GET /healthz`, `GET /readyz`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct HealthResponse {
    /// `ok`, `ready` or `warming_up`.
    pub status: String,
}
