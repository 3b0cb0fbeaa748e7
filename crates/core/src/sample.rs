//! The training-sample schema and its shard writer: the seam through which the simulator and the
//! Waymo converter write what the trainer reads (docs/DATA.md). Also the JPEG round trip both use,
//! cut the way the server cuts a request's crops.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::RgbImage;
use ndarray::{ArrayD, IxDyn};
use ndarray_npy::{NpzWriter, WritableElement};

use crate::error::{Error, Result};
use crate::image_decode;
use crate::keypoints::K;
use crate::pipeline::{input_seed, select_indices, CropTransform, PipelineConfig, PreparedPerson};

/// Samples per shard.
pub const SHARD_SIZE: usize = 1024;
/// JPEG quality of request images.
pub const JPEG_QUALITY: u8 = 92;

/// One prepared pedestrian, laid out as the shard arrays (docs/DATA.md).
#[derive(Debug, Clone)]
pub struct Sample {
    pub image: Vec<u8>,
    pub points_xyz: Vec<[f32; 3]>,
    pub points_uv: Vec<[f32; 2]>,
    pub serve_xyz: Vec<[f32; 3]>,
    pub serve_uv: Vec<[f32; 2]>,
    pub kp2d: [[f32; 2]; K],
    /// Labelled and not occluded: the training target.
    pub kp2d_visible: [u8; K],
    /// Labelled but occluded: scored, not trained on.
    pub kp2d_occluded: [u8; K],
    pub kp2d_image_true: [[f32; 2]; K],
    pub kp3d: [[f32; 3]; K],
    pub kp3d_vehicle: [[f32; 3]; K],
    pub kp3d_visible: [u8; K],
    /// Labelled but occluded; every labelled keypoint (visible or occluded) counts in the metrics.
    pub kp3d_occluded: [u8; K],
    pub box3d: [f32; 7],
    pub box2d: [f32; 4],
    pub crop: [f32; 3],
    pub intrinsic: [f32; 9],
    pub extrinsic: [f32; 16],
    pub image_size_wh: [i32; 2],
    pub sensor_xyz: [f32; 3],
    /// Yaw (vehicle frame, radians) of the model-input frame's x axis: where the box frame turns
    /// local coordinates back into the vehicle frame (docs/DATA.md).
    pub frame_yaw: f32,
    pub range_m: f32,
    pub frame_index: i32,
}

/// JPEG-encodes an image at the fixture quality.
pub fn encode_jpeg(img: &RgbImage) -> Result<Vec<u8>> {
    let mut buf = Cursor::new(Vec::new());
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut buf, JPEG_QUALITY)
        .encode_image(img)
        .map_err(|e| Error::Io(format!("jpeg encode: {e}")))?;
    Ok(buf.into_inner())
}

/// Decodes a JPEG the way the server does.
pub fn decode_jpeg(bytes: &[u8]) -> Result<RgbImage> {
    image::load_from_memory_with_format(bytes, image::ImageFormat::Jpeg)
        .map(|i| i.to_rgb8())
        .map_err(|e| Error::Io(format!("jpeg decode: {e}")))
}

/// The crops of `windows` from a JPEG, cut the way the server cuts a request's crops
/// (`image_decode::decode_crops`: each at its own DCT scale).
pub fn planned_crops(jpeg: &[u8], windows: &[CropTransform], width: u32, height: u32) -> Result<Vec<RgbImage>> {
    image_decode::decode_crops(&image_decode::CameraImage::Jpeg(jpeg.to_vec()), windows, width, height, || Ok(()))?
        .map_err(|e| Error::Io(format!("jpeg decode: {e}")))
}

/// A sample's point fields: at most `points_cap` in-box points (box frame, model pixels), chosen
/// as the server chooses, and the exact serving input (zeros when the box holds no point).
pub struct SamplePoints {
    pub points_xyz: Vec<[f32; 3]>,
    pub points_uv: Vec<[f32; 2]>,
    pub serve_xyz: Vec<[f32; 3]>,
    pub serve_uv: Vec<[f32; 2]>,
}

/// The point fields of a prepared person; `points_uv` are its in-box points in model pixels.
pub fn sample_points(
    prepared: &PreparedPerson,
    points_uv: &[[f32; 2]],
    cfg: &PipelineConfig,
    points_cap: usize,
) -> SamplePoints {
    let pts = &prepared.points;
    let keep: Vec<usize> = if pts.len() > points_cap {
        select_indices(pts.len(), points_cap, input_seed(&pts.vehicle))
    } else {
        (0..pts.len()).collect()
    };
    let n = cfg.num_points as usize;
    let (serve_xyz, serve_uv) = match &prepared.input {
        Some(inp) => (inp.xyz.clone(), inp.uv.clone()),
        None => (vec![[0.0; 3]; n], vec![[0.0; 2]; n]),
    };
    SamplePoints {
        points_xyz: keep.iter().map(|&i| pts.local[i]).collect(),
        points_uv: keep.iter().map(|&i| points_uv[i]).collect(),
        serve_xyz,
        serve_uv,
    }
}

/// Writes samples into `shard-NNNNN.npz` files of `SHARD_SIZE`.
pub struct ShardWriter {
    dir: PathBuf,
    image_size: usize,
    points_cap: usize,
    num_points: usize,
    buf: Vec<Sample>,
    /// (file name, samples) of every shard written.
    pub written: Vec<(String, usize)>,
}

fn add<T: WritableElement>(
    npz: &mut NpzWriter<std::fs::File>,
    name: &str,
    shape: &[usize],
    data: Vec<T>,
) -> Result<()> {
    let a = ArrayD::from_shape_vec(IxDyn(shape), data).map_err(|e| Error::Io(format!("shard array {name}: {e}")))?;
    npz.add_array(name, &a).map_err(|e| Error::Io(format!("shard array {name}: {e}")))
}

impl ShardWriter {
    pub fn new(dir: &Path, cfg: &PipelineConfig, points_cap: usize) -> ShardWriter {
        ShardWriter {
            dir: dir.to_path_buf(),
            image_size: cfg.image_size as usize,
            points_cap,
            num_points: cfg.num_points as usize,
            buf: Vec::with_capacity(SHARD_SIZE),
            written: Vec::new(),
        }
    }

    pub fn push(&mut self, s: Sample) -> Result<()> {
        self.buf.push(s);
        if self.buf.len() == SHARD_SIZE {
            self.flush()?;
        }
        Ok(())
    }

    /// Writes the buffered samples (if any) as the next shard.
    pub fn flush(&mut self) -> Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let name = format!("shard-{:05}.npz", self.written.len());
        let file = std::fs::File::create(self.dir.join(&name))?;
        let mut npz = NpzWriter::new(file);
        let b = std::mem::take(&mut self.buf);
        let (m, s, cap, n) = (b.len(), self.image_size, self.points_cap, self.num_points);
        add(&mut npz, "image", &[m, s, s, 3], b.iter().flat_map(|x| x.image.iter().copied()).collect())?;
        let pad3 = |v: &[[f32; 3]]| {
            let mut out: Vec<f32> = v.iter().flatten().copied().collect();
            out.resize(cap * 3, 0.0);
            out
        };
        let pad2 = |v: &[[f32; 2]]| {
            let mut out: Vec<f32> = v.iter().flatten().copied().collect();
            out.resize(cap * 2, 0.0);
            out
        };
        add(&mut npz, "points_xyz", &[m, cap, 3], b.iter().flat_map(|x| pad3(&x.points_xyz)).collect())?;
        add(&mut npz, "points_uv", &[m, cap, 2], b.iter().flat_map(|x| pad2(&x.points_uv)).collect())?;
        add(&mut npz, "points_count", &[m], b.iter().map(|x| x.points_xyz.len() as i32).collect())?;
        add(&mut npz, "serve_xyz", &[m, n, 3], b.iter().flat_map(|x| x.serve_xyz.iter().flatten().copied()).collect())?;
        add(&mut npz, "serve_uv", &[m, n, 2], b.iter().flat_map(|x| x.serve_uv.iter().flatten().copied()).collect())?;
        add(&mut npz, "kp2d", &[m, K, 2], b.iter().flat_map(|x| x.kp2d.iter().flatten().copied()).collect())?;
        add(&mut npz, "kp2d_visible", &[m, K], b.iter().flat_map(|x| x.kp2d_visible).collect())?;
        add(&mut npz, "kp2d_occluded", &[m, K], b.iter().flat_map(|x| x.kp2d_occluded).collect())?;
        add(
            &mut npz,
            "kp2d_image_true",
            &[m, K, 2],
            b.iter().flat_map(|x| x.kp2d_image_true.iter().flatten().copied()).collect(),
        )?;
        add(&mut npz, "kp3d", &[m, K, 3], b.iter().flat_map(|x| x.kp3d.iter().flatten().copied()).collect())?;
        add(
            &mut npz,
            "kp3d_vehicle",
            &[m, K, 3],
            b.iter().flat_map(|x| x.kp3d_vehicle.iter().flatten().copied()).collect(),
        )?;
        add(&mut npz, "kp3d_visible", &[m, K], b.iter().flat_map(|x| x.kp3d_visible).collect())?;
        add(&mut npz, "kp3d_occluded", &[m, K], b.iter().flat_map(|x| x.kp3d_occluded).collect())?;
        add(&mut npz, "box3d", &[m, 7], b.iter().flat_map(|x| x.box3d).collect())?;
        add(&mut npz, "box2d", &[m, 4], b.iter().flat_map(|x| x.box2d).collect())?;
        add(&mut npz, "crop", &[m, 3], b.iter().flat_map(|x| x.crop).collect())?;
        add(&mut npz, "intrinsic", &[m, 9], b.iter().flat_map(|x| x.intrinsic).collect())?;
        add(&mut npz, "extrinsic", &[m, 16], b.iter().flat_map(|x| x.extrinsic).collect())?;
        add(&mut npz, "image_size_wh", &[m, 2], b.iter().flat_map(|x| x.image_size_wh).collect())?;
        add(&mut npz, "sensor_xyz", &[m, 3], b.iter().flat_map(|x| x.sensor_xyz).collect())?;
        add(&mut npz, "frame_yaw", &[m], b.iter().map(|x| x.frame_yaw).collect())?;
        add(&mut npz, "range_m", &[m], b.iter().map(|x| x.range_m).collect())?;
        add(&mut npz, "frame_index", &[m], b.iter().map(|x| x.frame_index).collect())?;
        npz.finish().map_err(|e| Error::Io(format!("shard {name}: {e}")))?;
        self.written.push((name, m));
        Ok(())
    }
}
