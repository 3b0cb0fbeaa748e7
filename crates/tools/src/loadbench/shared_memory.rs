//! The bench's `rgb-shm` form: each fixture's RGB8 pixels and LiDAR points written once into a
//! POSIX shared-memory object of its own and registered with the server (KServe's system
//! shared-memory extension, docs/KSERVE.md), as a camera driver on the same host leaves its
//! frames; each request is the Open Inference Protocol's JSON naming those regions. The server
//! must run with `--system-shared-memory` (the bench passes it to the server it starts).

use std::path::PathBuf;

use posefuse_core::frame::Frame;
use posefuse_data::bail;
use posefuse_data::error::{Context, Result};
use serde_json::{json, Value};

/// Where shared-memory objects live on Linux.
const SHM_DIR: &str = "/dev/shm";

/// The fixtures' objects, unlinked when dropped (a registered region stays readable by the
/// server until it exits or unregisters it).
#[derive(Debug, Default)]
pub struct Objects {
    /// Per object: the region name and the shm key.
    regions: Vec<(String, String)>,
    paths: Vec<PathBuf>,
}

impl Drop for Objects {
    fn drop(&mut self) {
        for p in &self.paths {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// Writes frame `index`'s pixels (`[H, W, 3]` RGB8) and points (`[N, 3]` little-endian FP32) into
/// a new object, and returns the inference request body naming them.
pub fn write_frame(objects: &mut Objects, model: &str, index: usize, f: &Frame, pixels: &[u8]) -> Result<Vec<u8>> {
    let pts: Vec<u8> = f.points.decode()?.into_iter().flatten().flat_map(f32::to_le_bytes).collect();
    let name = format!("posefuse-bench-{}-{index}", std::process::id());
    let path = PathBuf::from(SHM_DIR).join(&name);
    let mut bytes = Vec::with_capacity(pixels.len() + pts.len());
    bytes.extend_from_slice(pixels);
    bytes.extend_from_slice(&pts);
    std::fs::write(&path, &bytes).with_context(|| format!("writing {}", path.display()))?;
    objects.paths.push(path);
    let region = name.clone();
    objects.regions.push((region.clone(), format!("/{name}")));
    let body = request(model, &region, f, pixels.len(), pts.len())?;
    Ok(serde_json::to_vec(&body)?)
}

/// Registers every object as its region (`POST /v2/systemsharedmemory/region/NAME/register`).
pub async fn register(url: &str, objects: &Objects) -> Result<()> {
    let client = reqwest::Client::new();
    for ((region, key), path) in objects.regions.iter().zip(&objects.paths) {
        let byte_size = std::fs::metadata(path)?.len();
        let r = client
            .post(format!("{url}/v2/systemsharedmemory/region/{region}/register"))
            .json(&json!({"key": key, "offset": 0, "byte_size": byte_size}))
            .send()
            .await
            .with_context(|| format!("registering {region} with {url}"))?;
        if !r.status().is_success() {
            let status = r.status();
            let text = r.text().await.unwrap_or_default();
            bail!("registering shared memory region {region}: {status} {text} (is the server's --system-shared-memory on?)");
        }
    }
    Ok(())
}

/// Unregisters the objects' regions, so that a server that keeps running (`--url`) has room for
/// the next bench.
pub async fn unregister(url: &str, objects: &Objects) -> Result<()> {
    let client = reqwest::Client::new();
    for (region, _) in &objects.regions {
        client
            .post(format!("{url}/v2/systemsharedmemory/region/{region}/unregister"))
            .send()
            .await
            .with_context(|| format!("unregistering {region} from {url}"))?;
    }
    Ok(())
}

/// The Open Inference Protocol request: pixels and points in the frame's region, the rest JSON.
fn request(model: &str, region: &str, f: &Frame, pixel_bytes: usize, point_bytes: usize) -> Result<Value> {
    let Some(c) = f.calibration.as_ref() else { bail!("a fixture without a calibration") };
    let m = f.persons.len();
    let b3: Vec<f64> = f.persons.iter().flat_map(|p| p.box_3d.to_row()).collect();
    // JSON has no NaN: a null row is "no 2D box".
    let b2: Vec<Option<f64>> = f
        .persons
        .iter()
        .flat_map(|p| match p.box_2d {
            Some(b) => [Some(b.center_x), Some(b.center_y), Some(b.width), Some(b.height)],
            None => [None; 4],
        })
        .collect();
    let ids: Vec<&str> = f.persons.iter().map(|p| p.id.as_str()).collect();
    let shm = |size: usize, offset: usize| json!({"shared_memory_region": region, "shared_memory_byte_size": size, "shared_memory_offset": offset});
    Ok(json!({
        "id": f.frame_id,
        "model_name": model,
        "inputs": [
            {"name": "image_rgb", "datatype": "UINT8", "shape": [c.height, c.width, 3], "parameters": shm(pixel_bytes, 0)},
            {"name": "points", "datatype": "FP32", "shape": [point_bytes / 12, 3], "parameters": shm(point_bytes, pixel_bytes)},
            {"name": "calibration_intrinsic", "datatype": "FP64", "shape": [c.intrinsic.len()], "data": c.intrinsic},
            {"name": "calibration_extrinsic", "datatype": "FP64", "shape": [c.extrinsic.len()], "data": c.extrinsic},
            {"name": "image_size", "datatype": "INT32", "shape": [2], "data": [c.width, c.height]},
            {"name": "boxes_3d", "datatype": "FP64", "shape": [m, 7], "data": b3},
            {"name": "boxes_2d", "datatype": "FP64", "shape": [m, 4], "data": b2},
            {"name": "person_ids", "datatype": "BYTES", "shape": [m], "data": ids},
        ],
    }))
}
