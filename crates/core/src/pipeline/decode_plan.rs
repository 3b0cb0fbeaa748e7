//! How much of a camera image each crop needs: the smallest JPEG DCT scale (1, ½, ¼, ⅛) at which
//! the crop window still spans at least the network's S pixels, and the full-resolution region
//! the crops read. Pure: the decoder (`crate::image_decode`) carries the plan out.
//!
//! The scale is chosen per window, from that window alone ([`window_denominator`]), never per
//! image: a person's crop is then the same whoever else is in the frame (docs/ARCHITECTURE.md,
//! "A person's answer is its own"). Windows of the same scale share one decode pass
//! ([`plan_passes`]) over the union of their regions; the region only saves work, it never
//! changes a pixel the crops read.
//!
//! A crop cut from an image decoded at `1/d` uses the window [`scaled`] by `d`: pixel `(i, j)` of
//! the scaled image covers full-resolution pixels `[d·j, d·(j+1)) × [d·i, d·(i+1))`, so the window
//! covers the same part of the scene, and the resize still only reduces (never enlarges).

use super::CropTransform;

/// The DCT scales a baseline JPEG decoder offers, as denominators, largest reduction first.
pub const DCT_DENOMINATORS: [u32; 4] = [8, 4, 2, 1];

/// The scales crops are cut at, largest reduction first: ¼ is left out. A frame pays one decode
/// pass per distinct scale among its windows, and on the street frames ½ and ¼ windows are the
/// ones that mix; without ¼ the passes per frame fall from 1.55 to 1.33 and the decode from 9.1
/// to 6.8 ms (4:4:4), while the ¼ windows' regions cost little more at ½ (BENCHMARKS.md,
/// "A person's crop is its own").
pub const CROP_DENOMINATORS: [u32; 3] = [8, 2, 1];

/// A rectangle of full-resolution pixels, half-open: columns `x0..x1`, rows `y0..y1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl PixelRect {
    /// Pixels in the rectangle.
    pub fn area(&self) -> u64 {
        (self.x1.saturating_sub(self.x0)) as u64 * (self.y1.saturating_sub(self.y0)) as u64
    }
}

/// One decode of an image: a DCT scale and the part of the image to decode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodePlan {
    /// Decode at `1/denominator` of full resolution (1, 2, 4 or 8).
    pub denominator: u32,
    /// The full-resolution pixels the crops read (windows plus the resize filter's margin),
    /// clipped to the image; `None` when no window touches the image (every crop is black).
    pub region: Option<PixelRect>,
}

impl DecodePlan {
    /// Full resolution, whole image.
    pub fn full(width: u32, height: u32) -> DecodePlan {
        DecodePlan { denominator: 1, region: Some(PixelRect { x0: 0, y0: 0, x1: width, y1: height }) }
    }

    /// The same scale over the whole image (`POSEFUSE_DECODE=full`): the crops' pixels are the
    /// same, only more of the image is decoded.
    pub fn whole_image(self, width: u32, height: u32) -> DecodePlan {
        DecodePlan { region: self.region.map(|_| PixelRect { x0: 0, y0: 0, x1: width, y1: height }), ..self }
    }
}

/// One decode pass and the windows (indices into the planned slice) cut from it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DecodePass {
    pub plan: DecodePlan,
    pub windows: Vec<usize>,
}

/// The crop window `t` on an image decoded at `1/denominator`.
pub fn scaled(t: &CropTransform, denominator: u32) -> CropTransform {
    let d = denominator.max(1) as f64;
    CropTransform { x0: t.x0 / d, y0: t.y0 / d, scale: t.scale * d, size: t.size }
}

/// Whether `t` is a window `crop_rgb` cuts from the image at all (finite, not absurdly large,
/// overlapping it); other windows give black crops at any scale and constrain nothing.
fn usable(t: &CropTransform, width: u32, height: u32) -> bool {
    let side = t.side();
    let (w, h) = (width as f64, height as f64);
    let limit = 16.0 * w.max(h).max(1.0);
    t.x0.is_finite()
        && t.y0.is_finite()
        && side.is_finite()
        && side > 0.0
        && side <= limit
        && t.x0 < w
        && t.y0 < h
        && t.x0 + side > 0.0
        && t.y0 + side > 0.0
}

/// The largest reduction of [`CROP_DENOMINATORS`] at which window `t` keeps at least its output
/// size `S` in decoded pixels (`side / d ≥ S`): a function of the window alone.
pub fn window_denominator(t: &CropTransform) -> u32 {
    CROP_DENOMINATORS.into_iter().find(|&d| t.side() / d as f64 >= t.size as f64).unwrap_or(1)
}

/// The plan for crop windows `windows` that share one DCT scale on a `width`×`height` image:
/// the largest reduction every usable window allows, and the union of the windows'
/// full-resolution reads. [`plan_passes`] groups a frame's windows so that each keeps its own.
pub fn plan_decode(windows: &[CropTransform], width: u32, height: u32) -> DecodePlan {
    let used: Vec<&CropTransform> = windows.iter().filter(|t| usable(t, width, height)).collect();
    if used.is_empty() {
        return DecodePlan { denominator: 1, region: None };
    }
    let denominator = used.iter().map(|t| window_denominator(t)).min().unwrap_or(1);
    DecodePlan { denominator, region: region_at(&used, denominator, width, height) }
}

/// The full-resolution pixels `crop_rgb` reads for `windows` cut at full resolution (raw pixels:
/// no DCT scale), clipped to the image; `None` when no window touches it.
pub fn pixel_region(windows: &[CropTransform], width: u32, height: u32) -> Option<PixelRect> {
    let used: Vec<&CropTransform> = windows.iter().filter(|t| usable(t, width, height)).collect();
    if used.is_empty() {
        return None;
    }
    region_at(&used, 1, width, height)
}

/// The union of the usable windows' reads on the image decoded at `1/denominator`, in
/// full-resolution pixels, clipped to the image.
fn region_at(used: &[&CropTransform], denominator: u32, width: u32, height: u32) -> Option<PixelRect> {
    let (mut x0, mut y0, mut x1, mut y1) = (i64::MAX, i64::MAX, i64::MIN, i64::MIN);
    for t in used {
        // `crop_rgb`'s read on the scaled image (window plus filter margin), in full-res pixels
        let s = scaled(t, denominator);
        let margin = (1.0 / s.scale).ceil() as i64 + 2;
        let d = denominator as i64;
        x0 = x0.min((s.x0.floor() as i64 - margin) * d);
        y0 = y0.min((s.y0.floor() as i64 - margin) * d);
        x1 = x1.max(((s.x0 + s.side()).ceil() as i64 + margin) * d);
        y1 = y1.max(((s.y0 + s.side()).ceil() as i64 + margin) * d);
    }
    let clip = |v: i64, n: u32| v.clamp(0, n as i64) as u32;
    let region = PixelRect { x0: clip(x0, width), y0: clip(y0, height), x1: clip(x1, width), y1: clip(y1, height) };
    (region.area() > 0).then_some(region)
}

/// The decode passes for a frame's crop windows: one per DCT scale that some usable window
/// needs (each window at its own [`window_denominator`]), largest reduction first. Windows that
/// miss the image are in no pass (their crops are black).
pub fn plan_passes(windows: &[CropTransform], width: u32, height: u32) -> Vec<DecodePass> {
    let mut passes = Vec::new();
    for d in CROP_DENOMINATORS {
        let members: Vec<usize> = (0..windows.len())
            .filter(|&i| usable(&windows[i], width, height) && window_denominator(&windows[i]) == d)
            .collect();
        if members.is_empty() {
            continue;
        }
        let group: Vec<CropTransform> = members.iter().map(|&i| windows[i]).collect();
        passes.push(DecodePass { plan: plan_decode(&group, width, height), windows: members });
    }
    passes
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::Box2d;
    use crate::pipeline::PipelineConfig;

    fn window(cx: f64, cy: f64, side: f64, s: u32) -> CropTransform {
        CropTransform { x0: cx - side / 2.0, y0: cy - side / 2.0, scale: s as f64 / side, size: s }
    }

    #[test]
    fn the_smallest_window_sets_the_scale() {
        // S = 64: a 300 px window allows 1/4 (75 ≥ 64) but not 1/8 (37.5 < 64); crops are not cut
        // at 1/4 (`CROP_DENOMINATORS`), so it gets 1/2
        assert_eq!(plan_decode(&[window(500.0, 500.0, 300.0, 64)], 1920, 1280).denominator, 2);
        assert_eq!(plan_decode(&[window(500.0, 500.0, 511.9, 64)], 1920, 1280).denominator, 2);
        assert_eq!(plan_decode(&[window(500.0, 500.0, 512.0, 64)], 1920, 1280).denominator, 8);
        assert_eq!(plan_decode(&[window(500.0, 500.0, 128.0, 64)], 1920, 1280).denominator, 2);
        assert_eq!(plan_decode(&[window(500.0, 500.0, 127.9, 64)], 1920, 1280).denominator, 1);
        // windows planned together share the finest scale among them...
        let both = [window(500.0, 500.0, 512.0, 64), window(1500.0, 300.0, 140.0, 64)];
        assert_eq!(plan_decode(&both, 1920, 1280).denominator, 2);
        // ...but a frame's passes give each window its own
        let passes = plan_passes(&both, 1920, 1280);
        let scales: Vec<(u32, Vec<usize>)> = passes.iter().map(|p| (p.plan.denominator, p.windows.clone())).collect();
        assert_eq!(scales, vec![(8, vec![0]), (2, vec![1])]);
    }

    #[test]
    fn a_windows_pass_and_scale_do_not_depend_on_the_other_windows() {
        let me = window(700.0, 600.0, 300.0, 64);
        let alone = plan_passes(&[me], 1920, 1280);
        assert_eq!(alone.len(), 1);
        assert_eq!(alone[0].plan.denominator, window_denominator(&me));
        let crowd =
            [window(100.0, 100.0, 70.0, 64), me, window(1500.0, 900.0, 900.0, 64), window(1200.0, 300.0, 280.0, 64)];
        let passes = plan_passes(&crowd, 1920, 1280);
        let mine = passes.iter().find(|p| p.windows.contains(&1)).unwrap();
        assert_eq!(mine.plan.denominator, alone[0].plan.denominator);
        // its region holds its own read (the union of the pass's windows)
        let (r, own) = (mine.plan.region.unwrap(), alone[0].plan.region.unwrap());
        assert!(r.x0 <= own.x0 && r.y0 <= own.y0 && r.x1 >= own.x1 && r.y1 >= own.y1, "{r:?} vs {own:?}");
        // every usable window is in exactly one pass, passes are distinct scales, coarsest first
        let mut seen: Vec<usize> = passes.iter().flat_map(|p| p.windows.clone()).collect();
        seen.sort();
        assert_eq!(seen, vec![0, 1, 2, 3]);
        let ds: Vec<u32> = passes.iter().map(|p| p.plan.denominator).collect();
        assert!(ds.windows(2).all(|w| w[0] > w[1]), "{ds:?}");
    }

    #[test]
    fn every_window_keeps_at_least_s_decoded_pixels() {
        let cfg = PipelineConfig::with_image_size(64);
        for h in [20.0, 60.0, 107.0, 110.0, 250.0, 433.0, 900.0] {
            let b = Box2d { center_x: 900.0, center_y: 600.0, width: h / 3.0, height: h };
            let t = CropTransform::for_box(&b, &cfg);
            let p = plan_decode(&[t], 1920, 1280);
            let s = scaled(&t, p.denominator);
            assert!(s.side() >= 64.0 - 1e-9 || p.denominator == 1, "box {h}: side {} at 1/{}", s.side(), p.denominator);
            // and the next coarser crop scale would not
            let next = CROP_DENOMINATORS.iter().rev().find(|&&d| d > p.denominator);
            assert!(next.is_none_or(|&d| t.side() / (d as f64) < 64.0), "box {h}");
        }
    }

    #[test]
    fn the_region_covers_every_window_and_its_filter_margin_and_stays_in_the_image() {
        let a = window(300.0, 400.0, 200.0, 64);
        let b = window(1200.0, 900.0, 150.0, 64);
        let p = plan_decode(&[a, b], 1920, 1280);
        assert_eq!(p.denominator, 2);
        let r = p.region.unwrap();
        for t in [a, b] {
            assert!(r.x0 as f64 <= t.x0 - 2.0 && r.y0 as f64 <= t.y0 - 2.0);
            assert!(r.x1 as f64 >= t.x0 + t.side() + 2.0 && r.y1 as f64 >= t.y0 + t.side() + 2.0);
        }
        // not much more than the windows' bounding box (margin of a few pixels)
        assert!(r.x0 >= 190 && r.y0 >= 290 && r.x1 <= 1290 && r.y1 <= 990, "{r:?}");
        // a window hanging off the corner is clipped
        let edge = plan_decode(&[window(10.0, 10.0, 200.0, 64)], 1920, 1280).region.unwrap();
        assert_eq!((edge.x0, edge.y0), (0, 0));
        assert!(edge.x1 < 200 && edge.y1 < 200);
    }

    #[test]
    fn the_whole_image_plan_keeps_the_scale() {
        let p = plan_decode(&[window(900.0, 600.0, 600.0, 64)], 1920, 1280);
        let w = p.whole_image(1920, 1280);
        assert_eq!((w.denominator, w.region), (8, Some(PixelRect { x0: 0, y0: 0, x1: 1920, y1: 1280 })));
        let none = DecodePlan { denominator: 1, region: None };
        assert_eq!(none.whole_image(1920, 1280), none);
    }

    #[test]
    fn windows_that_miss_the_image_constrain_nothing() {
        let off = window(-500.0, 300.0, 100.0, 64);
        let nan = CropTransform { x0: f64::NAN, ..off };
        assert_eq!(plan_decode(&[off, nan], 1920, 1280), DecodePlan { denominator: 1, region: None });
        assert!(plan_passes(&[off, nan], 1920, 1280).is_empty());
        // a window of no size (an infinite scale) inside the image cuts nothing either
        let empty = CropTransform { x0: 500.0, y0: 300.0, scale: f64::INFINITY, size: 64 };
        assert_eq!(empty.side(), 0.0);
        assert_eq!(plan_decode(&[empty], 1920, 1280), DecodePlan { denominator: 1, region: None });
        assert!(plan_passes(&[empty], 1920, 1280).is_empty());
        let big = window(900.0, 600.0, 600.0, 64);
        assert_eq!(plan_decode(&[off, big], 1920, 1280).denominator, 8);
        assert_eq!(plan_decode(&[], 1920, 1280).region, None);
    }

    #[test]
    fn a_scaled_window_maps_the_same_scene_point_to_the_same_model_pixel() {
        let t = window(701.3, 455.9, 333.0, 64);
        for d in DCT_DENOMINATORS {
            let s = scaled(&t, d);
            let p = [812.5, 520.25];
            let a = t.to_model(p);
            let b = s.to_model([p[0] / d as f64, p[1] / d as f64]);
            assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
        }
    }
}
