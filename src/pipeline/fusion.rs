//! Modality fusion (paper sec. 3.2): smooth the camera network's heatmaps with a Gaussian and
//! sample each point's cell, giving every LiDAR point K camera features.

use super::PipelineConfig;

/// A `size × size` Gaussian with standard deviation `sigma` (cells), normalized to sum 1,
/// row-major.
pub fn gaussian_kernel(size: u32, sigma: f32) -> Vec<f32> {
    let g = gaussian_1d(size, sigma);
    g.iter().flat_map(|a| g.iter().map(move |b| a * b)).collect()
}

/// The separable factor of [`gaussian_kernel`]: the 2D kernel is its outer product.
fn gaussian_1d(size: u32, sigma: f32) -> Vec<f32> {
    let c = (size as f64 - 1.0) / 2.0;
    let s2 = 2.0 * (sigma as f64) * (sigma as f64);
    let g: Vec<f64> = (0..size).map(|i| (-(i as f64 - c).powi(2) / s2).exp()).collect();
    let sum: f64 = g.iter().sum();
    g.iter().map(|v| (v / sum) as f32).collect()
}

/// Each of the `k` channels of `heatmaps` (`[k, h, w]`) convolved with the Gaussian of `cfg`,
/// zero-padded, same size.
pub fn smooth_heatmaps(heatmaps: &[f32], k: usize, h: usize, w: usize, cfg: &PipelineConfig) -> Vec<f32> {
    let g = gaussian_1d(cfg.smoothing_kernel, cfg.smoothing_sigma);
    let r = g.len() / 2;
    let mut tmp = vec![0.0f32; h * w];
    let mut out = vec![0.0f32; k * h * w];
    for c in 0..k {
        let src = &heatmaps[c * h * w..(c + 1) * h * w];
        // rows
        for i in 0..h {
            let row = &src[i * w..(i + 1) * w];
            for j in 0..w {
                let lo = j.saturating_sub(r);
                let hi = (j + r).min(w - 1);
                let mut acc = 0.0;
                for (jj, v) in row.iter().enumerate().take(hi + 1).skip(lo) {
                    acc += v * g[jj + r - j];
                }
                tmp[i * w + j] = acc;
            }
        }
        // columns
        let dst = &mut out[c * h * w..(c + 1) * h * w];
        for i in 0..h {
            let lo = i.saturating_sub(r);
            let hi = (i + r).min(h - 1);
            let d = &mut dst[i * w..(i + 1) * w];
            for ii in lo..=hi {
                let wgt = g[ii + r - i];
                for (o, v) in d.iter_mut().zip(&tmp[ii * w..(ii + 1) * w]) {
                    *o += wgt * v;
                }
            }
        }
    }
    out
}

/// The heatmap cell of a model-input pixel coordinate: `floor(x · W'/S + 0.5)`, clamped.
pub fn cell_index(x: f32, cells: usize, image_size: u32) -> usize {
    let m = (x * cells as f32 / image_size as f32 + 0.5).floor();
    m.clamp(0.0, (cells - 1) as f32) as usize
}

/// `[N, K]` features: every point's cell in every smoothed channel; a point without a projection
/// (NaN) gets zeros.
pub fn sample_features(smoothed: &[f32], k: usize, h: usize, w: usize, uv: &[[f32; 2]], image_size: u32) -> Vec<f32> {
    let mut out = vec![0.0f32; uv.len() * k];
    for (n, p) in uv.iter().enumerate() {
        if !(p[0].is_finite() && p[1].is_finite()) {
            continue;
        }
        let (i, j) = (cell_index(p[1], h, image_size), cell_index(p[0], w, image_size));
        for c in 0..k {
            out[n * k + c] = smoothed[c * h * w + i * w + j];
        }
    }
    out
}

/// [`smooth_heatmaps`] followed by [`sample_features`], computing the smoothed value only at the
/// sampled cells (N·K·(k+k) taps instead of K·H·W·2k), with the same summation order, so the
/// result is bit-identical.
pub fn smoothed_features(
    heatmaps: &[f32],
    k: usize,
    h: usize,
    w: usize,
    uv: &[[f32; 2]],
    cfg: &PipelineConfig,
) -> Vec<f32> {
    let g = gaussian_1d(cfg.smoothing_kernel, cfg.smoothing_sigma);
    let r = g.len() / 2;
    let mut out = vec![0.0f32; uv.len() * k];
    let mut cache: std::collections::HashMap<(usize, usize), usize> = std::collections::HashMap::new();
    for (n, p) in uv.iter().enumerate() {
        if !(p[0].is_finite() && p[1].is_finite()) {
            continue;
        }
        let (i, j) = (cell_index(p[1], h, cfg.image_size), cell_index(p[0], w, cfg.image_size));
        if let Some(&done) = cache.get(&(i, j)) {
            out.copy_within(done * k..(done + 1) * k, n * k);
            continue;
        }
        cache.insert((i, j), n);
        let (jlo, jhi) = (j.saturating_sub(r), (j + r).min(w - 1));
        let (ilo, ihi) = (i.saturating_sub(r), (i + r).min(h - 1));
        for c in 0..k {
            let src = &heatmaps[c * h * w..(c + 1) * h * w];
            let mut acc = 0.0f32;
            for ii in ilo..=ihi {
                let row = &src[ii * w..(ii + 1) * w];
                let mut rs = 0.0f32;
                for jj in jlo..=jhi {
                    rs += row[jj] * g[jj + r - j];
                }
                acc += g[ii + r - i] * rs;
            }
            out[n * k + c] = acc;
        }
    }
    out
}

/// `[N, 3 + K]` point-network input: each point's coordinates followed by its camera features.
pub fn fused_points(xyz: &[[f32; 3]], features: &[f32], k: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(xyz.len() * (3 + k));
    for (n, p) in xyz.iter().enumerate() {
        out.extend_from_slice(p);
        out.extend_from_slice(&features[n * k..(n + 1) * k]);
    }
    out
}

/// The point-network input without camera features.
pub fn lidar_points(xyz: &[[f32; 3]]) -> Vec<f32> {
    xyz.iter().flatten().copied().collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernel_sums_to_one_and_is_symmetric_with_the_peak_in_the_middle() {
        let g = gaussian_kernel(7, 3.0);
        assert_eq!(g.len(), 49);
        assert!((g.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert!(g.iter().all(|&v| v <= g[24]));
        assert!((g[0] - g[48]).abs() < 1e-9 && (g[3] - g[21]).abs() < 1e-9);
        // neighbour ratio exp(−1/(2σ²)) along a row
        assert!((g[25] / g[24] - (-1.0f32 / 18.0).exp()).abs() < 1e-6);
    }

    #[test]
    fn smoothing_a_delta_gives_the_kernel_and_zero_padding_loses_mass_at_edges() {
        let cfg = PipelineConfig::default();
        let (h, w) = (9, 9);
        let mut hm = vec![0.0; h * w];
        hm[4 * w + 4] = 1.0;
        let s = smooth_heatmaps(&hm, 1, h, w, &cfg);
        let g = gaussian_kernel(7, 3.0);
        for di in 0..7 {
            for dj in 0..7 {
                assert!((s[(1 + di) * w + 1 + dj] - g[di * 7 + dj]).abs() < 1e-6);
            }
        }
        let mut corner = vec![0.0; h * w];
        corner[0] = 1.0;
        let s = smooth_heatmaps(&corner, 1, h, w, &cfg);
        let inside: f32 = g.iter().enumerate().filter(|(i, _)| i / 7 >= 3 && i % 7 >= 3).map(|(_, v)| v).sum();
        assert!((s.iter().sum::<f32>() - inside).abs() < 1e-6);
    }

    #[test]
    fn sampling_rounds_per_the_paper_and_clamps() {
        // S = 64, W' = 16: x = 2.0 → 0.5 → cell 1; x = 1.99 → cell 0; x = 63.9 → 16.475 → clamp 15.
        assert_eq!(cell_index(2.0, 16, 64), 1);
        assert_eq!(cell_index(1.99, 16, 64), 0);
        assert_eq!(cell_index(63.9, 16, 64), 15);
        assert_eq!(cell_index(-10.0, 16, 64), 0);
        let (k, h, w) = (2, 4, 4);
        let hm: Vec<f32> = (0..k * h * w).map(|v| v as f32).collect();
        let f = sample_features(&hm, k, h, w, &[[9.0, 4.0], [f32::NAN, 1.0]], 16);
        // x = 9 → 2.25+0.5 → col 2; y = 4 → 1.5 → row 1
        assert_eq!(f, vec![6.0, 22.0, 0.0, 0.0]);
        let cfg =
            PipelineConfig { image_size: 16, smoothing_kernel: 3, smoothing_sigma: 1.0, ..PipelineConfig::default() };
        let uv = [[9.0, 4.0], [f32::NAN, 1.0], [0.0, 15.0], [9.2, 4.1]];
        let lazy = smoothed_features(&hm, k, h, w, &uv, &cfg);
        assert_eq!(lazy, sample_features(&smooth_heatmaps(&hm, k, h, w, &cfg), k, h, w, &uv, 16));
        assert_eq!(
            fused_points(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], &f, k),
            vec![1., 2., 3., 6., 22., 4., 5., 6., 0., 0.]
        );
    }
}
