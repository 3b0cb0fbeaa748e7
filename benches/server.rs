//! Server latency against raw ONNX Runtime, in one run: a single-person fusion request on the
//! default bundle sent sequentially (HTTP JSON and gRPC), and the camera + point-fusion sessions
//! run directly on the same model inputs. `cargo bench --bench server`; results in BENCHMARKS.md.
//! `POSEFUSE_BENCH_N` sets the request count, `POSEFUSE_BENCH_MODEL_DIR` another bundle, and
//! `POSEFUSE_BENCH_FRAME` a request file (e.g. a simulator fixture: a 1920×1280 JPEG and a full
//! LiDAR sweep) whose first person is sent instead of the built-in 640×480 PNG frame.

#[path = "../tests/server_support/mod.rs"]
mod server_support;

use std::time::{Duration, Instant};

use base64::Engine;
use posefuse::frame::Frame;
use posefuse::pipeline::fusion_input;
use posefuse::runtime::{env, Bundle, ModelKind, Models};
use posefuse::server::grpc::frame_to_proto;
use posefuse::server::grpc::proto::posefuse_client::PosefuseClient;
use posefuse::service::planned_inputs;
use server_support::*;

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() as f64 - 1.0) * p).round() as usize]
}

fn summary(name: &str, mut d: Vec<Duration>) -> (Duration, Duration) {
    d.sort();
    let (p50, p99) = (percentile(&d, 0.5), percentile(&d, 0.99));
    println!("{name:<34} n={:<5} p50 {:>8.3} ms   p99 {:>8.3} ms", d.len(), ms(p50), ms(p99));
    (p50, p99)
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// The request: the built-in one-person frame, or the first person of `POSEFUSE_BENCH_FRAME`.
fn bench_frame() -> (Frame, String) {
    match std::env::var_os("POSEFUSE_BENCH_FRAME") {
        None => (fusion_frame(), "640x480 PNG, 300 points".into()),
        Some(path) => {
            let mut frame: Frame = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
            frame.persons.truncate(1);
            for p in &mut frame.persons {
                p.ground_truth = None;
            }
            let c = frame.calibration.as_ref().unwrap();
            let label = format!("{}x{} image, {} points", c.width, c.height, frame.points.decode().unwrap().len());
            (frame, label)
        }
    }
}

fn image_bytes(frame: &Frame) -> Vec<u8> {
    base64::engine::general_purpose::STANDARD.decode(frame.image.as_ref().unwrap()).unwrap()
}

/// The model inputs the server builds for the frame's person (`service::planned_inputs`,
/// `pipeline::fusion_input`).
fn model_inputs(models: &mut Models, bundle: &Bundle, frame: &Frame) -> (Vec<f32>, Vec<f32>) {
    let cfg = bundle.config();
    let p = planned_inputs(frame.clone(), cfg).unwrap().remove(0);
    assert_eq!(p.mode, posefuse::service::api::Mode::Fusion, "the bench's person runs in fusion mode");
    let image_input = p.image.unwrap();
    let hm = models.run(ModelKind::Camera, 1, &image_input).unwrap();
    let fused = fusion_input(&hm, &p.points.xyz, &p.points.uv, cfg);
    (image_input, fused)
}

fn main() {
    // `cargo test --all-targets` runs benches without `--bench`: a short smoke run keeps the suite fast
    let full = std::env::args().any(|a| a == "--bench");
    let n: usize =
        std::env::var("POSEFUSE_BENCH_N").ok().and_then(|v| v.parse().ok()).unwrap_or(if full { 1000 } else { 20 });
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    let mut cfg = config();
    // another bundle (a larger camera net) shows how the fixed per-request costs weigh against inference
    if let Some(dir) = std::env::var_os("POSEFUSE_BENCH_MODEL_DIR") {
        cfg.model_dir = dir.into();
    }
    println!(
        "bundle {} | workers {} | intra-op threads {} | {n} sequential requests",
        cfg.model_dir.display(),
        cfg.runtime.workers,
        cfg.runtime.intra_threads
    );

    // Raw ONNX Runtime: own sessions, same thread settings, same inputs.
    let bundle = Bundle::load(&cfg.model_dir).unwrap();
    let ort_env = env::environment(&env::resolve_lib(None)).unwrap();
    let mut models = Models::load(&ort_env, &bundle, cfg.runtime.intra_threads, cfg.runtime.device).unwrap();
    let (frame, frame_label) = bench_frame();
    let (image_input, fused) = model_inputs(&mut models, &bundle, &frame);
    for _ in 0..50 {
        models.run(ModelKind::Camera, 1, &image_input).unwrap();
        models.run(ModelKind::PointFusion, 1, &fused).unwrap();
    }

    let server = rt.block_on(start(cfg));
    let client = reqwest::Client::new();
    let body = serde_json::to_vec(&frame).unwrap();
    let grpc_req = frame_to_proto(&frame, image_bytes(&frame)).unwrap();
    let mut grpc = rt.block_on(PosefuseClient::connect(server.url(""))).unwrap();

    let server_times = std::cell::RefCell::new(Vec::new());
    let http_once = || {
        let (elapsed, bytes) = rt.block_on(async {
            let t = Instant::now();
            let r = client
                .post(server.url("/v1/poses"))
                .header("content-type", "application/json")
                .body(body.clone())
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200);
            let bytes = r.bytes().await.unwrap();
            (t.elapsed(), bytes)
        });
        let resp: posefuse::service::api::PoseResponse = serde_json::from_slice(&bytes).unwrap();
        // raw ONNX Runtime runs the fusion models: the request must take the same path
        assert_eq!(resp.persons[0].mode, posefuse::service::api::Mode::Fusion, "{}", resp.persons[0].mode_reason);
        server_times.borrow_mut().push(resp.timings);
        elapsed
    };
    let mut grpc_once = || {
        rt.block_on(async {
            let t = Instant::now();
            grpc.predict(grpc_req.clone()).await.unwrap();
            t.elapsed()
        })
    };
    let health_once = || {
        rt.block_on(async {
            let t = Instant::now();
            let r = client.get(server.url("/healthz")).send().await.unwrap();
            assert_eq!(r.status(), 200);
            r.bytes().await.unwrap();
            t.elapsed()
        })
    };
    let raw_once = |models: &mut Models| {
        let t = Instant::now();
        models.run(ModelKind::Camera, 1, &image_input).unwrap();
        models.run(ModelKind::PointFusion, 1, &fused).unwrap();
        t.elapsed()
    };
    for _ in 0..50 {
        http_once();
        grpc_once();
    }
    // Interleave so that machine load drifts hit all three alike.
    let (mut raw, mut http, mut g, mut health) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for _ in 0..n {
        raw.push(raw_once(&mut models));
        http.push(http_once());
        g.push(grpc_once());
        health.push(health_once());
    }
    println!("request body {} bytes ({frame_label})", body.len());
    let (raw50, raw99) = summary("raw ONNX Runtime (camera + fusion)", raw);
    let (h50, h99) = summary("HTTP POST /v1/poses", http);
    let (g50, g99) = summary("gRPC Predict", g);
    summary("HTTP GET /healthz (transport floor)", health);
    let t = server_times.borrow();
    let mean = |f: fn(&posefuse::service::api::Timings) -> f64| t.iter().map(f).sum::<f64>() / t.len() as f64;
    println!(
        "server-side means (HTTP): decode {:.3} ms, pre/post {:.3} ms, queue {:.3} ms, inference {:.3} ms, total {:.3} ms",
        mean(|x| x.decode_ms),
        mean(|x| x.preprocess_ms),
        mean(|x| x.queue_ms),
        mean(|x| x.inference_ms),
        mean(|x| x.total_ms)
    );
    println!(
        "ratio to raw: HTTP p50 {:.3} p99 {:.3} | gRPC p50 {:.3} p99 {:.3}",
        ms(h50) / ms(raw50),
        ms(h99) / ms(raw99),
        ms(g50) / ms(raw50),
        ms(g99) / ms(raw99)
    );
    rt.block_on(server.shutdown()).unwrap();
}
