"""The 13 keypoints, in the project's order (mirrors crates/core/src/keypoints.rs)."""

K = 13

NAMES = [
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
]

WAYMO_TYPES = [1, 5, 13, 6, 14, 7, 15, 8, 16, 9, 17, 10, 18]

# Waymo's per-type OKS scale (twice the COCO sigma).
OKS_SCALES = [0.052, 0.158, 0.158, 0.144, 0.144, 0.124, 0.124, 0.214, 0.214, 0.174, 0.174, 0.178, 0.178]

SKELETON = [
    (1, 2),
    (1, 3),
    (3, 5),
    (2, 4),
    (4, 6),
    (1, 7),
    (2, 8),
    (7, 8),
    (7, 9),
    (9, 11),
    (8, 10),
    (10, 12),
]

# Mirror partner of each keypoint: a horizontally flipped image swaps left and right.
FLIP = [0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11]

# Paper Table 2 groups left/right pairs into one row.
PARTS = {
    "nose": [0],
    "shoulder": [1, 2],
    "elbow": [3, 4],
    "wrist": [5, 6],
    "hip": [7, 8],
    "knee": [9, 10],
    "ankle": [11, 12],
}
