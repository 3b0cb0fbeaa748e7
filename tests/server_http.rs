//! HTTP API against a real in-process server on the default bundle: modes, batch (JSON and
//! NDJSON), evaluation, health, models, metrics and the OpenAPI document.

mod server_support;

use posefuse::eval::EvaluateResponse;
use posefuse::frame::{Frame, RequestedMode};
use posefuse::keypoints::{K, NAMES, WAYMO_TYPES};
use posefuse::service::api::{BatchItem, Mode, PoseResponse};
use serde_json::Value;
use server_support::*;

async fn post_frame(s: &TestServer, frame: &Frame) -> reqwest::Response {
    reqwest::Client::new().post(s.url("/v1/poses")).json(frame).send().await.unwrap()
}

fn assert_pose_is_sane(r: &PoseResponse, id: &str, mode: Mode) {
    let p = r.persons.iter().find(|p| p.id == id).unwrap_or_else(|| panic!("person {id} missing"));
    assert_eq!(p.mode, mode, "{id}: {}", p.mode_reason);
    assert_eq!(p.keypoints.len(), K);
    for (k, kp) in p.keypoints.iter().enumerate() {
        assert_eq!(kp.name, NAMES[k]);
        assert_eq!(kp.waymo_type, WAYMO_TYPES[k]);
        assert!(kp.xyz.iter().all(|v| v.is_finite()));
        assert_eq!(kp.score.is_some(), mode != Mode::Lidar);
    }
    // The facing is the vehicle-frame keypoints' (not the box frame's, turned by the heading).
    let xyz: Vec<[f64; 3]> = p.keypoints.iter().map(|k| k.xyz).collect();
    match (p.facing, posefuse::pipeline::facing(&xyz)) {
        (Some(a), Some(b)) => {
            assert!((a.yaw - b.yaw).abs() < 1e-9 && (a.confidence - b.confidence).abs() < 1e-9, "{id}: {a:?} {b:?}")
        }
        (a, b) => assert!(a.is_none() && b.is_none(), "{id}: {a:?} vs {b:?}"),
    }
    // Camera-only lifting onto a handful of points may put both shoulders on one point.
    assert!(p.facing.is_some() || mode == Mode::Camera, "{id}: no facing");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_frame_runs_each_mode_where_it_applies() {
    let s = start(config()).await;
    let resp = post_frame(&s, &three_mode_frame()).await;
    assert_eq!(resp.status(), 200);
    let r: PoseResponse = resp.json().await.unwrap();
    assert_eq!(r.frame_id.as_deref(), Some("f-3"));
    assert_eq!(r.model.name, "default");
    let ids: Vec<&str> = r.persons.iter().map(|p| p.id.as_str()).collect();
    assert_eq!(ids, ["near", "behind", "sparse"]);
    assert_pose_is_sane(&r, "near", Mode::Fusion);
    assert_pose_is_sane(&r, "behind", Mode::Lidar);
    assert_pose_is_sane(&r, "sparse", Mode::Camera);
    assert_eq!(r.persons[0].num_points, 300);
    assert_eq!(r.persons[2].num_points, 3);
    assert!(r.persons[1].mode_reason.contains("outside the camera view"), "{}", r.persons[1].mode_reason);
    // The person behind the vehicle projects nowhere; the others project into the image.
    assert!(r.persons[1].keypoints.iter().all(|k| k.uv.is_none()));
    assert!(r.persons[1].box_2d.is_none());
    // "sparse" had no 2D box: it was derived from the projected 3D box.
    assert_eq!(r.persons[2].box_2d, Some(box_2d(&person_box(12.0, -1.5))));
    assert!(r.timings.total_ms > 0.0 && r.timings.inference_ms > 0.0);
    // Camera-only lifting averages the box's own points: the result stays inside their hull.
    let pts = points_in(&person_box(12.0, -1.5), 3);
    for kp in &r.persons[2].keypoints {
        for a in 0..3 {
            let lo = pts.iter().map(|p| p[a] as f64).fold(f64::INFINITY, f64::min);
            let hi = pts.iter().map(|p| p[a] as f64).fold(f64::NEG_INFINITY, f64::max);
            assert!(kp.xyz[a] >= lo - 1e-4 && kp.xyz[a] <= hi + 1e-4, "{} axis {a}: {}", kp.name, kp.xyz[a]);
        }
    }
    // 2D positions are the projections of the 3D ones.
    let cam = camera();
    for kp in &r.persons[0].keypoints {
        let uv = cam.project(kp.xyz).uv;
        let got = kp.uv.unwrap();
        assert!((uv[0] - got[0]).abs() < 1e-9 && (uv[1] - got[1]).abs() < 1e-9);
    }
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn modes_can_be_forced_and_the_image_is_optional() {
    let s = start(config()).await;
    for (forced, want) in [(RequestedMode::Lidar, Mode::Lidar), (RequestedMode::Camera, Mode::Camera)] {
        let mut f = fusion_frame();
        f.mode = forced;
        let r: PoseResponse = post_frame(&s, &f).await.json().await.unwrap();
        assert_pose_is_sane(&r, "ped-1", want);
        assert_eq!(r.persons[0].mode_reason, "requested");
    }
    // No image: lidar, and it says why.
    let mut f = fusion_frame();
    f.image = None;
    let r: PoseResponse = post_frame(&s, &f).await.json().await.unwrap();
    assert_pose_is_sane(&r, "ped-1", Mode::Lidar);
    assert!(r.persons[0].mode_reason.contains("no image"));
    // An undecodable image degrades to lidar in auto mode ...
    let mut f = fusion_frame();
    f.image = Some("aGVsbG8=".into());
    let r: PoseResponse = post_frame(&s, &f).await.json().await.unwrap();
    assert_pose_is_sane(&r, "ped-1", Mode::Lidar);
    assert!(r.persons[0].mode_reason.contains("decodable"), "{}", r.persons[0].mode_reason);
    // ... and is refused when the camera is demanded.
    f.mode = RequestedMode::Fusion;
    let resp = post_frame(&s, &f).await;
    assert_eq!(resp.status(), 422);
    let e: Value = resp.json().await.unwrap();
    assert_eq!(e["error"]["field"], "image");
    // The same frame gives the same answer (deterministic point choice).
    let a: PoseResponse = post_frame(&s, &fusion_frame()).await.json().await.unwrap();
    let b: PoseResponse = post_frame(&s, &fusion_frame()).await.json().await.unwrap();
    assert_eq!(a.persons, b.persons);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batch_json_keeps_order_and_isolates_errors() {
    let s = start(config()).await;
    let good = serde_json::to_value(fusion_frame()).unwrap();
    let mut bad = good.clone();
    bad["persons"][0]["box_3d"]["height"] = (-1.0).into();
    let body = Value::Array(vec![good.clone(), bad, serde_json::json!({"nonsense": 1}), good]);
    let resp = reqwest::Client::new().post(s.url("/v1/poses:batch")).json(&body).send().await.unwrap();
    assert_eq!(resp.status(), 200);
    let items: Vec<BatchItem> = resp.json().await.unwrap();
    assert_eq!(items.iter().map(|i| i.index).collect::<Vec<_>>(), [0, 1, 2, 3]);
    assert!(items[0].response.is_some() && items[3].response.is_some());
    let e1 = items[1].error.as_ref().unwrap();
    assert_eq!((e1.code.as_str(), e1.field.as_deref()), ("invalid_field", Some("persons[0].box_3d.height")));
    assert_eq!(items[2].error.as_ref().unwrap().code, "invalid_field");
    assert_eq!(items[0].response.as_ref().unwrap().persons, items[3].response.as_ref().unwrap().persons);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batch_ndjson_streams_results_in_order() {
    let s = start(config()).await;
    let mut body = String::new();
    let mut lidar = fusion_frame();
    lidar.mode = RequestedMode::Lidar;
    for f in [fusion_frame(), three_mode_frame()] {
        body.push_str(&serde_json::to_string(&f).unwrap());
        body.push('\n');
    }
    body.push_str("{not json\n\n");
    body.push_str(&serde_json::to_string(&lidar).unwrap());
    let resp = s.post_ndjson(body).await;
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["content-type"], "application/x-ndjson");
    let text = resp.text().await.unwrap();
    let items: Vec<BatchItem> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(items.len(), 4, "{text}");
    assert_eq!(items.iter().map(|i| i.index).collect::<Vec<_>>(), [0, 1, 2, 3]);
    assert_eq!(items[0].response.as_ref().unwrap().persons.len(), 1);
    assert_eq!(items[1].response.as_ref().unwrap().persons.len(), 3);
    assert_eq!(items[2].error.as_ref().unwrap().code, "malformed_request");
    assert_eq!(items[3].response.as_ref().unwrap().persons[0].mode, Mode::Lidar);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn evaluate_scores_frames_with_ground_truth() {
    let s = start(config()).await;
    let mut f = three_mode_frame();
    for p in &mut f.persons {
        p.ground_truth = Some(ground_truth(&p.box_3d));
    }
    let mut bad = fusion_frame();
    bad.points = posefuse::frame::Points::Flat(vec![]);
    let resp = reqwest::Client::new().post(s.url("/v1/evaluate")).json(&vec![f.clone(), bad]).send().await.unwrap();
    assert_eq!(resp.status(), 200);
    let r: EvaluateResponse = resp.json().await.unwrap();
    assert_eq!(r.failed_frames, 1);
    assert_eq!(r.predictions[1].error.as_ref().unwrap().field.as_deref(), Some("points"));
    let all = &r.metrics["all"];
    assert_eq!(all.count_3d, 3);
    // OKS@2D needs a 2D box: "near" has one and "sparse" gets the derived one; "behind" has none.
    assert_eq!(all.count_2d, 2);
    for m in ["fusion", "lidar", "camera"] {
        assert_eq!(r.metrics[m].count_3d, 1, "{m}");
    }
    // Recompute the fusion person's 3D metrics with the library: the endpoint must agree.
    let pose = &r.predictions[0].response.as_ref().unwrap().persons[0];
    let pred: Vec<[f64; 3]> = pose.keypoints.iter().map(|k| k.xyz).collect();
    let gt = f.persons[0].ground_truth.as_ref().unwrap().keypoints_3d.as_ref().unwrap();
    let mut acc = posefuse::metrics::MetricsAccumulator::new();
    acc.add_3d(&pred, &gt.xyz, &gt.visible, &f.persons[0].box_3d).unwrap();
    let want = acc.report();
    let close = |a: Option<f64>, b: Option<f64>| (a.unwrap() - b.unwrap()).abs() < 1e-12;
    assert!(close(r.metrics["fusion"].mpjpe_3d_m, want.mpjpe_3d_m));
    assert!(close(r.metrics["fusion"].oks_acc_3d, want.oks_acc_3d));
    assert!(close(r.metrics["fusion"].mean_oks_3d, want.mean_oks_3d));
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_models_metrics_and_openapi() {
    let s = start(config()).await;
    let c = reqwest::Client::new();
    let h: Value = c.get(s.url("/healthz")).send().await.unwrap().json().await.unwrap();
    assert_eq!(h["status"], "ok");
    let r: Value = c.get(s.url("/readyz")).send().await.unwrap().json().await.unwrap();
    assert_eq!(r["status"], "ready");
    let m: Value = c.get(s.url("/v1/models")).send().await.unwrap().json().await.unwrap();
    let manifest: Value = serde_json::from_slice(&std::fs::read(model_dir().join("manifest.json")).unwrap()).unwrap();
    assert_eq!((&m["name"], &m["version"]), (&manifest["name"], &manifest["version"]));
    assert_eq!(m["preprocessing"]["image_size"], manifest["preprocessing"]["image_size"]);
    assert_eq!(m["preprocessing"]["heatmap_size"], manifest["preprocessing"]["heatmap_size"]);
    // One request so the histograms have samples.
    assert_eq!(post_frame(&s, &fusion_frame()).await.status(), 200);
    let text = c.get(s.url("/metrics")).send().await.unwrap().text().await.unwrap();
    for name in [
        "posefuse_http_requests_total",
        "posefuse_queue_wait_seconds_bucket",
        "posefuse_inference_seconds_bucket",
        "posefuse_batch_size_bucket",
        "posefuse_preprocess_seconds_bucket",
        "posefuse_frames_total",
    ] {
        assert!(text.contains(name), "{name} missing from /metrics:\n{text}");
    }
    assert!(text.contains(r#"route="/v1/poses",status="200""#), "{text}");
    let doc: Value = c.get(s.url("/openapi.json")).send().await.unwrap().json().await.unwrap();
    for path in ["/v1/poses", "/v1/poses:batch", "/v1/evaluate", "/healthz", "/readyz", "/v1/models", "/metrics"] {
        assert!(doc["paths"][path].is_object(), "{path} missing from the OpenAPI document");
    }
    for schema in ["Frame", "FrameCamera", "PoseResponse", "ErrorBody", "MetricsReport", "BatchItem"] {
        assert!(doc["components"]["schemas"][schema].is_object(), "schema {schema} missing");
    }
    // several cameras per frame: the request's cameras, a person's and an answer's camera
    let schemas = &doc["components"]["schemas"];
    for (schema, field) in [("Frame", "cameras"), ("Person", "camera"), ("PersonPose", "camera")] {
        assert!(schemas[schema]["properties"][field].is_object(), "{schema}.{field} missing");
    }
    let nf = c.get(s.url("/nope")).send().await.unwrap();
    assert_eq!(nf.status(), 404);
    let e: Value = nf.json().await.unwrap();
    assert_eq!(e["error"]["code"], "not_found");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_heading_stage_keeps_its_own_precision_when_the_main_camera_serves_int8() {
    // models/view has no INT8 camera file: `--precision int8` names the main bundle's camera only.
    let mut c = config();
    c.heading_model_dir = Some(model_dir().with_file_name("view"));
    c.runtime.precision = Some(posefuse::runtime::Precision::Int8);
    let s = start(c).await;
    let r = post_frame(&s, &fusion_frame()).await;
    assert_eq!(r.status(), 200);
    let body: PoseResponse = r.json().await.unwrap();
    assert!(!body.persons.is_empty());
}
