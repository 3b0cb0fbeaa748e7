//! The fuzz targets' bodies, shared by the `cargo fuzz` targets (fuzz_targets/) and by the
//! regression test over the kept corpus (tests/fuzz_corpus.rs), so a finding stays a test.
//! Each parses untrusted bytes the way a request path does and must return, never panic;
//! errors are expected answers.
#![allow(dead_code)]

use std::io::Cursor;

use posefuse::frame::{Box2d, CameraCalibration, Frame, Points};
use posefuse::geometry::{best_camera, projected_box, Camera};
use posefuse::image_decode::{decode_crops, open_camera, CameraImage, ImageInput};
use posefuse::pipeline::{prepare_person, CropTransform, PipelineConfig};

/// Largest image the JPEG target decodes (the server's own limit is far larger; a fuzzer's time
/// is better spent on many small files).
const MAX_SIDE: u32 = 2048;

/// The native frame JSON (`POST /v1/poses`): parse, validate, decode the points, then the
/// geometry every person goes through before any pixel (camera choice, projected box, the
/// person's points and crop).
pub fn frame_json(data: &[u8]) {
    let Ok(frame) = posefuse::json::parse_json::<Frame>(data) else { return };
    frame_checks(frame);
}

fn frame_checks(frame: Frame) {
    if frame.validate().is_err()
        || posefuse::service::limits::FrameLimits::DEFAULT.check_declared_sizes(&frame).is_err()
    {
        return;
    }
    let Ok(points) = frame.points.decode() else { return };
    let cameras: Vec<Camera> =
        frame.camera_calibrations().into_iter().filter_map(|(_, _, c)| Camera::from_calibration(c).ok()).collect();
    let cfg = PipelineConfig::default();
    for p in frame.persons.iter().take(16) {
        let cam = best_camera(&cameras, &p.box_3d).and_then(|i| cameras.get(i));
        let b2 = p.box_2d.or_else(|| cam.and_then(|c| projected_box(c, &p.box_3d)));
        let _ = prepare_person(None, cam, &points, &p.box_3d, b2.as_ref(), &cfg);
    }
}

/// A KServe v2 REST body: the first two bytes (little-endian) are the JSON part's length
/// (`Inference-Header-Content-Length`), 0xFFFF for none; then the tensors become a frame.
pub fn kserve_request(data: &[u8]) {
    if data.len() < 2 {
        return;
    }
    let (len, body) = (u16::from_le_bytes([data[0], data[1]]), &data[2..]);
    let mut headers = axum::http::HeaderMap::new();
    if len != u16::MAX {
        headers.insert("inference-header-content-length", axum::http::HeaderValue::from(len));
    }
    let Ok(req) = posefuse::server::kserve::rest::parse_request(&headers, body, "default".into(), None) else {
        return;
    };
    if let Ok((frame, _image)) = posefuse::server::kserve::tensors::frame_from_inputs(req.inputs, req.id) {
        frame_checks(frame);
    }
}

/// A gRPC `posefuse.v1.Posefuse/Predict` message: protobuf decode, then the frame conversion.
pub fn proto_frame(data: &[u8]) {
    use prost::Message;
    let Ok(msg) = posefuse::server::grpc::proto::PredictRequest::decode(data) else { return };
    if let Ok((frame, _raw)) = posefuse::server::grpc::frame_from_proto(msg) {
        frame_checks(frame);
    }
}

/// Base64 points (`points.b64`).
pub fn points_b64(data: &[u8]) {
    let points = Points::Encoded { b64: String::from_utf8_lossy(data).into_owned() };
    if let Ok(p) = points.decode() {
        assert!(p.iter().flatten().all(|v| v.is_finite()), "decoded points are finite or refused");
    }
}

/// A camera image: the header check against a calibration of the header's size, then crops at
/// several DCT scales (windows from the last bytes), as a request's decode.
pub fn jpeg_decode(data: &[u8]) {
    let Ok((w, h)) = image::ImageReader::new(Cursor::new(data))
        .with_guessed_format()
        .map_err(drop)
        .and_then(|r| r.into_dimensions().map_err(drop))
    else {
        return;
    };
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return;
    }
    let calibration = CameraCalibration {
        intrinsic: vec![w as f64, w as f64, w as f64 / 2.0, h as f64 / 2.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        extrinsic: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        width: w,
        height: h,
    };
    let input = ImageInput { raw: Some(data.to_vec()), base64: None, pixels: None, rows: None };
    let Ok(image) = open_camera(input, &calibration) else { return };
    if !matches!(image, CameraImage::Jpeg(_) | CameraImage::Png(_)) {
        return;
    }
    let tail: Vec<u8> = data.iter().rev().take(6).copied().collect();
    let windows: Vec<CropTransform> = tail
        .chunks(2)
        .map(|c| {
            let side = 8.0 + (c[0] as f64 / 255.0) * 2.0 * w.max(h) as f64;
            let b = Box2d {
                center_x: (c.get(1).copied().unwrap_or(0) as f64 / 255.0) * w as f64,
                center_y: h as f64 / 2.0,
                width: side / 2.0,
                height: side,
            };
            CropTransform::for_box(&b, &PipelineConfig::default())
        })
        .collect();
    if let Ok(Ok(crops)) = decode_crops(&image, &windows, w, h, || Ok(())) {
        assert_eq!(crops.len(), windows.len());
    }
}
