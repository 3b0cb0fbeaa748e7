//! The gRPC API (tonic), served on the HTTP port: `Predict`, `PredictStream` and
//! `grpc.health.v1.Health`. Image and points travel as raw bytes; everything else is the JSON
//! API's frame, so both transports share `Predictor::predict`.

use std::pin::Pin;
use std::time::Instant;

use futures::{Stream, StreamExt};
use tonic::{Request, Response, Status};

use super::api::{Mode, PoseResponse};
use super::errors::grpc_status;
use super::AppState;
use crate::error::{Error, Result};
use crate::frame::{Box2d, Box3d, CameraCalibration, Frame, Person, Points, RequestedMode, RgbPixels};

/// Generated messages, server and client of `proto/posefuse.proto`.
#[allow(clippy::all, missing_docs)]
pub mod proto {
    tonic::include_proto!("posefuse.v1");
}

use proto::posefuse_server::{Posefuse, PosefuseServer};
use tonic_health::pb::health_server::{Health, HealthServer};

/// The gRPC routes: the Posefuse service (with the body limit) and health checking.
pub fn router<H: Health>(state: AppState, health: HealthServer<H>) -> axum::Router {
    let limit = state.body_limit;
    let svc = PosefuseServer::new(GrpcService { state }).max_decoding_message_size(limit);
    tonic::service::Routes::new(svc)
        .add_service(health)
        .prepare()
        .into_axum_router()
        .layer(axum::middleware::map_response(too_large_is_resource_exhausted))
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

/// A gRPC request as a frame plus the raw image bytes.
pub fn frame_from_proto(r: proto::PredictRequest) -> Result<(Frame, Option<Vec<u8>>)> {
    let c = r.calibration.ok_or_else(|| Error::field("calibration", "required"))?;
    if !r.points.len().is_multiple_of(12) {
        return Err(Error::field(
            "points",
            format!("{} bytes is not a whole number of f32 xyz triples (12 bytes each)", r.points.len()),
        ));
    }
    let flat: Vec<f32> = r.points.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    let mut persons = Vec::with_capacity(r.persons.len());
    for (i, p) in r.persons.into_iter().enumerate() {
        let b = p.box_3d.ok_or_else(|| Error::field(format!("persons[{i}].box_3d"), "required"))?;
        persons.push(Person {
            id: p.id,
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
    let rgb_given = !r.image_rgb.is_empty() || r.image_rgb_width != 0 || r.image_rgb_height != 0;
    let image_rgb =
        rgb_given.then_some(RgbPixels { width: r.image_rgb_width, height: r.image_rgb_height, pixels: r.image_rgb });
    let frame = Frame {
        frame_id: (!r.frame_id.is_empty()).then_some(r.frame_id),
        image: None,
        image_rgb,
        calibration: CameraCalibration {
            intrinsic: c.intrinsic,
            extrinsic: c.extrinsic,
            width: c.width,
            height: c.height,
        },
        points: Points::Flat(flat),
        persons,
        mode: mode_from_proto(r.mode)?,
    };
    Ok((frame, Some(r.image)))
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

async fn predict_message(state: &AppState, msg: proto::PredictRequest) -> Result<proto::PredictResponse> {
    let t0 = Instant::now();
    let r = match frame_from_proto(msg) {
        Ok((frame, image)) => state.predictor.predict_within(frame, image, state.request_timeout).await,
        Err(e) => Err(e),
    };
    super::metrics::frame_outcome(&r);
    metrics::histogram!("posefuse_request_seconds").record(t0.elapsed().as_secs_f64());
    r.map(response_to_proto)
}

fn count(method: &'static str, code: tonic::Code) {
    metrics::counter!("posefuse_grpc_requests_total", "method" => method, "code" => format!("{code:?}")).increment(1);
}

type ResponseStream = Pin<Box<dyn Stream<Item = std::result::Result<proto::StreamResponse, Status>> + Send>>;

#[tonic::async_trait]
impl Posefuse for GrpcService {
    async fn predict(
        &self,
        request: Request<proto::PredictRequest>,
    ) -> std::result::Result<Response<proto::PredictResponse>, Status> {
        let r = predict_message(&self.state, request.into_inner()).await;
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
        let out = request
            .into_inner()
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
                        Err(s) => return Err(s),
                    };
                    let result = match predict_message(&state, msg).await {
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
