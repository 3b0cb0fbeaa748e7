//! Following a request: `x-request-id` and W3C `traceparent` on HTTP and gRPC, the access log
//! (read as JSON lines from a `posefuse serve` process), and the Prometheus page's conventions.

mod server_support;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use posefuse::server::grpc::frame_to_proto;
use posefuse::server::grpc::proto::posefuse_client::PosefuseClient;
use serde_json::Value;
use server_support::process::ServeProcess;
use server_support::*;

const GIVEN_TRACE: &str = "4bf92f3577b34da6a3ce929d0e0e4736";
const GIVEN: &str = "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01";

/// (trace id, span id, flags) of a `traceparent` the server wrote.
fn traceparent(h: &reqwest::header::HeaderMap) -> (String, String, String) {
    let v = h.get("traceparent").expect("a traceparent in the answer").to_str().unwrap();
    let f: Vec<&str> = v.split('-').collect();
    assert_eq!((f.len(), f[0], f[1].len(), f[2].len(), f[3].len()), (4, "00", 32, 16, 2), "{v}");
    (f[1].to_string(), f[2].to_string(), f[3].to_string())
}

fn request_id(h: &reqwest::header::HeaderMap) -> String {
    h.get("x-request-id").expect("an x-request-id in the answer").to_str().unwrap().to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ids_and_trace_context_come_back_on_http_and_grpc() {
    let s = start(config()).await;
    let http = reqwest::Client::new();
    let r = http
        .post(s.url("/v1/poses"))
        .header("x-request-id", "req-7")
        .header("traceparent", GIVEN)
        .json(&fusion_frame())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(request_id(r.headers()), "req-7");
    let (trace, span, flags) = traceparent(r.headers());
    assert_eq!((trace.as_str(), flags.as_str()), (GIVEN_TRACE, "01"), "the caller's trace is continued");
    assert_ne!(span, "00f067aa0ba902b7", "under this server's own span");

    // Without headers (or with an unusable id): an id is made, the trace id, one per request.
    let mut made = BTreeSet::new();
    for given in [None, Some("two words")] {
        let mut req = http.get(s.url("/healthz")).header("traceparent", "00-not-a-trace-01");
        if let Some(id) = given {
            req = req.header("x-request-id", id);
        }
        let r = req.send().await.unwrap();
        let (trace, _, flags) = traceparent(r.headers());
        assert_eq!((request_id(r.headers()), flags.as_str()), (trace.clone(), "00"));
        assert_ne!(trace, GIVEN_TRACE);
        made.insert(trace);
    }
    assert_eq!(made.len(), 2, "{made:?}");

    // gRPC: the same headers as metadata.
    let mut c = PosefuseClient::connect(s.url("")).await.unwrap();
    let mut req = tonic::Request::new(frame_to_proto(&fusion_frame(), Vec::new()).unwrap());
    req.metadata_mut().insert("x-request-id", "grpc-1".parse().unwrap());
    req.metadata_mut().insert("traceparent", GIVEN.parse().unwrap());
    let r = c.predict(req).await.unwrap();
    assert_eq!(r.metadata().get("x-request-id").unwrap(), "grpc-1");
    let tp = r.metadata().get("traceparent").unwrap().to_str().unwrap().to_string();
    assert!(tp.starts_with(&format!("00-{GIVEN_TRACE}-")) && !tp.contains("00f067aa0ba902b7"), "{tp}");
    let mut bad = tonic::Request::new(posefuse::server::grpc::proto::PredictRequest::default());
    bad.metadata_mut().insert("x-request-id", "grpc-bad".parse().unwrap());
    let status = c.predict(bad).await.unwrap_err();
    assert_eq!(status.metadata().get("x-request-id").unwrap(), "grpc-bad", "{status:?}");
    s.shutdown().await.unwrap();
}

/// The `# HELP` and `# TYPE` names of a Prometheus text page, and its samples.
fn exposition(page: &str) -> (BTreeSet<String>, BTreeSet<String>, Vec<&str>) {
    let named = |prefix: &str| -> BTreeSet<String> {
        page.lines()
            .filter_map(|l| l.strip_prefix(prefix))
            .filter_map(|r| r.split(' ').next())
            .map(String::from)
            .collect()
    };
    let samples = page.lines().filter(|l| !l.starts_with('#') && !l.is_empty()).collect();
    (named("# HELP "), named("# TYPE "), samples)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_follow_prometheus_conventions() {
    let s = start(config()).await;
    let http = reqwest::Client::new();
    assert_eq!(http.post(s.url("/v1/poses")).json(&fusion_frame()).send().await.unwrap().status(), 200);
    let mut c = PosefuseClient::connect(s.url("")).await.unwrap();
    let bad = posefuse::server::grpc::proto::PredictRequest::default();
    assert_eq!(c.predict(bad).await.unwrap_err().code(), tonic::Code::InvalidArgument);
    let page = http.get(s.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let (help, types, samples) = exposition(&page);
    assert!(!types.is_empty());
    let without: Vec<&String> = types.difference(&help).collect();
    assert!(without.is_empty(), "metrics without HELP: {without:?}");
    let has = |prefix: &str| samples.iter().any(|l| l.starts_with(prefix));
    // counters present before their first event
    for zero in
        ["posefuse_admission_refused_total 0", "posefuse_frames_abandoned_total 0", "posefuse_accept_errors_total 0"]
    {
        assert!(samples.contains(&zero), "{zero} missing:\n{page}");
    }
    for model in ["camera", "point_fusion", "point_lidar"] {
        assert!(has(&format!("posefuse_queue_wait_seconds_count{{model=\"{model}\"}}")), "queue wait of {model}");
    }
    // the fusion frame's point input, chained behind its camera, waited for its network too
    for model in ["camera", "point_fusion"] {
        let count = format!("posefuse_queue_wait_seconds_count{{model=\"{model}\"}} ");
        let n = samples.iter().find_map(|l| l.strip_prefix(count.as_str())).and_then(|v| v.parse::<f64>().ok());
        assert!(n.is_some_and(|n| n >= 1.0), "{count}: {n:?}\n{page}");
    }
    let version = env!("CARGO_PKG_VERSION");
    let bundle = &s.predictor.bundle().manifest;
    let info = format!(
        "posefuse_build_info{{version=\"{version}\",bundle=\"{}\",bundle_version=\"{}\"}} 1",
        bundle.name, bundle.version
    );
    assert!(samples.contains(&info.as_str()), "{info} missing:\n{page}");
    assert!(has("posefuse_grpc_requests_total{method=\"Predict\",code=\"INVALID_ARGUMENT\"} "), "{page}");
    let latency = |transport: &str, route: &str, status: &str| {
        format!("posefuse_request_duration_seconds_count{{transport=\"{transport}\",route=\"{route}\",status=\"{status}\"}}")
    };
    assert!(has(&latency("http", "/v1/poses", "200")), "{page}");
    assert!(has(&latency("grpc", "/posefuse.v1.Posefuse/Predict", "INVALID_ARGUMENT")), "{page}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_request_has_one_access_log_line_carrying_its_id() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("serve.log");
    let s = ServeProcess::start_logging(&["--log-json"], &log);
    let http = reqwest::Client::new();
    let answers = [
        ("a-1", http.post(s.url("/v1/poses")).json(&fusion_frame())),
        ("a-2", http.get(s.url("/v1/models"))),
        ("a-3", http.get(s.url("/no/such/route"))),
    ];
    for (id, req) in answers {
        req.header("x-request-id", id).send().await.unwrap();
    }
    drop(s);
    let text = std::fs::read_to_string(&log).unwrap();
    let lines: Vec<Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let access: Vec<&Value> = lines.iter().filter(|l| l["target"] == "posefuse::access").collect();
    for (id, path, status) in [("a-1", "/v1/poses", 200), ("a-2", "/v1/models", 200), ("a-3", "/no/such/route", 404)] {
        let mine: Vec<&&Value> = access.iter().filter(|l| l["span"]["request_id"] == id).collect();
        assert_eq!(mine.len(), 1, "{id}: {mine:?}\n{text}");
        let f = &mine[0]["fields"];
        assert_eq!(
            (f["path"].as_str(), f["status"].as_str(), f["transport"].as_str()),
            (Some(path), Some(&*status.to_string()), Some("http"))
        );
        assert!(f["duration_ms"].as_f64().is_some_and(|d| d > 0.0), "{f}");
        assert_eq!(mine[0]["level"], "INFO");
    }
}

const GIVE_UP: Duration = Duration::from_millis(50);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_whose_client_goes_away_is_logged_as_499_or_cancelled() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("serve.log");
    let s = ServeProcess::start_logging(&["--log-json"], &log);
    // Long pre-processing (about 0.3 s over gRPC, which parses no JSON, on a fast machine): the
    // clients give up after 50 ms, long before an answer.
    let heavy = heavy_frame(256, 200_000);
    let body = serde_json::to_value(&heavy).unwrap();
    let http = reqwest::Client::new().post(s.url("/v1/poses")).header("x-request-id", "gone-http").json(&body);
    assert!(tokio::time::timeout(GIVE_UP, http.send()).await.is_err(), "answered too soon");
    let mut c = PosefuseClient::connect(s.url("")).await.unwrap();
    let mut req = tonic::Request::new(frame_to_proto(&heavy, Vec::new()).unwrap());
    req.metadata_mut().insert("x-request-id", "gone-grpc".parse().unwrap());
    assert!(tokio::time::timeout(GIVE_UP, c.predict(req)).await.is_err(), "answered too soon");
    drop(c);
    // The server notices each hang-up at its next step, then writes the line.
    let t = Instant::now();
    let page = loop {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let page = reqwest::get(s.url("/metrics")).await.unwrap().text().await.unwrap();
        if page.contains(r#"status="CANCELLED""#) && page.contains(r#"status="499""#) {
            break page;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "no line for the hung-up requests:\n{page}");
    };
    for gone in [
        r#"posefuse_request_duration_seconds_count{transport="http",route="/v1/poses",status="499"} 1"#,
        r#"posefuse_request_duration_seconds_count{transport="grpc",route="/posefuse.v1.Posefuse/Predict",status="CANCELLED"} 1"#,
    ] {
        assert!(page.lines().any(|l| l == gone), "{gone} missing:\n{page}");
    }
    assert!(!page.contains(r#"route="/v1/poses",status="503""#), "{page}");
    drop(s);
    let text = std::fs::read_to_string(&log).unwrap();
    let lines: Vec<Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    for (id, transport, status) in [("gone-http", "http", "499"), ("gone-grpc", "grpc", "CANCELLED")] {
        let mine: Vec<&Value> =
            lines.iter().filter(|l| l["target"] == "posefuse::access" && l["span"]["request_id"] == id).collect();
        assert_eq!(mine.len(), 1, "{id}: {mine:?}\n{text}");
        let f = &mine[0]["fields"];
        assert_eq!((f["transport"].as_str(), f["status"].as_str()), (Some(transport), Some(status)), "{f}");
    }
    // Nothing about them at error level: the server did not fail.
    assert!(!lines.iter().any(|l| l["level"] == "ERROR"), "{text}");
}
