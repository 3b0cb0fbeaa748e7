//! The 13 keypoints shared by every part of posefuse, in Waymo's order (docs/ARCHITECTURE.md, "Conventions").

/// Number of keypoints.
pub const K: usize = 13;

/// Keypoint names, in the project's order.
pub const NAMES: [&str; K] = [
    "nose",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
];

/// Waymo Open Dataset `KeypointType` ids for each keypoint.
pub const WAYMO_TYPES: [u32; K] = [1, 5, 13, 6, 14, 7, 15, 8, 16, 9, 17, 10, 18];

/// Waymo's per-type OKS scale (twice the COCO sigma).
pub const OKS_SCALES: [f64; K] =
    [0.052, 0.158, 0.158, 0.144, 0.144, 0.124, 0.124, 0.214, 0.214, 0.174, 0.174, 0.178, 0.178];

/// Skeleton edges for drawing (pairs of keypoint indices).
pub const SKELETON: [(usize, usize); 12] =
    [(1, 2), (1, 3), (3, 5), (2, 4), (4, 6), (1, 7), (2, 8), (7, 8), (7, 9), (9, 11), (8, 10), (10, 12)];

/// For each keypoint, the index of its mirror image (left <-> right); used by flip augmentation.
pub const FLIP: [usize; K] = [0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11];

/// Index of a keypoint by name.
pub fn index_of(name: &str) -> Option<usize> {
    NAMES.iter().position(|n| *n == name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flip_is_an_involution_that_swaps_sides() {
        for k in 0..K {
            assert_eq!(FLIP[FLIP[k]], k);
            let (a, b) = (NAMES[k], NAMES[FLIP[k]]);
            if a.starts_with("left_") {
                assert_eq!(b, a.replacen("left_", "right_", 1));
            }
        }
    }

    #[test]
    fn waymo_ids_are_unique() {
        let mut ids = WAYMO_TYPES.to_vec();
        ids.sort();
        ids.dedup();
        assert_eq!(ids.len(), K);
        assert_eq!(index_of("right_knee"), Some(10));
    }
}
