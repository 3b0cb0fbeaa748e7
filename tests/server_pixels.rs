//! Raw RGB8 pixels in (`image_rgb` in JSON, `image_rgb` bytes in gRPC) against a real in-process
//! server: the same answer as the lossless PNG of the same pixels, and size errors named.

mod server_support;

use base64::Engine;
use posefuse::frame::RgbPixels;
use posefuse::server::grpc::frame_to_proto;
use posefuse::server::grpc::proto;
use posefuse::server::grpc::proto::posefuse_client::PosefuseClient;
use serde_json::{json, Value};
use server_support::*;

async fn post_json(s: &TestServer, body: &Value) -> (u16, Value) {
    let r = reqwest::Client::new().post(s.url("/v1/poses")).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// The fusion frame's PNG, decoded: width, height, RGB8 bytes.
fn pixels_of_fusion_frame() -> (u32, u32, Vec<u8>) {
    let f = fusion_frame();
    let png = base64::engine::general_purpose::STANDARD.decode(f.image.unwrap()).unwrap();
    let img = image::load_from_memory(&png).unwrap().into_rgb8();
    (img.width(), img.height(), img.into_raw())
}

fn with_pixels(width: u32, height: u32, bytes: &[u8]) -> Value {
    let mut v = serde_json::to_value(fusion_frame()).unwrap();
    v.as_object_mut().unwrap().remove("image");
    v["image_rgb"] =
        json!({"width": width, "height": height, "b64": base64::engine::general_purpose::STANDARD.encode(bytes)});
    v
}

fn xyz(body: &Value) -> Vec<f64> {
    body["persons"][0]["keypoints"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|k| k["xyz"].as_array().unwrap().clone())
        .map(|x| x.as_f64().unwrap())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn raw_pixels_answer_like_the_png_of_the_same_pixels() {
    let s = start(config()).await;
    let (status, png_answer) = post_json(&s, &serde_json::to_value(fusion_frame()).unwrap()).await;
    assert_eq!(status, 200, "{png_answer}");
    let (w, h, bytes) = pixels_of_fusion_frame();
    let (status, raw_answer) = post_json(&s, &with_pixels(w, h, &bytes)).await;
    assert_eq!(status, 200, "{raw_answer}");
    assert_eq!(raw_answer["persons"][0]["mode"], "fusion", "{raw_answer}");
    assert_eq!(xyz(&raw_answer), xyz(&png_answer));

    // gRPC: the bytes themselves
    let mut f = fusion_frame();
    f.image = None;
    f.image_rgb = Some(RgbPixels { width: w, height: h, pixels: bytes.clone() });
    let request = frame_to_proto(&f, Vec::new()).unwrap();
    let mut c = PosefuseClient::connect(s.url("")).await.unwrap();
    let r = c.predict(request.clone()).await.unwrap().into_inner();
    assert_eq!(r.persons[0].mode, proto::Mode::Fusion as i32);
    let grpc_xyz: Vec<f64> = r.persons[0].keypoints.iter().flat_map(|k| [k.x, k.y, k.z]).collect();
    // equal up to the last digit JSON's decimal form keeps
    assert!(grpc_xyz.iter().zip(xyz(&png_answer)).all(|(a, b)| (a - b).abs() < 1e-12), "{grpc_xyz:?}");
    // a byte short
    let short = proto::PredictRequest { image_rgb: bytes[1..].to_vec(), ..request };
    let e = c.predict(short).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e:?}");
    assert!(e.message().contains("image_rgb.b64"), "{}", e.message());
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn raw_pixel_size_errors_name_their_field() {
    let s = start(config()).await;
    let (w, h, bytes) = pixels_of_fusion_frame();
    let field = |body: &Value| body["error"]["field"].as_str().unwrap_or("").to_string();
    // fewer bytes than width·height·3
    let (status, body) = post_json(&s, &with_pixels(w, h, &bytes[..bytes.len() - 3])).await;
    assert_eq!((status, field(&body).as_str()), (422, "image_rgb.b64"), "{body}");
    // a size that is not the calibration's (with a matching byte count)
    let (status, body) = post_json(&s, &with_pixels(w - 1, h, &bytes[..((w - 1) * h * 3) as usize])).await;
    assert_eq!((status, field(&body).as_str()), (422, "image_rgb.width/height"), "{body}");
    // not base64
    let mut v = with_pixels(w, h, &bytes);
    v["image_rgb"]["b64"] = json!("*** not base64 ***");
    let (status, body) = post_json(&s, &v).await;
    assert_eq!((status, field(&body).as_str()), (422, "image_rgb.b64"), "{body}");
    // both an encoded image and pixels
    let mut v = with_pixels(w, h, &bytes);
    v["image"] = serde_json::to_value(fusion_frame()).unwrap()["image"].clone();
    let (status, body) = post_json(&s, &v).await;
    assert_eq!((status, field(&body).as_str()), (422, "image_rgb"), "{body}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jpeg_frame_answers_like_its_pixels() {
    // A JPEG of the fusion frame's pixels: the decoded JPEG and the raw pixels
    // give crops that differ by the codec's loss only, so the keypoints stay close.
    let s = start(config()).await;
    let (w, h, bytes) = pixels_of_fusion_frame();
    let img = image::RgbImage::from_raw(w, h, bytes.clone()).unwrap();
    let jpeg = posefuse::sample::encode_jpeg(&img).unwrap();
    let mut v = serde_json::to_value(fusion_frame()).unwrap();
    v["image"] = json!(base64::engine::general_purpose::STANDARD.encode(&jpeg));
    let (status, jpeg_answer) = post_json(&s, &v).await;
    assert_eq!(status, 200, "{jpeg_answer}");
    assert_eq!(jpeg_answer["persons"][0]["mode"], "fusion");
    let (_, raw_answer) = post_json(&s, &with_pixels(w, h, &bytes)).await;
    let worst = xyz(&jpeg_answer).iter().zip(xyz(&raw_answer)).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(worst < 0.05, "keypoints moved {worst} m between the JPEG and its pixels");
    s.shutdown().await.unwrap();
}

#[test]
fn the_openapi_document_describes_raw_pixels() {
    let doc = serde_json::to_value(posefuse::server::http::openapi_doc()).unwrap();
    let schemas = &doc["components"]["schemas"];
    assert!(schemas["Frame"]["properties"]["image_rgb"].is_object(), "{}", schemas["Frame"]);
    let rgb = &schemas["RgbPixels"]["properties"];
    for key in ["width", "height", "b64"] {
        assert!(rgb[key].is_object(), "RgbPixels.{key} missing: {rgb}");
    }
    assert_eq!(rgb["b64"]["type"], "string");
}
