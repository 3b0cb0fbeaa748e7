//! Faults and load, each on a loopback server with bounded counts: the drain (half-open
//! connections, a running stream), connection timeouts and the cap, model reload under load,
//! work that stops when nobody waits, and checks before decoding.

mod server_support;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use server_support::process::ServeProcess;
use server_support::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

fn frame_json() -> Value {
    serde_json::to_value(fusion_frame()).unwrap()
}

async fn post(s: &TestServer, path: &str, body: &Value) -> (u16, Value) {
    let r = reqwest::Client::new().post(s.url(path)).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// Reads until the peer closes; true when it closed (EOF or reset) within `within`.
async fn closed_within(stream: &mut TcpStream, within: Duration) -> bool {
    let mut buf = [0u8; 1024];
    let deadline = Instant::now() + within;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, stream.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return true,
            Ok(Ok(_)) => continue,
            Err(_) => return false,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drain_answers_what_was_sent_ends_streams_and_cuts_the_rest_at_the_deadline() {
    let mut cfg = config();
    cfg.drain_timeout = Duration::from_millis(1500);
    cfg.drain_delay = Duration::from_millis(300);
    let mut s = start(cfg).await;
    let addr = s.addr;
    // Half-open connections: headers begun, and a body half sent.
    let mut half = Vec::new();
    for i in 0..10 {
        let mut c = TcpStream::connect(addr).await.unwrap();
        let msg = if i % 2 == 0 {
            "POST /v1/poses HTTP/1.1\r\nHost: x\r\n".to_string()
        } else {
            "POST /v1/poses HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"a\":"
                .to_string()
        };
        c.write_all(msg.as_bytes()).await.unwrap();
        half.push(c);
    }
    // A running NDJSON stream: one frame sent, the body left open.
    let (tx, rx) = futures::channel::mpsc::unbounded::<Result<Vec<u8>, std::io::Error>>();
    let mut line = serde_json::to_vec(&frame_json()).unwrap();
    line.push(b'\n');
    tx.unbounded_send(Ok(line)).unwrap();
    let stream_url = s.url("/v1/poses:batch");
    let stream = tokio::spawn(async move {
        let r = reqwest::Client::new()
            .post(stream_url)
            .header("content-type", "application/x-ndjson")
            .body(reqwest::Body::wrap_stream(rx))
            .send()
            .await
            .unwrap();
        r.text().await.unwrap()
    });
    // A request fully sent, held in the queue while the workers are paused.
    let pause = s.predictor.runtime().pause();
    let (url, body) = (s.url("/v1/poses"), frame_json());
    let in_flight = tokio::spawn(async move { reqwest::Client::new().post(url).json(&body).send().await.unwrap() });
    tokio::time::sleep(Duration::from_millis(200)).await;

    let t0 = Instant::now();
    s.signal_shutdown();
    tokio::time::sleep(Duration::from_millis(50)).await;
    // Readiness is 503 while the listener still answers (the drain delay).
    let r = reqwest::Client::new().get(s.url("/readyz")).send().await.unwrap();
    assert_eq!(r.status(), 503);
    let grpc = posefuse::server::health::check(addr, Duration::from_secs(2)).await.unwrap();
    assert_eq!(grpc, tonic_health::pb::health_check_response::ServingStatus::NotServing);
    drop(pause);
    // The request that was fully sent is answered.
    let r = in_flight.await.unwrap();
    assert_eq!(r.status(), 200);
    // The stream was told to end: its frame answered, then an `unavailable` item.
    let text = tokio::time::timeout(Duration::from_secs(5), stream).await.unwrap().unwrap();
    let items: Vec<Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(items.iter().any(|i| i["response"].is_object()), "{text}");
    assert_eq!(items.last().unwrap()["error"]["code"], "unavailable", "{text}");
    // The half-open connections do not hold the process past the drain deadline.
    let task = s.task.take().unwrap();
    tokio::time::timeout(Duration::from_secs(5), task).await.expect("drain deadline not kept").unwrap().unwrap();
    assert!(t0.elapsed() < Duration::from_millis(300 + 1500 + 1000), "{:?}", t0.elapsed());
    drop(tx);
    drop(half);
}

fn hygiene_config() -> posefuse::server::ServerConfig {
    let mut cfg = config();
    cfg.conn.idle_timeout = Duration::from_millis(400);
    cfg.conn.header_read_timeout = Duration::from_millis(400);
    cfg.conn.body_read_timeout = Duration::from_millis(400);
    cfg
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_slow_header_and_slow_body_connections_are_closed() {
    let s = start(hygiene_config()).await;
    // Says nothing.
    let mut idle = TcpStream::connect(s.addr).await.unwrap();
    // Starts headers and stops.
    let mut slow_head = TcpStream::connect(s.addr).await.unwrap();
    slow_head.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").await.unwrap();
    // Sends headers, then a body that stalls.
    let mut slow_body = TcpStream::connect(s.addr).await.unwrap();
    slow_body
        .write_all(
            b"POST /v1/poses HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{",
        )
        .await
        .unwrap();
    for (name, c) in [("idle", &mut idle), ("slow header", &mut slow_head), ("slow body", &mut slow_body)] {
        assert!(closed_within(c, Duration::from_secs(3)).await, "{name} connection still open");
    }
    // A keep-alive client that keeps talking is not cut.
    let c = reqwest::Client::new();
    for _ in 0..4 {
        assert_eq!(c.get(s.url("/healthz")).send().await.unwrap().status(), 200);
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_the_connection_cap_the_idlest_goes_and_busy_ones_are_kept() {
    let mut cfg = hygiene_config();
    cfg.conn.idle_timeout = Duration::from_secs(30);
    cfg.conn.max_connections = 4;
    let s = start(cfg).await;
    // Fill the cap with idle connections: a new client still gets served (an idle one is evicted).
    let mut idle = Vec::new();
    for _ in 0..4 {
        idle.push(TcpStream::connect(s.addr).await.unwrap());
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    for _ in 0..3 {
        let r = reqwest::Client::new().get(s.url("/healthz")).send().await.unwrap();
        assert_eq!(r.status(), 200);
    }
    let mut evicted = 0;
    for c in &mut idle {
        if closed_within(c, Duration::from_millis(200)).await {
            evicted += 1;
        }
    }
    assert!(evicted >= 1, "no idle connection was evicted");
    drop(idle);
    tokio::time::sleep(Duration::from_millis(100)).await;
    // Fill the cap with connections that keep talking (never idle): a new one is closed at once.
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut talkers = Vec::new();
    for _ in 0..4 {
        let mut c = TcpStream::connect(s.addr).await.unwrap();
        let stop = stop.clone();
        talkers.push(tokio::spawn(async move {
            let _ = c.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").await;
            while !stop.load(Ordering::SeqCst) {
                if c.write_all(b"X-A: b\r\n").await.is_err() {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }));
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let t = Instant::now();
    let mut extra = TcpStream::connect(s.addr).await.unwrap();
    assert!(closed_within(&mut extra, Duration::from_millis(500)).await, "over the cap and not closed");
    assert!(t.elapsed() < Duration::from_millis(500));
    stop.store(true, Ordering::SeqCst);
    for t in talkers {
        let _ = t.await;
    }
    s.shutdown().await.unwrap();
}

/// A copy of the default bundle as `repository/version`, with that version in its manifest.
fn copy_bundle(repository: &std::path::Path, version: &str) -> std::path::PathBuf {
    let d = repository.join(version);
    std::fs::create_dir_all(&d).unwrap();
    for e in std::fs::read_dir(model_dir()).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, d.join(p.file_name().unwrap())).unwrap();
    }
    let p = d.join("manifest.json");
    let mut m: Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    m["version"] = json!(version);
    std::fs::write(p, serde_json::to_string_pretty(&m).unwrap()).unwrap();
    d
}

fn version_of(v: &Value) -> String {
    v["model"]["version"].as_str().unwrap_or("").to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reload_under_load_fails_no_request_and_a_broken_bundle_leaves_the_old_one() {
    let repository = tempfile::tempdir().unwrap();
    let mut c = config();
    c.admin.repository = Some(repository.path().to_path_buf());
    let (s, admin) = start_with_admin(c, true).await;
    let (s, admin) = (Arc::new(s), admin.unwrap());
    let original = reqwest::get(s.url("/v1/models")).await.unwrap().json::<Value>().await.unwrap();
    let original = original["version"].as_str().unwrap().to_string();
    copy_bundle(repository.path(), "reloaded-1");
    // Steady load: 3 clients, one frame after another, until told to stop.
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (ok, failed) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
    let versions = Arc::new(std::sync::Mutex::new(std::collections::BTreeSet::new()));
    let mut clients = Vec::new();
    for _ in 0..3 {
        let (s, stop, ok, failed, versions) = (s.clone(), stop.clone(), ok.clone(), failed.clone(), versions.clone());
        clients.push(tokio::spawn(async move {
            let body = frame_json();
            while !stop.load(Ordering::SeqCst) {
                let (status, v) = post(&s, "/v1/poses", &body).await;
                if status == 200 {
                    ok.fetch_add(1, Ordering::SeqCst);
                    versions.lock().unwrap().insert(version_of(&v));
                } else {
                    failed.fetch_add(1, Ordering::SeqCst);
                }
            }
        }));
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let reload_url = format!("{admin}/v1/models:reload");
    let (status, r) = post_to(&reload_url, &json!({"model_dir": "reloaded-1"})).await;
    assert_eq!(status, 200, "{r}");
    assert_eq!(
        (r["model"]["version"].as_str(), r["previous"]["version"].as_str()),
        (Some("reloaded-1"), Some(original.as_str()))
    );
    tokio::time::sleep(Duration::from_millis(300)).await;
    // A broken bundle: the reason comes back, the serving one stays.
    let broken = copy_bundle(repository.path(), "broken");
    std::fs::write(broken.join("point_lidar.onnx"), b"not onnx").unwrap();
    let (status, r) = post_to(&reload_url, &json!({"model_dir": "broken"})).await;
    assert_eq!(status, 422, "{r}");
    assert_eq!(r["error"]["field"], "model_dir");
    assert!(r["error"]["message"].as_str().unwrap().contains("point_lidar"), "{r}");
    // Reload of the serving directory (an empty body).
    let r = reqwest::Client::new().post(&reload_url).send().await.unwrap();
    assert_eq!(r.status(), 200);
    tokio::time::sleep(Duration::from_millis(300)).await;
    stop.store(true, Ordering::SeqCst);
    for c in clients {
        c.await.unwrap();
    }
    assert_eq!(failed.load(Ordering::SeqCst), 0, "requests failed during the reload");
    assert!(ok.load(Ordering::SeqCst) > 10);
    let versions = versions.lock().unwrap().clone();
    assert!(versions.contains(&original) && versions.contains("reloaded-1"), "{versions:?}");
    let models = reqwest::get(s.url("/v1/models")).await.unwrap().json::<Value>().await.unwrap();
    assert_eq!(models["version"], "reloaded-1");
    let (status, v) = post(&s, "/v1/poses", &frame_json()).await;
    assert_eq!((status, version_of(&v).as_str()), (200, "reloaded-1"));
    Arc::into_inner(s).unwrap().shutdown().await.unwrap();
}

/// Metric `name`'s value in a Prometheus text page (0 when absent).
fn metric(page: &str, name: &str) -> f64 {
    page.lines().find_map(|l| l.strip_prefix(name).and_then(|v| v.trim().parse().ok())).unwrap_or(0.0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn out_of_file_descriptors_accept_backs_off_and_the_server_recovers() {
    // 128 descriptors and a connection cap above them: past about a hundred connections the
    // server's accept fails with EMFILE while the rest wait in the listen backlog.
    let s = ServeProcess::start_with(&[], &["--max-connections", "1000"], Some(128));
    let held: Vec<std::net::TcpStream> = (0..200).filter_map(|_| std::net::TcpStream::connect(&s.addr).ok()).collect();
    assert!(held.len() > 150, "only {} connections opened", held.len());
    tokio::time::sleep(Duration::from_millis(300)).await;
    let cpu = s.cpu_seconds();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let spent = s.cpu_seconds() - cpu;
    // A retry loop without a pause would keep a core busy (about 2 CPU-s here).
    assert!(spent < 0.5, "{spent:.2} CPU-s in 2 s while out of descriptors");
    drop(held);
    let t = Instant::now();
    let page = loop {
        if let Ok(r) = reqwest::get(s.url("/metrics")).await {
            if r.status() == 200 {
                break r.text().await.unwrap();
            }
        }
        assert!(t.elapsed() < Duration::from_secs(10), "not served again after the descriptors came back");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let errors = metric(&page, "posefuse_accept_errors_total");
    // About one failed accept per 50 ms pause over the 2.3 s: the loop hit the limit and waited.
    assert!((5.0..=200.0).contains(&errors), "{errors} accept errors");
    assert!(s.ready());
}

/// The server's CPU seconds in the second after a request ends (with 150 ms for the step in hand).
async fn cpu_after(s: &ServeProcess, body: &Value, hang_up_after: Option<Duration>) -> (Option<u16>, f64) {
    let req = reqwest::Client::new().post(s.url("/v1/poses")).json(body);
    let status = match hang_up_after {
        None => Some(req.send().await.unwrap().status().as_u16()),
        Some(d) => {
            let _ = tokio::time::timeout(d, req.send()).await;
            None
        }
    };
    tokio::time::sleep(Duration::from_millis(150)).await;
    let c0 = s.cpu_seconds();
    tokio::time::sleep(Duration::from_millis(1000)).await;
    (status, s.cpu_seconds() - c0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_cpu_work_after_a_504_or_a_hang_up() {
    let body = serde_json::to_value(heavy_frame(256, 200_000)).unwrap();
    // How long the frame takes, and its CPU, when someone waits for it.
    let s = ServeProcess::start(&[]);
    let (t, c0) = (Instant::now(), s.cpu_seconds());
    let (status, _) = post_to(&s.url("/v1/poses"), &body).await;
    let (full, full_cpu) = (t.elapsed(), s.cpu_seconds() - c0);
    assert_eq!(status, 200);
    drop(s);
    assert!(full_cpu > 0.5, "the frame is too light to show anything: {full_cpu:.2} CPU-s");

    let cut = full / 10;
    let s = ServeProcess::start(&[("POSEFUSE_REQUEST_TIMEOUT_MS", cut.as_millis().to_string())]);
    let (status, cpu) = cpu_after(&s, &body, None).await;
    assert_eq!(status, Some(504));
    assert!(cpu < 0.1, "{cpu:.3} CPU-s spent after the 504 (the frame takes {full_cpu:.2} CPU-s)");
    drop(s);
    let s = ServeProcess::start(&[]);
    let (_, cpu) = cpu_after(&s, &body, Some(cut)).await;
    assert!(cpu < 0.1, "{cpu:.3} CPU-s spent after the client hung up (the frame takes {full_cpu:.2} CPU-s)");
}

async fn post_to(url: &str, body: &Value) -> (u16, Value) {
    let r = reqwest::Client::new().post(url).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_image_whose_header_disagrees_is_refused_before_decoding() {
    let s = start(config()).await;
    // 13000x13000 declared by the image, 640x480 by the calibration: refused from the header.
    let mut big = Vec::new();
    image::DynamicImage::new_luma8(13_000, 13_000)
        .write_to(&mut std::io::Cursor::new(&mut big), image::ImageFormat::Png)
        .unwrap();
    let mut v = frame_json();
    v["image"] = json!(base64_encode(&big));
    let t = Instant::now();
    let (status, r) = post(&s, "/v1/poses", &v).await;
    assert_eq!(status, 422, "{r}");
    assert_eq!(r["error"]["field"], "image");
    assert!(r["error"]["message"].as_str().unwrap().contains("not decoded"), "{r}");
    assert!(t.elapsed() < Duration::from_secs(2));
    // A declared size over the pixel limit.
    let mut v = frame_json();
    v["calibration"]["width"] = json!(20_000);
    v["calibration"]["height"] = json!(20_000);
    let (status, r) = post(&s, "/v1/poses", &v).await;
    assert_eq!((status, r["error"]["field"].as_str()), (422, Some("calibration.width/height")), "{r}");
    s.shutdown().await.unwrap();
}

fn base64_encode(b: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(b)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_show_admission_and_in_flight_gauges() {
    let s = start(config()).await;
    let (status, _) = post(&s, "/v1/poses", &frame_json()).await;
    assert_eq!(status, 200);
    let text = reqwest::get(s.url("/metrics")).await.unwrap().text().await.unwrap();
    for g in [
        "posefuse_requests_in_flight",
        "posefuse_preprocess_in_flight",
        "posefuse_admission_waiting",
        "posefuse_admission_line",
        "posefuse_queue_depth",
        "posefuse_connections_open",
    ] {
        assert!(text.contains(g), "{g} missing from /metrics");
    }
    s.shutdown().await.unwrap();
}

/// The `posefuse serve` process: SIGHUP reloads (the process stays), SIGTERM drains and exits 0
/// within the drain deadline although a client holds a half-sent request.
#[test]
fn the_serve_process_reloads_on_sighup_and_exits_0_on_sigterm() {
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let addr = format!("127.0.0.1:{port}");
    let log = tempfile::NamedTempFile::new().unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(["serve", "--addr", &addr, "--model-dir"])
        .arg(model_dir())
        .env("ORT_DYLIB_PATH", std::env::var("ORT_DYLIB_PATH").unwrap_or_else(|_| ".ort/lib/libonnxruntime.so".into()))
        .env("POSEFUSE_DRAIN_TIMEOUT", "2")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stderr(log.reopen().unwrap())
        .spawn()
        .unwrap();
    let pid = child.id() as i32;
    let ready = || {
        std::net::TcpStream::connect(&addr).ok().is_some_and(|mut c| {
            use std::io::{Read, Write};
            let _ = c.set_read_timeout(Some(Duration::from_secs(2)));
            let _ = c.write_all(b"GET /readyz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n");
            let mut s = String::new();
            let _ = c.read_to_string(&mut s);
            s.starts_with("HTTP/1.1 200")
        })
    };
    let t = Instant::now();
    while !ready() {
        assert!(t.elapsed() < Duration::from_secs(60), "not ready");
        std::thread::sleep(Duration::from_millis(50));
    }
    // SIGHUP: reload, not exit.
    unsafe { libc::kill(pid, libc::SIGHUP) };
    let t = Instant::now();
    let logged = |what: &str| std::fs::read_to_string(log.path()).unwrap_or_default().contains(what);
    while !logged("reloaded") {
        assert!(child.try_wait().unwrap().is_none(), "SIGHUP killed the process");
        assert!(t.elapsed() < Duration::from_secs(60), "no reload logged");
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(ready());
    // A half-sent request, then SIGTERM: exit 0 within the drain deadline, the cut logged.
    let mut half = std::net::TcpStream::connect(&addr).unwrap();
    std::io::Write::write_all(&mut half, b"POST /v1/poses HTTP/1.1\r\nHost: x\r\nContent-Length: 50\r\n\r\n{").unwrap();
    std::thread::sleep(Duration::from_millis(100));
    let t = Instant::now();
    unsafe { libc::kill(pid, libc::SIGTERM) };
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t.elapsed() > Duration::from_secs(10) {
            let _ = child.kill();
            panic!("still running 10 s after SIGTERM");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert_eq!(status.code(), Some(0));
    assert!(t.elapsed() < Duration::from_secs(4), "{:?}", t.elapsed());
    assert!(logged("drain deadline passed"), "{}", std::fs::read_to_string(log.path()).unwrap());
    drop(half);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn per_frame_limits_on_persons_points_and_image_size_are_flags() {
    let mut cfg = config();
    // the test camera's own size is the largest image allowed
    let max_image_pixels = (WIDTH * HEIGHT) as u64;
    cfg.frame_limits = posefuse::service::limits::FrameLimits { max_persons: 2, max_points: 400, max_image_pixels };
    let s = start(cfg).await;
    // three_mode_frame: 3 persons, 553 points.
    let mut frame = three_mode_frame();
    let (status, r) = post(&s, "/v1/poses", &serde_json::to_value(&frame).unwrap()).await;
    assert_eq!((status, r["error"]["field"].as_str()), (422, Some("persons")), "{r}");
    frame.persons.truncate(2);
    let (status, r) = post(&s, "/v1/poses", &serde_json::to_value(&frame).unwrap()).await;
    assert_eq!((status, r["error"]["field"].as_str()), (422, Some("points")), "{r}");
    let (status, r) = post(&s, "/v1/poses", &frame_json()).await;
    assert_eq!(status, 200, "{r}");
    // one row more than allowed is refused for its declared size, before its image is read
    let mut taller = frame_json();
    taller["calibration"]["height"] = json!(HEIGHT + 1);
    let (status, r) = post(&s, "/v1/poses", &taller).await;
    assert_eq!((status, r["error"]["field"].as_str()), (422, Some("calibration.width/height")), "{r}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn large_bodies_are_parsed_off_the_async_threads() {
    let s = start(config()).await;
    // 4 bodies of ~24 MB of flat points at once (refused for the point count after parsing).
    let mut v = frame_json();
    v["points"] = json!("POINTS");
    let text = serde_json::to_string(&v).unwrap();
    let numbers = format!("[{}0.25]", "0.25,".repeat(4_800_000));
    let body = text.replace("\"POINTS\"", &numbers);
    let mut posts = Vec::new();
    for _ in 0..4 {
        let (url, body) = (s.url("/v1/poses"), body.clone());
        posts.push(tokio::spawn(async move {
            let r = reqwest::Client::new().post(url).header("content-type", "application/json").body(body).send().await;
            r.map(|r| r.status().as_u16()).unwrap_or(0)
        }));
    }
    // Health checks keep answering while they are read and parsed.
    let c = reqwest::Client::new();
    let mut worst = Duration::ZERO;
    while posts.iter().any(|p| !p.is_finished()) {
        let t = Instant::now();
        assert_eq!(c.get(s.url("/healthz")).send().await.unwrap().status(), 200);
        worst = worst.max(t.elapsed());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    for p in posts {
        assert_eq!(p.await.unwrap(), 422);
    }
    assert!(worst < Duration::from_millis(500), "/healthz took {worst:?} while bodies were parsed");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn many_of_the_largest_boxes_are_refused_before_cropping() {
    let s = start(config()).await;
    let b = person_box(8.0, 0.5);
    let mut frame = fusion_frame();
    frame.persons = (0..256)
        .map(|i| {
            let mut p = person(&format!("p{i}"), b, true);
            // The largest box allowed: twice the image on each side.
            p.box_2d = Some(posefuse::frame::Box2d {
                center_x: WIDTH as f64 / 2.0,
                center_y: HEIGHT as f64 / 2.0,
                width: 2.0 * WIDTH as f64,
                height: 2.0 * HEIGHT as f64,
            });
            p
        })
        .collect();
    let t = Instant::now();
    let (status, r) = post(&s, "/v1/poses", &serde_json::to_value(&frame).unwrap()).await;
    assert_eq!(status, 422, "{r}");
    assert!(r["error"]["field"].as_str().unwrap().starts_with("persons["), "{r}");
    assert!(r["error"]["message"].as_str().unwrap().contains("times the image"), "{r}");
    assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
    s.shutdown().await.unwrap();
}

/// One HTTP/1 response read off a raw connection: status and body (by its Content-Length).
async fn read_response(stream: &mut TcpStream) -> (u16, Vec<u8>) {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    let head_end = loop {
        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
        let n = tokio::time::timeout(Duration::from_secs(5), stream.read(&mut chunk)).await.unwrap().unwrap();
        assert!(n > 0, "connection closed before a response: {:?}", String::from_utf8_lossy(&buf));
        buf.extend_from_slice(&chunk[..n]);
    };
    let head = String::from_utf8_lossy(&buf[..head_end]).to_lowercase();
    let status: u16 = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    let len: usize =
        head.lines().find_map(|l| l.strip_prefix("content-length:")).map_or(0, |v| v.trim().parse().unwrap());
    while buf.len() < head_end + len {
        let n = tokio::time::timeout(Duration::from_secs(5), stream.read(&mut chunk)).await.unwrap().unwrap();
        assert!(n > 0, "connection closed inside a response body");
        buf.extend_from_slice(&chunk[..n]);
    }
    (status, buf[head_end..head_end + len].to_vec())
}

/// The test server's configuration with no waiting line (`--admission-wait-ms 0`): a frame that
/// finds the server full is refused at once.
fn without_line() -> posefuse::server::ServerConfig {
    let mut cfg = config();
    cfg.admission_line = posefuse::service::admission::Line::OFF;
    cfg
}

/// A server with room for one frame, and that one frame in it: admitted, its inference paused.
/// Returns the server, the pause (drop it to let the frame finish) and the frame's answer.
async fn full_server(
    cfg: posefuse::server::ServerConfig,
) -> (TestServer, posefuse::runtime::PauseGuard, tokio::task::JoinHandle<reqwest::Result<u16>>) {
    let mut cfg = cfg;
    (cfg.decode_permits, cfg.admission_queue) = (1, 0);
    let s = start(cfg).await;
    let pause = s.predictor.runtime().pause();
    let first = {
        let (url, body) = (s.url("/v1/poses"), frame_json());
        tokio::spawn(
            async move { reqwest::Client::new().post(url).json(&body).send().await.map(|r| r.status().as_u16()) },
        )
    };
    let t0 = Instant::now();
    while s.predictor.admission().admitted() == 0 {
        assert!(t0.elapsed() < Duration::from_secs(5), "the first frame was never admitted");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    (s, pause, first)
}

/// A frame of 4 MB (a long `frame_id`) for `POST /v1/poses` over a raw connection: its head and body.
fn big_frame_post() -> (String, Vec<u8>) {
    let mut big = frame_json();
    big["frame_id"] = json!("x".repeat(4 << 20));
    let body = serde_json::to_vec(&big).unwrap();
    let head = format!(
        "POST /v1/poses HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    (head, body)
}

/// A connection that has sent `head` and the first 64 KB of `body`.
async fn begin_post(s: &TestServer, head: &str, body: &[u8]) -> TcpStream {
    let mut c = TcpStream::connect(s.addr).await.unwrap();
    c.write_all(head.as_bytes()).await.unwrap();
    c.write_all(&body[..64 << 10]).await.unwrap();
    c
}

/// Waits until `n` frames are in the admission line, failing after `within`.
async fn until_in_line(admission: &posefuse::service::admission::Admission, n: usize, within: Duration) {
    let t0 = Instant::now();
    while admission.in_line() != n {
        assert!(t0.elapsed() < within, "still {} in line after {within:?}, not {n}", admission.in_line());
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_request_gets_its_429_early_and_its_connection_stays_usable() {
    let (s, pause, first) = full_server(without_line()).await;
    // A 4 MB body, of which only the first 64 KB are sent before the answer is read.
    let (head, big) = big_frame_post();
    let mut c = begin_post(&s, &head, &big).await;
    let (status, body) = read_response(&mut c).await;
    assert_eq!(status, 429, "{}", String::from_utf8_lossy(&body));
    // The rest of the body is taken (not a reset), and the same connection serves the next request.
    c.write_all(&big[64 << 10..]).await.unwrap();
    c.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    assert_eq!(read_response(&mut c).await.0, 200);
    // A client that waits for `100 Continue` is refused without being invited to send its body.
    let mut polite = TcpStream::connect(s.addr).await.unwrap();
    let head = head.replace("\r\n\r\n", "\r\nExpect: 100-continue\r\n\r\n");
    polite.write_all(head.as_bytes()).await.unwrap();
    assert_eq!(read_response(&mut polite).await.0, 429, "a 100 Continue came first");
    // and the server does not wait for that body (which will not come)
    assert!(closed_within(&mut polite, Duration::from_secs(2)).await, "the server waits for the body");
    drop(pause);
    assert_eq!(first.await.unwrap().unwrap(), 200);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_body_is_read_no_further_than_the_body_limit() {
    let mut cfg = without_line();
    cfg.body_limit = 1 << 20;
    let (s, pause, first) = full_server(cfg).await;
    // 8 MB declared, 8 times the limit: refused at once, then read only up to the limit
    let mut c = TcpStream::connect(s.addr).await.unwrap();
    let len = 8usize << 20;
    let head = format!(
        "POST /v1/poses HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: {len}\r\n\r\n"
    );
    c.write_all(head.as_bytes()).await.unwrap();
    assert_eq!(read_response(&mut c).await.0, 429);
    let chunk = vec![b' '; 64 << 10];
    let mut sent = 0;
    while sent < len {
        // the server stops reading past the limit and closes: the write fails or stalls there
        match tokio::time::timeout(Duration::from_millis(500), c.write_all(&chunk)).await {
            Ok(Ok(())) => sent += chunk.len(),
            _ => break,
        }
    }
    assert!(sent < len, "all {len} bytes were taken");
    assert!(closed_within(&mut c, Duration::from_secs(2)).await, "the connection stays open");
    drop(pause);
    assert_eq!(first.await.unwrap().unwrap(), 200);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_transport_refuses_a_frame_before_reading_it_when_the_server_is_full() {
    use posefuse::server::grpc::proto::posefuse_client::PosefuseClient;
    use posefuse::server::kserve::grpc::proto::{
        grpc_inference_service_client::GrpcInferenceServiceClient, ModelInferRequest,
    };
    let (s, pause, first) = full_server(without_line()).await;
    let http = reqwest::Client::new();
    // Bodies that would be 400 if they were read: the 429 shows they were not.
    for path in ["/v1/poses", "/v2/models/default/infer", "/v2/models/default/versions/9/infer"] {
        let r = http.post(s.url(path)).header("content-type", "application/json").body("{not json").send().await;
        let r = r.unwrap();
        assert_eq!(r.status().as_u16(), 429, "{path}");
        assert_eq!(r.headers().get("retry-after").map(|v| v.to_str().unwrap().to_string()), Some("1".into()));
        let body: Value = r.json().await.unwrap();
        let shape_ok =
            if path.starts_with("/v2") { body["error"].is_string() } else { body["error"]["code"] == "overloaded" };
        assert!(shape_ok, "{path}: {body}");
    }
    // gRPC: messages that would be INVALID_ARGUMENT if they were read.
    let mut native = PosefuseClient::connect(s.url("")).await.unwrap();
    let e = native.predict(posefuse::server::grpc::proto::PredictRequest::default()).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
    let mut v2 = GrpcInferenceServiceClient::connect(s.url("")).await.unwrap();
    let e = v2.model_infer(ModelInferRequest::default()).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
    // Batches: each frame is admitted before it is parsed, so even the malformed one is refused.
    let (status, items) = post(&s, "/v1/poses:batch", &json!([frame_json(), {"points": 3}])).await;
    assert_eq!(status, 200);
    let codes: Vec<&str> = items.as_array().unwrap().iter().map(|i| i["error"]["code"].as_str().unwrap()).collect();
    assert_eq!(codes, ["overloaded", "overloaded"], "{items}");
    let lines = s.post_ndjson("{not json\n".into()).await.text().await.unwrap();
    assert!(lines.contains("\"overloaded\""), "{lines}");
    // Routes that carry no frame are not admitted: they answer while the server is full.
    assert_eq!(http.get(s.url("/v2/models/default")).send().await.unwrap().status().as_u16(), 200);
    drop(pause);
    assert_eq!(first.await.unwrap().unwrap(), 200);
    // With room again the same bodies are read, and refused for what they are.
    let r = http.post(s.url("/v2/models/default/infer")).body("{not json").send().await.unwrap();
    assert_eq!(r.status().as_u16(), 400);
    let e = v2.model_infer(ModelInferRequest::default()).await.unwrap_err();
    assert_ne!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
    s.shutdown().await.unwrap();
}

/// [`full_server`] with a waiting line of `max` frames, each waiting at most `wait`.
async fn full_server_with_line(
    wait: Duration,
    max: usize,
) -> (TestServer, posefuse::runtime::PauseGuard, tokio::task::JoinHandle<reqwest::Result<u16>>) {
    let mut cfg = config();
    cfg.admission_line = posefuse::service::admission::Line { wait, max };
    full_server(cfg).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_a_line_a_full_server_makes_frames_wait_their_turn_before_reading_them() {
    use posefuse::server::grpc::proto::posefuse_client::PosefuseClient;
    let (s, pause, first) = full_server_with_line(Duration::from_secs(20), 3).await;
    let admission = s.predictor.admission().clone();
    let until_in_line = |n: usize| until_in_line(&admission, n, Duration::from_secs(5));
    let waiter = {
        let (url, body) = (s.url("/v1/poses"), frame_json());
        tokio::spawn(async move {
            let r = reqwest::Client::new().post(url).json(&body).send().await.unwrap();
            (r.status().as_u16(), r.json::<Value>().await.unwrap())
        })
    };
    until_in_line(1).await;
    let grpc_waiter = {
        let mut native = PosefuseClient::connect(s.url("")).await.unwrap();
        tokio::spawn(async move { native.predict(posefuse::server::grpc::proto::PredictRequest::default()).await })
    };
    until_in_line(2).await;
    // A gRPC caller that gives up while it waits (its stream reset) leaves the line at once.
    let gone = {
        let mut native = PosefuseClient::connect(s.url("")).await.unwrap();
        tokio::spawn(async move { native.predict(posefuse::server::grpc::proto::PredictRequest::default()).await })
    };
    until_in_line(3).await;
    gone.abort();
    until_in_line(2).await;
    // A third waiter fills the line: a fourth frame is refused at once, unread, as without a line.
    let third = {
        let (url, body) = (s.url("/v1/poses"), frame_json());
        tokio::spawn(
            async move { reqwest::Client::new().post(url).json(&body).send().await.map(|r| r.status().as_u16()) },
        )
    };
    until_in_line(3).await;
    let t0 = Instant::now();
    let r = reqwest::Client::new().post(s.url("/v1/poses")).body("{not json").send().await.unwrap();
    assert_eq!(r.status().as_u16(), 429);
    assert!(t0.elapsed() < Duration::from_secs(2), "the refusal waited {:?}", t0.elapsed());
    drop(pause);
    assert_eq!(first.await.unwrap().unwrap(), 200);
    // The waiters were read only once admitted: the frames are answered, the empty gRPC message
    // gets the error of what it is (not RESOURCE_EXHAUSTED).
    let (status, body) = waiter.await.unwrap();
    assert_eq!(status, 200, "{body}");
    let e = grpc_waiter.await.unwrap().unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e:?}");
    assert_eq!(third.await.unwrap().unwrap(), 200);
    assert_eq!(admission.in_line(), 0);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_http1_client_that_hangs_up_while_it_waits_leaves_the_line() {
    let (s, pause, first) = full_server_with_line(Duration::from_secs(30), 1).await;
    let admission = s.predictor.admission().clone();
    let until_in_line = |n: usize, within: Duration| until_in_line(&admission, n, within);
    let abandoned = || async {
        let page = reqwest::get(s.url("/metrics")).await.unwrap().text().await.unwrap();
        metric(&page, "posefuse_frames_abandoned_total")
    };
    let before = abandoned().await;
    // A 4 MB body, of which the first 64 KB are sent before the client hangs up: hyper reads none
    // of a waiting frame's body, so only the socket can tell that its client has gone.
    let (head, body) = big_frame_post();
    let c = begin_post(&s, &head, &body).await;
    until_in_line(1, Duration::from_secs(5)).await;
    // The line (of one) is full: a frame is refused at once.
    let r = reqwest::Client::new().post(s.url("/v1/poses")).json(&frame_json()).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 429);
    drop(c);
    // Seen within a second, not at the end of its 30 s wait or at its turn.
    until_in_line(0, Duration::from_secs(1)).await;
    assert_eq!(abandoned().await, before + 1.0);
    // Logged and counted as the client's doing (nginx's 499), not as a server error.
    let page = reqwest::get(s.url("/metrics")).await.unwrap().text().await.unwrap();
    let gone = r#"posefuse_request_duration_seconds_count{transport="http",route="/v1/poses",status="499"}"#;
    assert_eq!(metric(&page, gone), 1.0, "{page}");
    assert_eq!(
        metric(&page, r#"posefuse_request_duration_seconds_count{transport="http",route="/v1/poses",status="503"}"#),
        0.0
    );
    // Its place in the line is free for a client that stays.
    let stays = {
        let (url, body) = (s.url("/v1/poses"), frame_json());
        tokio::spawn(
            async move { reqwest::Client::new().post(url).json(&body).send().await.map(|r| r.status().as_u16()) },
        )
    };
    until_in_line(1, Duration::from_secs(5)).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(admission.in_line(), 1, "a client that stays is not taken for gone");
    drop(pause);
    assert_eq!(first.await.unwrap().unwrap(), 200);
    assert_eq!(stays.await.unwrap().unwrap(), 200);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wait_in_the_line_that_ends_is_a_429() {
    let (s, pause, first) = full_server_with_line(Duration::from_millis(300), 4).await;
    let t0 = Instant::now();
    let r = reqwest::Client::new().post(s.url("/v1/poses")).json(&frame_json()).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 429);
    assert_eq!(r.headers().get("retry-after").map(|v| v.to_str().unwrap().to_string()), Some("1".into()));
    assert!(t0.elapsed() >= Duration::from_millis(300), "refused after {:?}", t0.elapsed());
    assert_eq!(s.predictor.admission().in_line(), 0);
    drop(pause);
    assert_eq!(first.await.unwrap().unwrap(), 200);
    s.shutdown().await.unwrap();
}
