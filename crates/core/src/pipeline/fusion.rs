//! Modality fusion (paper sec. 3.2): smooth the camera network's heatmaps with a Gaussian and
//! sample each point's cell, giving every LiDAR point K camera features.

use super::{PipelineConfig, Sampling};
use crate::keypoints::K;

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
    if w == 0 {
        return out;
    }
    for c in 0..k {
        let src = &heatmaps[c * h * w..(c + 1) * h * w];
        // rows, a tap at a time over the whole row (so that it vectorises); each cell still sums
        // its taps left to right from zero, as a loop per cell would
        for (row, t) in src.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
            t.fill(0.0);
            for (tap, wgt) in g.iter().enumerate() {
                // cell j reads row[j + tap − r] where that lies inside the row
                let (from, to) = if tap >= r { (tap - r, 0) } else { (0, r - tap) };
                if from >= w || to >= w {
                    continue;
                }
                let n = w - from.max(to);
                for (o, v) in t[to..to + n].iter_mut().zip(&row[from..from + n]) {
                    *o += v * wgt;
                }
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
    let cells: Vec<Option<(usize, usize)>> = uv
        .iter()
        .map(|p| {
            (p[0].is_finite() && p[1].is_finite())
                .then(|| (cell_index(p[1], h, cfg.image_size), cell_index(p[0], w, cfg.image_size)))
        })
        .collect();
    // Row-smoothed values are shared by vertically neighbouring cells: each is computed once,
    // for all channels, within the window the points need.
    let Some((i0, i1, j0, j1)) =
        cells.iter().flatten().fold(None, |b: Option<(usize, usize, usize, usize)>, &(i, j)| {
            Some(b.map_or((i, i, j, j), |(a0, a1, b0, b1)| (a0.min(i), a1.max(i), b0.min(j), b1.max(j))))
        })
    else {
        return out;
    };
    let (i0, i1) = (i0.saturating_sub(r), (i1 + r).min(h - 1));
    let bw = j1 - j0 + 1;
    let window = (i1 - i0 + 1) * bw;
    let mut row_smoothed = vec![0.0f32; window * k];
    let mut smoothed_done = vec![false; window];
    // points falling in one cell share its features: the first such point's row, per cell
    let mut first = vec![u32::MAX; window];
    for (n, cell) in cells.iter().enumerate() {
        let Some((i, j)) = *cell else { continue };
        let done = first[(i - i0) * bw + j - j0] as usize;
        if done < n {
            out.copy_within(done * k..(done + 1) * k, n * k);
            continue;
        }
        first[(i - i0) * bw + j - j0] = n as u32;
        let (jlo, jhi) = (j.saturating_sub(r), (j + r).min(w - 1));
        let (ilo, ihi) = (i.saturating_sub(r), (i + r).min(h - 1));
        let (gx, gy) = (&g[jlo + r - j..=jhi + r - j], &g[ilo + r - i..=ihi + r - i]);
        for (ii, wy) in (ilo..=ihi).zip(gy) {
            let at = (ii - i0) * bw + j - j0;
            let rows = &mut row_smoothed[at * k..(at + 1) * k];
            if !smoothed_done[at] {
                smoothed_done[at] = true;
                for (c, v) in rows.iter_mut().enumerate() {
                    let row = &heatmaps[c * h * w + ii * w + jlo..=c * h * w + ii * w + jhi];
                    *v = row.iter().zip(gx).fold(0.0f32, |s, (x, wx)| s + x * wx);
                }
            }
            for (o, v) in out[n * k..(n + 1) * k].iter_mut().zip(rows.iter()) {
                *o += wy * v;
            }
        }
    }
    out
}

/// The K camera features of each point of a person (paper sec. 3.2): the camera network's
/// `heatmaps` (`[K, H, H]`, `H = cfg.heatmap_size`) smoothed and sampled at the points'
/// model-input pixels `uv`, `[N, K]`.
pub fn fusion_features(heatmaps: &[f32], uv: &[[f32; 2]], cfg: &PipelineConfig) -> Vec<f32> {
    let h = cfg.heatmap_size as usize;
    match cfg.sampling {
        Sampling::Nearest => smoothed_features(heatmaps, K, h, h, uv, cfg),
        Sampling::Bilinear => sample_bilinear(&smooth_heatmaps(heatmaps, K, h, h, cfg), K, h, h, uv, cfg.image_size),
    }
}

/// The lower of the two cells around model-input pixel `x` and the weight of the upper one:
/// `c = x · W'/S` clamped to `[0, W' − 1]` (cell `j`'s centre is at `x = j · S/W'`, as
/// [`cell_index`] rounds to it).
pub fn bilinear_cell(x: f32, cells: usize, image_size: u32) -> (usize, f32) {
    let c = (x * cells as f32 / image_size as f32).clamp(0.0, (cells - 1) as f32);
    let lo = c.floor().min(cells.saturating_sub(2) as f32);
    (lo as usize, c - lo)
}

/// `[N, K]` features interpolated between the four smoothed cells around each point (rows, then
/// the two rows blended); a point without a projection (NaN) gets zeros.
pub fn sample_bilinear(smoothed: &[f32], k: usize, h: usize, w: usize, uv: &[[f32; 2]], image_size: u32) -> Vec<f32> {
    let mut out = vec![0.0f32; uv.len() * k];
    for (n, p) in uv.iter().enumerate() {
        if !(p[0].is_finite() && p[1].is_finite()) {
            continue;
        }
        let ((i0, ty), (j0, tx)) = (bilinear_cell(p[1], h, image_size), bilinear_cell(p[0], w, image_size));
        let (i1, j1) = ((i0 + 1).min(h - 1), (j0 + 1).min(w - 1));
        for c in 0..k {
            let at = |i: usize, j: usize| smoothed[c * h * w + i * w + j];
            let top = (1.0 - tx) * at(i0, j0) + tx * at(i0, j1);
            let bottom = (1.0 - tx) * at(i1, j0) + tx * at(i1, j1);
            out[n * k + c] = (1.0 - ty) * top + ty * bottom;
        }
    }
    out
}

/// The fusion point-network input `[N, 3 + K]` of a person from its camera network's
/// `heatmaps`: [`fusion_features`] at `uv` beside each point's `xyz`. The serving path, the
/// benchmarks and the load bench all build it here.
pub fn fusion_input(heatmaps: &[f32], xyz: &[[f32; 3]], uv: &[[f32; 2]], cfg: &PipelineConfig) -> Vec<f32> {
    fused_points(xyz, &fusion_features(heatmaps, uv, cfg), K)
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

    /// Each cell's taps summed one by one, the plain way: what [`smooth_heatmaps`] must equal bit
    /// for bit.
    fn smoothed_cell_by_cell(hm: &[f32], k: usize, h: usize, w: usize, g: &[f32]) -> Vec<f32> {
        let r = g.len() / 2;
        let mut out = vec![0.0f32; k * h * w];
        for c in 0..k {
            let mut tmp = vec![0.0f32; h * w];
            for i in 0..h {
                for j in 0..w {
                    let mut acc = 0.0;
                    for jj in j.saturating_sub(r)..=(j + r).min(w - 1) {
                        acc += hm[c * h * w + i * w + jj] * g[jj + r - j];
                    }
                    tmp[i * w + j] = acc;
                }
            }
            for i in 0..h {
                for j in 0..w {
                    let mut acc = 0.0;
                    for ii in i.saturating_sub(r)..=(i + r).min(h - 1) {
                        acc += g[ii + r - i] * tmp[ii * w + j];
                    }
                    out[c * h * w + i * w + j] = acc;
                }
            }
        }
        out
    }

    #[test]
    fn smoothing_a_tap_at_a_time_equals_summing_each_cell_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        // grids narrower and shorter than the kernel, square and not
        let grids = [(13, 32, 32, 5, 1.5), (2, 9, 3, 7, 3.0), (1, 2, 11, 7, 2.0), (3, 1, 1, 3, 1.0), (1, 3, 1, 7, 2.0)];
        for (k, h, w, size, sigma) in grids {
            let cfg = PipelineConfig { smoothing_kernel: size, smoothing_sigma: sigma, ..PipelineConfig::default() };
            let hm: Vec<f32> = (0..k * h * w).map(|_| rng.random::<f32>()).collect();
            let want = smoothed_cell_by_cell(&hm, k, h, w, &gaussian_1d(size, sigma));
            assert_eq!(smooth_heatmaps(&hm, k, h, w, &cfg), want, "{k}×{h}×{w}, kernel {size}");
        }
        assert!(smooth_heatmaps(&[], 2, 4, 0, &PipelineConfig::default()).is_empty());
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
        // without the camera: the coordinates alone, in the same order
        assert_eq!(lidar_points(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), vec![1., 2., 3., 4., 5., 6.]);
    }

    #[test]
    fn smoothing_only_the_sampled_cells_equals_smoothing_everything() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (k, h, w) = (13, 16, 16);
        let cfg =
            PipelineConfig { image_size: 64, smoothing_kernel: 7, smoothing_sigma: 3.0, ..PipelineConfig::default() };
        let hm: Vec<f32> = (0..k * h * w).map(|_| rng.random::<f32>()).collect();
        // corners, edges, repeated cells, points outside the crop and without a projection
        let mut uv: Vec<[f32; 2]> =
            (0..300).map(|_| [rng.random_range(-8.0..72.0), rng.random_range(-8.0..72.0)]).collect();
        uv.extend([[0.0, 0.0], [63.9, 63.9], [0.0, 63.9], [f32::NAN, 3.0], [f32::INFINITY, 1.0], [10.0, 10.0]]);
        let lazy = smoothed_features(&hm, k, h, w, &uv, &cfg);
        assert_eq!(lazy, sample_features(&smooth_heatmaps(&hm, k, h, w, &cfg), k, h, w, &uv, 64));
        assert!(lazy.iter().any(|v| *v != 0.0));
    }

    #[test]
    fn smoothing_only_the_sampled_cells_equals_smoothing_everything_in_any_band_of_cells() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let (k, h, w) = (13, 16, 16);
        let hm: Vec<f32> = (0..k * h * w).map(|_| rng.random::<f32>()).collect();
        // the window the points need is cut to their rows and columns, plus the kernel's reach
        // where the grid has it: points in the first row or two, in the last, in one column, alone
        let bands: [(std::ops::Range<f32>, std::ops::Range<f32>); 5] = [
            (0.0..64.0, 0.0..4.0),
            (0.0..64.0, 0.0..8.0),
            (0.0..64.0, 60.0..64.0),
            (28.0..32.0, 0.0..64.0),
            (63.0..63.5, 63.0..63.5),
        ];
        for kernel in [3, 5, 7] {
            let cfg = PipelineConfig {
                image_size: 64,
                smoothing_kernel: kernel,
                smoothing_sigma: 3.0,
                ..PipelineConfig::default()
            };
            for (xs, ys) in bands.clone() {
                let uv: Vec<[f32; 2]> =
                    (0..40).map(|_| [rng.random_range(xs.clone()), rng.random_range(ys.clone())]).collect();
                let lazy = smoothed_features(&hm, k, h, w, &uv, &cfg);
                let all = sample_features(&smooth_heatmaps(&hm, k, h, w, &cfg), k, h, w, &uv, 64);
                assert_eq!(lazy, all, "kernel {kernel}, x in {xs:?}, y in {ys:?}");
            }
        }
    }

    #[test]
    fn bilinear_sampling_blends_the_four_cells_around_a_point() {
        // S = 16, W' = 4: cell j's centre is at x = 4j
        assert_eq!(bilinear_cell(6.0, 4, 16), (1, 0.5));
        assert_eq!(bilinear_cell(4.0, 4, 16), (1, 0.0));
        // clamped to the last cell centre, reached from the cell below it
        assert_eq!(bilinear_cell(15.0, 4, 16), (2, 1.0));
        assert_eq!(bilinear_cell(-3.0, 4, 16), (0, 0.0));
        let hm: Vec<f32> = (0..16).map(|v| v as f32).collect();
        let uv = [[6.0, 2.0], [4.0, 4.0], [-3.0, 15.0], [f32::NAN, 1.0], [13.0, 9.0]];
        let f = sample_bilinear(&hm, 1, 4, 4, &uv, 16);
        // (6, 2): cells (0,1)=1 (0,2)=2 (1,1)=5 (1,2)=6, halfway in both → 3.5;
        // (13, 9): x → 3.25 clamps to 3 (col 3), y → 2.25 between rows 2 and 3 → 11 + 0.25·4 = 12
        assert_eq!(f, vec![3.5, 5.0, 12.0, 0.0, 12.0]);
        // on a cell centre it is the nearest cell's value
        let nearest = sample_features(&hm, 1, 4, 4, &[[8.0, 12.0]], 16);
        assert_eq!(sample_bilinear(&hm, 1, 4, 4, &[[8.0, 12.0]], 16), nearest);
        // a second channel is read from its own plane
        let two: Vec<f32> = (0..32).map(|v| v as f32).collect();
        assert_eq!(sample_bilinear(&two, 2, 4, 4, &[[6.0, 2.0], [4.0, 4.0]], 16), vec![3.5, 19.5, 5.0, 21.0]);
        // a grid one cell high or wide has no second row or column to blend with
        let row = [1.0, 2.0, 3.0, 4.0];
        assert_eq!(sample_bilinear(&row, 1, 1, 4, &[[6.0, 2.0]], 16), vec![2.5]);
        assert_eq!(sample_bilinear(&row, 1, 4, 1, &[[2.0, 6.0], [2.0, 15.0]], 16), vec![2.5, 4.0]);
    }

    #[test]
    fn the_configured_sampling_is_the_one_fusion_uses() {
        let (h, s) = (8usize, 32u32);
        let hm: Vec<f32> = (0..K * h * h).map(|v| (v % 13) as f32).collect();
        let uv = [[5.0, 7.0], [30.0, 1.0]];
        let nearest = PipelineConfig { heatmap_size: 8, ..PipelineConfig::with_image_size(s) };
        let bilinear = PipelineConfig { sampling: Sampling::Bilinear, ..nearest.clone() };
        let smoothed = smooth_heatmaps(&hm, K, h, h, &nearest);
        assert_eq!(fusion_features(&hm, &uv, &nearest), sample_features(&smoothed, K, h, h, &uv, s));
        assert_eq!(fusion_features(&hm, &uv, &bilinear), sample_bilinear(&smoothed, K, h, h, &uv, s));
        assert_ne!(fusion_features(&hm, &uv, &bilinear), fusion_features(&hm, &uv, &nearest));
    }
}
