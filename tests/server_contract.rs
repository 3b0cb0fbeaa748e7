//! The API contract at its edges: type errors in well-formed JSON name their field (422), 405 and
//! other errors use the JSON error body, unknown fields are refused everywhere, integer ranges
//! hold, malformed protobuf is INVALID_ARGUMENT, and every status a route returns is documented.

mod server_support;

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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_returned_status_is_in_the_openapi_document() {
    let doc = serde_json::to_value(posefuse::server::http::openapi_doc()).unwrap();
    let statuses = |path: &str| -> Vec<String> {
        doc["paths"][path]["post"]["responses"].as_object().unwrap().keys().cloned().collect()
    };
    for (path, want) in [
        ("/v1/poses", vec!["200", "400", "413", "422", "429", "503", "504"]),
        ("/v1/poses:batch", vec!["200", "400", "413", "422"]),
        ("/v1/evaluate", vec!["200", "400", "413", "422"]),
        ("/v1/models:reload", vec!["200", "400", "403", "422"]),
    ] {
        let have = statuses(path);
        for w in want {
            assert!(have.iter().any(|h| h == w), "{path}: {w} missing from {have:?}");
        }
    }
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
