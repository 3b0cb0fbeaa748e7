//! The gRPC API (tonic), served on the HTTP port: `Predict`, `PredictStream` and
//! `grpc.health.v1.Health`. Image and points travel as raw bytes; everything else is the JSON
//! API's frame, so both transports share `Predictor::predict`.

use std::pin::Pin;

use futures::{Stream, StreamExt};
use tonic::{Request, Response, Status};

use super::errors::grpc_status;
use super::metrics::count_grpc as count;
use super::AppState;
use crate::service::admission::Ticket;
use crate::service::api::{Mode, PoseResponse};
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{
    Box2d, Box3d, CameraCalibration, Frame, FrameCamera, Person, Points, RequestedMode, RgbPixels,
};
use posefuse_core::image_decode::{RawImage, RawImages};

/// Generated messages, server and client of `proto/posefuse.proto`.
#[allow(clippy::all, missing_docs)]
pub mod proto {
    tonic::include_proto!("posefuse.v1");
}

use proto::posefuse_server::{Posefuse, PosefuseServer};
use tonic_health::pb::health_server::{Health, HealthServer};

/// The gRPC routes: the Posefuse service (with the body limit), health checking and the Open
/// Inference Protocol's `inference.GRPCInferenceService`.
pub fn router<H: Health>(state: AppState, health: HealthServer<H>) -> axum::Router {
    let limit = state.body_limit;
    let kserve = super::kserve::grpc::service(state.clone());
    let svc = PosefuseServer::new(GrpcService { state }).max_decoding_message_size(limit);
    tonic::service::Routes::new(svc)
        .add_service(health)
        .add_service(kserve)
        .prepare()
        .into_axum_router()
        .layer(axum::middleware::map_response(too_large_is_resource_exhausted))
        .layer(axum::middleware::map_response(undecodable_is_invalid_argument))
}

/// tonic reports a message that is not valid protobuf as INTERNAL; it is the client's error.
async fn undecodable_is_invalid_argument(mut resp: axum::response::Response) -> axum::response::Response {
    let h = resp.headers();
    let internal = h.get("grpc-status").is_some_and(|v| v == "13");
    let undecodable = h.get("grpc-message").and_then(|v| v.to_str().ok()).is_some_and(is_decode_error);
    if internal && undecodable {
        resp.headers_mut().insert("grpc-status", axum::http::HeaderValue::from_static("3"));
    }
    resp
}

fn is_decode_error(message: &str) -> bool {
    message.contains("decode Protobuf") || message.contains("decode%20Protobuf")
}

/// tonic reports an over-limit message as OUT_OF_RANGE; the API promises RESOURCE_EXHAUSTED
/// (the unary case arrives as a trailers-only response, i.e. in the headers).
async fn too_large_is_resource_exhausted(mut resp: axum::response::Response) -> axum::response::Response {
    let h = resp.headers();
    let out_of_range = h.get("grpc-status").is_some_and(|v| v == "11");
    let too_large = h
        .get("grpc-message")
        .and_then(|v| v.to_str().ok())
        .is_some_and(|m| m.contains("too large") || m.contains("too%20large"));
    if out_of_range && too_large {
        resp.headers_mut().insert("grpc-status", axum::http::HeaderValue::from_static("8"));
    }
    resp
}

/// Implements the Posefuse service.
pub struct GrpcService {
    state: AppState,
}

fn mode_from_proto(v: i32) -> Result<RequestedMode> {
    match proto::Mode::try_from(v) {
        Ok(proto::Mode::Auto) => Ok(RequestedMode::Auto),
        Ok(proto::Mode::Fusion) => Ok(RequestedMode::Fusion),
        Ok(proto::Mode::Lidar) => Ok(RequestedMode::Lidar),
        Ok(proto::Mode::Camera) => Ok(RequestedMode::Camera),
        Err(_) => Err(Error::field("mode", format!("unknown mode {v}"))),
    }
}

fn mode_to_proto(m: Mode) -> proto::Mode {
    match m {
        Mode::Fusion => proto::Mode::Fusion,
        Mode::Lidar => proto::Mode::Lidar,
        Mode::Camera => proto::Mode::Camera,
    }
}

fn calibration_from_proto(c: proto::Calibration) -> CameraCalibration {
    CameraCalibration { intrinsic: c.intrinsic, extrinsic: c.extrinsic, width: c.width, height: c.height }
}

fn calibration_to_proto(c: &CameraCalibration) -> proto::Calibration {
    proto::Calibration {
        intrinsic: c.intrinsic.clone(),
        extrinsic: c.extrinsic.clone(),
        width: c.width,
        height: c.height,
    }
}

/// Decoded pixels from a message's `image_rgb` fields, when any is set.
fn rgb_from_proto(pixels: Vec<u8>, width: u32, height: u32) -> Option<RgbPixels> {
    let given = !pixels.is_empty() || width != 0 || height != 0;
    given.then_some(RgbPixels { width, height, pixels })
}

/// A gRPC request as a frame plus the raw image bytes (camera order).
pub fn frame_from_proto(r: proto::PredictRequest) -> Result<(Frame, Option<RawImages>)> {
    if !r.cameras.is_empty() && !r.image.is_empty() {
        return Err(Error::field(
            "cameras",
            "given together with the single-camera `image`: send every camera inside `cameras`, or one camera \
             without `cameras`",
        ));
    }
    if !r.points.len().is_multiple_of(12) {
        return Err(Error::field(
            "points",
            format!("{} bytes is not a whole number of f32 xyz triples (12 bytes each)", r.points.len()),
        ));
    }
    let flat = posefuse_core::frame::f32_from_le_bytes(&r.points);
    let mut persons = Vec::with_capacity(r.persons.len());
    for (i, p) in r.persons.into_iter().enumerate() {
        let b = p.box_3d.ok_or_else(|| Error::field(format!("persons[{i}].box_3d"), "required"))?;
        persons.push(Person {
            id: p.id,
            camera: (!p.camera.is_empty()).then_some(p.camera),
            box_2d: p.box_2d.map(|b| Box2d {
                center_x: b.center_x,
                center_y: b.center_y,
                width: b.width,
                height: b.height,
            }),
            box_3d: Box3d {
                center_x: b.center_x,
                center_y: b.center_y,
                center_z: b.center_z,
                length: b.length,
                width: b.width,
                height: b.height,
                heading: b.heading,
            },
            ground_truth: None,
        });
    }
    let mut images = Vec::with_capacity(r.cameras.len().max(1));
    let mut cameras = Vec::with_capacity(r.cameras.len());
    for (i, c) in r.cameras.into_iter().enumerate() {
        let calibration = c.calibration.ok_or_else(|| Error::field(format!("cameras[{i}].calibration"), "required"))?;
        images.push(c.image);
        cameras.push(FrameCamera {
            name: c.name,
            image: None,
            image_rgb: rgb_from_proto(c.image_rgb, c.image_rgb_width, c.image_rgb_height),
            calibration: calibration_from_proto(calibration),
        });
    }
    if cameras.is_empty() {
        images.push(r.image);
    }
    let frame = Frame {
        frame_id: (!r.frame_id.is_empty()).then_some(r.frame_id),
        image: None,
        image_rgb: rgb_from_proto(r.image_rgb, r.image_rgb_width, r.image_rgb_height),
        calibration: r.calibration.map(calibration_from_proto),
        cameras,
        points: Points::Flat(flat),
        persons,
        mode: mode_from_proto(r.mode)?,
    };
    Ok((frame, Some(RawImages(images.into_iter().map(RawImage::Encoded).collect()))))
}

/// A frame as its gRPC message, with the single camera's image as encoded bytes (empty: no
/// image; each of `cameras` sends its own, from its base64): the inverse of
/// [`frame_from_proto`], for clients, benches and tests.
pub fn frame_to_proto(f: &Frame, image: Vec<u8>) -> Result<proto::PredictRequest> {
    use base64::Engine;
    let mut cameras = Vec::with_capacity(f.cameras.len());
    for (i, c) in f.cameras.iter().enumerate() {
        let image = match &c.image {
            Some(text) => base64::engine::general_purpose::STANDARD
                .decode(text.as_bytes())
                .map_err(|e| Error::field(format!("cameras[{i}].image"), format!("not valid base64: {e}")))?,
            None => Vec::new(),
        };
        cameras.push(proto::Camera {
            name: c.name.clone(),
            image,
            calibration: Some(calibration_to_proto(&c.calibration)),
            image_rgb: c.image_rgb.as_ref().map(|p| p.pixels.clone()).unwrap_or_default(),
            image_rgb_width: c.image_rgb.as_ref().map_or(0, |p| p.width),
            image_rgb_height: c.image_rgb.as_ref().map_or(0, |p| p.height),
        });
    }
    Ok(proto::PredictRequest {
        frame_id: f.frame_id.clone().unwrap_or_default(),
        image,
        calibration: f.calibration.as_ref().map(calibration_to_proto),
        cameras,
        points: posefuse_core::frame::f32_to_le_bytes(&f.points.decode()?),
        persons: f
            .persons
            .iter()
            .map(|p| proto::Person {
                id: p.id.clone(),
                camera: p.camera.clone().unwrap_or_default(),
                box_2d: p.box_2d.map(box2d_to_proto),
                box_3d: Some(proto::Box3d {
                    center_x: p.box_3d.center_x,
                    center_y: p.box_3d.center_y,
                    center_z: p.box_3d.center_z,
                    length: p.box_3d.length,
                    width: p.box_3d.width,
                    height: p.box_3d.height,
                    heading: p.box_3d.heading,
                }),
            })
            .collect(),
        mode: mode_request_to_proto(f.mode) as i32,
        image_rgb: f.image_rgb.as_ref().map(|p| p.pixels.clone()).unwrap_or_default(),
        image_rgb_width: f.image_rgb.as_ref().map_or(0, |p| p.width),
        image_rgb_height: f.image_rgb.as_ref().map_or(0, |p| p.height),
    })
}

fn mode_request_to_proto(m: RequestedMode) -> proto::Mode {
    match m {
        RequestedMode::Auto => proto::Mode::Auto,
        RequestedMode::Fusion => proto::Mode::Fusion,
        RequestedMode::Lidar => proto::Mode::Lidar,
        RequestedMode::Camera => proto::Mode::Camera,
    }
}

/// A response as its gRPC message (pixels of keypoints behind the camera are NaN).
pub fn response_to_proto(r: PoseResponse) -> proto::PredictResponse {
    proto::PredictResponse {
        frame_id: r.frame_id.unwrap_or_default(),
        model_name: r.model.name,
        model_version: r.model.version,
        persons: r
            .persons
            .into_iter()
            .map(|p| proto::PersonPose {
                id: p.id,
                mode: mode_to_proto(p.mode) as i32,
                mode_reason: p.mode_reason,
                num_points: p.num_points as u32,
                keypoints: p
                    .keypoints
                    .into_iter()
                    .map(|k| {
                        let [u, v] = k.uv.unwrap_or([f64::NAN; 2]);
                        proto::Keypoint {
                            name: k.name,
                            waymo_type: k.waymo_type,
                            x: k.xyz[0],
                            y: k.xyz[1],
                            z: k.xyz[2],
                            u,
                            v,
                            score: k.score.unwrap_or(f32::NAN),
                        }
                    })
                    .collect(),
                facing: p.facing.map(|f| proto::Facing { yaw: f.yaw, confidence: f.confidence }),
                camera: p.camera.unwrap_or_default(),
                box_2d: p.box_2d.map(box2d_to_proto),
            })
            .collect(),
        skipped: r
            .skipped
            .into_iter()
            .map(|s| proto::SkippedPerson {
                index: s.index as u32,
                id: s.id,
                error: Some(proto::Error { code: s.error.code, message: s.error.message }),
            })
            .collect(),
        timings: Some(proto::Timings {
            decode_ms: r.timings.decode_ms,
            preprocess_ms: r.timings.preprocess_ms,
            queue_ms: r.timings.queue_ms,
            inference_ms: r.timings.inference_ms,
            total_ms: r.timings.total_ms,
        }),
    }
}

/// The path of the unary `Predict` method (admitted before its message is read).
pub const PREDICT_PATH: &str = "/posefuse.v1.Posefuse/Predict";

async fn predict_message(
    state: &AppState,
    msg: proto::PredictRequest,
    early: Option<std::sync::Arc<Ticket>>,
) -> Result<proto::PredictResponse> {
    let (p, timeout) = (&state.predictor, state.request_timeout);
    let ticket = p.admitted(early)?;
    let (frame, image) = frame_from_proto(msg)?;
    p.answer_admitted(&ticket, frame, image, timeout).await.map(response_to_proto)
}

type ResponseStream = Pin<Box<dyn Stream<Item = std::result::Result<proto::StreamResponse, Status>> + Send>>;

#[tonic::async_trait]
impl Posefuse for GrpcService {
    async fn predict(
        &self,
        request: Request<proto::PredictRequest>,
    ) -> std::result::Result<Response<proto::PredictResponse>, Status> {
        let ticket = super::early_admission::ticket(request.extensions());
        let r = predict_message(&self.state, request.into_inner(), ticket).await;
        count("Predict", r.as_ref().map_or_else(super::errors::grpc_code, |_| tonic::Code::Ok));
        r.map(Response::new).map_err(|e| grpc_status(&e))
    }

    type PredictStreamStream = ResponseStream;

    async fn predict_stream(
        &self,
        request: Request<tonic::Streaming<proto::PredictRequest>>,
    ) -> std::result::Result<Response<Self::PredictStreamStream>, Status> {
        let state = self.state.clone();
        let concurrency = state.batch_concurrency;
        // On drain the messages already read finish, then the stream ends with UNAVAILABLE.
        let input = super::lifecycle::end_on_drain(request.into_inner(), state.drain.clone(), || {
            Err(Status::unavailable("the server is shutting down: no further messages are read"))
        });
        let out = input
            .enumerate()
            .map(move |(i, msg)| {
                let state = state.clone();
                async move {
                    let msg = match msg {
                        Ok(m) => m,
                        // The stream cannot go on after a framing error; end it with the cause.
                        Err(s) if s.code() == tonic::Code::OutOfRange => {
                            return Err(Status::resource_exhausted(s.message().to_string()))
                        }
                        Err(s) if s.code() == tonic::Code::Internal && is_decode_error(s.message()) => {
                            return Err(Status::invalid_argument(s.message().to_string()))
                        }
                        Err(s) => return Err(s),
                    };
                    let result = match predict_message(&state, msg, None).await {
                        Ok(r) => proto::stream_response::Result::Response(r),
                        Err(e) => proto::stream_response::Result::Error(proto::Error {
                            code: e.code().to_string(),
                            message: e.to_string(),
                        }),
                    };
                    Ok(proto::StreamResponse { index: i as u64, result: Some(result) })
                }
            })
            .buffered(concurrency);
        count("PredictStream", tonic::Code::Ok);
        Ok(Response::new(Box::pin(out)))
    }
}

/// A 2D box as its message.
fn box2d_to_proto(b: posefuse_core::frame::Box2d) -> proto::Box2d {
    proto::Box2d { center_x: b.center_x, center_y: b.center_y, width: b.width, height: b.height }
}
