//! The API contract at its edges: type errors in well-formed JSON name their field (422), 405 and
//! other errors use the JSON error body, unknown fields are refused everywhere, integer ranges
//! hold, malformed protobuf is INVALID_ARGUMENT, and every status a route returns is documented.

mod server_support;

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use serde_json::{json, Value};
use server_support::*;

fn frame_json() -> Value {
    serde_json::to_value(fusion_frame()).unwrap()
}

async fn post(s: &TestServer, path: &str, body: &Value) -> (u16, Value) {
    let r = reqwest::Client::new().post(s.url(path)).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn type_errors_in_well_formed_json_are_422_naming_the_field() {
    let s = start(config()).await;
    type Case = (Box<dyn Fn(&mut Value)>, &'static str);
    let cases: Vec<Case> = vec![
        (Box::new(|v| v["mode"] = json!(1)), "mode"),
        (Box::new(|v| v["points"] = json!({"b64": "AAAA", "extra": 1})), "points"),
        (Box::new(|v| v["points"] = json!([1.0, "x", 2.0])), "points[1]"),
        (Box::new(|v| v["calibration"]["width"] = json!(4_294_967_296u64)), "calibration.width"),
        (Box::new(|v| v["calibration"]["width"] = json!(3_000_000_000u64)), "calibration.width/height"),
        (Box::new(|v| v["calibration"]["height"] = json!(-1)), "calibration.height"),
    ];
    for (edit, field) in cases {
        let mut v = frame_json();
        edit(&mut v);
        let (status, r) = post(&s, "/v1/poses", &v).await;
        assert_eq!(status, 422, "{field}: {r}");
        assert_eq!(r["error"]["field"], field, "{r}");
    }
    // A 4-number xyz in ground truth, on /v1/evaluate.
    let b = person_box(8.0, 0.5);
    let mut frame = fusion_frame();
    frame.persons[0].ground_truth = Some(ground_truth(&b));
    let mut v = serde_json::to_value(&frame).unwrap();
    v["persons"][0]["ground_truth"]["keypoints_3d"]["xyz"][0] = json!([1.0, 2.0, 3.0, 4.0]);
    let (status, r) = post(&s, "/v1/evaluate", &json!([v])).await;
    assert_eq!(status, 200, "{r}");
    let e = &r["predictions"][0]["error"];
    assert_eq!(e["code"], "invalid_field", "{r}");
    assert!(e["field"].as_str().unwrap().starts_with("persons[0].ground_truth.keypoints_3d.xyz"), "{r}");
    // The body itself of the wrong shape: 422, documented.
    let (status, r) = post(&s, "/v1/evaluate", &json!({"not": "an array"})).await;
    assert_eq!(status, 422, "{r}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn method_not_allowed_uses_the_error_body() {
    let s = start(config()).await;
    let r = reqwest::Client::new().get(s.url("/v1/poses")).send().await.unwrap();
    assert_eq!(r.status(), 405);
    let body: Value = r.json().await.unwrap();
    assert!(body["error"]["message"].as_str().unwrap().contains("GET"), "{body}");
    s.shutdown().await.unwrap();
}

/// The documented statuses of a route (`"post"` operations; the keys of `responses`).
fn documented(doc: &Value, path: &str) -> BTreeSet<u16> {
    doc["paths"][path]["post"]["responses"]
        .as_object()
        .map_or_else(BTreeSet::new, |r| r.keys().map(|k| k.parse().unwrap()).collect())
}

/// What the router answers for a table of requests per route, each status checked against the
/// OpenAPI document the server publishes; and each documented status is one the table provoked,
/// or one named below with why it is provoked elsewhere.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_returned_status_is_in_the_openapi_document() {
    const TOKEN: &str = "an-admin-token-of-some-length";
    let repository = tempfile::tempdir().unwrap();
    std::fs::create_dir(repository.path().join("broken")).unwrap();
    let frame = frame_json();
    let frame_bytes = serde_json::to_vec(&frame).unwrap().len();
    let mut cfg = config();
    cfg.body_limit = 4 * frame_bytes + 4096;
    cfg.request_timeout = Duration::from_millis(300);
    cfg.runtime.queue_size = 1;
    cfg.runtime.max_batch = 1;
    cfg.admin.token = Some(TOKEN.into());
    cfg.admin.repository = Some(repository.path().to_path_buf());
    let too_large = format!("{}{{}}", " ".repeat(cfg.body_limit + 1));
    let s = start(cfg).await;
    let doc: Value = reqwest::get(s.url("/openapi.json")).await.unwrap().json().await.unwrap();
    let client = reqwest::Client::new();
    let send = |path: &str, body: String, token: Option<&str>| {
        let mut r = client.post(s.url(path)).header("content-type", "application/json").body(body);
        if let Some(t) = token {
            r = r.bearer_auth(t);
        }
        r.send()
    };
    let mut seen: BTreeMap<&str, BTreeSet<u16>> = BTreeMap::new();
    let one = serde_json::to_string(&frame).unwrap();
    let many = serde_json::to_string(&json!([frame, frame])).unwrap();
    let bad_field = serde_json::to_string(&json!({"mode": 1})).unwrap();
    let table: Vec<(&str, String, Option<&str>)> = vec![
        ("/v1/poses", one.clone(), None),
        ("/v1/poses", "{not json".into(), None),
        ("/v1/poses", too_large.clone(), None),
        ("/v1/poses", bad_field.clone(), None),
        ("/v1/poses:batch", many.clone(), None),
        ("/v1/poses:batch", "[{not json".into(), None),
        ("/v1/poses:batch", too_large.clone(), None),
        ("/v1/poses:batch", r#"{"not": "an array"}"#.into(), None),
        ("/v1/evaluate", many.clone(), None),
        ("/v1/evaluate", "[{not json".into(), None),
        ("/v1/evaluate", too_large.clone(), None),
        ("/v1/evaluate", r#"{"not": "an array"}"#.into(), None),
        ("/v1/models:reload", "{}".into(), None),
        ("/v1/models:reload", "{not json".into(), Some(TOKEN)),
        ("/v1/models:reload", r#"{"model_dir": "broken"}"#.into(), Some(TOKEN)),
        ("/v1/models:reload", "{}".into(), Some(TOKEN)),
    ];
    for (path, body, token) in table {
        let status = send(path, body, token).await.unwrap().status().as_u16();
        seen.entry(path).or_default().insert(status);
    }
    // Paused workers and a queue of one: the first waits past its deadline, the rest are refused.
    let pause = s.predictor.runtime().pause();
    let waits = (0..4).map(|_| send("/v1/poses", one.clone(), None)).collect::<Vec<_>>();
    for r in futures::future::join_all(waits).await {
        seen.entry("/v1/poses").or_default().insert(r.unwrap().status().as_u16());
    }
    drop(pause);
    // Provoked by their own tests: warm-up is held process-wide (tests/server_readiness.rs).
    let elsewhere: BTreeMap<&str, BTreeSet<u16>> = BTreeMap::from([("/v1/poses", BTreeSet::from([503]))]);
    for (path, statuses) in &seen {
        let doc_statuses = documented(&doc, path);
        assert!(statuses.is_subset(&doc_statuses), "{path}: returned {statuses:?}, documented {doc_statuses:?}");
        let covered: BTreeSet<u16> = statuses.union(elsewhere.get(path).unwrap_or(&BTreeSet::new())).copied().collect();
        assert_eq!(covered, doc_statuses, "{path}: documented statuses no request here provoked");
    }
    assert_eq!(seen.len(), 4);
    s.shutdown().await.unwrap();
}

/// A message with a varint where PredictRequest has a string: not decodable as one.
#[derive(Clone, PartialEq, prost::Message)]
struct NotAPredictRequest {
    #[prost(uint64, tag = "1")]
    frame_id: u64,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_protobuf_is_invalid_argument() {
    let s = start(config()).await;
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.unwrap();
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.unwrap();
    let codec =
        tonic_prost::ProstCodec::<NotAPredictRequest, posefuse::server::grpc::proto::PredictResponse>::default();
    let path = axum::http::uri::PathAndQuery::from_static("/posefuse.v1.Posefuse/Predict");
    let e = grpc.unary(tonic::Request::new(NotAPredictRequest { frame_id: 7 }), path, codec).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e:?}");
    s.shutdown().await.unwrap();
}
