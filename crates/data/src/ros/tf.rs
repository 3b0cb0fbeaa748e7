//! The static transform tree of `/tf_static`: each frame's pose in its parent, composed into
//! the transform between any two frames of one tree.

use std::collections::BTreeMap;

use super::msgs::{Pose, TransformStamped};
use posefuse_core::geometry::rigid::{mul, rigid_inverse, Mat4, IDENTITY};

/// More links than any robot has: a loop in a malformed log ends the walk.
const MAX_DEPTH: usize = 64;

/// Latest static transform of each child frame.
#[derive(Debug, Default, Clone)]
pub struct TfTree {
    parent: BTreeMap<String, (String, Mat4)>,
}

/// The 4×4 row-major transform of a pose (`p_parent = R p_child + t`).
pub fn pose_matrix(p: &Pose) -> Mat4 {
    let [x, y, z, w] = p.rotation;
    let n = (x * x + y * y + z * z + w * w).sqrt();
    let (x, y, z, w) = if n > 0.0 { (x / n, y / n, z / n, w / n) } else { (0.0, 0.0, 0.0, 1.0) };
    let t = p.translation;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w), t[0]],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w), t[1]],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y), t[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// The unit quaternion `[x, y, z, w]` of a rotation matrix (the upper-left 3×3 of `m`).
pub fn matrix_quaternion(m: &Mat4) -> [f64; 4] {
    let trace = m[0][0] + m[1][1] + m[2][2];
    if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        [(m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, s / 4.0]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [s / 4.0, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [(m[0][1] + m[1][0]) / s, s / 4.0, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [(m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, s / 4.0, (m[1][0] - m[0][1]) / s]
    }
}

/// Yaw about +z of a quaternion `[x, y, z, w]`.
pub fn yaw(q: [f64; 4]) -> f64 {
    let [x, y, z, w] = q;
    (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z))
}

impl TfTree {
    pub fn insert(&mut self, transforms: &[TransformStamped]) {
        for t in transforms {
            self.parent.insert(t.child_frame_id.clone(), (t.header.frame_id.clone(), pose_matrix(&t.transform)));
        }
    }

    /// Frames with a parent.
    pub fn len(&self) -> usize {
        self.parent.len()
    }

    pub fn is_empty(&self) -> bool {
        self.parent.is_empty()
    }

    /// The frame's pose in its tree's root, and the root.
    fn to_root(&self, frame: &str) -> Option<(String, Mat4)> {
        let mut m: Mat4 = IDENTITY;
        let mut at = frame.to_owned();
        for _ in 0..MAX_DEPTH {
            match self.parent.get(&at) {
                Some((parent, link)) => {
                    m = mul(link, &m);
                    at = parent.clone();
                }
                None => return Some((at, m)),
            }
        }
        None
    }

    /// The transform taking points in `source` to `target`, when both are in one tree.
    pub fn lookup(&self, target: &str, source: &str) -> Result<Mat4, String> {
        let (root_t, t) = self.to_root(target).ok_or_else(|| format!("the transforms above `{target}` loop"))?;
        let (root_s, s) = self.to_root(source).ok_or_else(|| format!("the transforms above `{source}` loop"))?;
        if root_t != root_s {
            return Err(format!("no transform from `{source}` to `{target}` in /tf_static"));
        }
        Ok(mul(&rigid_inverse(&t), &s))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::msgs::Header;
    use posefuse_core::geometry::rigid::apply;

    fn link(parent: &str, child: &str, t: [f64; 3], q: [f64; 4]) -> TransformStamped {
        TransformStamped {
            header: Header { stamp_ns: 0, frame_id: parent.into() },
            child_frame_id: child.into(),
            transform: Pose { translation: t, rotation: q },
        }
    }

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
    }

    #[test]
    fn transforms_compose_through_the_tree_both_ways() {
        let half = std::f64::consts::FRAC_1_SQRT_2;
        let mut tf = TfTree::default();
        // lidar 1 m up, camera 2 m forward and yawed 90° left, both under base_link
        tf.insert(&[
            link("base_link", "lidar", [0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]),
            link("base_link", "cam", [2.0, 0.0, 0.0], [0.0, 0.0, half, half]),
        ]);
        let m = tf.lookup("base_link", "lidar").unwrap();
        assert!(close(apply(&m, [1.0, 0.0, 0.0]), [1.0, 0.0, 1.0]));
        // a point 1 m along the camera's x is 1 m to the left of it in base_link
        let c = tf.lookup("base_link", "cam").unwrap();
        assert!(close(apply(&c, [1.0, 0.0, 0.0]), [2.0, 1.0, 0.0]));
        // from the lidar to the camera: up 1 m, back 2 m, turned
        let lc = tf.lookup("cam", "lidar").unwrap();
        assert!(close(apply(&lc, [2.0, 1.0, -1.0]), [1.0, 0.0, 0.0]));
        assert!(close(apply(&tf.lookup("lidar", "lidar").unwrap(), [3.0, 4.0, 5.0]), [3.0, 4.0, 5.0]));
    }

    #[test]
    fn disconnected_and_looping_frames_are_named() {
        let mut tf = TfTree::default();
        tf.insert(&[link("a", "b", [0.0; 3], [0.0, 0.0, 0.0, 1.0]), link("b", "a", [0.0; 3], [0.0, 0.0, 0.0, 1.0])]);
        assert!(tf.lookup("a", "x").unwrap_err().contains("loop"));
        let mut tf = TfTree::default();
        tf.insert(&[link("base", "lidar", [0.0; 3], [0.0, 0.0, 0.0, 1.0])]);
        let e = tf.lookup("base", "camera").unwrap_err();
        assert!(e.contains("`camera`") && e.contains("`base`"), "{e}");
    }

    #[test]
    fn quaternions_round_trip_through_matrices_and_give_the_yaw() {
        for yaw_deg in [-170.0f64, -90.0, -10.0, 0.0, 45.0, 135.0, 179.0] {
            let h = yaw_deg.to_radians() / 2.0;
            let q = [0.0, 0.0, h.sin(), h.cos()];
            assert!((yaw(q) - yaw_deg.to_radians()).abs() < 1e-12);
            let back = matrix_quaternion(&pose_matrix(&Pose { translation: [0.0; 3], rotation: q }));
            let same = back.iter().zip(q).all(|(a, b)| (a - b).abs() < 1e-12);
            let opposite = back.iter().zip(q).all(|(a, b)| (a + b).abs() < 1e-12);
            assert!(same || opposite, "{yaw_deg}: {back:?} vs {q:?}");
        }
        // the optical frame's rotation (z forward, x right, y down) and a roll about x
        let optical = [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
        let q = matrix_quaternion(&optical);
        let m = pose_matrix(&Pose { translation: [0.0; 3], rotation: q });
        for r in 0..3 {
            for c in 0..3 {
                assert!((m[r][c] - optical[r][c]).abs() < 1e-12);
            }
        }
    }
}
