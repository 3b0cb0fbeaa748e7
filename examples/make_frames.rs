//! Shrinks `posefuse simulate` request fixtures into small example frames (run by
//! scripts/make-examples.sh): `cargo run --example make_frames -- IN_DIR OUT_DIR`.
//!
//! A fixture carries the full 1920×1280 camera image and the whole LiDAR sweep (~600 KB of JSON).
//! Each output frame keeps what the server looks at: the image is cropped to the region around the
//! persons' 2D boxes (the principal point, 2D boxes and 2D ground truth shift with the crop, so the
//! camera model is unchanged) and re-encoded, and only the points near the persons' 3D boxes stay.

use std::path::Path;

use anyhow::{anyhow, Context, Result};
use base64::Engine;
use serde_json::{json, Value};

/// Square context kept around each person's 2D box, as a multiple of its longer side.
const CONTEXT: f64 = 1.6;
/// Points kept within this distance (metres) of a person's 3D box.
const POINT_MARGIN: f64 = 0.5;
const JPEG_QUALITY: u8 = 85;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output] = args.as_slice() else {
        return Err(anyhow!("usage: make_frames IN_DIR OUT_DIR"));
    };
    std::fs::create_dir_all(output)?;
    let mut names: Vec<_> = std::fs::read_dir(input)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    names.sort();
    for path in names {
        let mut frame: Value = serde_json::from_slice(&std::fs::read(&path)?)?;
        shrink(&mut frame).with_context(|| path.display().to_string())?;
        let name = path.file_name().ok_or_else(|| anyhow!("no file name"))?;
        std::fs::write(Path::new(output).join(name), serde_json::to_vec(&frame)?)?;
    }
    Ok(())
}

fn num(v: &Value, key: &str) -> Result<f64> {
    v[key].as_f64().ok_or_else(|| anyhow!("`{key}` is not a number"))
}

fn shrink(frame: &mut Value) -> Result<()> {
    let b64 = base64::engine::general_purpose::STANDARD;
    let persons = frame["persons"].as_array().cloned().ok_or_else(|| anyhow!("no persons"))?;
    let (width, height) = (num(&frame["calibration"], "width")?, num(&frame["calibration"], "height")?);

    // The crop: the union of square windows around the persons' 2D boxes, inside the image.
    let (mut x0, mut y0, mut x1, mut y1) = (width, height, 0.0f64, 0.0f64);
    for p in &persons {
        let b = &p["box_2d"];
        let half = 0.5 * CONTEXT * num(b, "width")?.max(num(b, "height")?);
        x0 = x0.min(num(b, "center_x")? - half);
        y0 = y0.min(num(b, "center_y")? - half);
        x1 = x1.max(num(b, "center_x")? + half);
        y1 = y1.max(num(b, "center_y")? + half);
    }
    let (x0, y0) = (x0.max(0.0).floor(), y0.max(0.0).floor());
    let (x1, y1) = (x1.min(width).ceil(), y1.min(height).ceil());
    if x1 <= x0 || y1 <= y0 {
        return Err(anyhow!("the persons are outside the image"));
    }
    if let Some(image) = frame["image"].as_str() {
        let img = image::load_from_memory(&b64.decode(image)?)?.to_rgb8();
        let crop = image::imageops::crop_imm(&img, x0 as u32, y0 as u32, (x1 - x0) as u32, (y1 - y0) as u32).to_image();
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, JPEG_QUALITY).encode_image(&crop)?;
        frame["image"] = json!(b64.encode(jpeg));
    }
    let cal = &mut frame["calibration"];
    let (cu, cv) = (
        cal["intrinsic"][2].as_f64().ok_or_else(|| anyhow!("intrinsic"))?,
        cal["intrinsic"][3].as_f64().ok_or_else(|| anyhow!("intrinsic"))?,
    );
    cal["intrinsic"][2] = json!(cu - x0);
    cal["intrinsic"][3] = json!(cv - y0);
    cal["width"] = json!((x1 - x0) as u32);
    cal["height"] = json!((y1 - y0) as u32);

    // The points near a person's 3D box (in the box frame: heading removed).
    let raw = b64.decode(frame["points"]["b64"].as_str().ok_or_else(|| anyhow!("points are not base64"))?)?;
    let mut kept = Vec::new();
    for p in raw.chunks_exact(12) {
        let f = |i: usize| f32::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]) as f64;
        let (x, y, z) = (f(0), f(4), f(8));
        let near = persons.iter().any(|person| {
            let b = &person["box_3d"];
            let g = |k: &str| num(b, k).unwrap_or(f64::NAN);
            let (dx, dy, dz) = (x - g("center_x"), y - g("center_y"), z - g("center_z"));
            let (s, c) = g("heading").sin_cos();
            let (lx, ly) = (c * dx + s * dy, -s * dx + c * dy);
            lx.abs() <= 0.5 * g("length") + POINT_MARGIN
                && ly.abs() <= 0.5 * g("width") + POINT_MARGIN
                && dz.abs() <= 0.5 * g("height") + POINT_MARGIN
        });
        if near {
            kept.extend_from_slice(p);
        }
    }
    frame["points"] = json!({ "b64": b64.encode(kept) });

    // 2D boxes and 2D ground truth follow the crop.
    for p in frame["persons"].as_array_mut().into_iter().flatten() {
        let b = &mut p["box_2d"];
        b["center_x"] = json!(num(b, "center_x")? - x0);
        b["center_y"] = json!(num(b, "center_y")? - y0);
        if let Some(uv) = p["ground_truth"]["keypoints_2d"]["uv"].as_array_mut() {
            for k in uv {
                k[0] = json!(k[0].as_f64().unwrap_or(f64::NAN) - x0);
                k[1] = json!(k[1].as_f64().unwrap_or(f64::NAN) - y0);
            }
        }
    }
    Ok(())
}
