//! The Open Inference Protocol (KServe v2) on the in-process server: REST with JSON tensors and
//! with the binary tensor extension, and `inference.GRPCInferenceService`, each answering with
//! the keypoints of `POST /v1/poses` for the same frame; health, metadata and errors.

mod server_support;

use base64::Engine;
use posefuse::frame::Frame;
use posefuse::keypoints::K;
use posefuse::server::kserve::grpc::proto::{
    self, grpc_inference_service_client::GrpcInferenceServiceClient, model_infer_request::InferInputTensor,
};
use posefuse::service::api::{Mode, PoseResponse};
use serde_json::{json, Value};
use server_support::*;

/// One tensor: name, datatype, shape and its elements as JSON values (`null` for NaN).
struct Tensor {
    name: &'static str,
    datatype: &'static str,
    shape: Vec<i64>,
    json: Vec<Value>,
    raw: Vec<u8>,
}

fn f32s(name: &'static str, shape: Vec<i64>, v: &[f32]) -> Tensor {
    Tensor {
        name,
        datatype: "FP32",
        shape,
        json: v.iter().map(|x| json!(x)).collect(),
        raw: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}

fn f64s(name: &'static str, shape: Vec<i64>, v: &[f64]) -> Tensor {
    Tensor {
        name,
        datatype: "FP64",
        shape,
        json: v.iter().map(|x| if x.is_nan() { Value::Null } else { json!(x) }).collect(),
        raw: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}

fn bytes(name: &'static str, items: Vec<Vec<u8>>, as_text: Vec<String>) -> Tensor {
    let raw = items.iter().flat_map(|b| (b.len() as u32).to_le_bytes().into_iter().chain(b.iter().copied())).collect();
    Tensor {
        name,
        datatype: "BYTES",
        shape: vec![items.len() as i64],
        json: as_text.into_iter().map(Value::from).collect(),
        raw,
    }
}

/// A frame as the contract's input tensors (image as PNG bytes; base64 text in JSON).
fn tensors(f: &Frame, png: &[u8]) -> Vec<Tensor> {
    let pts: Vec<f32> = f.points.decode().unwrap().into_iter().flatten().collect();
    let b3: Vec<f64> = f.persons.iter().flat_map(|p| p.box_3d.to_row()).collect();
    let b2: Vec<f64> = f
        .persons
        .iter()
        .flat_map(|p| p.box_2d.map_or([f64::NAN; 4], |b| [b.center_x, b.center_y, b.width, b.height]))
        .collect();
    let m = f.persons.len() as i64;
    let ids: Vec<String> = f.persons.iter().map(|p| p.id.clone()).collect();
    let c = f.calibration.as_ref().unwrap();
    vec![
        bytes("image", vec![png.to_vec()], vec![base64::engine::general_purpose::STANDARD.encode(png)]),
        f32s("points", vec![pts.len() as i64 / 3, 3], &pts),
        f64s("calibration_intrinsic", vec![9], &c.intrinsic),
        f64s("calibration_extrinsic", vec![4, 4], &c.extrinsic),
        Tensor {
            name: "image_size",
            datatype: "INT32",
            shape: vec![2],
            json: vec![json!(c.width), json!(c.height)],
            raw: [c.width as i32, c.height as i32].iter().flat_map(|v| v.to_le_bytes()).collect(),
        },
        f64s("boxes_3d", vec![m, 7], &b3),
        f64s("boxes_2d", vec![m, 4], &b2),
        bytes("person_ids", ids.iter().map(|s| s.as_bytes().to_vec()).collect(), ids.clone()),
    ]
}

/// The three-mode frame plus a fourth person with no LiDAR point in its box (skipped).
fn four_person_frame() -> (Frame, Vec<u8>) {
    let mut f = three_mode_frame();
    f.persons.push(person("empty", person_box(15.0, 4.0), false));
    let png = image_png(&[box_2d(&f.persons[0].box_3d), box_2d(&f.persons[2].box_3d)]);
    (f, png)
}

fn json_body(ts: &[Tensor]) -> Value {
    let inputs: Vec<Value> =
        ts.iter().map(|t| json!({"name": t.name, "datatype": t.datatype, "shape": t.shape, "data": t.json})).collect();
    json!({"id": "req-7", "inputs": inputs})
}

/// The JSON part and the binary part of a binary-extension request.
fn binary_body(ts: &[Tensor], extra: Value) -> (Vec<u8>, usize) {
    let inputs: Vec<Value> = ts
        .iter()
        .map(|t| {
            json!({"name": t.name, "datatype": t.datatype, "shape": t.shape,
                   "parameters": {"binary_data_size": t.raw.len()}})
        })
        .collect();
    let mut head = json!({"inputs": inputs});
    if let Value::Object(m) = extra {
        head.as_object_mut().unwrap().extend(m);
    }
    let mut body = serde_json::to_vec(&head).unwrap();
    let n = body.len();
    for t in ts {
        body.extend(&t.raw);
    }
    (body, n)
}

async fn v1_poses(s: &TestServer, f: &Frame) -> PoseResponse {
    let r = reqwest::Client::new().post(s.url("/v1/poses")).json(f).send().await.unwrap();
    assert_eq!(r.status(), 200);
    r.json().await.unwrap()
}

/// The decoded outputs of one answer.
#[derive(Debug, Default)]
struct Outputs {
    kp3: Vec<f32>,
    kp2: Vec<f32>,
    scores: Vec<f32>,
    mode: Vec<String>,
    status: Vec<String>,
    num_points: Vec<i32>,
}

fn floats_of(v: &Value) -> Vec<f32> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().map_or(f32::NAN, |x| x as f32)).collect()
}

/// The elements of a raw BYTES tensor (each behind a 4-byte little-endian length).
fn items_of_raw(raw: &[u8]) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut rest = raw;
    while !rest.is_empty() {
        let n = u32::from_le_bytes(rest[..4].try_into().unwrap()) as usize;
        out.push(rest[4..4 + n].to_vec());
        rest = &rest[4 + n..];
    }
    out
}

fn strings_of_raw(raw: &[u8]) -> Vec<String> {
    items_of_raw(raw).into_iter().map(|b| String::from_utf8(b).unwrap()).collect()
}

fn set_raw(out: &mut Outputs, name: &str, raw: &[u8]) {
    let f = || raw.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect::<Vec<_>>();
    match name {
        "keypoints_3d" => out.kp3 = f(),
        "keypoints_2d" => out.kp2 = f(),
        "scores" => out.scores = f(),
        "mode" => out.mode = strings_of_raw(raw),
        "status" => out.status = strings_of_raw(raw),
        "num_points" => {
            out.num_points = raw.chunks_exact(4).map(|c| i32::from_le_bytes(c.try_into().unwrap())).collect()
        }
        other => panic!("unexpected output {other}"),
    }
}

/// Checks the outputs against the native answer: request order, NaN where that answer has none.
fn assert_matches_v1(o: &Outputs, v1: &PoseResponse, m: usize) {
    assert_eq!(o.kp3.len(), m * K * 3);
    assert_eq!(o.kp2.len(), m * K * 2);
    assert_eq!(o.scores.len(), m * K);
    let mut poses = v1.persons.iter();
    for i in 0..m {
        if let Some(s) = v1.skipped.iter().find(|s| s.index == i) {
            assert_eq!((o.mode[i].as_str(), o.status[i].as_str()), ("none", s.error.code.as_str()));
            assert_eq!(o.num_points[i], -1);
            assert!(o.kp3[i * K * 3..(i + 1) * K * 3].iter().all(|v| v.is_nan()));
            assert!(o.scores[i * K..(i + 1) * K].iter().all(|v| v.is_nan()));
            continue;
        }
        let p = poses.next().unwrap();
        assert_eq!((o.mode[i].as_str(), o.status[i].as_str()), (p.mode.as_str(), "ok"));
        assert_eq!(o.num_points[i] as usize, p.num_points);
        for (k, kp) in p.keypoints.iter().enumerate() {
            for a in 0..3 {
                let got = o.kp3[(i * K + k) * 3 + a];
                assert!((f64::from(got) - kp.xyz[a]).abs() < 1e-5, "person {i} kp {k}: {got} vs {}", kp.xyz[a]);
            }
            for a in 0..2 {
                let got = o.kp2[(i * K + k) * 2 + a];
                match kp.uv {
                    Some(uv) => assert!((f64::from(got) - uv[a]).abs() < 1e-3, "{got} vs {}", uv[a]),
                    None => assert!(got.is_nan()),
                }
            }
            let got = o.scores[i * K + k];
            match kp.score {
                Some(s) => assert!((got - s).abs() < 1e-6),
                None => assert!(got.is_nan()),
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rest_json_rest_binary_and_grpc_answer_the_v1_keypoints() {
    let s = start(config()).await;
    let (frame, png) = four_person_frame();
    let m = frame.persons.len();
    let v1 = v1_poses(&s, &frame).await;
    let modes: Vec<Mode> = v1.persons.iter().map(|p| p.mode).collect();
    assert_eq!(modes, [Mode::Fusion, Mode::Lidar, Mode::Camera], "the frame exercises every mode");
    assert_eq!(v1.skipped.len(), 1);
    let ts = tensors(&frame, &png);
    let http = reqwest::Client::new();

    // REST, JSON tensors in and out (the image as base64 text, NaN 2D-box rows as null).
    let r = http.post(s.url("/v2/models/default/infer")).json(&json_body(&ts)).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert!(r.headers().get("inference-header-content-length").is_none());
    let body: Value = r.json().await.unwrap();
    assert_eq!((body["model_name"].as_str(), body["id"].as_str()), (Some("default"), Some("req-7")));
    assert_eq!(body["model_version"], json!(v1.model.version));
    let mut o = Outputs::default();
    for out in body["outputs"].as_array().unwrap() {
        let data = &out["data"];
        match out["name"].as_str().unwrap() {
            "keypoints_3d" => {
                assert_eq!(out["shape"], json!([m, K, 3]));
                assert_eq!(out["datatype"], "FP32");
                o.kp3 = floats_of(data);
            }
            "keypoints_2d" => o.kp2 = floats_of(data),
            "scores" => o.scores = floats_of(data),
            "mode" => o.mode = data.as_array().unwrap().iter().map(|v| v.as_str().unwrap().to_string()).collect(),
            "status" => o.status = data.as_array().unwrap().iter().map(|v| v.as_str().unwrap().to_string()).collect(),
            "num_points" => {
                o.num_points = data.as_array().unwrap().iter().map(|v| v.as_i64().unwrap() as i32).collect()
            }
            other => panic!("unexpected output {other}"),
        }
    }
    assert_matches_v1(&o, &v1, m);

    // REST, binary tensors in and out (all outputs binary by the request's default).
    let (body, n) = binary_body(&ts, json!({"parameters": {"binary_data_output": true}}));
    let r = http
        .post(s.url(&format!("/v2/models/default/versions/{}/infer", v1.model.version)))
        .header("Inference-Header-Content-Length", n)
        .header("content-type", "application/octet-stream")
        .body(body)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let head_len: usize = r.headers()["inference-header-content-length"].to_str().unwrap().parse().unwrap();
    let bytes = r.bytes().await.unwrap();
    let head: Value = serde_json::from_slice(&bytes[..head_len]).unwrap();
    let mut at = head_len;
    let mut o = Outputs::default();
    for out in head["outputs"].as_array().unwrap() {
        assert!(out.get("data").is_none());
        let size = out["parameters"]["binary_data_size"].as_u64().unwrap() as usize;
        set_raw(&mut o, out["name"].as_str().unwrap(), &bytes[at..at + size]);
        at += size;
    }
    assert_eq!(at, bytes.len());
    assert_matches_v1(&o, &v1, m);

    // Requested outputs: in the requested order, each in its own form.
    let (body, n) = binary_body(
        &ts,
        json!({"outputs": [{"name": "status", "parameters": {"binary_data": true}}, {"name": "mode"}]}),
    );
    let r = http
        .post(s.url("/v2/models/default/infer"))
        .header("Inference-Header-Content-Length", n)
        .body(body)
        .send()
        .await
        .unwrap();
    let head_len: usize = r.headers()["inference-header-content-length"].to_str().unwrap().parse().unwrap();
    let bytes = r.bytes().await.unwrap();
    let head: Value = serde_json::from_slice(&bytes[..head_len]).unwrap();
    let names: Vec<&str> = head["outputs"].as_array().unwrap().iter().map(|o| o["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["status", "mode"]);
    assert_eq!(strings_of_raw(&bytes[head_len..]), ["ok", "ok", "ok", "insufficient_data"]);
    assert_eq!(head["outputs"][1]["data"], json!(["fusion", "lidar", "camera", "none"]));

    // gRPC with raw_input_contents, and with typed contents: the same answer.
    let mut c = GrpcInferenceServiceClient::connect(s.url("")).await.unwrap();
    let inputs: Vec<InferInputTensor> = ts
        .iter()
        .map(|t| InferInputTensor {
            name: t.name.into(),
            datatype: t.datatype.into(),
            shape: t.shape.clone(),
            parameters: Default::default(),
            contents: None,
        })
        .collect();
    let req = proto::ModelInferRequest {
        model_name: "default".into(),
        id: "g-1".into(),
        inputs: inputs.clone(),
        raw_input_contents: ts.iter().map(|t| t.raw.clone()).collect(),
        ..Default::default()
    };
    let r = c.model_infer(req).await.unwrap().into_inner();
    assert_eq!((r.model_name.as_str(), r.id.as_str()), ("default", "g-1"));
    assert_eq!(r.raw_output_contents.len(), r.outputs.len());
    let mut o = Outputs::default();
    for (out, raw) in r.outputs.iter().zip(&r.raw_output_contents) {
        set_raw(&mut o, &out.name, raw);
    }
    assert_eq!(r.outputs[0].shape, vec![m as i64, K as i64, 3]);
    assert_matches_v1(&o, &v1, m);

    let typed: Vec<InferInputTensor> = inputs
        .into_iter()
        .zip(&ts)
        .map(|(mut i, t)| {
            let mut c = proto::InferTensorContents::default();
            match t.datatype {
                "FP32" => {
                    c.fp32_contents = t.raw.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect()
                }
                "FP64" => {
                    c.fp64_contents = t.raw.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().unwrap())).collect()
                }
                "INT32" => {
                    c.int_contents = t.raw.chunks_exact(4).map(|b| i32::from_le_bytes(b.try_into().unwrap())).collect()
                }
                _ => c.bytes_contents = items_of_raw(&t.raw),
            }
            i.contents = Some(c);
            i
        })
        .collect();
    let req = proto::ModelInferRequest {
        model_name: "default".into(),
        inputs: typed,
        outputs: vec![proto::model_infer_request::InferRequestedOutputTensor {
            name: "keypoints_3d".into(),
            parameters: Default::default(),
        }],
        ..Default::default()
    };
    let r = c.model_infer(req).await.unwrap().into_inner();
    assert_eq!(r.outputs.len(), 1);
    let mut typed_out = Outputs::default();
    set_raw(&mut typed_out, "keypoints_3d", &r.raw_output_contents[0]);
    let same = typed_out.kp3.iter().zip(&o.kp3).all(|(a, b)| (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-5);
    assert!(same, "typed contents answer as raw contents");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_metadata_name_the_model_and_every_tensor() {
    let s = start(config()).await;
    let http = reqwest::Client::new();
    let get = |path: &str| http.get(s.url(path)).send();
    let version = s.predictor.bundle().manifest.version.clone();
    assert_eq!(get("/v2/health/live").await.unwrap().status(), 200);
    assert_eq!(get("/v2/health/ready").await.unwrap().status(), 200);
    assert_eq!(get("/v2/models/default/ready").await.unwrap().status(), 200);
    assert_eq!(get(&format!("/v2/models/default/versions/{version}/ready")).await.unwrap().status(), 200);
    let server: Value = get("/v2").await.unwrap().json().await.unwrap();
    assert_eq!(server["name"], "posefuse");
    assert_eq!(server["extensions"], json!(["binary_tensor_data"]));
    let meta: Value = get("/v2/models/default").await.unwrap().json().await.unwrap();
    assert_eq!(meta["versions"], json!([version]));
    let inputs: Vec<(&str, &str)> = meta["inputs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| (t["name"].as_str().unwrap(), t["datatype"].as_str().unwrap()))
        .collect();
    assert_eq!(
        inputs,
        [
            ("image", "BYTES"),
            ("image_rgb", "UINT8"),
            ("points", "FP32"),
            ("calibration_intrinsic", "FP64"),
            ("calibration_extrinsic", "FP64"),
            ("image_size", "INT32"),
            ("boxes_3d", "FP64"),
            ("boxes_2d", "FP64"),
            ("person_ids", "BYTES"),
            ("mode", "BYTES"),
        ]
    );
    assert_eq!(meta["outputs"][0], json!({"name": "keypoints_3d", "datatype": "FP32", "shape": [-1, K, 3]}));
    assert_eq!(meta["outputs"].as_array().unwrap().len(), 6);
    let versioned: Value = get(&format!("/v2/models/default/versions/{version}")).await.unwrap().json().await.unwrap();
    assert_eq!(versioned, meta);
    for path in ["/v2/models/other", "/v2/models/other/ready", "/v2/models/default/versions/9.9.9"] {
        let r = get(path).await.unwrap();
        assert_eq!(r.status(), 404, "{path}");
        let body: Value = r.json().await.unwrap();
        assert!(body["error"].as_str().unwrap().contains("not found"), "{path}: {body}");
    }

    let mut c = GrpcInferenceServiceClient::connect(s.url("")).await.unwrap();
    assert!(c.server_live(proto::ServerLiveRequest {}).await.unwrap().into_inner().live);
    assert!(c.server_ready(proto::ServerReadyRequest {}).await.unwrap().into_inner().ready);
    let ready = c.model_ready(proto::ModelReadyRequest { name: "default".into(), version: String::new() }).await;
    assert!(ready.unwrap().into_inner().ready);
    let m = c
        .model_metadata(proto::ModelMetadataRequest { name: "default".into(), version: version.clone() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!((m.name.as_str(), m.versions.clone()), ("default", vec![version]));
    assert_eq!(m.inputs.len(), 10);
    assert_eq!((m.outputs[3].name.as_str(), m.outputs[3].datatype.as_str()), ("mode", "BYTES"));
    let e = c.model_metadata(proto::ModelMetadataRequest { name: "other".into(), version: String::new() }).await;
    assert_eq!(e.unwrap_err().code(), tonic::Code::NotFound);
    let sm = c.server_metadata(proto::ServerMetadataRequest {}).await.unwrap().into_inner();
    assert_eq!(sm.extensions, ["binary_tensor_data"]);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_tensors_are_400_or_invalid_argument_naming_the_tensor() {
    let mut cfg = config();
    cfg.body_limit = 1_000_000;
    let s = start(cfg).await;
    let (frame, png) = four_person_frame();
    let http = reqwest::Client::new();
    let post = |body: Value| http.post(s.url("/v2/models/default/infer")).json(&body).send();
    let error_of = |status: u16, body: &Value| -> String {
        let e = body["error"].as_str().unwrap_or_else(|| panic!("not the protocol's error shape: {body}"));
        format!("{status} {e}")
    };

    let mut cases: Vec<(Value, &str)> = Vec::new();
    let mut b = json_body(&tensors(&frame, &png));
    b["inputs"][1]["shape"] = json!([b["inputs"][1]["data"].as_array().unwrap().len() / 2, 2]);
    cases.push((b, "`points`"));
    let mut b = json_body(&tensors(&frame, &png));
    b["inputs"][5]["datatype"] = json!("INT64");
    b["inputs"][5]["data"] = json!(vec![1; 28]);
    cases.push((b, "`boxes_3d`"));
    let mut b = json_body(&tensors(&frame, &png));
    b["inputs"].as_array_mut().unwrap().remove(2);
    cases.push((b, "`calibration_intrinsic`"));
    let mut b = json_body(&tensors(&frame, &png));
    b["inputs"][3]["data"][0] = json!(2.0);
    cases.push((b, "`calibration_extrinsic`"));
    let mut b = json_body(&tensors(&frame, &png));
    b["inputs"][6]["data"][2] = json!(-5.0);
    cases.push((b, "`boxes_2d[0].width`"));
    let mut b = json_body(&tensors(&frame, &png));
    b["inputs"][0]["data"] = json!(["not base64!"]);
    cases.push((b, "`image`"));
    let mut b = json_body(&tensors(&frame, &png));
    b["outputs"] = json!([{"name": "heatmaps"}]);
    cases.push((b, "`heatmaps`"));
    let mut b = json_body(&tensors(&frame, &png));
    b["inputs"].as_array_mut().unwrap().push(json!({"name": "radar", "datatype": "FP32", "shape": [1], "data": [0]}));
    cases.push((b, "`radar`"));
    for (body, want) in cases {
        let r = post(body).await.unwrap();
        let status = r.status().as_u16();
        let e = error_of(status, &r.json().await.unwrap());
        assert!(e.starts_with("400 ") && e.contains(want), "{want}: {e}");
    }
    // Binary data that does not add up.
    let ts = tensors(&frame, &png);
    let (mut body, n) = binary_body(&ts, json!({}));
    body.truncate(body.len() - 2);
    let r = http
        .post(s.url("/v2/models/default/infer"))
        .header("Inference-Header-Content-Length", n)
        .body(body)
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    let e = error_of(status, &r.json().await.unwrap());
    assert!(e.starts_with("400 ") && e.contains("`person_ids`"), "{e}");
    // Unknown model: 404; a body over the limit: 413, both in the protocol's shape.
    let r = http.post(s.url("/v2/models/other/infer")).json(&json_body(&ts)).send().await.unwrap();
    assert_eq!(r.status(), 404);
    let r = http.post(s.url("/v2/models/default/infer")).body(vec![b' '; 1_200_000]).send().await.unwrap();
    let status = r.status().as_u16();
    assert!(error_of(status, &r.json().await.unwrap()).starts_with("413 "));

    // gRPC: INVALID_ARGUMENT naming the tensor; NOT_FOUND for another model.
    let mut c = GrpcInferenceServiceClient::connect(s.url("")).await.unwrap();
    let req = |model: &str, points_shape: Vec<i64>| proto::ModelInferRequest {
        model_name: model.into(),
        inputs: ts
            .iter()
            .map(|t| InferInputTensor {
                name: t.name.into(),
                datatype: t.datatype.into(),
                shape: if t.name == "points" { points_shape.clone() } else { t.shape.clone() },
                parameters: Default::default(),
                contents: None,
            })
            .collect(),
        raw_input_contents: ts.iter().map(|t| t.raw.clone()).collect(),
        ..Default::default()
    };
    let p = ts[1].shape[0];
    let e = c.model_infer(req("default", vec![p * 3])).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(e.message().contains("`points`"), "{}", e.message());
    let e = c.model_infer(req("default", vec![p, 4])).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    let e = c.model_infer(req("other", vec![p, 3])).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound);
    s.shutdown().await.unwrap();
}
