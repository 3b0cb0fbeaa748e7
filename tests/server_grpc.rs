//! gRPC on the HTTP port: Predict, PredictStream, health (and `posefuse health`), limits and overload.

mod server_support;

use std::time::Duration;

use posefuse::frame::Frame;
use posefuse::server::grpc::proto::{self, posefuse_client::PosefuseClient};
use server_support::*;
use tonic_health::pb::{health_check_response::ServingStatus, health_client::HealthClient, HealthCheckRequest};

/// A JSON frame as its gRPC message: raw image bytes and little-endian f32 points.
fn to_proto(f: &Frame, image: Option<Vec<u8>>) -> proto::PredictRequest {
    let pts = f.points.decode().unwrap();
    proto::PredictRequest {
        frame_id: f.frame_id.clone().unwrap_or_default(),
        image: image.unwrap_or_default(),
        calibration: Some(proto::Calibration {
            intrinsic: f.calibration.intrinsic.clone(),
            extrinsic: f.calibration.extrinsic.clone(),
            width: f.calibration.width,
            height: f.calibration.height,
        }),
        points: pts.iter().flatten().flat_map(|v| v.to_le_bytes()).collect(),
        persons: f
            .persons
            .iter()
            .map(|p| proto::Person {
                id: p.id.clone(),
                box_2d: p.box_2d.map(|b| proto::Box2d {
                    center_x: b.center_x,
                    center_y: b.center_y,
                    width: b.width,
                    height: b.height,
                }),
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
        mode: proto::Mode::Auto as i32,
        ..Default::default()
    }
}

fn three_mode_request() -> proto::PredictRequest {
    let f = three_mode_frame();
    let image = image_png(&[box_2d(&f.persons[0].box_3d), box_2d(&f.persons[2].box_3d)]);
    to_proto(&f, Some(image))
}

async fn client(s: &TestServer) -> PosefuseClient<tonic::transport::Channel> {
    PosefuseClient::connect(s.url("")).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn predict_matches_the_http_answer() {
    let s = start(config()).await;
    let mut c = client(&s).await;
    let r = c.predict(three_mode_request()).await.unwrap().into_inner();
    assert_eq!(r.frame_id, "f-3");
    assert_eq!(r.model_name, "default");
    let modes: Vec<i32> = r.persons.iter().map(|p| p.mode).collect();
    assert_eq!(modes, [proto::Mode::Fusion as i32, proto::Mode::Lidar as i32, proto::Mode::Camera as i32]);
    assert!(r.persons.iter().all(|p| p.keypoints.len() == 13));
    assert_eq!(r.persons[0].keypoints[0].name, "nose");
    // Behind the camera: no pixels (NaN); LiDAR-only: no score (NaN).
    assert!(r.persons[1].keypoints.iter().all(|k| k.u.is_nan() && k.score.is_nan()));
    // Same frame over HTTP (image as base64 of the same PNG): same keypoints.
    let http: posefuse::server::api::PoseResponse = reqwest::Client::new()
        .post(s.url("/v1/poses"))
        .json(&three_mode_frame())
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    for (g, h) in r.persons.iter().zip(&http.persons) {
        for (a, b) in g.keypoints.iter().zip(&h.keypoints) {
            assert!((a.x - b.xyz[0]).abs() < 1e-9 && (a.y - b.xyz[1]).abs() < 1e-9 && (a.z - b.xyz[2]).abs() < 1e-9);
        }
    }
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_messages_are_invalid_argument_naming_the_field() {
    let s = start(config()).await;
    let mut c = client(&s).await;
    let mut req = three_mode_request();
    req.points.pop();
    let e = c.predict(req).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(e.message().contains("`points`"), "{}", e.message());
    let mut req = three_mode_request();
    req.calibration = None;
    let e = c.predict(req).await.unwrap_err();
    assert!(e.message().contains("`calibration`"), "{}", e.message());
    let mut req = three_mode_request();
    req.persons[1].box_3d.as_mut().unwrap().length = f64::NAN;
    let e = c.predict(req).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(e.message().contains("persons[1].box_3d.length"), "{}", e.message());
    let mut req = three_mode_request();
    req.mode = 42;
    assert_eq!(c.predict(req).await.unwrap_err().code(), tonic::Code::InvalidArgument);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn predict_stream_answers_in_order_with_error_items() {
    let s = start(config()).await;
    let mut c = client(&s).await;
    let mut bad = three_mode_request();
    bad.persons.clear();
    let mut lidar = three_mode_request();
    lidar.mode = proto::Mode::Lidar as i32;
    let reqs = vec![three_mode_request(), bad, lidar];
    let mut out = c.predict_stream(futures::stream::iter(reqs)).await.unwrap().into_inner();
    let mut got = Vec::new();
    while let Some(item) = out.message().await.unwrap() {
        got.push(item);
    }
    assert_eq!(got.iter().map(|i| i.index).collect::<Vec<_>>(), [0, 1, 2]);
    use proto::stream_response::Result as R;
    assert!(matches!(&got[0].result, Some(R::Response(r)) if r.persons.len() == 3));
    assert!(matches!(&got[1].result, Some(R::Error(e)) if e.code == "invalid_field" && e.message.contains("persons")));
    match &got[2].result {
        Some(R::Response(r)) => assert!(r.persons.iter().all(|p| p.mode == proto::Mode::Lidar as i32)),
        other => panic!("{other:?}"),
    }
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_service_reports_serving() {
    let s = start(config()).await;
    let channel = tonic::transport::Endpoint::from_shared(s.url("")).unwrap().connect().await.unwrap();
    let mut h = HealthClient::new(channel);
    for service in ["", "posefuse.v1.Posefuse"] {
        let r = h.check(HealthCheckRequest { service: service.into() }).await.unwrap().into_inner();
        assert_eq!(r.status, ServingStatus::Serving as i32, "{service}");
    }
    let e = h.check(HealthCheckRequest { service: "nope".into() }).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound);
    s.shutdown().await.unwrap();
}

/// `posefuse health --addr ADDR`, as the container's HEALTHCHECK runs it.
async fn health_command(addr: String) -> std::process::Output {
    tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
            .args(["health", "--addr", &addr, "--timeout-s", "5"])
            .env_remove("POSEFUSE_ADDR")
            .output()
            .unwrap()
    })
    .await
    .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_health_command_passes_on_a_ready_server_and_fails_once_it_is_gone() {
    let s = start(config()).await;
    let port = s.addr.port();
    // the server's own address, and the wildcard form that POSEFUSE_ADDR holds in the container
    for addr in [s.addr.to_string(), format!("0.0.0.0:{port}")] {
        let out = health_command(addr.clone()).await;
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{addr}: {}", String::from_utf8_lossy(&out.stderr));
        assert!(stdout.contains("SERVING"), "{stdout}");
    }
    s.shutdown().await.unwrap();
    let out = health_command(format!("127.0.0.1:{port}")).await;
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("cannot connect"), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limits_and_overload_are_resource_exhausted() {
    let mut cfg = config();
    cfg.body_limit = 4_000;
    cfg.runtime.queue_size = 1;
    cfg.runtime.max_batch = 1;
    let s = start(cfg).await;
    let mut c = client(&s).await;
    let e = c.predict(three_mode_request()).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
    // Within the limit but the queue is full (workers paused).
    let pause = s.predictor.runtime().pause();
    let mut small = three_mode_request();
    small.image.clear();
    small.points = small.points[..12 * 300].to_vec();
    small.persons.truncate(1);
    let mut calls = Vec::new();
    for _ in 0..5 {
        let (mut c, req) = (c.clone(), small.clone());
        calls.push(tokio::spawn(async move { c.predict(req).await }));
        tokio::time::sleep(Duration::from_millis(30)).await;
    }
    let mut exhausted = 0;
    let mut waiting = Vec::new();
    for t in calls {
        if t.is_finished() {
            let e = t.await.unwrap().unwrap_err();
            assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
            exhausted += 1;
        } else {
            waiting.push(t);
        }
    }
    assert!(exhausted >= 3, "{exhausted}");
    drop(pause);
    for t in waiting {
        let r = tokio::time::timeout(Duration::from_secs(20), t).await.unwrap().unwrap();
        assert!(r.is_ok() || r.unwrap_err().code() == tonic::Code::ResourceExhausted);
    }
    s.shutdown().await.unwrap();
}
