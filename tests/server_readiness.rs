//! Before the models have warmed up, the server answers but is not ready: /readyz and gRPC
//! health say so and predictions get 503 / UNAVAILABLE. (Its own test binary: holding warm-up
//! is process-wide.)

mod server_support;

use std::time::Duration;

use posefuse::server::App;
use serde_json::Value;
use server_support::*;
use tonic_health::pb::{health_check_response::ServingStatus, health_client::HealthClient, HealthCheckRequest};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_warming_up_is_alive_but_not_ready() {
    posefuse::runtime::hold_warm_up(true);
    let app = tokio::task::spawn_blocking(|| App::start(&config())).await.unwrap().unwrap();
    posefuse::runtime::hold_warm_up(false);
    let predictor = app.predictor().clone();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(app.serve(listener, async move {
        let _ = stopped.await;
    }));
    let url = |p: &str| format!("http://{addr}{p}");
    let c = reqwest::Client::new();

    let live = c.get(url("/healthz")).send().await.unwrap();
    assert_eq!(live.status(), 200);
    let ready = c.get(url("/readyz")).send().await.unwrap();
    assert_eq!(ready.status(), 503);
    assert_eq!(ready.json::<Value>().await.unwrap()["status"], "warming_up");
    let channel = tonic::transport::Endpoint::from_shared(url("")).unwrap().connect().await.unwrap();
    let mut health = HealthClient::new(channel);
    let status = health.check(HealthCheckRequest { service: String::new() }).await.unwrap().into_inner().status;
    assert_eq!(status, ServingStatus::NotServing as i32);
    let r = c.post(url("/v1/poses")).json(&fusion_frame()).send().await.unwrap();
    assert_eq!(r.status(), 503);
    assert_eq!(r.json::<Value>().await.unwrap()["error"]["code"], "unavailable");

    // Let the workers warm up: readiness follows.
    drop(predictor.runtime().pause());
    let mut ok = false;
    for _ in 0..500 {
        if c.get(url("/readyz")).send().await.unwrap().status() == 200 {
            ok = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(ok, "never became ready");
    let status = health.check(HealthCheckRequest { service: String::new() }).await.unwrap().into_inner().status;
    assert_eq!(status, ServingStatus::Serving as i32);
    assert_eq!(c.post(url("/v1/poses")).json(&fusion_frame()).send().await.unwrap().status(), 200);
    let _ = stop.send(());
    task.await.unwrap().unwrap();
}
