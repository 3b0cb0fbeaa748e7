//! OpenTelemetry export (`posefuse serve --otlp-endpoint`): a request's spans reach an OTLP/HTTP
//! collector (here an in-process one that decodes the protobuf with OpenTelemetry's own message
//! types), in the caller's trace, the `request` span the caller's span's child and every stage the
//! `request` span's descendant; the `traceparent` the server returns names the exported span.

mod server_support;

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use axum::body::Bytes;
use opentelemetry_proto::tonic::collector::trace::v1::{ExportTraceServiceRequest, ExportTraceServiceResponse};
use prost::Message;
use server_support::process::ServeProcess;
use server_support::*;

/// What the collector kept of one span.
#[derive(Debug, Clone)]
struct Got {
    name: String,
    trace_id: String,
    span_id: String,
    parent: String,
}

type Spans = Arc<Mutex<Vec<Got>>>;

/// An OTLP/HTTP traces endpoint on a free port: `http://ADDR` and what it received.
async fn collector() -> (String, Spans) {
    let spans: Spans = Arc::default();
    let kept = spans.clone();
    let app = axum::Router::new().route(
        "/v1/traces",
        axum::routing::post(move |body: Bytes| {
            let kept = kept.clone();
            async move {
                let req = ExportTraceServiceRequest::decode(body).expect("OTLP protobuf");
                let mut out = kept.lock().unwrap();
                for s in req.resource_spans.iter().flat_map(|r| &r.scope_spans).flat_map(|s| &s.spans) {
                    out.push(Got {
                        name: s.name.clone(),
                        trace_id: hex(&s.trace_id),
                        span_id: hex(&s.span_id),
                        parent: hex(&s.parent_span_id),
                    });
                }
                ([("content-type", "application/x-protobuf")], ExportTraceServiceResponse::default().encode_to_vec())
            }
        }),
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (format!("http://{addr}"), spans)
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_requests_stages_reach_the_collector_in_the_callers_trace() {
    let (endpoint, spans) = collector().await;
    let s = ServeProcess::start_with(&[], &["--otlp-endpoint", &endpoint], None);
    let trace = "4bf92f3577b34da6a3ce929d0e0e4736";
    let caller = "00f067aa0ba902b7";
    let resp = reqwest::Client::new()
        .post(s.url("/v1/poses"))
        .header("traceparent", format!("00-{trace}-{caller}-01"))
        .json(&fusion_frame())
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), 200);
    let returned = resp.headers()["traceparent"].to_str().unwrap().to_string();
    // a request without a traceparent starts its own, sampled trace
    let own = reqwest::Client::new().get(s.url("/v1/models")).send().await.unwrap();
    let own_parent = own.headers()["traceparent"].to_str().unwrap().to_string();
    // the exporter sends what it holds when the server stops
    assert!(tokio::task::spawn_blocking(move || s.terminate()).await.unwrap().success());

    let got = spans.lock().unwrap().clone();
    let mine: Vec<&Got> = got.iter().filter(|g| g.trace_id == trace).collect();
    let by_id: BTreeMap<&str, &Got> = mine.iter().map(|g| (g.span_id.as_str(), *g)).collect();
    let request = mine.iter().find(|g| g.name == "request").unwrap_or_else(|| panic!("no request span: {got:?}"));
    assert_eq!(request.parent, caller, "the request span continues the caller's span");
    assert_eq!(returned, format!("00-{trace}-{}-01", request.span_id), "the returned traceparent names it");
    for stage in ["admission", "preprocess", "queue", "inference", "response"] {
        let g = mine.iter().find(|g| g.name == stage).unwrap_or_else(|| panic!("no {stage} span: {mine:?}"));
        // each stage hangs, through its parents, under the request span
        let mut at = *g;
        while at.span_id != request.span_id {
            at = by_id.get(at.parent.as_str()).unwrap_or_else(|| panic!("{stage}: broken parent chain: {mine:?}"));
        }
    }
    let (own_trace, own_flags) = (&own_parent[3..35], &own_parent[53..]);
    assert_eq!(own_flags, "01", "sampled: {own_parent}");
    assert!(got.iter().any(|g| g.trace_id == own_trace && g.name == "request"), "{own_parent}: {got:?}");
}
