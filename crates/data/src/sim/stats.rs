//! Realism statistics of a generated set: LiDAR points per pedestrian by range band against what
//! the 64-beam geometry implies, how often a visible keypoint has a LiDAR point near it in 2D
//! (the paper's assumption for pseudo labels), and how many keypoints are occluded.

use serde::Serialize;

use super::dataset::SampleStats;
use super::lidar::{inclinations, COLUMNS};
use super::world::LIDAR_ORIGIN;
use posefuse_core::keypoints::K;

/// Range bands of the realism table (metres).
pub const BANDS: [(f64, f64); 4] = [(3.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0)];

/// Points the beam geometry puts on an upright 1.7 m × 0.5 m person at horizontal range `r`
/// (before dropouts): beams whose inclination crosses the person × columns across its width.
pub fn expected_points(r: f64) -> f64 {
    let (feet, head) = ((-LIDAR_ORIGIN[2]).atan2(r), (1.7 - LIDAR_ORIGIN[2]).atan2(r));
    let beams = inclinations().iter().filter(|&&e| e >= feet && e <= head).count() as f64;
    let columns = (0.5 / r) / (std::f64::consts::TAU / COLUMNS as f64);
    beams * columns
}

#[derive(Debug, Serialize)]
pub struct Band {
    pub range_m: String,
    pub persons: usize,
    pub mean_person_points: f64,
    pub median_person_points: f64,
    pub mean_in_box_points: f64,
    pub expected_points_geometry: f64,
    pub visible_keypoints_with_point_near: f64,
    pub occluded_keypoints: f64,
}

#[derive(Debug, Serialize)]
pub struct Report {
    pub samples: usize,
    /// Radius (model-input pixels) of the "LiDAR point near the keypoint" test.
    pub near_px: f64,
    pub bands: Vec<Band>,
    pub visible_keypoints_with_point_near: f64,
    /// Keypoints inside the image that are occluded.
    pub occluded_keypoints: f64,
    pub keypoints_outside_image: f64,
    pub persons_without_points: f64,
    pub activities: Vec<(String, usize)>,
}

fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 {
        f64::NAN
    } else {
        a as f64 / b as f64
    }
}

fn keypoint_counts(st: &[&SampleStats]) -> (usize, usize, usize, usize, usize) {
    let (mut vis, mut vis_near, mut in_img, mut occl, mut total) = (0, 0, 0, 0, 0);
    for s in st {
        for k in 0..K {
            total += 1;
            if s.in_image[k] {
                in_img += 1;
                if !s.visible_2d[k] {
                    occl += 1;
                }
            }
            if s.visible_2d[k] {
                vis += 1;
                if s.near_point[k] {
                    vis_near += 1;
                }
            }
        }
    }
    (vis, vis_near, in_img, occl, total)
}

/// Summarizes the statistics of all samples.
pub fn report(stats: &[SampleStats], near_px: f64) -> Report {
    let all: Vec<&SampleStats> = stats.iter().collect();
    let bands = BANDS
        .iter()
        .map(|&(lo, hi)| {
            let sel: Vec<&SampleStats> = stats.iter().filter(|s| s.range_m >= lo && s.range_m < hi).collect();
            let n = sel.len();
            let mut pts: Vec<usize> = sel.iter().map(|s| s.person_points).collect();
            pts.sort_unstable();
            let mean = |f: &dyn Fn(&SampleStats) -> f64| {
                if n == 0 {
                    f64::NAN
                } else {
                    sel.iter().map(|s| f(s)).sum::<f64>() / n as f64
                }
            };
            let (vis, vis_near, in_img, occl, _) = keypoint_counts(&sel);
            Band {
                range_m: format!("{lo:.0}-{hi:.0}"),
                persons: n,
                mean_person_points: mean(&|s| s.person_points as f64),
                median_person_points: if n == 0 { f64::NAN } else { pts[n / 2] as f64 },
                mean_in_box_points: mean(&|s| s.in_box_points as f64),
                expected_points_geometry: mean(&|s| expected_points(s.range_m)),
                visible_keypoints_with_point_near: ratio(vis_near, vis),
                occluded_keypoints: ratio(occl, in_img),
            }
        })
        .collect();
    let (vis, vis_near, in_img, occl, total) = keypoint_counts(&all);
    let mut activities: Vec<(String, usize)> = Vec::new();
    for s in stats {
        match activities.iter_mut().find(|(a, _)| a == s.activity) {
            Some((_, c)) => *c += 1,
            None => activities.push((s.activity.to_string(), 1)),
        }
    }
    activities.sort();
    Report {
        samples: stats.len(),
        near_px,
        bands,
        visible_keypoints_with_point_near: ratio(vis_near, vis),
        occluded_keypoints: ratio(occl, in_img),
        keypoints_outside_image: ratio(total - in_img, total),
        persons_without_points: ratio(stats.iter().filter(|s| s.in_box_points == 0).count(), stats.len()),
        activities,
    }
}

impl Report {
    /// The realism table as Markdown.
    pub fn markdown(&self) -> String {
        let mut s = String::from(
            "| range (m) | persons | LiDAR points on person (mean / median) | in-box points (mean) | 64-beam geometry (1.7 m × 0.5 m) | visible kp with a point ≤ r px | occluded kp |\n|---|---|---|---|---|---|---|\n",
        );
        for b in &self.bands {
            s += &format!(
                "| {} | {} | {:.0} / {:.0} | {:.0} | {:.0} | {:.1}% | {:.1}% |\n",
                b.range_m,
                b.persons,
                b.mean_person_points,
                b.median_person_points,
                b.mean_in_box_points,
                b.expected_points_geometry,
                100.0 * b.visible_keypoints_with_point_near,
                100.0 * b.occluded_keypoints
            );
        }
        s += &format!(
            "\nAll: {} persons; visible keypoints with a LiDAR point within r = {:.1} px: {:.1}%; occluded keypoints (in image): {:.1}%; outside the image: {:.1}%; persons without points: {:.2}%\n",
            self.samples,
            self.near_px,
            100.0 * self.visible_keypoints_with_point_near,
            100.0 * self.occluded_keypoints,
            100.0 * self.keypoints_outside_image,
            100.0 * self.persons_without_points
        );
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geometry_expectation_falls_with_range() {
        let near = expected_points(8.0);
        let far = expected_points(50.0);
        assert!(near > 10.0 * far, "{near} vs {far}");
        // At 20 m: 0.5 m is 0.025 rad = 10.5 columns of 0.136°.
        let cols = (0.5f64 / 20.0) / (std::f64::consts::TAU / 2650.0);
        assert!((cols - 10.54).abs() < 0.01);
        assert!((expected_points(20.0) / cols).fract() == 0.0);
    }
}
