"""Weak supervision from 2D labels (paper sec. 3.4.1): pseudo 3D keypoints by eq. 1, their
reliability, pointwise segmentation labels, and an optional correction of eq. 1's surface bias.

Distances are in model-input pixels divided by S (the contract's units), so temperatures do not
depend on the crop size. Only visible 2D keypoints produce labels."""

from __future__ import annotations

import numpy as np

from .keypoints import K

# Distance from the visible body surface to the joint centre for a 1.75 m adult, metres: roughly
# half the limb thickness at that joint (anthropometric averages; the nose lies on the surface).
JOINT_DEPTH_M = np.array(
    [0.01, 0.06, 0.06, 0.035, 0.035, 0.025, 0.025, 0.08, 0.08, 0.05, 0.05, 0.035, 0.035], dtype=np.float32
)
REFERENCE_HEIGHT_M = 1.75


def _d2(kp_uv: np.ndarray, points_uv: np.ndarray, image_size: int) -> np.ndarray:
    """[M,K,2] x [M,P,2] -> squared distances in S units [M,K,P] (NaN where no projection)."""
    diff = (
        kp_uv[:, :, None, :].astype(np.float64) - points_uv[:, None, :, :].astype(np.float64)
    ) / image_size
    return (diff**2).sum(axis=3)


def lift(
    kp_uv: np.ndarray,
    points_uv: np.ndarray,
    points_xyz: np.ndarray,
    counts: np.ndarray | None,
    image_size: int,
    temperature: float,
) -> np.ndarray:
    """Eq. 1 for a batch: [M,K,2], [M,P,2], [M,P,3], counts [M] -> [M,K,3]. Rows at or past a
    person's count and points without a projection are ignored; NaN where no point is usable."""
    d2 = _d2(kp_uv, points_uv, image_size)
    usable = np.isfinite(d2)
    if counts is not None:
        usable &= (np.arange(points_uv.shape[1])[None, :] < counts[:, None])[:, None, :]
    logits = np.where(usable, -temperature * np.where(usable, d2, 0.0), -np.inf)
    mx = logits.max(axis=2, keepdims=True)
    ok = np.isfinite(mx)
    w = np.exp(logits - np.where(ok, mx, 0.0))
    w = np.where(usable, w, 0.0)
    total = w.sum(axis=2, keepdims=True)
    out = np.einsum("mkp,mpc->mkc", w, points_xyz.astype(np.float64)) / np.where(total > 0, total, 1.0)
    out[~ok[..., 0]] = np.nan
    return out.astype(np.float32)


def reliability(
    kp_uv: np.ndarray, points_uv: np.ndarray, counts: np.ndarray | None, image_size: int, t_r: float
) -> np.ndarray:
    """r_k = exp(-T_r * min_i d_ik^2) -> [M,K]; 0 when no point has a projection."""
    d2 = _d2(kp_uv, points_uv, image_size)
    usable = np.isfinite(d2)
    if counts is not None:
        usable &= (np.arange(points_uv.shape[1])[None, :] < counts[:, None])[:, None, :]
    m = np.where(usable, d2, np.inf).min(axis=2)
    return np.where(np.isfinite(m), np.exp(-t_r * np.where(np.isfinite(m), m, 0.0)), 0.0).astype(np.float32)


def segmentation_labels(kp_uv, kp_visible, points_uv, image_size: int, radius: float):
    """l_ik = 1 when point i's projection is within `radius` (S units) of visible keypoint k.
    Works on numpy arrays or torch tensors: [B,K,2], [B,K], [B,N,2] -> [B,N,K] float."""
    diff = (points_uv[:, :, None, :] - kp_uv[:, None, :, :]) / image_size
    d2 = (diff**2).sum(-1)
    near = d2 <= radius**2  # NaN compares False: points without a projection are negatives
    vis = kp_visible[:, None, :] > 0
    out = near & vis
    return out.float() if hasattr(out, "float") else out.astype(np.float32)


def depth_offsets(box_height_m: np.ndarray) -> np.ndarray:
    """Per-person, per-keypoint surface-to-joint depth [M,K], scaled by the person's height (the 3D
    box is an input at serve time; no 3D keypoint is used)."""
    return box_height_m[:, None].astype(np.float32) / REFERENCE_HEIGHT_M * JOINT_DEPTH_M[None, :]


def push_along_rays(labels: np.ndarray, sensor_xyz: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Moves each pseudo label away from the sensor along its viewing ray by `offsets` metres.
    LiDAR returns lie on the body's near surface while joints are inside; moving along the ray
    keeps the label's 2D projection (to first order) and so its agreement with the 2D label."""
    ray = labels - sensor_xyz[:, None, :]
    norm = np.linalg.norm(ray, axis=2, keepdims=True)
    unit = ray / np.where(norm > 1e-6, norm, 1.0)
    return (labels + unit * offsets[..., None]).astype(np.float32)


def pseudo_labels(data: dict, cfg, t_r: float, depth_correction: bool = False, chunk: int = 512) -> dict:
    """Pseudo 3D labels for a whole dataset from ALL in-box points (before any subsampling).

    Returns kp3d [M,K,3] (0 where unusable), weight [M,K] = visibility x reliability (0 where no
    label), and visible [M,K] (the 2D labels that produced a pseudo label)."""
    m = len(data["kp2d"])
    s = cfg.image_size
    kp3d = np.zeros((m, K, 3), np.float32)
    rel = np.zeros((m, K), np.float32)
    for a in range(0, m, chunk):
        b = min(m, a + chunk)
        p = int(max(1, data["points_count"][a:b].max()))
        args = (data["kp2d"][a:b], data["points_uv"][a:b, :p], data["points_count"][a:b])
        kp3d[a:b] = lift(args[0], args[1], data["points_xyz"][a:b, :p], args[2], s, cfg.lift_temperature)
        rel[a:b] = reliability(*args, s, t_r)
    ok = (data["kp2d_visible"] > 0) & np.isfinite(kp3d).all(axis=2) & (rel > 0)
    kp3d = np.where(ok[..., None], kp3d, 0.0).astype(np.float32)
    if depth_correction:
        off = depth_offsets(data["box3d"][:, 5])
        kp3d = np.where(ok[..., None], push_along_rays(kp3d, data["sensor_xyz"], off), 0.0)
    return {"kp3d": kp3d, "weight": np.where(ok, rel, 0.0).astype(np.float32), "visible": ok}
