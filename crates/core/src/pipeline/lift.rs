//! 2D → 3D: the paper's eq. 1 (a softmax over 2D distances averages the 3D points near a 2D
//! keypoint), its reliability, and decoding 2D keypoints from heatmaps.

/// For each 2D keypoint (model px), `Σ_i α_i x_i` with `α = softmax(−T·d²)`, `d` the distance to
/// point i's projection divided by `image_size`. Points without a projection are ignored; with no
/// usable point the result is NaN.
pub fn lift(
    kp_uv: &[[f32; 2]],
    points_uv: &[[f32; 2]],
    points_xyz: &[[f32; 3]],
    image_size: u32,
    temperature: f64,
) -> Vec<[f32; 3]> {
    let s = image_size as f64;
    kp_uv
        .iter()
        .map(|kp| {
            let logits: Vec<Option<f64>> =
                points_uv.iter().map(|p| dist2(kp, p, s).map(|d2| -temperature * d2)).collect();
            let max = logits.iter().flatten().fold(f64::NEG_INFINITY, |a, &b| a.max(b));
            if !max.is_finite() {
                return [f32::NAN; 3];
            }
            let (mut acc, mut total) = ([0.0f64; 3], 0.0f64);
            for (l, x) in logits.iter().zip(points_xyz) {
                if let Some(l) = l {
                    let w = (l - max).exp();
                    total += w;
                    for a in 0..3 {
                        acc[a] += w * x[a] as f64;
                    }
                }
            }
            acc.map(|v| (v / total) as f32)
        })
        .collect()
}

/// `r_k = exp(−T_r · min_i d_ik²)` (same units as [`lift`]); 0 when no point has a projection.
pub fn reliability(kp_uv: &[[f32; 2]], points_uv: &[[f32; 2]], image_size: u32, t_r: f64) -> Vec<f32> {
    let s = image_size as f64;
    kp_uv
        .iter()
        .map(|kp| {
            let m = points_uv.iter().filter_map(|p| dist2(kp, p, s)).fold(f64::INFINITY, f64::min);
            if m.is_finite() {
                (-t_r * m).exp() as f32
            } else {
                0.0
            }
        })
        .collect()
}

fn dist2(a: &[f32; 2], b: &[f32; 2], s: f64) -> Option<f64> {
    let (dx, dy) = ((a[0] - b[0]) as f64 / s, (a[1] - b[1]) as f64 / s);
    let d2 = dx * dx + dy * dy;
    d2.is_finite().then_some(d2)
}

/// Per channel of `[k, h, w]` heatmaps: the argmax cell moved a quarter cell toward its larger
/// neighbour, in model px (cell (i, j) is centred at (j·S/w, i·S/h)), and the peak value.
pub fn decode_heatmaps(heatmaps: &[f32], k: usize, h: usize, w: usize, image_size: u32) -> Vec<([f32; 2], f32)> {
    (0..k)
        .map(|c| {
            let m = &heatmaps[c * h * w..(c + 1) * h * w];
            let (best, score) =
                m.iter().enumerate().fold((0, f32::NEG_INFINITY), |acc, (i, &v)| if v > acc.1 { (i, v) } else { acc });
            let (i, j) = (best / w, best % w);
            let shift = |lo: Option<f32>, hi: Option<f32>| match (lo, hi) {
                (Some(a), Some(b)) if b > a => 0.25,
                (Some(a), Some(b)) if a > b => -0.25,
                _ => 0.0,
            };
            let dx = shift((j > 0).then(|| m[i * w + j - 1]), (j + 1 < w).then(|| m[i * w + j + 1]));
            let dy = shift((i > 0).then(|| m[(i - 1) * w + j]), (i + 1 < h).then(|| m[(i + 1) * w + j]));
            let sx = image_size as f32 / w as f32;
            let sy = image_size as f32 / h as f32;
            ([(j as f32 + dx) * sx, (i as f32 + dy) * sy], score)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lifting_matches_a_hand_computed_softmax() {
        // S = 10, T = 100: point A at distance 0.1 (d² = 0.01 → logit −1), point B at 0.2 (−4).
        let kp = [[5.0, 5.0]];
        let uv = [[6.0, 5.0], [5.0, 7.0], [f32::NAN, f32::NAN]];
        let xyz = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [100.0, 100.0, 100.0]];
        let out = lift(&kp, &uv, &xyz, 10, 100.0);
        let (wa, wb) = ((-1.0f64).exp(), (-4.0f64).exp());
        let (ea, eb) = (wa / (wa + wb), wb / (wa + wb));
        assert!((out[0][0] as f64 - ea).abs() < 1e-6 && (out[0][1] as f64 - eb).abs() < 1e-6 && out[0][2] == 0.0);
        let r = reliability(&kp, &uv, 10, 2.0);
        assert!((r[0] as f64 - (-0.02f64).exp()).abs() < 1e-6);
        assert!(lift(&kp, &uv[2..], &xyz[2..], 10, 100.0)[0][0].is_nan());
        assert_eq!(reliability(&kp, &uv[2..], 10, 2.0), vec![0.0]);
    }

    #[test]
    fn a_high_temperature_picks_the_nearest_point() {
        let out = lift(&[[0.0, 0.0]], &[[1.0, 0.0], [3.0, 0.0]], &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], 64, 1e7);
        assert_eq!(out[0], [1.0, 2.0, 3.0]);
    }

    #[test]
    fn decoding_finds_the_peak_with_a_quarter_shift() {
        let (h, w) = (4, 4);
        let mut hm = vec![0.0; 3 * h * w];
        hm[w + 2] = 0.9; // channel 0 peak at (1, 2), right neighbour larger than left
        hm[w + 3] = 0.5;
        hm[h * w + 3 * w] = 0.7; // channel 1 peak at (3, 0), corner: no shift

        // channel 2 peak at (2, 1), its left and upper neighbours larger than their opposites
        let c2 = |i: usize, j: usize| 2 * h * w + i * w + j;
        for (i, j, v) in [(2, 1, 0.8), (2, 0, 0.6), (2, 2, 0.1), (1, 1, 0.3), (3, 1, 0.2)] {
            hm[c2(i, j)] = v;
        }
        let d = decode_heatmaps(&hm, 3, h, w, 16);
        assert_eq!(d[0], ([(2.0 + 0.25) * 4.0, 4.0], 0.9));
        assert_eq!(d[1], ([0.0, 12.0], 0.7));
        assert_eq!(d[2], ([(1.0 - 0.25) * 4.0, (2.0 - 0.25) * 4.0], 0.8));
    }
}
