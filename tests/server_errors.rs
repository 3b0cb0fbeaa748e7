//! Bad input, limits, overload, deadlines and shutdown against a real in-process server.

mod server_support;

use std::time::Duration;

use posefuse::frame::Points;
use serde_json::{json, Value};
use server_support::*;

async fn post_json(s: &TestServer, body: &Value) -> (u16, Value) {
    let r = reqwest::Client::new().post(s.url("/v1/poses")).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

fn frame_json() -> Value {
    serde_json::to_value(fusion_frame()).unwrap()
}

/// Asserts the `{"error": {"code", "message", "field"}}` shape and returns (code, field).
fn error_of(status: u16, body: &Value, want_status: u16) -> (String, String) {
    assert_eq!(status, want_status, "{body}");
    let e = &body["error"];
    assert!(e["message"].as_str().is_some_and(|m| !m.is_empty()), "{body}");
    (e["code"].as_str().unwrap_or("").to_string(), e["field"].as_str().unwrap_or("").to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_class_of_bad_input_names_its_field() {
    let s = start(config()).await;
    let c = reqwest::Client::new();

    // Malformed JSON.
    let r = c
        .post(s.url("/v1/poses"))
        .header("content-type", "application/json")
        .body("{\"points\": [1,")
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    let (code, _) = error_of(status, &r.json().await.unwrap(), 400);
    assert_eq!(code, "malformed_request");
    // Wrong content type.
    let r = c.post(s.url("/v1/poses")).header("content-type", "text/plain").body("{}").send().await.unwrap();
    assert_eq!(r.status(), 400);

    type Case = (&'static str, Box<dyn Fn(&mut Value)>, u16, &'static str);
    let cases: Vec<Case> = vec![
        ("missing field", Box::new(|v| drop(v.as_object_mut().unwrap().remove("calibration"))), 422, "calibration"),
        (
            "missing nested field",
            Box::new(|v| drop(v["persons"][0]["box_3d"].as_object_mut().unwrap().remove("heading"))),
            422,
            "persons[0].box_3d.heading",
        ),
        ("wrong type", Box::new(|v| v["calibration"]["width"] = json!("wide")), 422, "calibration.width"),
        ("unknown field", Box::new(|v| v["persons"][0]["colour"] = json!("red")), 422, "persons[0].colour"),
        ("unknown mode", Box::new(|v| v["mode"] = json!("telepathy")), 422, "mode"),
        ("infinite coordinate", Box::new(|v| v["points"] = json!([1.0, 2.0, 1e39])), 422, "points[0]"),
        ("zero points", Box::new(|v| v["points"] = json!([])), 422, "points"),
        ("points not triples", Box::new(|v| v["points"] = json!([1.0, 2.0])), 422, "points"),
        ("points bytes not triples", Box::new(|v| v["points"] = json!({"b64": "AAAAAAAAAAA="})), 422, "points.b64"),
        (
            "short intrinsic",
            Box::new(|v| v["calibration"]["intrinsic"] = json!([500.0, 500.0, 320.0])),
            422,
            "calibration.intrinsic",
        ),
        (
            "zero focal length",
            Box::new(|v| v["calibration"]["intrinsic"][0] = json!(0.0)),
            422,
            "calibration.intrinsic[0] (f_u)",
        ),
        ("not a rotation", Box::new(|v| v["calibration"]["extrinsic"][0] = json!(2.0)), 422, "calibration.extrinsic"),
        ("zero image size", Box::new(|v| v["calibration"]["width"] = json!(0)), 422, "calibration.width/height"),
        ("image size disagrees", Box::new(|v| v["calibration"]["width"] = json!(641)), 422, "image"),
        (
            "box outside image",
            Box::new(|v| v["persons"][0]["box_2d"]["center_x"] = json!(5000.0)),
            422,
            "persons[0].box_2d",
        ),
        (
            "negative box size",
            Box::new(|v| v["persons"][0]["box_2d"]["width"] = json!(-3.0)),
            422,
            "persons[0].box_2d.width",
        ),
        ("no persons", Box::new(|v| v["persons"] = json!([])), 422, "persons"),
    ];
    for (name, mutate, want_status, want_field) in cases {
        let mut v = frame_json();
        mutate(&mut v);
        let (status, body) = post_json(&s, &v).await;
        let (_, field) = error_of(status, &body, want_status);
        assert_eq!(field, want_field, "{name}: {body}");
    }
    s.shutdown().await.unwrap();
}

/// A person whose 3D box holds no LiDAR point is data the sensors lack, not a bad request: it is
/// listed under `skipped` with the reason, and the frame's other persons are still answered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_person_without_points_is_skipped_not_the_frame() {
    let s = start(config()).await;
    let mut v = frame_json();
    let mut empty = v["persons"][0].clone();
    empty["id"] = json!("far-away");
    empty["box_3d"]["center_y"] = json!(30.0);
    empty.as_object_mut().unwrap().remove("box_2d");
    v["persons"].as_array_mut().unwrap().insert(0, empty.clone());
    let (status, body) = post_json(&s, &v).await;
    assert_eq!(status, 200, "{body}");
    let answered: Vec<&str> = body["persons"].as_array().unwrap().iter().map(|p| p["id"].as_str().unwrap()).collect();
    assert_eq!(answered, vec![v["persons"][1]["id"].as_str().unwrap()], "{body}");
    let skipped = &body["skipped"];
    assert_eq!(skipped.as_array().map(Vec::len), Some(1), "{body}");
    assert_eq!((skipped[0]["index"].as_u64(), skipped[0]["id"].as_str()), (Some(0), Some("far-away")));
    assert_eq!(skipped[0]["error"]["field"], "persons[0].box_3d", "{body}");
    assert!(skipped[0]["error"]["message"].as_str().unwrap().contains("no LiDAR point"), "{body}");

    // Alone in its frame: an answer with no poses, still not an error.
    let mut alone = frame_json();
    alone["persons"] = json!([empty]);
    let (status, body) = post_json(&s, &alone).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["persons"].as_array().map(Vec::len), Some(0), "{body}");
    assert_eq!(body["skipped"][0]["error"]["code"], "insufficient_data", "{body}");
    s.shutdown().await.unwrap();
}

/// Replaces every leaf of the frame (one at a time) with hostile values: the server answers
/// 200, 400 or 422 with the error shape, never 5xx, and keeps serving.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_values_never_break_the_server() {
    let s = start(config()).await;
    let mut base = serde_json::to_value(three_mode_frame()).unwrap();
    base["image"] = json!(image_b64(&[]));
    base["points"] = json!(Points::encode(&points_in(&person_box(8.0, 0.5), 20))
        .decode()
        .unwrap()
        .iter()
        .flatten()
        .copied()
        .collect::<Vec<f32>>());
    fn leaves(v: &Value, path: Vec<Value>, out: &mut Vec<Vec<Value>>) {
        match v {
            Value::Object(m) => m.iter().for_each(|(k, x)| {
                let mut p = path.clone();
                p.push(json!(k));
                leaves(x, p, out)
            }),
            Value::Array(a) => a.iter().enumerate().take(4).for_each(|(i, x)| {
                let mut p = path.clone();
                p.push(json!(i));
                leaves(x, p, out)
            }),
            _ => out.push(path),
        }
    }
    let mut paths = Vec::new();
    leaves(&base, vec![], &mut paths);
    let hostile = [json!(0), json!(-1), json!(1e300), json!(-1e300), json!("x"), json!(null), json!([]), json!({})];
    let mut seen = std::collections::BTreeMap::new();
    for p in &paths {
        for h in &hostile {
            let mut v = base.clone();
            let mut slot = &mut v;
            for k in p {
                slot = match k {
                    Value::String(s) => &mut slot[s.as_str()],
                    Value::Number(n) => &mut slot[n.as_u64().unwrap() as usize],
                    _ => unreachable!(),
                };
            }
            *slot = h.clone();
            let (status, body) = post_json(&s, &v).await;
            assert!([200, 400, 422].contains(&status), "{p:?} = {h}: {status} {body}");
            if status != 200 {
                assert!(body["error"]["code"].is_string(), "{p:?} = {h}: {body}");
            }
            *seen.entry(status).or_insert(0) += 1;
        }
    }
    assert!(seen.len() >= 2, "{seen:?}");
    assert_eq!(reqwest::get(s.url("/healthz")).await.unwrap().status(), 200);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bodies_over_the_limit_get_413() {
    let mut cfg = config();
    cfg.body_limit = 4_000;
    let s = start(cfg).await;
    let big = serde_json::to_vec(&fusion_frame()).unwrap();
    assert!(big.len() > 4_000);
    let c = reqwest::Client::new();
    for path in ["/v1/poses", "/v1/poses:batch", "/v1/evaluate"] {
        let r = c.post(s.url(path)).header("content-type", "application/json").body(big.clone()).send().await.unwrap();
        let status = r.status().as_u16();
        let (code, _) = error_of(status, &r.json().await.unwrap(), 413);
        assert_eq!(code, "payload_too_large", "{path}");
    }
    // NDJSON applies the limit per line: the long line fails, the short one goes through.
    let mut small = fusion_frame();
    small.image = None;
    small.points = Points::encode(&points_in(&small.persons[0].box_3d, 50));
    let body = format!("{}\n{}\n", String::from_utf8(big).unwrap(), serde_json::to_string(&small).unwrap());
    let r = s.post_ndjson(body).await;
    let lines: Vec<Value> = r.text().await.unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 2);
    assert_eq!(lines[0]["error"]["code"], "payload_too_large");
    assert!(lines[1]["response"].is_object(), "{}", lines[1]);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_answers_429_and_recovers() {
    let mut cfg = config();
    cfg.runtime.queue_size = 1;
    cfg.runtime.max_batch = 1;
    let s = start(cfg).await;
    let pause = s.predictor.runtime().pause();
    let frame = frame_json();
    let mut tasks = Vec::new();
    for _ in 0..6 {
        let (url, body) = (s.url("/v1/poses"), frame.clone());
        tasks.push(tokio::spawn(async move {
            let r = reqwest::Client::new().post(url).json(&body).send().await.unwrap();
            let status = r.status().as_u16();
            (status, r.headers().get("retry-after").is_some(), r.json::<Value>().await.unwrap())
        }));
        tokio::time::sleep(Duration::from_millis(30)).await;
    }
    // The worker holds one job and the queue one more: the others are refused at once.
    let mut refused = 0;
    let mut waiting = Vec::new();
    for t in tasks {
        if t.is_finished() {
            let (status, retry, body) = t.await.unwrap();
            assert_eq!((status, retry), (429, true), "{body}");
            assert_eq!(body["error"]["code"], "overloaded");
            refused += 1;
        } else {
            waiting.push(t);
        }
    }
    assert!(refused >= 4, "only {refused} refused");
    drop(pause);
    for t in waiting {
        if let Ok(Ok((status, _, body))) = tokio::time::timeout(Duration::from_secs(20), t).await {
            assert!(status == 200 || status == 429, "{status} {body}");
        }
    }
    let (status, _) = post_json(&s, &frame).await;
    assert_eq!(status, 200);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_past_its_deadline_gets_504() {
    let mut cfg = config();
    cfg.request_timeout = Duration::from_millis(150);
    let s = start(cfg).await;
    let pause = s.predictor.runtime().pause();
    let (status, body) = post_json(&s, &frame_json()).await;
    let (code, _) = error_of(status, &body, 504);
    assert_eq!(code, "timeout");
    drop(pause);
    let (status, _) = post_json(&s, &frame_json()).await;
    assert_eq!(status, 200);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_finishes_in_flight_requests() {
    let mut s = start(config()).await;
    let pause = s.predictor.runtime().pause();
    let (url, body) = (s.url("/v1/poses"), frame_json());
    let in_flight = tokio::spawn(async move { reqwest::Client::new().post(url).json(&body).send().await.unwrap() });
    tokio::time::sleep(Duration::from_millis(200)).await;
    s.signal_shutdown();
    tokio::time::sleep(Duration::from_millis(100)).await;
    // No longer accepting connections, and not finished while a request is in flight.
    assert!(reqwest::Client::new().get(s.url("/healthz")).send().await.is_err());
    let task = s.task.take().unwrap();
    assert!(!task.is_finished());
    drop(pause);
    let r = in_flight.await.unwrap();
    assert_eq!(r.status(), 200);
    let pose: posefuse::service::api::PoseResponse = r.json().await.unwrap();
    assert_eq!(pose.persons.len(), 1);
    tokio::time::timeout(Duration::from_secs(10), task).await.unwrap().unwrap().unwrap();
}
