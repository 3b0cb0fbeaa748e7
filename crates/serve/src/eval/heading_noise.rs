//! Box headings made wrong on purpose, as a detector's are: `posefuse eval --heading-noise` turns
//! each request box by a fixed error (random sign) or by a uniformly random angle, so a bundle's
//! dependence on the heading can be measured. Deterministic for a seed.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use posefuse_core::frame::Frame;

/// How request headings are perturbed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HeadingNoise {
    /// Each box turned by this many degrees, clockwise or anticlockwise at random.
    Degrees(f64),
    /// Each box given a uniformly random heading error in [−180°, 180°).
    Uniform,
}

impl std::str::FromStr for HeadingNoise {
    type Err = String;

    fn from_str(s: &str) -> Result<HeadingNoise, String> {
        if s.eq_ignore_ascii_case("uniform") {
            return Ok(HeadingNoise::Uniform);
        }
        match s.parse::<f64>() {
            Ok(d) if d.is_finite() && d >= 0.0 => Ok(HeadingNoise::Degrees(d)),
            _ => Err(format!("`{s}`: expected degrees (a number ≥ 0) or `uniform`")),
        }
    }
}

impl std::fmt::Display for HeadingNoise {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HeadingNoise::Degrees(d) => write!(f, "{d}"),
            HeadingNoise::Uniform => write!(f, "uniform"),
        }
    }
}

impl serde::Serialize for HeadingNoise {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_string())
    }
}

/// Turns every person's 3D box heading in `frames` (in order) by the noise; the 2D boxes and the
/// ground truth stay.
pub fn perturb_headings(frames: &mut [Frame], noise: HeadingNoise, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for frame in frames {
        for person in &mut frame.persons {
            let delta = match noise {
                HeadingNoise::Degrees(d) => {
                    let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
                    sign * d.to_radians()
                }
                HeadingNoise::Uniform => rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
            };
            person.box_3d.heading += delta;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posefuse_core::frame::{Box3d, CameraCalibration, Person, Points, RequestedMode};

    fn frames(n: usize) -> Vec<Frame> {
        let person = |h: f64| Person {
            id: "p".into(),
            camera: None,
            box_2d: None,
            box_3d: Box3d {
                center_x: 5.0,
                center_y: 0.0,
                center_z: 0.9,
                length: 0.6,
                width: 0.7,
                height: 1.8,
                heading: h,
            },
            ground_truth: None,
        };
        (0..n)
            .map(|i| Frame {
                frame_id: None,
                image: None,
                image_rgb: None,
                calibration: Some(CameraCalibration { intrinsic: vec![], extrinsic: vec![], width: 1, height: 1 }),
                cameras: Vec::new(),
                points: Points::Flat(vec![]),
                persons: vec![person(0.1 * i as f64), person(-1.0)],
                mode: RequestedMode::Auto,
            })
            .collect()
    }

    fn deltas(noise: HeadingNoise, seed: u64) -> Vec<f64> {
        let (before, mut after) = (frames(20), frames(20));
        perturb_headings(&mut after, noise, seed);
        before
            .iter()
            .zip(&after)
            .flat_map(|(b, a)| b.persons.iter().zip(&a.persons).map(|(p, q)| q.box_3d.heading - p.box_3d.heading))
            .collect()
    }

    #[test]
    fn fixed_errors_have_their_size_and_both_signs() {
        let d = deltas(HeadingNoise::Degrees(45.0), 3);
        assert!(d.iter().all(|x| (x.abs() - 45f64.to_radians()).abs() < 1e-12), "{d:?}");
        assert!(d.iter().any(|x| *x > 0.0) && d.iter().any(|x| *x < 0.0));
        assert_eq!(deltas(HeadingNoise::Degrees(0.0), 3), vec![0.0; 40]);
        assert_eq!(d, deltas(HeadingNoise::Degrees(45.0), 3), "same seed, same errors");
        assert_ne!(d, deltas(HeadingNoise::Degrees(45.0), 4));
    }

    #[test]
    fn uniform_errors_cover_the_circle() {
        let d = deltas(HeadingNoise::Uniform, 1);
        assert!(d.iter().all(|x| (-std::f64::consts::PI..std::f64::consts::PI).contains(x)));
        assert!(d.iter().any(|x| *x > 2.0) && d.iter().any(|x| *x < -2.0), "{d:?}");
    }

    #[test]
    fn parsing() {
        assert_eq!("uniform".parse::<HeadingNoise>(), Ok(HeadingNoise::Uniform));
        assert_eq!("15".parse::<HeadingNoise>(), Ok(HeadingNoise::Degrees(15.0)));
        assert!("-3".parse::<HeadingNoise>().is_err() && "x".parse::<HeadingNoise>().is_err());
    }
}
