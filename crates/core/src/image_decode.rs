//! The frame's camera image, decoded only as far as its crops need.
//!
//! [`open`] reads the header only and refuses an image whose size disagrees with the calibration
//! before any pixel is decoded; a JPEG that does not end with its end-of-image marker (cut
//! short, or followed by other bytes) is undecodable there, in every decode mode. [`decode_crops`]
//! then cuts each crop window from the image decoded at that window's own DCT scale
//! (`pipeline::plan_passes`): one libjpeg-turbo pass ([`turbo`]) per scale the frame's windows
//! need (½, ¼ or ⅛: a reduced inverse transform per 8×8 block, or 1/1), each over the union of
//! its windows' regions (rows above it skipped, columns outside it not transformed); the last
//! pass reads the file to its end, so corrupt data anywhere is an error whatever the region.
//! The region never changes a crop's pixels, so a person's crop is the same alone, in a crowd and
//! under `POSEFUSE_DECODE=full` (read once: every pass decodes the whole image). The simulator
//! cuts its training crops and fixtures through the same function. PNG and raw RGB8 pixels are
//! used at full resolution.

mod turbo;
pub use turbo::simd as jpeg_simd;

use std::io::Cursor;
use std::sync::{Arc, OnceLock};

use base64::Engine;
use image::{ImageBuffer, Rgb, RgbImage};

use crate::error::{Error, Result};
use crate::frame::{CameraCalibration, Frame, RgbPixels};
use crate::pipeline::{crop_rgb, pixel_region, plan_passes, scaled, CropTransform, DecodePlan, PixelRect};

/// The camera image of a request, before its pixels are decoded.
pub enum CameraImage {
    /// No image in the request.
    Absent,
    /// An image the camera models cannot use, and why.
    Undecodable(String),
    /// JPEG file bytes whose header matches the calibration.
    Jpeg(Vec<u8>),
    /// PNG file bytes whose header matches the calibration.
    Png(Vec<u8>),
    /// Decoded RGB8 pixels sent by the caller, size checked.
    Pixels(RgbImage),
    /// Decoded RGB8 pixels read on demand, size checked: only the rows the crops need are read.
    Rows(Arc<dyn PixelSource>),
}

impl CameraImage {
    /// Whether the camera models can run on this image (its header, at least, is sound).
    pub fn usable(&self) -> bool {
        matches!(self, CameraImage::Jpeg(_) | CameraImage::Png(_) | CameraImage::Pixels(_) | CameraImage::Rows(_))
    }
}

/// Decoded RGB8 pixels that the caller reads on demand, the rectangle the crops need at a time:
/// KServe's shared memory, where reading the 7 MB of a 1920×1280 frame (and faulting in the pages
/// to hold it) costs more than the rest of the request, while its crops need a part of it.
pub trait PixelSource: Send + Sync {
    /// Width and height in pixels.
    fn size(&self) -> (u32, u32);
    /// The pixels of `r` (inside the image) into `out` (`r.area() · 3` bytes, caller's: a buffer
    /// kept from crop to crop is not faulted in anew), row by row, or why they cannot be read.
    fn read_rect_into(&self, r: PixelRect, out: &mut [u8]) -> std::result::Result<(), String>;
}

/// One camera's image sent beside the frame rather than in it.
#[derive(Clone)]
pub enum RawImage {
    /// JPEG or PNG file bytes (gRPC, KServe); empty: no image.
    Encoded(Vec<u8>),
    /// Decoded pixels read on demand.
    Rows(Arc<dyn PixelSource>),
}

impl std::fmt::Debug for RawImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RawImage::Encoded(b) => write!(f, "Encoded({} bytes)", b.len()),
            RawImage::Rows(r) => write!(f, "Rows({:?})", r.size()),
        }
    }
}

/// An image decoded at `1/denominator` of its full resolution, whole or a part of it.
pub struct DecodedImage {
    pub image: RgbImage,
    pub denominator: u32,
    /// Where `image` starts in the image scaled by `1/denominator`: `(0, 0)` for a whole decode.
    pub origin: (u32, u32),
}

impl DecodedImage {
    /// A whole image at full resolution.
    pub fn whole(image: RgbImage) -> DecodedImage {
        DecodedImage { image, denominator: 1, origin: (0, 0) }
    }

    /// The S×S crop of full-resolution window `t` (see `pipeline::scaled`). A part holds every
    /// pixel the plan's windows read, so a crop from it equals one from the whole scaled image.
    pub fn crop(&self, t: &CropTransform) -> RgbImage {
        let mut s = scaled(t, self.denominator);
        s.x0 -= self.origin.0 as f64;
        s.y0 -= self.origin.1 as f64;
        crop_rgb(&self.image, &s)
    }
}

/// Whether JPEG passes decode their planned region (the default) rather than the whole image at
/// the same scale (`POSEFUSE_DECODE=full`).
pub fn planned_decode_enabled() -> bool {
    static PLANNED: OnceLock<bool> = OnceLock::new();
    *PLANNED.get_or_init(|| planned_unless_full(std::env::var("POSEFUSE_DECODE").ok().as_deref()))
}

/// The value of `POSEFUSE_DECODE` read as "decode as planned": any value but `full`.
fn planned_unless_full(value: Option<&str>) -> bool {
    !value.is_some_and(|v| v.eq_ignore_ascii_case("full"))
}

/// Images that travel beside the frame (gRPC, KServe) rather than as base64 in it, in camera
/// order: the single camera's, or each of the frame's `cameras`'. An empty encoded entry is no
/// image.
#[derive(Debug, Clone, Default)]
pub struct RawImages(pub Vec<RawImage>);

/// One camera's image as the request carries it, before its header is read.
#[derive(Debug, Default)]
pub struct ImageInput<'a> {
    /// File bytes sent beside the frame; when given they replace `base64` (empty: no image).
    pub raw: Option<Vec<u8>>,
    /// Base64 of the file, from the JSON frame.
    pub base64: Option<&'a str>,
    /// Decoded pixels (moved out of the frame, so that they are not copied).
    pub pixels: Option<RgbPixels>,
    /// Decoded pixels read on demand, sent beside the frame.
    pub rows: Option<Arc<dyn PixelSource>>,
}

impl std::fmt::Debug for dyn PixelSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PixelSource({:?})", self.size())
    }
}

/// The single-camera frame's image, header read and checked: `raw_image` (file bytes, as gRPC
/// sends them) replaces `frame.image` (base64) when given; `pixels` (taken out of
/// `frame.image_rgb`, so that they are not copied) are raw pixels.
pub fn open(frame: &Frame, raw_image: Option<Vec<u8>>, pixels: Option<RgbPixels>) -> Result<CameraImage> {
    let c = frame.calibration.as_ref().ok_or_else(|| Error::field("calibration", "required"))?;
    let input = ImageInput {
        raw: raw_image,
        base64: frame.image.as_deref(),
        pixels: pixels.or_else(|| frame.image_rgb.clone()),
        rows: None,
    };
    open_camera(input, c)
}

/// One camera's image, header read and checked against its calibration `c`. Errors name the
/// single-camera fields (`image`, `image_rgb`); a multi-camera caller names them within its
/// camera (`Error::within`).
pub fn open_camera(input: ImageInput<'_>, c: &CameraCalibration) -> Result<CameraImage> {
    let ImageInput { raw, base64, pixels, rows } = input;
    let encoded_given = raw.as_ref().is_some_and(|b| !b.is_empty()) || base64.is_some();
    if let Some(rows) = rows {
        if encoded_given || pixels.is_some() {
            return Err(Error::field("image_rgb", "send the image once: file bytes, pixels, or shared memory"));
        }
        let (w, h) = rows.size();
        if (w, h) != (c.width, c.height) {
            return Err(Error::field(
                "image_rgb.width/height",
                format!("{w}x{h} but calibration.width/height say {}x{}", c.width, c.height),
            ));
        }
        return Ok(CameraImage::Rows(rows));
    }
    if let Some(px) = pixels {
        if encoded_given {
            return Err(Error::field("image_rgb", "send either an encoded image or image_rgb pixels, not both"));
        }
        return px.into_image(c.width, c.height).map(CameraImage::Pixels);
    }
    let bytes = match raw {
        Some(b) if b.is_empty() => return Ok(CameraImage::Absent),
        Some(b) => b,
        None => match base64 {
            None => return Ok(CameraImage::Absent),
            Some(text) => match base64::engine::general_purpose::STANDARD.decode(text.as_bytes()) {
                Ok(b) => b,
                Err(e) => return Ok(CameraImage::Undecodable(format!("image is not valid base64: {e}"))),
            },
        },
    };
    let (size, image) = if bytes.starts_with(&[0xFF, 0xD8]) {
        match jpeg_size(&bytes) {
            Ok(size) => (size, CameraImage::Jpeg(bytes)),
            Err(e) => return Ok(CameraImage::Undecodable(format!("image is not a decodable JPEG: {e}"))),
        }
    } else if bytes.starts_with(b"\x89PNG") {
        match png_size(&bytes) {
            Ok(size) => (size, CameraImage::Png(bytes)),
            Err(e) => return Ok(CameraImage::Undecodable(format!("image is not a decodable PNG: {e}"))),
        }
    } else {
        return Ok(CameraImage::Undecodable("image is not a decodable JPEG or PNG: unknown file signature".into()));
    };
    if size != (c.width, c.height) {
        return Err(Error::field(
            "image",
            format!(
                "image header says {}x{} but calibration.width/height say {}x{}: not decoded",
                size.0, size.1, c.width, c.height
            ),
        ));
    }
    Ok(image)
}

/// The end-of-image marker every complete JPEG ends with.
const JPEG_EOI: [u8; 2] = [0xFF, 0xD9];

fn jpeg_size(bytes: &[u8]) -> std::result::Result<(u32, u32), String> {
    // A region decode never reads the rows below its crops: a file cut short (or with bytes
    // after its end) is refused here, before any pixel, whatever the decode mode.
    if !bytes.ends_with(&JPEG_EOI) {
        return Err("the file does not end with the end-of-image marker (cut short, or other bytes follow it)".into());
    }
    let mut d = jpeg_decoder::Decoder::new(bytes);
    guard(|| d.read_info().map_err(|e| e.to_string()))?;
    let info = d.info().ok_or("no frame header")?;
    Ok((info.width as u32, info.height as u32))
}

fn png_size(bytes: &[u8]) -> std::result::Result<(u32, u32), String> {
    image::ImageReader::with_format(Cursor::new(bytes), image::ImageFormat::Png)
        .into_dimensions()
        .map_err(|e| e.to_string())
}

/// Runs a third-party decoder step, turning a panic on hostile input into an error.
fn guard<T>(f: impl FnOnce() -> std::result::Result<T, String>) -> std::result::Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|_| Err("decoder failed".into()))
}

/// `plan`, or under `POSEFUSE_DECODE=full` the whole image at its scale.
fn mode_plan(plan: &DecodePlan, bytes: &[u8]) -> std::result::Result<DecodePlan, String> {
    if planned_decode_enabled() {
        return Ok(*plan);
    }
    let (w, h) = jpeg_size(bytes).map_err(|e| format!("image is not a decodable JPEG: {e}"))?;
    Ok(plan.whole_image(w, h))
}

/// The crop of each window, each cut from `image` decoded at the window's own DCT scale (see the
/// module docs): the same crop whatever the other windows are, so crops may be cut again later
/// from the same image, some at a time. The passes run side by side (`side_by_side`), so their
/// decoded images are held together; `still_wanted` is asked before the passes and before each
/// crop (a frame may cut hundreds, none cheap).
pub fn decode_crops(
    image: &CameraImage,
    windows: &[CropTransform],
    width: u32,
    height: u32,
    mut still_wanted: impl FnMut() -> Result<()>,
) -> Result<std::result::Result<Vec<RgbImage>, String>> {
    let black = |t: &CropTransform| RgbImage::new(t.size, t.size);
    let bytes = match image {
        CameraImage::Jpeg(bytes) => bytes,
        CameraImage::Pixels(image) => {
            let crops = windows.iter().map(|t| still_wanted().map(|()| crop_rgb(image, &scaled(t, 1))));
            return crops.collect::<Result<_>>().map(Ok);
        }
        CameraImage::Rows(rows) => {
            let crop = |t: &CropTransform| {
                still_wanted()?;
                crop_from_rows(rows.as_ref(), t, width, height).map_err(|e| Error::field("image_rgb", e))
            };
            return windows.iter().map(crop).collect::<Result<_>>().map(Ok);
        }
        CameraImage::Png(bytes) => {
            still_wanted()?;
            let img = match decode_with_image_crate(bytes, image::ImageFormat::Png) {
                Ok(img) => img,
                Err(e) => return Ok(Err(e)),
            };
            return windows.iter().map(|t| still_wanted().map(|()| img.crop(t))).collect::<Result<_>>().map(Ok);
        }
        CameraImage::Absent => return Ok(Err("no image in the request".into())),
        CameraImage::Undecodable(why) => return Ok(Err(why.clone())),
    };
    let mut crops: Vec<Option<RgbImage>> = vec![None; windows.len()];
    let passes = plan_passes(windows, width, height);
    // the pass reaching lowest reads on to the end: the fewest rows read only to check them
    let last = (0..passes.len()).max_by_key(|&i| passes[i].plan.region.map_or(0, |r| r.y1)).unwrap_or(0);
    still_wanted()?;
    let decode = |i: usize| mode_plan(&passes[i].plan, bytes).and_then(|plan| decode_planned(bytes, &plan, i == last));
    for (pass, img) in passes.iter().zip(side_by_side(passes.len(), &decode)) {
        let img = match img {
            Ok(img) => img,
            Err(e) => return Ok(Err(e)),
        };
        for &w in &pass.windows {
            still_wanted()?;
            crops[w] = Some(img.crop(&windows[w]));
        }
    }
    Ok(Ok(crops.into_iter().zip(windows).map(|(c, t)| c.unwrap_or_else(|| black(t))).collect()))
}

/// `work(0)` … `work(n − 1)`, in order, the first on this thread and each other on a thread of
/// its own (inline when none can be started). A frame's decode passes are independent decodes of
/// the same bytes, so a frame of mixed scales takes its longest pass rather than their sum; there
/// are at most `CROP_DENOMINATORS.len()` of them, so a frame starts at most two threads.
fn side_by_side<T: Send>(
    n: usize,
    work: &(impl Fn(usize) -> std::result::Result<T, String> + Sync),
) -> Vec<std::result::Result<T, String>> {
    std::thread::scope(|s| {
        let others: Vec<_> = (1..n)
            .map(|i| {
                std::thread::Builder::new()
                    .name("posefuse-decode".into())
                    .spawn_scoped(s, move || work(i))
                    .map_err(|_| i)
            })
            .collect();
        let first = (n > 0).then(|| work(0));
        let joined = others.into_iter().map(|h| match h {
            Ok(h) => h.join().unwrap_or_else(|_| Err("decoder failed".into())),
            Err(i) => work(i),
        });
        first.into_iter().chain(joined).collect()
    })
}

/// Scratch buffers kept for windows' pixels up to this size (a near person's window is about
/// 1.5 MB); a larger window reads into a buffer of its own, so that no idle thread holds more.
const KEPT_SCRATCH_BYTES: usize = 4 << 20;

thread_local! {
    // One per thread rather than one per crop: allocating and faulting in a fresh buffer cost
    // as much as reading the pixels into it.
    static SCRATCH: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// The crop of window `t` from pixels read on demand: only the window's own rectangle
/// (`pipeline::pixel_region`) is read, so the crop equals one cut from the whole image, whatever
/// the other windows are. A window that misses the image reads nothing and is black.
fn crop_from_rows(
    source: &dyn PixelSource,
    t: &CropTransform,
    width: u32,
    height: u32,
) -> std::result::Result<RgbImage, String> {
    let Some(r) = pixel_region(std::slice::from_ref(t), width, height) else {
        return Ok(RgbImage::new(t.size, t.size));
    };
    let len = usize::try_from(r.area() * 3).map_err(|_| "the window is too large")?;
    let crop = |buf: &mut Vec<u8>| {
        // never shrunk: zeroing what is about to be overwritten costs as much as the read
        if buf.len() < len {
            buf.resize(len, 0);
        }
        let buf = &mut buf[..len];
        source.read_rect_into(r, buf)?;
        let view = ImageBuffer::<Rgb<u8>, &[u8]>::from_raw(r.x1 - r.x0, r.y1 - r.y0, &*buf)
            .ok_or("the pixels read have the wrong size")?;
        let mut s = *t;
        s.x0 -= r.x0 as f64;
        s.y0 -= r.y0 as f64;
        Ok(crop_rgb(&view, &s))
    };
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut kept) if len <= KEPT_SCRATCH_BYTES => crop(&mut kept),
        _ => crop(&mut Vec::new()),
    })
}

fn decode_with_image_crate(bytes: &[u8], format: image::ImageFormat) -> std::result::Result<DecodedImage, String> {
    let image = image::load_from_memory_with_format(bytes, format)
        .map_err(|e| format!("image is not a decodable JPEG or PNG: {e}"))?
        .into_rgb8();
    Ok(DecodedImage::whole(image))
}

/// A JPEG decoded as `plan` says with libjpeg-turbo: at its DCT scale, only its region, and read
/// on to the end of the file when `to_end` (corrupt data below the region is then an error too).
/// A plan without a region (no crop reads the image) decodes nothing and gives an empty image:
/// every crop of it is black, as it would be from the whole image.
pub fn decode_planned(bytes: &[u8], plan: &DecodePlan, to_end: bool) -> std::result::Result<DecodedImage, String> {
    let d = plan.denominator.clamp(1, 8);
    let Some(r) = plan.region else {
        return Ok(DecodedImage { image: RgbImage::new(0, 0), denominator: d, origin: (0, 0) });
    };
    match turbo::decode_region(bytes, d, (r.x0, r.y0, r.x1, r.y1), to_end) {
        Ok(part) => {
            let image = RgbImage::from_raw(part.width, part.height, part.pixels)
                .ok_or("decoded JPEG has the wrong number of pixels")?;
            Ok(DecodedImage { image, denominator: d, origin: (part.x0, part.y0) })
        }
        // CMYK and other colour spaces the region decoder leaves alone: the general decoder, whole
        Err(turbo::RegionError::Unsupported) => decode_with_image_crate(bytes, image::ImageFormat::Jpeg),
        Err(turbo::RegionError::Invalid(why)) => Err(format!("image is not a decodable JPEG: {why}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{plan_decode, DCT_DENOMINATORS};

    /// A smooth test pattern with some detail, JPEG-encoded at quality 92 (4:2:0, like the
    /// simulator's fixtures).
    fn pattern(w: u32, h: u32) -> (RgbImage, Vec<u8>) {
        let img = RgbImage::from_fn(w, h, |x, y| {
            let (fx, fy) = (x as f64 / w as f64, y as f64 / h as f64);
            let r = 128.0 + 100.0 * (fx * 9.0).sin() * (fy * 5.0).cos();
            let g = 128.0 + 90.0 * ((fx + fy) * 7.0).cos();
            let b = if (x / 40 + y / 40) % 2 == 0 { 200.0 } else { 60.0 };
            image::Rgb([r as u8, g as u8, b as u8])
        });
        let jpeg = crate::sample::encode_jpeg(&img).unwrap();
        (img, jpeg)
    }

    fn whole_plan(d: u32, w: u32, h: u32) -> DecodePlan {
        DecodePlan { denominator: d, ..DecodePlan::full(w, h) }
    }

    #[test]
    fn scaled_decodes_have_the_planned_size_and_full_matches_the_image_crate() {
        let (_, jpeg) = pattern(333, 250);
        for d in DCT_DENOMINATORS {
            let out = decode_planned(&jpeg, &whole_plan(d, 333, 250), false).unwrap();
            assert_eq!((out.denominator, out.origin), (d, (0, 0)));
            assert_eq!(out.image.dimensions(), (333u32.div_ceil(d), 250u32.div_ceil(d)));
        }
        // two conforming decoders of the same file differ by rounding only
        let ours = decode_planned(&jpeg, &whole_plan(1, 333, 250), true).unwrap().image;
        let reference = decode_with_image_crate(&jpeg, image::ImageFormat::Jpeg).unwrap().image;
        let worst = ours.as_raw().iter().zip(reference.as_raw()).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(worst <= 8, "full decodes differ by {worst}");
    }

    #[test]
    fn a_crop_from_a_scaled_decode_matches_the_full_decode_crop() {
        let (_, jpeg) = pattern(960, 640);
        let full = decode_with_image_crate(&jpeg, image::ImageFormat::Jpeg).unwrap();
        let t = CropTransform { x0: 301.7, y0: 122.4, scale: 64.0 / 410.0, size: 64 };
        let plan = plan_decode(&[t], 960, 640);
        assert_eq!(plan.denominator, 2);
        let reference = full.crop(&t);
        for d in [2, 4] {
            let crop = decode_planned(&jpeg, &whole_plan(d, 960, 640), false).unwrap().crop(&t);
            let diffs: Vec<u32> =
                crop.as_raw().iter().zip(reference.as_raw()).map(|(a, b)| a.abs_diff(*b) as u32).collect();
            let mean = diffs.iter().sum::<u32>() as f64 / diffs.len() as f64;
            // a reduced IDCT keeps the block's low frequencies rather than averaging its pixels:
            // close to the box filter's result, not equal (sharp 140-level edges in this pattern)
            assert!(mean < 3.0, "1/{d}: mean difference {mean}");
        }
    }

    #[test]
    fn a_jpeg_is_decoded_as_planned_by_default() {
        let (_, jpeg) = pattern(960, 640);
        let t = CropTransform { x0: 301.7, y0: 122.4, scale: 64.0 / 410.0, size: 64 };
        let plan = plan_decode(&[t], 960, 640);
        let out = decode_planned(&jpeg, &plan, true).unwrap();
        assert_eq!(out.denominator, plan.denominator);
        assert!(out.origin != (0, 0) && out.image.width() < 960 / plan.denominator, "{:?}", out.origin);
        let whole = decode_planned(&jpeg, &DecodePlan::full(960, 640), true).unwrap();
        assert_eq!((whole.denominator, whole.origin, whole.image.dimensions()), (1, (0, 0), (960, 640)));
        // `POSEFUSE_DECODE=full` (any case) asks for the whole decode; anything else, or nothing, plans
        assert!(!planned_unless_full(Some("full")) && !planned_unless_full(Some("FULL")));
        assert!(planned_unless_full(None) && planned_unless_full(Some("planned")));
    }

    /// Crop windows of several sizes (so several DCT scales) spread over a 960×640 image.
    fn crowd() -> Vec<CropTransform> {
        [(301.7, 22.4, 610.0), (20.5, 300.2, 150.0), (611.3, 97.8, 260.0), (700.0, 420.0, 90.0), (-30.0, 500.0, 140.0)]
            .into_iter()
            .map(|(x0, y0, side)| CropTransform { x0, y0, scale: 64.0 / side, size: 64 })
            .collect()
    }

    #[test]
    fn a_crop_is_the_same_alone_in_a_crowd_and_from_the_whole_image() {
        let (_, jpeg) = pattern(960, 640);
        let windows = crowd();
        let ok = || Ok(());
        let together = decode_crops(&CameraImage::Jpeg(jpeg.clone()), &windows, 960, 640, ok).unwrap().unwrap();
        assert_eq!(together.len(), windows.len());
        for (i, t) in windows.iter().enumerate() {
            let alone = decode_crops(&CameraImage::Jpeg(jpeg.clone()), &[*t], 960, 640, ok).unwrap().unwrap();
            assert!(alone[0] == together[i], "window {i} differs alone and in the crowd");
            // what `POSEFUSE_DECODE=full` decodes: the whole image at the window's own scale
            let d = crate::pipeline::window_denominator(t);
            let whole = decode_planned(&jpeg, &whole_plan(d, 960, 640), true).unwrap();
            assert!(whole.crop(t) == together[i], "window {i} differs from the whole image's crop");
        }
        // the crowd really mixes scales (otherwise this shows nothing)
        let scales: std::collections::BTreeSet<u32> = windows.iter().map(crate::pipeline::window_denominator).collect();
        assert!(scales.len() >= 3, "{scales:?}");
    }

    #[test]
    fn crops_of_pixels_and_pngs_come_from_the_whole_image_and_cancellation_stops_every_crop() {
        let (img, jpeg) = pattern(960, 640);
        let windows = crowd();
        let from_pixels =
            decode_crops(&CameraImage::Pixels(img.clone()), &windows, 960, 640, || Ok(())).unwrap().unwrap();
        for (t, c) in windows.iter().zip(&from_pixels) {
            assert!(*c == DecodedImage::whole(img.clone()).crop(t));
        }
        let mut png = Vec::new();
        img.write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png).unwrap();
        // every form asks before each crop (and before each decode), and stops at the first
        // "no" however many windows are left
        for image in [CameraImage::Pixels(img.clone()), CameraImage::Png(png), CameraImage::Jpeg(jpeg)] {
            let mut asked = 0;
            decode_crops(&image, &windows, 960, 640, || {
                asked += 1;
                Ok(())
            })
            .unwrap()
            .unwrap();
            assert!(asked >= windows.len(), "{asked} asks for {} crops", windows.len());
            let mut asked = 0;
            let gone = decode_crops(&image, &windows, 960, 640, || {
                asked += 1;
                if asked > 2 {
                    Err(Error::Unavailable("gone".into()))
                } else {
                    Ok(())
                }
            });
            assert!(matches!(gone, Err(Error::Unavailable(_))), "crops cut once nobody waits");
            assert_eq!(asked, 3);
        }
        let none = decode_crops(&CameraImage::Absent, &windows, 960, 640, || Ok(())).unwrap();
        assert_eq!(none.unwrap_err(), "no image in the request");
    }

    #[test]
    fn the_planned_region_gives_the_crops_of_the_whole_scaled_image() {
        let (_, jpeg) = pattern(960, 640);
        // two persons, one at the image's left edge, one inside; a third window off the image
        let windows = [
            CropTransform { x0: -20.5, y0: 300.2, scale: 64.0 / 150.0, size: 64 },
            CropTransform { x0: 611.3, y0: 97.8, scale: 64.0 / 260.0, size: 64 },
            CropTransform { x0: 2000.0, y0: 100.0, scale: 64.0 / 200.0, size: 64 },
        ];
        let plan = plan_decode(&windows, 960, 640);
        let region = plan.region.unwrap();
        assert!(region.area() < 960 * 640 * 3 / 5, "the plan reads {region:?}");
        let part = decode_planned(&jpeg, &plan, false).unwrap();
        assert!(part.origin != (0, 0) || part.image.width() < 960u32.div_ceil(plan.denominator));
        let whole = decode_planned(&jpeg, &whole_plan(plan.denominator, 960, 640), true).unwrap();
        for t in &windows {
            assert_eq!(part.crop(t), whole.crop(t), "window {t:?}");
        }
        // no window on the image: nothing decoded, black crops
        let none = plan_decode(&windows[2..], 960, 640);
        assert_eq!(decode_planned(&jpeg, &none, true).unwrap().crop(&windows[2]), RgbImage::new(64, 64));
    }

    fn frame_with(image: Option<String>, w: u32, h: u32) -> Frame {
        let mut f: Frame = serde_json::from_value(serde_json::json!({
            "calibration": {"intrinsic": [100.0, 100.0, 50.0, 40.0, 0, 0, 0, 0, 0],
                "extrinsic": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "width": w, "height": h},
            "points": [], "persons": []
        }))
        .unwrap();
        f.image = image;
        f
    }

    #[test]
    fn a_header_that_disagrees_with_the_calibration_is_refused_before_decoding() {
        let (_, jpeg) = pattern(120, 80);
        let b64 = base64::engine::general_purpose::STANDARD.encode(&jpeg);
        assert!(matches!(open(&frame_with(Some(b64.clone()), 120, 80), None, None).unwrap(), CameraImage::Jpeg(_)));
        let e = open(&frame_with(Some(b64), 121, 80), None, None).err().unwrap();
        assert_eq!(e.field_name(), Some("image"));
        assert!(e.to_string().contains("120x80"), "{e}");
        // a PNG goes the same way
        let mut png = Vec::new();
        pattern(50, 30).0.write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png).unwrap();
        assert!(matches!(open(&frame_with(None, 50, 30), Some(png.clone()), None).unwrap(), CameraImage::Png(_)));
        assert_eq!(open(&frame_with(None, 50, 31), Some(png.clone()), None).err().unwrap().field_name(), Some("image"));
        let CameraImage::Png(bytes) = open(&frame_with(None, 50, 30), Some(png), None).unwrap() else { unreachable!() };
        assert_eq!(decode_with_image_crate(&bytes, image::ImageFormat::Png).unwrap().image.dimensions(), (50, 30));
    }

    #[test]
    fn garbage_is_undecodable_not_an_error() {
        for bytes in [vec![0xFF, 0xD8, 0xFF, 0x00, 1, 2, 3], b"GIF89a....".to_vec()] {
            let got = open(&frame_with(None, 10, 10), Some(bytes), None).unwrap();
            assert!(matches!(got, CameraImage::Undecodable(_)));
        }
    }

    #[test]
    fn cut_short_corrupt_and_trailing_bytes_are_undecodable_in_every_region() {
        let (_, jpeg) = pattern(200, 120);
        let why = |bytes: Vec<u8>| match open(&frame_with(None, 200, 120), Some(bytes), None).unwrap() {
            CameraImage::Undecodable(m) => m,
            _ => "accepted".into(),
        };
        // cut short (a half, or one byte less) and followed by other bytes: refused before any pixel
        for cut in [jpeg[..jpeg.len() / 2].to_vec(), jpeg[..jpeg.len() - 1].to_vec(), [&jpeg[..], b"trailing"].concat()]
        {
            assert!(why(cut).contains("end-of-image marker"));
        }
        // corrupt entropy data near the end: a region at the top still fails, as the whole decode does
        let mut marked = jpeg.clone();
        let at = jpeg.len() - 40;
        marked[at..at + 2].copy_from_slice(&[0xFF, 0xD3]);
        let CameraImage::Jpeg(bytes) = open(&frame_with(None, 200, 120), Some(marked), None).unwrap() else {
            panic!("the header is sound")
        };
        let top = [CropTransform { x0: 10.0, y0: 5.0, scale: 64.0 / 40.0, size: 64 }];
        let planned = decode_crops(&CameraImage::Jpeg(bytes.clone()), &top, 200, 120, || Ok(())).unwrap();
        assert!(planned.unwrap_err().contains("corrupt data"));
        let whole = decode_planned(&bytes, &DecodePlan::full(200, 120), true);
        assert!(whole.err().is_some_and(|e| e.contains("corrupt data")));
    }

    /// Pixels read on demand from an image in memory, counting the rows read.
    struct Counted {
        image: RgbImage,
        rows_read: std::sync::Mutex<Vec<PixelRect>>,
    }

    impl PixelSource for Counted {
        fn size(&self) -> (u32, u32) {
            self.image.dimensions()
        }

        fn read_rect_into(&self, r: PixelRect, out: &mut [u8]) -> std::result::Result<(), String> {
            self.rows_read.lock().unwrap().push(r);
            let pixels = (r.y0..r.y1).flat_map(|y| (r.x0..r.x1).flat_map(move |x| self.image.get_pixel(x, y).0));
            let mut n = 0;
            for (o, v) in out.iter_mut().zip(pixels) {
                *o = v;
                n += 1;
            }
            assert_eq!((n, out.len() as u64), (r.area() * 3, r.area() * 3), "the buffer fits the rectangle");
            Ok(())
        }
    }

    #[test]
    fn crops_from_rows_read_on_demand_equal_crops_from_the_whole_image() {
        let (img, _) = pattern(640, 480);
        let w = |x0: f64, y0: f64, side: f64| CropTransform { x0, y0, scale: 64.0 / side, size: 64 };
        let cases: Vec<Vec<CropTransform>> = vec![
            vec![w(300.0, 200.0, 90.0)],
            vec![w(10.0, 150.0, 120.0), w(500.0, 260.0, 200.0)],
            vec![w(-30.0, -20.0, 100.0)],
            vec![w(600.0, 440.0, 150.0)],
            vec![w(700.0, 100.0, 50.0)],
            vec![w(-200.0, -200.0, 900.0), w(700.0, 100.0, 50.0), w(100.0, 100.0, 30.0)],
            vec![],
        ];
        for windows in cases {
            let rows = Arc::new(Counted { image: img.clone(), rows_read: Default::default() });
            let from_rows =
                decode_crops(&CameraImage::Rows(rows.clone()), &windows, 640, 480, || Ok(())).unwrap().unwrap();
            let whole =
                decode_crops(&CameraImage::Pixels(img.clone()), &windows, 640, 480, || Ok(())).unwrap().unwrap();
            assert_eq!(from_rows, whole, "{windows:?}");
            // each window reads its own rectangle (not the union of all); a miss reads nothing
            let read = rows.rows_read.lock().unwrap().clone();
            let own: Vec<PixelRect> = windows
                .iter()
                .filter_map(|t| crate::pipeline::pixel_region(std::slice::from_ref(t), 640, 480))
                .collect();
            assert_eq!(read, own, "{windows:?}");
        }
    }

    #[test]
    fn passes_side_by_side_answer_in_order_each_beside_the_first() {
        let caller = std::thread::current().id();
        let ran_on = std::sync::Mutex::new(Vec::new());
        let work = |i: usize| {
            ran_on.lock().unwrap().push((i, std::thread::current().id()));
            if i == 2 {
                Err(format!("pass {i} failed"))
            } else {
                Ok(i * 10)
            }
        };
        assert_eq!(side_by_side(4, &work), vec![Ok(0), Ok(10), Err("pass 2 failed".into()), Ok(30)]);
        let mut ran = ran_on.lock().unwrap().clone();
        ran.sort_by_key(|r| r.0);
        assert_eq!(ran.iter().map(|r| r.0).collect::<Vec<_>>(), vec![0, 1, 2, 3], "each pass once");
        assert_eq!(ran[0].1, caller, "the first pass on the caller's thread");
        let others: std::collections::HashSet<_> = ran[1..].iter().map(|r| r.1).collect();
        assert!(!others.contains(&caller) && others.len() == 3, "the others each on a thread of its own");
        assert!(side_by_side(0, &work).is_empty());
    }

    #[test]
    fn a_window_beyond_the_kept_scratch_reads_into_its_own_buffer() {
        let (img, _) = pattern(1400, 1100);
        let windows = [CropTransform { x0: -10.0, y0: -10.0, scale: 64.0 / 1420.0, size: 64 }];
        let region = crate::pipeline::pixel_region(&windows, 1400, 1100).unwrap();
        assert!(region.area() * 3 > KEPT_SCRATCH_BYTES as u64);
        let rows = Arc::new(Counted { image: img.clone(), rows_read: Default::default() });
        let from_rows = decode_crops(&CameraImage::Rows(rows), &windows, 1400, 1100, || Ok(())).unwrap().unwrap();
        let whole = decode_crops(&CameraImage::Pixels(img), &windows, 1400, 1100, || Ok(())).unwrap().unwrap();
        assert_eq!(from_rows, whole);
        assert!(SCRATCH.with(|s| s.borrow().capacity()) <= KEPT_SCRATCH_BYTES, "no thread keeps it");
    }

    #[test]
    fn a_near_persons_window_is_read_into_the_buffer_its_thread_keeps() {
        // a 1,000 px window on a 1920×1280 frame: 3 MB of pixels, kept for the next request
        let (img, _) = pattern(1920, 1280);
        let windows = [CropTransform { x0: 400.0, y0: 100.0, scale: 64.0 / 1000.0, size: 64 }];
        let bytes = crate::pipeline::pixel_region(&windows, 1920, 1280).unwrap().area() as usize * 3;
        assert!(bytes > 3_000_000);
        let rows = Arc::new(Counted { image: img.clone(), rows_read: Default::default() });
        let from_rows = decode_crops(&CameraImage::Rows(rows), &windows, 1920, 1280, || Ok(())).unwrap().unwrap();
        assert_eq!(
            from_rows,
            decode_crops(&CameraImage::Pixels(img), &windows, 1920, 1280, || Ok(())).unwrap().unwrap()
        );
        assert!(SCRATCH.with(|s| s.borrow().len()) >= bytes, "the thread keeps the window's buffer");
    }

    #[test]
    fn rows_are_checked_against_the_calibration_and_sent_once() {
        let c = CameraCalibration { intrinsic: vec![500.0; 9], extrinsic: vec![0.0; 16], width: 640, height: 480 };
        let rows = |w, h| {
            let image = RgbImage::new(w, h);
            Some(Arc::new(Counted { image, rows_read: Default::default() }) as Arc<dyn PixelSource>)
        };
        let ok = open_camera(ImageInput { rows: rows(640, 480), ..Default::default() }, &c).unwrap();
        assert!(matches!(ok, CameraImage::Rows(_)) && ok.usable());
        assert!(!CameraImage::Absent.usable() && !CameraImage::Undecodable("x".into()).usable());
        let e = open_camera(ImageInput { rows: rows(320, 480), ..Default::default() }, &c).err().unwrap();
        assert_eq!(e.field_name(), Some("image_rgb.width/height"));
        let both = ImageInput { rows: rows(640, 480), raw: Some(vec![0xFF, 0xD8]), ..Default::default() };
        assert_eq!(open_camera(both, &c).err().unwrap().field_name(), Some("image_rgb"));
        let px = RgbPixels { width: 640, height: 480, pixels: vec![0; 640 * 480 * 3] };
        let both = ImageInput { rows: rows(640, 480), pixels: Some(px), ..Default::default() };
        assert_eq!(open_camera(both, &c).err().unwrap().field_name(), Some("image_rgb"));
    }
}
