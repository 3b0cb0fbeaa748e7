"""Weak supervision from 2D labels (paper sec. 3.4.1): pseudo 3D keypoints by eq. 1, their
reliability, pointwise segmentation labels, and an optional correction of eq. 1's surface bias.

Distances are in model-input pixels divided by S (the contract's units), so temperatures do not
depend on the crop size. Visible 2D keypoints produce eq. 1's labels; occluded ones, optionally, a
label on their camera ray (occluded_labels)."""

from __future__ import annotations

import numpy as np

from . import metrics
from .keypoints import K

# The positive radius r of the segmentation labels, in units of S (TrainPointConfig.seg_radius): a
# point this near a 2D label is that joint's; an occluded label with one this near is the occluder's.
SEGMENTATION_RADIUS = 0.05

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


def nearest_d2(
    kp_uv: np.ndarray, points_uv: np.ndarray, counts: np.ndarray | None, image_size: int
) -> np.ndarray:
    """[M,K] squared distance (S units) from each 2D keypoint to the nearest projected point of the
    person's first `counts` points; inf when none has a projection."""
    d2 = _d2(kp_uv, points_uv, image_size)
    usable = np.isfinite(d2)
    if counts is not None:
        usable &= (np.arange(points_uv.shape[1])[None, :] < counts[:, None])[:, None, :]
    return np.where(usable, d2, np.inf).min(axis=2)


def reliability(
    kp_uv: np.ndarray, points_uv: np.ndarray, counts: np.ndarray | None, image_size: int, t_r: float
) -> np.ndarray:
    """r_k = exp(-T_r * min_i d_ik^2) -> [M,K]; 0 when no point has a projection."""
    return _reliability_of(nearest_d2(kp_uv, points_uv, counts, image_size), t_r)


def _reliability_of(near: np.ndarray, t_r: float) -> np.ndarray:
    finite = np.isfinite(near)
    return np.where(finite, np.exp(-t_r * np.where(finite, near, 0.0)), 0.0).astype(np.float32)


def on_label_rays(data: dict, depth: np.ndarray) -> np.ndarray:
    """[M,K,3] model-input points on each 2D label's camera ray at `depth` [M,K] (metres along the
    camera's optical axis)."""
    crop = np.asarray(data["crop"], np.float64)
    px = np.asarray(data["kp2d"], np.float64) / crop[:, None, 2:3] + crop[:, None, :2]
    vehicle = metrics.unproject(px, depth, data["intrinsic"], data["extrinsic"])
    return metrics.vehicle_to_local(vehicle, data["box3d"], data["frame_yaw"]).astype(np.float32)


def on_rays_at_box_depth(data: dict) -> np.ndarray:
    """[M,K,3] points on each 2D label's ray at the depth of the person's 3D box centre: the 2D
    label fixes where a joint is across the ray; where no LiDAR return tells how deep it is, the
    box's middle is the depth least wrong on average whichever way the person faces."""
    depth = metrics.camera_depth(np.asarray(data["box3d"], np.float64)[:, None, :3], data["extrinsic"])
    return on_label_rays(data, np.repeat(depth, K, axis=1))


def snapped_to_label_rays(kp3d: np.ndarray, data: dict) -> np.ndarray:
    """Each label moved across its 2D label's camera ray onto it, at the depth it had: eq. 1's
    average of the points around a 2D label lies beside the label's ray by up to the points'
    spacing; the depth is what the points tell, where across the ray the joint is what the 2D
    label tells."""
    vehicle = metrics.local_to_vehicle(kp3d, data["box3d"], data["frame_yaw"])
    return on_label_rays(data, metrics.camera_depth(vehicle, data["extrinsic"]))


def occluded_labels(data: dict, near: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Labels for keypoints whose 2D label is marked occluded and has no in-box point within
    `radius` (S units; `near`: nearest_d2 of every keypoint): on the label's ray at the box
    centre's depth (on_rays_at_box_depth). Where a point is near, it is the occluder's, and a
    joint hidden behind a body part keeps no label: the net learns those from persons in which
    they are seen. -> kp3d [M,K,3] (0 elsewhere), mask [M,K]."""
    mask = (np.asarray(data["kp2d_occluded"]) > 0) & (near > radius**2)
    mask &= np.isfinite(data["kp2d"]).all(axis=2)
    kp3d = on_rays_at_box_depth(data)
    mask &= np.isfinite(kp3d).all(axis=2)
    return np.where(mask[..., None], kp3d, 0.0).astype(np.float32), mask


def relabelled(lab: dict, data: dict, pred: np.ndarray, other_weight: float) -> dict:
    """A second round of labels from the first round's `lab` (pseudo_labels()) and predictions
    `pred` [M,K,3] (model-input coordinates) of networks trained on it, every label on its 2D
    label's camera ray. A 2D label with a first-round label keeps its weight and takes the mean of
    its label's depth and the prediction's (the points' evidence and the pose's); every other
    finite 2D label, visible or occluded, takes the prediction's depth, at `other_weight`.
    `visible` is the first round's: segmentation still reads only what the points showed."""
    box, yaw, ext = data["box3d"], data["frame_yaw"], data["extrinsic"]
    depth_pred = metrics.camera_depth(metrics.local_to_vehicle(pred, box, yaw), ext)
    depth_lab = metrics.camera_depth(metrics.local_to_vehicle(lab["kp3d"], box, yaw), ext)
    ok = lab["visible"] & (lab["weight"] > 0)
    kp3d = on_label_rays(data, np.where(ok, 0.5 * (depth_lab + depth_pred), depth_pred))
    finite = np.isfinite(kp3d).all(axis=2)
    kept = ok & finite
    other = ~ok & finite & np.isfinite(data["kp2d"]).all(axis=2)
    other &= (np.asarray(data["kp2d_visible"]) > 0) | (np.asarray(data["kp2d_occluded"]) > 0)
    weight = np.where(kept, lab["weight"], np.where(other, other_weight, 0.0)).astype(np.float32)
    kp3d = np.where((weight > 0)[..., None], kp3d, 0.0).astype(np.float32)
    return {"kp3d": kp3d, "weight": weight, "visible": lab["visible"]}


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


def pseudo_labels(
    data: dict,
    cfg,
    t_r: float,
    depth_correction: bool = False,
    chunk: int = 512,
    occluded_weight: float = 0.0,
    occluded_radius: float = SEGMENTATION_RADIUS,
    snap_to_rays: bool = False,
) -> dict:
    """Pseudo 3D labels for a whole dataset from ALL in-box points (before any subsampling).

    Returns kp3d [M,K,3] (0 where unusable), weight [M,K] = visibility x reliability (0 where no
    label), and visible [M,K] (the 2D labels that produced a pseudo label). With `occluded_weight`
    > 0, occluded 2D labels with no point near them get occluded_labels() at that weight; they
    stay out of `visible`, which the segmentation labels read."""
    m = len(data["kp2d"])
    s = cfg.image_size
    kp3d = np.zeros((m, K, 3), np.float32)
    near = np.zeros((m, K), np.float64)
    for a in range(0, m, chunk):
        b = min(m, a + chunk)
        p = int(max(1, data["points_count"][a:b].max()))
        args = (data["kp2d"][a:b], data["points_uv"][a:b, :p], data["points_count"][a:b])
        kp3d[a:b] = lift(args[0], args[1], data["points_xyz"][a:b, :p], args[2], s, cfg.lift_temperature)
        near[a:b] = nearest_d2(*args, s)
    rel = _reliability_of(near, t_r)
    ok = (data["kp2d_visible"] > 0) & np.isfinite(kp3d).all(axis=2) & (rel > 0)
    kp3d = np.where(ok[..., None], kp3d, 0.0).astype(np.float32)
    if depth_correction:
        off = depth_offsets(data["box3d"][:, 5])
        kp3d = np.where(ok[..., None], push_along_rays(kp3d, data["sensor_xyz"], off), 0.0)
    if snap_to_rays:
        kp3d = np.where(ok[..., None], snapped_to_label_rays(kp3d, data), 0.0)
    weight = np.where(ok, rel, 0.0)
    if occluded_weight > 0:
        # a 2D label is visible or occluded, never both (kp2d_visible / kp2d_occluded): these fill
        # only keypoints the visible labels left empty
        occ, mask = occluded_labels(data, near, occluded_radius)
        kp3d = np.where(mask[..., None], occ, kp3d)
        weight = np.where(mask, occluded_weight, weight)
    return {"kp3d": kp3d.astype(np.float32), "weight": weight.astype(np.float32), "visible": ok}
