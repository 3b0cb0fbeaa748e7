//! Camera input: a square crop around the person's 2D box, resized to S×S and normalized.

use fast_image_resize::{images::Image, FilterType, PixelType, ResizeAlg, ResizeOptions, Resizer};
use image::{ImageBuffer, Rgb, RgbImage};
use serde::{Deserialize, Serialize};

use super::PipelineConfig;
use crate::frame::Box2d;

/// The affine map between image pixels and model-input (crop) pixels:
/// `model = (image − (x0, y0)) · scale`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CropTransform {
    pub x0: f64,
    pub y0: f64,
    pub scale: f64,
    pub size: u32,
}

impl CropTransform {
    /// The square of side `max(w, h) · crop_scale` centred on the box, mapped onto S×S.
    pub fn for_box(b: &Box2d, cfg: &PipelineConfig) -> CropTransform {
        let side = b.width.max(b.height) * cfg.crop_scale;
        CropTransform {
            x0: b.center_x - side / 2.0,
            y0: b.center_y - side / 2.0,
            scale: cfg.image_size as f64 / side,
            size: cfg.image_size,
        }
    }

    /// Image pixels → model-input pixels.
    pub fn to_model(&self, image_px: [f64; 2]) -> [f64; 2] {
        [(image_px[0] - self.x0) * self.scale, (image_px[1] - self.y0) * self.scale]
    }

    /// Model-input pixels → image pixels.
    pub fn to_image(&self, model_px: [f64; 2]) -> [f64; 2] {
        [model_px[0] / self.scale + self.x0, model_px[1] / self.scale + self.y0]
    }

    /// Side of the crop in image pixels.
    pub fn side(&self) -> f64 {
        self.size as f64 / self.scale
    }
}

/// The S×S crop of `image` described by `t`; pixels outside the image are black.
///
/// The resize filter reads a few pixels beyond the window, so the source is the window plus a
/// margin wider than the filter: the image itself when that fits inside it, otherwise a copy
/// padded with black. Both give the same result wherever they both apply.
pub fn crop_rgb<C: std::ops::Deref<Target = [u8]>>(image: &ImageBuffer<Rgb<u8>, C>, t: &CropTransform) -> RgbImage {
    let s = t.size;
    let side = t.side();
    let mut out = RgbImage::new(s, s);
    // A window far larger than the image (a corrupt box) would need a huge padded copy; nothing
    // of the image survives such a reduction anyway.
    let limit = 16.0 * (image.width().max(image.height()) as f64).max(1.0);
    let (w, h) = (image.width() as f64, image.height() as f64);
    let misses = t.x0 >= w || t.y0 >= h || t.x0 + side <= 0.0 || t.y0 + side <= 0.0;
    if !(t.x0.is_finite() && t.y0.is_finite() && side.is_finite()) || side > limit || side <= 0.0 || misses {
        return out;
    }
    // a box filter reads half a destination pixel (1/(2·scale) source pixels) around the window
    let margin = (1.0 / t.scale).ceil() as i64 + 2;
    let ix0 = t.x0.floor() as i64 - margin;
    let iy0 = t.y0.floor() as i64 - margin;
    let ix1 = (t.x0 + side).ceil() as i64 + margin;
    let iy1 = (t.y0 + side).ceil() as i64 + margin;
    let (iw, ih) = (image.width() as i64, image.height() as i64);
    // the resize writes straight into the returned image's buffer
    let Ok(mut dst) = Image::from_slice_u8(s, s, out.as_mut(), PixelType::U8x3) else {
        return RgbImage::new(s, s);
    };
    let inside = ix0 >= 0 && iy0 >= 0 && ix1 <= iw && iy1 <= ih;
    let done = if inside {
        // the filter reads at most `margin` pixels around the window, all inside the image
        let opts =
            ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Box)).crop(t.x0, t.y0, side, side);
        match fast_image_resize::images::ImageRef::new(image.width(), image.height(), image.as_raw(), PixelType::U8x3) {
            Ok(view) => resize(&view, &mut dst, &opts),
            Err(_) => false,
        }
    } else {
        let (pw, ph) = ((ix1 - ix0).max(1) as u32, (iy1 - iy0).max(1) as u32);
        let mut patch = vec![0u8; pw as usize * ph as usize * 3];
        let (cx0, cy0) = (ix0.max(0), iy0.max(0));
        let (cx1, cy1) = (ix1.min(iw), iy1.min(ih));
        if cx0 < cx1 && cy0 < cy1 {
            let row_bytes = ((cx1 - cx0) * 3) as usize;
            let src = image.as_raw();
            let dst_stride = pw as usize * 3;
            for y in cy0..cy1 {
                let so = ((y * iw + cx0) * 3) as usize;
                let d = ((y - iy0) as usize) * dst_stride + ((cx0 - ix0) * 3) as usize;
                patch[d..d + row_bytes].copy_from_slice(&src[so..so + row_bytes]);
            }
        }
        let opts = ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Box)).crop(
            t.x0 - ix0 as f64,
            t.y0 - iy0 as f64,
            side,
            side,
        );
        match Image::from_vec_u8(pw, ph, patch, PixelType::U8x3) {
            Ok(src) => resize(&src, &mut dst, &opts),
            Err(_) => false,
        }
    };
    drop(dst);
    if !done {
        // a refused resize (never expected: the crop box is checked above) leaves no half image
        out.as_mut().fill(0);
    }
    out
}

thread_local! {
    // A resizer keeps its scratch buffers: one per thread instead of one per crop.
    static RESIZER: std::cell::RefCell<Resizer> = std::cell::RefCell::new(Resizer::new());
}

fn resize(src: &impl fast_image_resize::IntoImageView, dst: &mut Image, opts: &ResizeOptions) -> bool {
    RESIZER.with(|r| r.try_borrow_mut().is_ok_and(|mut r| r.resize(src, dst, opts).is_ok()))
}

/// CHW float tensor `[3, S, S]`: `(value / 255 − mean) / std` per channel.
pub fn normalize(crop: &RgbImage, cfg: &PipelineConfig) -> Vec<f32> {
    // One table lookup per value: the same `v · scale − shift` in f32, without per-value math.
    let lut: [[f32; 256]; 3] = std::array::from_fn(|c| {
        let (scale, shift) = (1.0 / (255.0 * cfg.std[c]), cfg.mean[c] / cfg.std[c]);
        std::array::from_fn(|v| v as f32 * scale - shift)
    });
    let raw = crop.as_raw();
    // filled plane by plane from exact-size iterators: the tensor is written once, never zeroed
    let mut out = Vec::with_capacity(raw.len());
    for (c, table) in lut.iter().enumerate() {
        out.extend(raw.chunks_exact(3).map(|px| table[px[c] as usize]));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(s: u32) -> PipelineConfig {
        PipelineConfig::with_image_size(s)
    }

    #[test]
    fn transform_round_trips_and_centres_the_box() {
        let b = Box2d { center_x: 500.0, center_y: 300.0, width: 40.0, height: 100.0 };
        let t = CropTransform::for_box(&b, &cfg(64));
        assert!((t.side() - 120.0).abs() < 1e-9);
        let c = t.to_model([500.0, 300.0]);
        assert!((c[0] - 32.0).abs() < 1e-9 && (c[1] - 32.0).abs() < 1e-9);
        let back = t.to_image(t.to_model([123.4, 567.8]));
        assert!((back[0] - 123.4).abs() < 1e-9 && (back[1] - 567.8).abs() < 1e-9);
    }

    #[test]
    fn a_known_block_lands_where_the_transform_says() {
        // A 10×10 white block at image (100..110, 200..210) in a black 400×400 image; the crop
        // halves the resolution, so the block covers exactly model px [18, 23) × [20, 25).
        let mut img = RgbImage::new(400, 400);
        for y in 200..210 {
            for x in 100..110 {
                img.put_pixel(x, y, image::Rgb([255, 255, 255]));
            }
        }
        let t = CropTransform { x0: 64.0, y0: 160.0, scale: 0.5, size: 64 };
        let crop = crop_rgb(&img, &t);
        let [mx, my] = t.to_model([105.0, 205.0]);
        assert_eq!([mx, my], [20.5, 22.5]);
        assert_eq!(crop.get_pixel(20, 22).0, [255, 255, 255]);
        assert_eq!(crop.get_pixel(10, 10).0, [0, 0, 0]);
        assert_eq!(crop.get_pixel(30, 22).0, [0, 0, 0]);
        // the filter blurs the block's edge by a pixel at most; its mass stays centred on (20.5, 22.5)
        let (mut m, mut mx, mut my) = (0.0, 0.0, 0.0);
        for (x, y, p) in crop.enumerate_pixels() {
            let v = p.0[0] as f64;
            let inside = (17..24).contains(&x) && (19..26).contains(&y);
            assert!(inside || v == 0.0, "stray value {v} at ({x}, {y})");
            if (19..22).contains(&x) && (21..24).contains(&y) {
                assert_eq!(v, 255.0, "block interior at ({x}, {y})");
            }
            (m, mx, my) = (m + v, mx + v * (x as f64 + 0.5), my + v * (y as f64 + 0.5));
        }
        assert!((mx / m - 20.5).abs() < 0.01 && (my / m - 22.5).abs() < 0.01, "centroid ({}, {})", mx / m, my / m);
        assert!((m / 255.0 - 25.0).abs() < 0.5, "mass {}", m / 255.0);
    }

    #[test]
    fn outside_the_image_is_black_and_inside_is_kept() {
        let img = RgbImage::from_pixel(100, 100, image::Rgb([10, 200, 30]));
        // half of the window hangs off the left edge
        let t = CropTransform { x0: -50.0, y0: 0.0, scale: 1.0, size: 100 };
        let crop = crop_rgb(&img, &t);
        assert_eq!(crop.get_pixel(10, 50).0, [0, 0, 0]);
        assert_eq!(crop.get_pixel(80, 50).0, [10, 200, 30]);
        // and the same off the top edge
        let t = CropTransform { x0: 0.0, y0: -50.0, scale: 1.0, size: 100 };
        let crop = crop_rgb(&img, &t);
        assert_eq!(crop.get_pixel(50, 10).0, [0, 0, 0]);
        assert_eq!(crop.get_pixel(50, 80).0, [10, 200, 30]);
        // entirely outside
        let t = CropTransform { x0: 500.0, y0: 500.0, scale: 1.0, size: 16 };
        assert!(crop_rgb(&img, &t).as_raw().iter().all(|&v| v == 0));
    }

    #[test]
    fn the_in_image_and_padded_paths_agree() {
        let mut img = RgbImage::new(300, 200);
        for (x, y, p) in img.enumerate_pixels_mut() {
            *p = image::Rgb([(x * 7 % 256) as u8, (y * 13 % 256) as u8, ((x + y) % 256) as u8]);
        }
        // a window well inside (direct path), and the same window content shifted so that its
        // margin touches the border (padded path): equal where both read only image pixels
        let inside = CropTransform { x0: 100.3, y0: 60.7, scale: 64.0 / 90.0, size: 64 };
        let a = crop_rgb(&img, &inside);
        let mut shifted = RgbImage::new(300, 200);
        for y in 0..200 {
            for x in 0..300 {
                if x + 98 < 300 && y + 58 < 200 {
                    shifted.put_pixel(x, y, *img.get_pixel(x + 98, y + 58));
                }
            }
        }
        let near_edge = CropTransform { x0: 2.3, y0: 2.7, ..inside };
        let b = crop_rgb(&shifted, &near_edge);
        assert_eq!(a, b);
    }

    #[test]
    fn absurd_windows_give_black_crops_without_panicking() {
        let img = RgbImage::from_pixel(10, 10, image::Rgb([9, 9, 9]));
        for t in [
            CropTransform { x0: 0.0, y0: 0.0, scale: 1e-300, size: 8 },
            CropTransform { x0: f64::NAN, y0: 0.0, scale: 1.0, size: 8 },
            CropTransform { x0: 1e300, y0: -1e300, scale: 1.0, size: 8 },
        ] {
            assert!(crop_rgb(&img, &t).as_raw().iter().all(|&v| v == 0));
        }
    }

    #[test]
    fn normalize_is_chw_with_mean_and_std() {
        let mut img = RgbImage::new(2, 2);
        img.put_pixel(1, 0, image::Rgb([255, 0, 51]));
        let c = cfg(8);
        let t = normalize(&img, &c);
        assert_eq!(t.len(), 12);
        let expect = |v: f32, ch: usize| (v / 255.0 - c.mean[ch]) / c.std[ch];
        assert!((t[1] - expect(255.0, 0)).abs() < 1e-6);
        assert!((t[4 + 1] - expect(0.0, 1)).abs() < 1e-6);
        assert!((t[8 + 1] - expect(51.0, 2)).abs() < 1e-6);
        assert!((t[0] - expect(0.0, 0)).abs() < 1e-6);
    }
}
