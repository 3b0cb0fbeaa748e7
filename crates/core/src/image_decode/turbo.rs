//! libjpeg-turbo's decoder (the `mozjpeg-sys` build from source: its SIMD code, SSE2/AVX2 as
//! the CPU has them, where `nasm` was there at build time, else its C code; [`simd`] says which),
//! for what zune-jpeg cannot do: decode at a DCT scale (½, ¼, ⅛: a
//! reduced inverse transform per 8×8 block) and only a region. The rows above the region are
//! entropy-decoded and skipped, the rows below it are never read, and only the iMCU columns it
//! covers go through the inverse transform, upsampling and colour conversion.
//!
//! libjpeg reports errors through a callback that must not return; ours unwinds (the C code is
//! built with `-fexceptions` for that) with a private payload that [`decode_region`] catches, so
//! a corrupt file is an `Err` and never a panic message or an `exit()`. Its warnings (corrupt
//! data it would paper over with grey) are errors too.

use std::os::raw::c_int;
use std::panic::{catch_unwind, resume_unwind, AssertUnwindSafe};

use mozjpeg_sys as jpeg;

extern "C" {
    /// libjpeg-turbo's own probe (`jsimd.c`, or `jsimd_none.c` in a build without SIMD, which
    /// answers 0): 1 when the inverse DCT runs in SIMD code on this CPU.
    fn jsimd_can_idct_islow() -> c_int;
}

/// Whether the decoder runs its SIMD code: built with it (nasm at build time) on a CPU that has
/// it. (libjpeg-turbo's `JSIMD_FORCENONE` switch has no effect in this build.)
pub fn simd() -> bool {
    // SAFETY: a pure query of libjpeg-turbo's CPU-feature table, which it initialises on first use.
    unsafe { jsimd_can_idct_islow() == 1 }
}

/// Pixels `[x0, x0 + width) × [y0, y0 + height)` of a JPEG decoded at `1/denominator`, RGB8.
pub struct Region {
    pub pixels: Vec<u8>,
    pub width: u32,
    pub height: u32,
    pub x0: u32,
    pub y0: u32,
}

/// Output pixels decoded beyond each side of the region asked for (one iMCU at full scale).
const EDGE: u32 = 16;

/// Why a JPEG was not decoded.
#[derive(Debug)]
pub enum RegionError {
    /// A colour space the region decoder does not convert (CMYK, YCCK): another decoder may.
    Unsupported,
    /// A corrupt file, or a region that misses it.
    Invalid(String),
}

/// The unwinding payload of libjpeg's error callback.
struct JpegError(String);

fn message(err: &jpeg::jpeg_error_mgr) -> String {
    let code = err.msg_code;
    let table = err.jpeg_message_table;
    if table.is_null() || code <= 0 || code > err.last_jpeg_message {
        return format!("libjpeg error {code}");
    }
    // SAFETY: libjpeg's message table holds `last_jpeg_message + 1` NUL-terminated strings.
    let p = unsafe { *table.add(code as usize) };
    if p.is_null() {
        return format!("libjpeg error {code}");
    }
    // SAFETY: a non-null entry of the table is a NUL-terminated string.
    unsafe { std::ffi::CStr::from_ptr(p) }.to_string_lossy().into_owned()
}

unsafe extern "C-unwind" fn error_exit(cinfo: &mut jpeg::jpeg_common_struct) {
    // SAFETY: `err` points at the error manager the decoder was created with (see `Decoder`).
    let text = message(unsafe { &*cinfo.err });
    resume_unwind(Box::new(JpegError(text)));
}

unsafe extern "C-unwind" fn emit_message(cinfo: &mut jpeg::jpeg_common_struct, level: c_int) {
    if level < 0 {
        // SAFETY: as in `error_exit`.
        let text = message(unsafe { &*cinfo.err });
        resume_unwind(Box::new(JpegError(format!("corrupt data: {text}"))));
    }
}

unsafe extern "C-unwind" fn output_message(_: &mut jpeg::jpeg_common_struct) {}

/// A decompressor and its error manager, destroyed together (also while unwinding).
struct Decoder {
    cinfo: jpeg::jpeg_decompress_struct,
    err: jpeg::jpeg_error_mgr,
}

impl Drop for Decoder {
    fn drop(&mut self) {
        // SAFETY: `cinfo` was created by `jpeg_create_decompress`; destroying it frees its memory
        // in any state, after an error too.
        unsafe { jpeg::jpeg_destroy_decompress(&mut self.cinfo) };
    }
}

/// Decodes the full-resolution region `[x0, x1) × [y0, y1)` of `bytes` at `1/denominator` (1, 2,
/// 4 or 8). The result covers the region, scaled, and a margin around it (libjpeg also widens it
/// to whole iMCU columns); `x0`, `y0` say where it starts. With `to_end` the rows below the region
/// are read and skipped to the end of the image (entropy-decoded, not transformed), so corrupt
/// data there is an error too; without it they are never read.
pub fn decode_region(
    bytes: &[u8],
    denominator: u32,
    rect: (u32, u32, u32, u32),
    to_end: bool,
) -> Result<Region, RegionError> {
    match catch_unwind(AssertUnwindSafe(|| decode_unguarded(bytes, denominator, rect, to_end))) {
        Ok(r) => r,
        Err(payload) => match payload.downcast::<JpegError>() {
            Ok(e) => Err(RegionError::Invalid(e.0)),
            // not libjpeg's: a bug of ours, which must not be swallowed
            Err(other) => resume_unwind(other),
        },
    }
}

fn decode_unguarded(
    bytes: &[u8],
    denominator: u32,
    (x0, y0, x1, y1): (u32, u32, u32, u32),
    to_end: bool,
) -> Result<Region, RegionError> {
    use RegionError::{Invalid, Unsupported};
    let d = denominator.clamp(1, 8);
    // SAFETY: both structs are plain C data for which all-zero is the documented initial state;
    // the box keeps their addresses fixed while libjpeg holds pointers into them.
    let mut dec: Box<Decoder> = Box::new(unsafe { std::mem::zeroed() });
    // SAFETY: the calls follow libjpeg's documented sequence on one decompressor; `bytes`
    // outlives it (it is dropped before this function returns); every row pointer handed to
    // `jpeg_read_scanlines` points at `out_width * 3` writable bytes of `pixels`.
    unsafe {
        let err = jpeg::jpeg_std_error(&mut dec.err);
        err.error_exit = Some(error_exit);
        err.emit_message = Some(emit_message);
        err.output_message = Some(output_message);
        dec.cinfo.common.err = &mut dec.err;
        jpeg::jpeg_create_decompress(&mut dec.cinfo);
        jpeg::jpeg_mem_src(&mut dec.cinfo, bytes.as_ptr(), bytes.len() as _);
        jpeg::jpeg_read_header(&mut dec.cinfo, 1);
        let c = &mut dec.cinfo;
        if !matches!(c.jpeg_color_space, jpeg::J_COLOR_SPACE::JCS_YCbCr | jpeg::J_COLOR_SPACE::JCS_GRAYSCALE) {
            return Err(Unsupported);
        }
        c.out_color_space = jpeg::J_COLOR_SPACE::JCS_RGB;
        c.scale_num = 1;
        c.scale_denom = d;
        jpeg::jpeg_start_decompress(c);
        let (full_w, full_h) = (c.output_width, c.output_height);
        if c.output_width != c.image_width.div_ceil(d) || c.output_height != c.image_height.div_ceil(d) {
            return Err(Invalid(format!(
                "scaled size {}x{} is not 1/{d} of the image",
                c.output_width, c.output_height
            )));
        }
        let (rx0, rx1) = ((x0 / d).min(full_w), x1.div_ceil(d).min(full_w));
        let (ry0, ry1) = ((y0 / d).min(full_h), y1.div_ceil(d).min(full_h));
        if rx0 >= rx1 || ry0 >= ry1 {
            return Err(Invalid("the region misses the image".into()));
        }
        // Chroma upsampling reads one sample beyond a cut edge: a margin keeps the region's own
        // pixels equal to those of the whole decode.
        let (rx0, rx1) = (rx0.saturating_sub(EDGE), (rx1 + EDGE).min(full_w));
        let (ry0, ry1) = (ry0.saturating_sub(EDGE), (ry1 + EDGE).min(full_h));
        let (mut xoff, mut width) = (rx0, rx1 - rx0);
        if width < full_w {
            jpeg::jpeg_crop_scanline(c, &mut xoff, &mut width);
        }
        let out_w = c.output_width;
        if ry0 > 0 && jpeg::jpeg_skip_scanlines(c, ry0) != ry0 {
            return Err(Invalid("the image ends above the region".into()));
        }
        let stride = out_w as usize * 3;
        let height = ry1 - ry0;
        let mut pixels = vec![0u8; stride * height as usize];
        while c.output_scanline < ry1 {
            let i = (c.output_scanline - ry0) as usize;
            let mut row = pixels[i * stride..].as_mut_ptr();
            if jpeg::jpeg_read_scanlines(c, &mut row, 1) != 1 {
                return Err(Invalid("the image ended early".into()));
            }
        }
        if to_end {
            // libjpeg-turbo skips a skip that reaches the last row without reading anything, so
            // all but the last row are skipped (entropy-decoded, not transformed) and the last
            // one is read
            let rest = c.output_height - c.output_scanline;
            if rest > 1 && jpeg::jpeg_skip_scanlines(c, rest - 1) != rest - 1 {
                return Err(Invalid("the image ended early".into()));
            }
            if c.output_scanline < c.output_height {
                let mut last = vec![0u8; stride];
                let mut row = last.as_mut_ptr();
                if jpeg::jpeg_read_scanlines(c, &mut row, 1) != 1 {
                    return Err(Invalid("the image ended early".into()));
                }
            }
            // reads up to the end-of-image marker; corrupt data on the way is an error (see
            // `emit_message`)
            jpeg::jpeg_finish_decompress(c);
        } else {
            // the rows below the region are not needed: stop without reading them
            jpeg::jpeg_abort_decompress(c);
        }
        Ok(Region { pixels, width: out_w, height, x0: xoff, y0: ry0 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simd_is_on_where_nasm_is() {
        // nasm at test time stands for nasm at build time (the same machine); CI installs it
        // (.ci/run) and must not fall back to the C code silently.
        let nasm = std::process::Command::new("nasm").arg("-v").output().is_ok_and(|o| o.status.success());
        let ci = std::env::var("CI").is_ok_and(|v| v == "true");
        if nasm || ci {
            assert!(simd(), "libjpeg-turbo was built without its SIMD code (nasm: {nasm})");
        }
    }

    fn jpeg_of(w: u32, h: u32) -> (image::RgbImage, Vec<u8>) {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 3 % 256) as u8, (y * 5 % 256) as u8, 128]));
        let mut out = Vec::new();
        let mut enc = jpeg_encoder::Encoder::new(&mut out, 95);
        enc.set_sampling_factor(jpeg_encoder::SamplingFactor::R_4_2_0);
        enc.encode(img.as_raw(), w as u16, h as u16, jpeg_encoder::ColorType::Rgb).unwrap();
        (img, out)
    }

    #[test]
    fn a_region_holds_the_same_pixels_as_the_whole_decode() {
        let (_, bytes) = jpeg_of(200, 120);
        let whole = decode_region(&bytes, 1, (0, 0, 200, 120), false).unwrap();
        assert_eq!((whole.width, whole.height, whole.x0, whole.y0), (200, 120, 0, 0));
        let r = decode_region(&bytes, 1, (50, 30, 130, 90), false).unwrap();
        // the rows asked for and the margin, exactly (the columns are widened to iMCU edges)
        assert_eq!((r.y0, r.y0 + r.height), (30 - EDGE, 90 + EDGE));
        assert_eq!(r.pixels.len(), (r.width * r.height * 3) as usize);
        assert!(r.x0 <= 50 && r.x0 + r.width >= 130, "columns {}..{}", r.x0, r.x0 + r.width);
        for y in 30 - r.y0..90 - r.y0 {
            for x in 50 - r.x0..130 - r.x0 {
                let (gx, gy) = ((x + r.x0) as usize, (y + r.y0) as usize);
                let a = &r.pixels[(y as usize * r.width as usize + x as usize) * 3..][..3];
                let b = &whole.pixels[(gy * 200 + gx) * 3..][..3];
                assert_eq!(a, b, "pixel ({gx}, {gy})");
            }
        }
    }

    #[test]
    fn a_scaled_decode_is_close_to_the_image_averaged() {
        let (img, bytes) = jpeg_of(160, 96);
        let r = decode_region(&bytes, 4, (0, 0, 160, 96), false).unwrap();
        assert_eq!((r.width, r.height), (40, 24));
        // each output pixel is about the mean of its 4×4 block (the JPEG's loss aside)
        let mut worst = 0i32;
        for y in 0..24u32 {
            for x in 0..40u32 {
                let mean = |ch: usize| {
                    let s: u32 = (0..16).map(|k| img.get_pixel(x * 4 + k % 4, y * 4 + k / 4)[ch] as u32).sum();
                    (s / 16) as i32
                };
                let px = &r.pixels[((y * 40 + x) * 3) as usize..][..3];
                worst = worst.max((px[0] as i32 - mean(0)).abs()).max((px[1] as i32 - mean(1)).abs());
            }
        }
        assert!(worst <= 12, "largest difference {worst}");
    }

    #[test]
    fn corrupt_and_truncated_files_are_errors_not_panics() {
        let (_, bytes) = jpeg_of(64, 64);
        // libjpeg's own words, taken from its message table
        let why = |r: Result<Region, RegionError>| match r {
            Err(RegionError::Invalid(m)) => m,
            Err(RegionError::Unsupported) => "unsupported".into(),
            Ok(_) => "decoded".into(),
        };
        assert_eq!(
            why(decode_region(&bytes[..bytes.len() / 2], 1, (0, 0, 64, 64), false)),
            "corrupt data: Premature end of JPEG file"
        );
        assert!(decode_region(b"\xFF\xD8\xFF\xE0 not a jpeg", 1, (0, 0, 64, 64), false).is_err());
        // a marker in the middle of the entropy-coded data: libjpeg would warn and go on
        let mut marked = bytes.clone();
        let at = bytes.len() / 2;
        marked[at..at + 2].copy_from_slice(&[0xFF, 0xD3]);
        assert!(why(decode_region(&marked, 2, (0, 0, 64, 64), false)).starts_with("corrupt data: Corrupt JPEG data"));
        assert!(decode_region(&bytes, 1, (70, 0, 90, 64), false).is_err(), "a region outside the image");
    }

    #[test]
    fn corrupt_data_below_the_region_is_an_error_only_when_read_to_the_end() {
        let (_, bytes) = jpeg_of(64, 256);
        // a restart marker where none belongs, in the last quarter of the entropy-coded data
        let mut marked = bytes.clone();
        let at = bytes.len() * 7 / 8;
        marked[at..at + 2].copy_from_slice(&[0xFF, 0xD3]);
        let top = (0, 0, 64, 32);
        assert!(decode_region(&marked, 1, top, false).is_ok(), "the rows below the region are never read");
        match decode_region(&marked, 1, top, true) {
            Err(RegionError::Invalid(m)) => assert!(m.starts_with("corrupt data"), "{m}"),
            other => panic!("read to the end, the corrupt rows are an error: {:?}", other.map(|r| r.height)),
        }
        // a sound file reads to the end and gives the same region
        let a = decode_region(&bytes, 2, top, false).unwrap();
        let b = decode_region(&bytes, 2, top, true).unwrap();
        assert_eq!((a.pixels, a.x0, a.y0), (b.pixels, b.x0, b.y0));
    }
}
