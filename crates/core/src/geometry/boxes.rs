//! 3D boxes with heading and 2D boxes.

use crate::frame::{Box2d, Box3d};

/// The frame of a 3D box: origin at its centre, x along its heading, z up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxFrame {
    pub center: [f64; 3],
    pub size: [f64; 3],
    pub heading: f64,
    cos: f64,
    sin: f64,
}

impl BoxFrame {
    /// The frame of a 3D box.
    pub fn new(b: &Box3d) -> BoxFrame {
        BoxFrame {
            center: [b.center_x, b.center_y, b.center_z],
            size: [b.length, b.width, b.height],
            heading: b.heading,
            cos: b.heading.cos(),
            sin: b.heading.sin(),
        }
    }

    /// The same centre and size, turned to another heading.
    pub fn turned_to(&self, heading: f64) -> BoxFrame {
        BoxFrame { heading, cos: heading.cos(), sin: heading.sin(), ..*self }
    }

    /// Vehicle frame → box frame (translate to the centre, rotate by −heading).
    pub fn to_local(&self, p: [f64; 3]) -> [f64; 3] {
        let (dx, dy) = (p[0] - self.center[0], p[1] - self.center[1]);
        [self.cos * dx + self.sin * dy, -self.sin * dx + self.cos * dy, p[2] - self.center[2]]
    }

    /// Box frame → vehicle frame.
    pub fn to_vehicle(&self, q: [f64; 3]) -> [f64; 3] {
        [
            self.center[0] + self.cos * q[0] - self.sin * q[1],
            self.center[1] + self.sin * q[0] + self.cos * q[1],
            self.center[2] + q[2],
        ]
    }

    /// Whether `p` lies inside the box grown by `margin` metres on every side.
    pub fn contains(&self, p: [f64; 3], margin: f64) -> bool {
        let q = self.to_local(p);
        (0..3).all(|a| q[a].abs() <= self.size[a] / 2.0 + margin)
    }

    /// The 8 corners in the vehicle frame (bottom face first, counter-clockwise from front-left).
    pub fn corners(&self) -> [[f64; 3]; 8] {
        let [l, w, h] = self.size.map(|s| s / 2.0);
        let mut out = [[0.0; 3]; 8];
        let xy = [(l, w), (-l, w), (-l, -w), (l, -w)];
        for (i, z) in [-h, h].into_iter().enumerate() {
            for (j, (x, y)) in xy.iter().enumerate() {
                out[i * 4 + j] = self.to_vehicle([*x, *y, z]);
            }
        }
        out
    }

    /// Volume in m³.
    pub fn volume(&self) -> f64 {
        self.size.iter().product()
    }
}

/// Whether a pixel lies in a 2D box.
pub fn box2d_contains(b: &Box2d, uv: [f64; 2]) -> bool {
    (uv[0] - b.center_x).abs() <= b.width / 2.0 && (uv[1] - b.center_y).abs() <= b.height / 2.0
}

/// The tightest 2D box around some pixels (`None` when there are none).
pub fn box2d_from_points(uv: impl IntoIterator<Item = [f64; 2]>) -> Option<Box2d> {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    let mut any = false;
    for p in uv {
        any = true;
        for a in 0..2 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    any.then(|| Box2d {
        center_x: (lo[0] + hi[0]) / 2.0,
        center_y: (lo[1] + hi[1]) / 2.0,
        width: hi[0] - lo[0],
        height: hi[1] - lo[1],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn b(heading: f64) -> BoxFrame {
        BoxFrame::new(&Box3d {
            center_x: 10.0,
            center_y: 2.0,
            center_z: 1.0,
            length: 1.0,
            width: 0.5,
            height: 2.0,
            heading,
        })
    }

    #[test]
    fn containment_follows_the_heading() {
        let straight = b(0.0);
        let turned = b(std::f64::consts::FRAC_PI_2);
        // 0.45 m ahead of the centre: inside along the length (0.5), outside along the width (0.25)
        let p = [10.45, 2.0, 1.0];
        assert!(straight.contains(p, 0.0));
        assert!(!turned.contains(p, 0.0));
        assert!(turned.contains(p, 0.25));
        let q = [10.0, 2.45, 1.0];
        assert!(!straight.contains(q, 0.0) && turned.contains(q, 0.0));
        assert!(!straight.contains([10.0, 2.0, 2.01], 0.0));
    }

    #[test]
    fn local_round_trip_and_corners() {
        let f = b(0.7);
        let p = [11.3, 1.1, 0.4];
        let back = f.to_vehicle(f.to_local(p));
        for a in 0..3 {
            assert!((back[a] - p[a]).abs() < 1e-12);
        }
        for c in f.corners() {
            let q = f.to_local(c);
            assert!(
                (q[0].abs() - 0.5).abs() < 1e-12
                    && (q[1].abs() - 0.25).abs() < 1e-12
                    && (q[2].abs() - 1.0).abs() < 1e-12
            );
            assert!(f.contains(c, 1e-9));
        }
        assert!((f.volume() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn box2d_helpers() {
        let bb = box2d_from_points([[10.0, 20.0], [30.0, 5.0], [15.0, 8.0]]).unwrap();
        assert_eq!((bb.center_x, bb.center_y, bb.width, bb.height), (20.0, 12.5, 20.0, 15.0));
        assert!(box2d_contains(&bb, [10.0, 5.0]) && !box2d_contains(&bb, [9.9, 5.0]));
        assert!(box2d_from_points([]).is_none());
    }
}
