//! KServe's system shared-memory extension on the in-process server: off by default; once on,
//! raw RGB pixels and LiDAR points read from a registered POSIX shared-memory object, and
//! outputs written to one, give the keypoints of `POST /v1/poses` for the same frame, over REST
//! and gRPC; registration, status, unregistration and the bounds on what a region may name.

mod server_support;

use std::collections::HashMap;

use base64::Engine;
use posefuse::frame::Frame;
use posefuse::keypoints::K;
use posefuse::server::kserve::grpc::proto::{
    self, grpc_inference_service_client::GrpcInferenceServiceClient, infer_parameter::ParameterChoice,
};
use posefuse::server::kserve::shared_memory::SharedMemoryConfig;
use posefuse::service::api::PoseResponse;
use serde_json::{json, Value};
use server_support::*;

/// A POSIX shared-memory object (a file in /dev/shm), removed when dropped.
struct ShmObject {
    key: String,
    path: std::path::PathBuf,
}

impl ShmObject {
    fn new(tag: &str, bytes: &[u8]) -> ShmObject {
        let name = format!("posefuse-test-{}-{tag}", std::process::id());
        let path = std::path::Path::new("/dev/shm").join(&name);
        std::fs::write(&path, bytes).unwrap();
        ShmObject { key: format!("/{name}"), path }
    }

    fn read(&self) -> Vec<u8> {
        std::fs::read(&self.path).unwrap()
    }
}

impl Drop for ShmObject {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

fn shm_config(enabled: bool) -> posefuse::server::ServerConfig {
    let mut c = config();
    c.shared_memory = SharedMemoryConfig { enabled, max_regions: 4, ..Default::default() };
    c
}

/// The frame's image as RGB8 pixels and its points as little-endian FP32, one after the other.
fn pixels_and_points(f: &Frame) -> (Vec<u8>, Vec<u8>) {
    let png = base64::engine::general_purpose::STANDARD.decode(f.image.as_ref().unwrap()).unwrap();
    let rgb = image::load_from_memory(&png).unwrap().to_rgb8().into_raw();
    let pts: Vec<u8> = f.points.decode().unwrap().into_iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    (rgb, pts)
}

/// The frame's other inputs as JSON tensors.
fn json_inputs(f: &Frame) -> Vec<Value> {
    let c = f.calibration.as_ref().unwrap();
    let b3: Vec<f64> = f.persons.iter().flat_map(|p| p.box_3d.to_row()).collect();
    vec![
        json!({"name": "calibration_intrinsic", "datatype": "FP64", "shape": [9], "data": c.intrinsic}),
        json!({"name": "calibration_extrinsic", "datatype": "FP64", "shape": [16], "data": c.extrinsic}),
        json!({"name": "image_size", "datatype": "INT32", "shape": [2], "data": [c.width, c.height]}),
        json!({"name": "boxes_3d", "datatype": "FP64", "shape": [f.persons.len(), 7], "data": b3}),
    ]
}

fn shm_params(region: &str, byte_size: usize, offset: usize) -> Value {
    json!({"shared_memory_region": region, "shared_memory_byte_size": byte_size, "shared_memory_offset": offset})
}

async fn v1_poses(s: &TestServer, f: &Frame) -> PoseResponse {
    let r = reqwest::Client::new().post(s.url("/v1/poses")).json(f).send().await.unwrap();
    assert_eq!(r.status(), 200);
    r.json().await.unwrap()
}

fn f32s(raw: &[u8]) -> Vec<f32> {
    raw.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
}

/// `keypoints_3d` rows equal the native answer's keypoints, person by person.
fn assert_keypoints(kp3: &[f32], v1: &PoseResponse) {
    assert_eq!(kp3.len(), v1.persons.len() * K * 3);
    for (i, p) in v1.persons.iter().enumerate() {
        for (k, kp) in p.keypoints.iter().enumerate() {
            for a in 0..3 {
                let got = f64::from(kp3[(i * K + k) * 3 + a]);
                assert!((got - kp.xyz[a]).abs() < 1e-5, "person {i} keypoint {k}: {got} vs {}", kp.xyz[a]);
            }
        }
    }
}

async fn post(s: &TestServer, path: &str, body: Value) -> (u16, Value) {
    let r = reqwest::Client::new().post(s.url(path)).json(&body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

async fn get(s: &TestServer, path: &str) -> (u16, Value) {
    let r = reqwest::get(s.url(path)).await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn off_by_default_every_call_is_refused() {
    let s = start(shm_config(false)).await;
    let obj = ShmObject::new("off", &[0; 16]);
    let (code, body) =
        post(&s, "/v2/systemsharedmemory/region/r/register", json!({"key": obj.key, "byte_size": 16})).await;
    assert_eq!(code, 403);
    assert!(body["error"].as_str().unwrap().contains("--system-shared-memory"), "{body}");
    assert_eq!(get(&s, "/v2/systemsharedmemory/status").await.0, 403);
    let (_, meta) = get(&s, "/v2").await;
    assert_eq!(meta["extensions"], json!(["binary_tensor_data"]));
    let mut client = GrpcInferenceServiceClient::connect(s.url("")).await.unwrap();
    let e = client
        .system_shared_memory_register(proto::SystemSharedMemoryRegisterRequest {
            name: "r".into(),
            key: obj.key.clone(),
            offset: 0,
            byte_size: 16,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::PermissionDenied);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pixels_and_points_from_shared_memory_give_the_v1_keypoints_over_rest() {
    let s = start(shm_config(true)).await;
    let f = three_mode_frame();
    let v1 = v1_poses(&s, &f).await;
    let m = f.persons.len();
    let (rgb, pts) = pixels_and_points(&f);
    // One object holds both inputs, the points 64 bytes after the pixels; the outputs go to another.
    let mut input = rgb.clone();
    input.extend([0u8; 64]);
    input.extend(&pts);
    let inputs = ShmObject::new("in", &input);
    let outputs = ShmObject::new("out", &vec![0xAB; 4096]);
    for (name, obj, len) in [("in", &inputs, input.len()), ("out", &outputs, 4096)] {
        let (code, body) = post(
            &s,
            &format!("/v2/systemsharedmemory/region/{name}/register"),
            json!({"key": obj.key, "offset": 0, "byte_size": len}),
        )
        .await;
        assert_eq!(code, 200, "{body}");
    }
    let (_, meta) = get(&s, "/v2").await;
    assert_eq!(meta["extensions"], json!(["binary_tensor_data", "system_shared_memory"]));
    let (code, status) = get(&s, "/v2/systemsharedmemory/region/in/status").await;
    assert_eq!(code, 200);
    assert_eq!(status, json!([{"name": "in", "key": inputs.key, "offset": 0, "byte_size": input.len()}]));

    let c = f.calibration.as_ref().unwrap();
    let mut request_inputs = json_inputs(&f);
    request_inputs.push(json!({"name": "image_rgb", "datatype": "UINT8", "shape": [c.height, c.width, 3],
                               "parameters": shm_params("in", rgb.len(), 0)}));
    request_inputs.push(json!({"name": "points", "datatype": "FP32", "shape": [pts.len() / 12, 3],
                               "parameters": shm_params("in", pts.len(), rgb.len() + 64)}));
    let kp_bytes = m * K * 3 * 4;
    let body = json!({"id": "shm-1", "inputs": request_inputs, "outputs": [
        {"name": "keypoints_3d", "parameters": shm_params("out", 4096 - 100, 100)},
        {"name": "mode"}]});
    let (code, answer) = post(&s, "/v2/models/default/infer", body.clone()).await;
    assert_eq!(code, 200, "{answer}");
    let kp = &answer["outputs"][0];
    assert_eq!(kp["shape"], json!([m, K, 3]));
    assert_eq!(kp.get("data"), None);
    assert_eq!(kp["parameters"], shm_params("out", kp_bytes, 100));
    let written = outputs.read();
    assert_eq!(&written[..100], &[0xAB; 100][..], "nothing before the offset is touched");
    assert_keypoints(&f32s(&written[100..100 + kp_bytes]), &v1);
    let modes: Vec<&str> =
        answer["outputs"][1]["data"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
    assert_eq!(modes, v1.persons.iter().map(|p| p.mode.as_str()).collect::<Vec<_>>());

    // An output region too small for the output: 400 naming it, after inference ran.
    let mut small = body.clone();
    small["outputs"][0]["parameters"] = shm_params("out", kp_bytes - 4, 0);
    let (code, e) = post(&s, "/v2/models/default/infer", small).await;
    assert_eq!(code, 400);
    assert!(e["error"].as_str().unwrap().contains("keypoints_3d"), "{e}");
    // A span past the region: 400 naming the input; an unknown region likewise.
    let mut past = body.clone();
    past["inputs"][5]["parameters"] = shm_params("in", pts.len(), input.len() - 4);
    let (code, e) = post(&s, "/v2/models/default/infer", past).await;
    assert_eq!((code, e["error"].as_str().unwrap().contains("points")), (400, true), "{e}");

    // Unregistered: later requests naming it are refused; re-registering the name works again.
    assert_eq!(post(&s, "/v2/systemsharedmemory/region/in/unregister", Value::Null).await.0, 200);
    let (code, e) = post(&s, "/v2/models/default/infer", body.clone()).await;
    assert_eq!(code, 400);
    assert!(e["error"].as_str().unwrap().contains("not registered"), "{e}");
    assert_eq!(get(&s, "/v2/systemsharedmemory/region/in/status").await.0, 404);
    let (_, all) = get(&s, "/v2/systemsharedmemory/status").await;
    assert_eq!(all.as_array().unwrap().len(), 1);
    assert_eq!(post(&s, "/v2/systemsharedmemory/unregister", Value::Null).await.0, 200);
    assert_eq!(get(&s, "/v2/systemsharedmemory/status").await.1, json!([]));

    // Pixels alone in shared memory, points inline: the same keypoints. Pixels whose shape
    // disagrees with image_size, or an object shrunk under its region, are 400 naming image_rgb.
    let pixels_only = ShmObject::new("px", &rgb);
    let register = json!({"key": pixels_only.key, "byte_size": rgb.len()});
    assert_eq!(post(&s, "/v2/systemsharedmemory/region/px/register", register).await.0, 200);
    let pts_f32: Vec<f32> = f.points.decode().unwrap().into_iter().flatten().collect();
    let mut inputs = json_inputs(&f);
    inputs.push(json!({"name": "points", "datatype": "FP32", "shape": [pts_f32.len() / 3, 3], "data": pts_f32}));
    let image = |shape: Value| {
        json!({"name": "image_rgb", "datatype": "UINT8", "shape": shape,
                                      "parameters": shm_params("px", rgb.len(), 0)})
    };
    let with_image = |shape: Value| {
        let mut all = inputs.clone();
        all.push(image(shape));
        json!({"inputs": all, "outputs": [{"name": "keypoints_3d"}]})
    };
    let (code, answer) = post(&s, "/v2/models/default/infer", with_image(json!([c.height, c.width, 3]))).await;
    assert_eq!(code, 200, "{answer}");
    let kp: Vec<f32> =
        answer["outputs"][0]["data"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
    assert_keypoints(&kp, &v1);
    let (code, e) = post(&s, "/v2/models/default/infer", with_image(json!([c.width, c.height, 3]))).await;
    assert_eq!(code, 400);
    assert!(e["error"].as_str().unwrap().contains("`image_rgb`"), "{e}");
    std::fs::File::options().write(true).open(&pixels_only.path).unwrap().set_len(rgb.len() as u64 / 4).unwrap();
    let (code, e) = post(&s, "/v2/models/default/infer", with_image(json!([c.height, c.width, 3]))).await;
    assert_eq!(code, 400);
    assert!(
        e["error"].as_str().unwrap().contains("`image_rgb`") && e["error"].as_str().unwrap().contains("shrank"),
        "{e}"
    );
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registration_is_confined_and_bounded() {
    let mut config = shm_config(true);
    config.body_limit = 2048;
    let s = start(config).await;
    let obj = ShmObject::new("bounds", &[0; 4096]);
    let register = |name: &str, key: &str, byte_size: usize| {
        let (name, body) = (name.to_string(), json!({"key": key, "byte_size": byte_size}));
        let s = &s;
        async move { post(s, &format!("/v2/systemsharedmemory/region/{name}/register"), body).await }
    };
    for key in ["/../etc/passwd", "/etc/passwd", "/posefuse-test-missing", ""] {
        let (code, e) = register("r", key, 16).await;
        assert_eq!(code, 400, "{key}: {e}");
    }
    assert_eq!(register("r", &obj.key, 4097).await.0, 400, "past the object's end");
    assert_eq!(register("r", &obj.key, 4096).await.0, 200);
    assert_eq!(register("r", &obj.key, 16).await.0, 400, "a name is registered once");
    for name in ["a", "b", "c"] {
        assert_eq!(register(name, &obj.key, 16).await.0, 200);
    }
    assert_eq!(register("d", &obj.key, 16).await.0, 400, "at most max_regions");

    // What a request reads from shared memory counts against the body limit, before it is read.
    let f = three_mode_frame();
    let mut inputs = json_inputs(&f);
    inputs
        .push(json!({"name": "points", "datatype": "FP32", "shape": [341, 3], "parameters": shm_params("r", 4092, 0)}));
    let (code, e) = post(&s, "/v2/models/default/infer", json!({"inputs": inputs})).await;
    assert_eq!(code, 413, "{e}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_reads_and_writes_shared_memory_as_rest_does() {
    let s = start(shm_config(true)).await;
    let f = three_mode_frame();
    let v1 = v1_poses(&s, &f).await;
    let (rgb, pts) = pixels_and_points(&f);
    let mut input = rgb.clone();
    input.extend(&pts);
    let inputs = ShmObject::new("grpc-in", &input);
    let outputs = ShmObject::new("grpc-out", &[0; 1024]);
    let mut client = GrpcInferenceServiceClient::connect(s.url("")).await.unwrap();
    for (name, obj, len) in [("in", &inputs, input.len() as u64), ("out", &outputs, 1024)] {
        client
            .system_shared_memory_register(proto::SystemSharedMemoryRegisterRequest {
                name: name.into(),
                key: obj.key.clone(),
                offset: 0,
                byte_size: len,
            })
            .await
            .unwrap();
    }
    let status = client
        .system_shared_memory_status(proto::SystemSharedMemoryStatusRequest { name: String::new() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(status.regions.len(), 2);
    assert_eq!(status.regions["out"].byte_size, 1024);

    let p = |c: ParameterChoice| proto::InferParameter { parameter_choice: Some(c) };
    let shm = |region: &str, size: usize, offset: usize| {
        HashMap::from([
            ("shared_memory_region".to_string(), p(ParameterChoice::StringParam(region.into()))),
            ("shared_memory_byte_size".to_string(), p(ParameterChoice::Int64Param(size as i64))),
            ("shared_memory_offset".to_string(), p(ParameterChoice::Int64Param(offset as i64))),
        ])
    };
    let tensor =
        |name: &str, datatype: &str, shape: Vec<i64>, parameters| proto::model_infer_request::InferInputTensor {
            name: name.into(),
            datatype: datatype.into(),
            shape,
            parameters,
            contents: None,
        };
    let c = f.calibration.as_ref().unwrap();
    let m = f.persons.len();
    let b3: Vec<u8> = f.persons.iter().flat_map(|p| p.box_3d.to_row()).flat_map(f64::to_le_bytes).collect();
    let le = |v: &[f64]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let request = proto::ModelInferRequest {
        model_name: "default".into(),
        inputs: vec![
            tensor("image_rgb", "UINT8", vec![c.height as i64, c.width as i64, 3], shm("in", rgb.len(), 0)),
            tensor("points", "FP32", vec![pts.len() as i64 / 12, 3], shm("in", pts.len(), rgb.len())),
            tensor("calibration_intrinsic", "FP64", vec![9], HashMap::new()),
            tensor("calibration_extrinsic", "FP64", vec![16], HashMap::new()),
            tensor("image_size", "INT32", vec![2], HashMap::new()),
            tensor("boxes_3d", "FP64", vec![m as i64, 7], HashMap::new()),
        ],
        outputs: vec![proto::model_infer_request::InferRequestedOutputTensor {
            name: "keypoints_3d".into(),
            parameters: shm("out", 1024, 0),
        }],
        // The inputs not in shared memory only, in order.
        raw_input_contents: vec![
            le(&c.intrinsic),
            le(&c.extrinsic),
            [c.width as i32, c.height as i32].iter().flat_map(|v| v.to_le_bytes()).collect(),
            b3,
        ],
        ..Default::default()
    };
    let answer = client.model_infer(request).await.unwrap().into_inner();
    assert_eq!(answer.raw_output_contents, vec![Vec::<u8>::new()]);
    let size = &answer.outputs[0].parameters["shared_memory_byte_size"];
    assert_eq!(size.parameter_choice, Some(ParameterChoice::Int64Param((m * K * 3 * 4) as i64)));
    assert_keypoints(&f32s(&outputs.read()[..m * K * 3 * 4]), &v1);

    client
        .system_shared_memory_unregister(proto::SystemSharedMemoryUnregisterRequest { name: String::new() })
        .await
        .unwrap();
    let e = client
        .system_shared_memory_status(proto::SystemSharedMemoryStatusRequest { name: "in".into() })
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound);
    s.shutdown().await.unwrap();
}
