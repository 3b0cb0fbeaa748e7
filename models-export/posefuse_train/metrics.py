"""Evaluation metrics, the Python copy of crates/core/src/metrics/ (checked against
tests/golden/metrics.json).

A prediction of NaN is a missing keypoint: OKS 0, left out of MPJPE, fails PCK, costs the PEM clip.
Which keypoints count is the caller's mask: every labelled keypoint, occluded or not (Waymo's
convention, `labelled`). MPJPE, PCK and PEM pool every counted keypoint of every person; OKS/ACC
counts persons; a person without a counted keypoint is skipped."""

from __future__ import annotations

import numpy as np

from .keypoints import NAMES, OKS_SCALES, K

THRESHOLDS = np.array([(50 + 5 * i) / 100.0 for i in range(10)])
PCK_THRESHOLDS_3D_M = (0.1, 0.2)
# Which keypoints a bundle's recorded metrics count (manifest `metrics.convention`).
CONVENTION = "waymo: every labelled keypoint, occluded included"
PEM_CLIP_M = 0.25


def labelled(data: dict, dim: int) -> np.ndarray:
    """Waymo's mask over a shard's `kp{dim}d_visible` / `kp{dim}d_occluded`: labelled, occluded
    or not (docs/DATA.md)."""
    return (data[f"kp{dim}d_visible"] > 0) | (data[f"kp{dim}d_occluded"] > 0)


def keypoint_oks(d, type_scale, box_scale):
    s = np.asarray(type_scale, np.float64) * np.asarray(box_scale, np.float64)
    return np.exp(-(np.asarray(d, np.float64) ** 2) / (2.0 * s * s))


def box_scale_3d(box3d: np.ndarray) -> np.ndarray:
    b = np.asarray(box3d, np.float64)
    return np.cbrt(b[..., 3] * b[..., 4] * b[..., 5])


def box_scale_2d(box2d: np.ndarray) -> np.ndarray:
    b = np.asarray(box2d, np.float64)
    return np.sqrt(b[..., 2] * b[..., 3])


def oks_acc(oks: np.ndarray) -> float | None:
    oks = np.asarray(oks, np.float64)
    if oks.size == 0:
        return None
    return float(np.mean([(oks >= t).mean() for t in THRESHOLDS]))


def evaluate_persons(pred, gt, visible, box_scale) -> dict:
    """pred/gt [M,K,D], visible [M,K], box_scale [M] -> per-person arrays:
    oks [M] (NaN: no visible keypoint), per_keypoint_oks [M,K] (NaN: invisible),
    errors [M,K] (NaN: invisible or missing prediction), visible [M,K]."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    vis = np.asarray(visible).astype(bool)
    missing = ~np.isfinite(pred).all(axis=2)
    d = np.sqrt(((pred - gt) ** 2).sum(axis=2))
    kp = keypoint_oks(d, np.array(OKS_SCALES)[None, :], np.asarray(box_scale, np.float64)[:, None])
    kp = np.where(missing, 0.0, kp)
    kp = np.where(vis, kp, np.nan)
    errors = np.where(vis & ~missing, d, np.nan)
    n = vis.sum(axis=1)
    with np.errstate(invalid="ignore"):
        oks = np.where(n > 0, np.nansum(np.where(vis, kp, 0.0), axis=1) / np.maximum(n, 1), np.nan)
    return {"oks": oks, "per_keypoint_oks": kp, "errors": errors, "visible": vis}


def _ratio(num, den):
    return float(num / den) if den > 0 else None


def summarize(e: dict, three_d: bool) -> dict:
    scored = np.isfinite(e["oks"])
    vis = e["visible"][scored]
    kp = e["per_keypoint_oks"][scored]
    err = e["errors"][scored]
    oks = e["oks"][scored]
    out = {
        "count": int(scored.sum()),
        "skipped": int((~scored).sum()),
        "oks_acc": oks_acc(oks),
        "mean_oks": _ratio(oks.sum(), len(oks)),
        "mpjpe": _ratio(np.nansum(err), int(np.isfinite(err).sum())),
        "per_keypoint_oks": [
            {"name": NAMES[k], "oks": _ratio(np.nansum(kp[:, k]), int(vis[:, k].sum()))} for k in range(K)
        ],
    }
    if three_d:
        nvis = int(vis.sum())
        hit = np.where(np.isfinite(err), err, np.inf)
        for t in PCK_THRESHOLDS_3D_M:
            out[f"pck_{int(round(t * 100))}cm"] = _ratio(((hit <= t) & vis).sum(), nvis)
        out["pem"] = _ratio(np.where(vis, np.minimum(hit, PEM_CLIP_M), 0.0).sum(), nvis)
    return out


def report(e3: dict, e2: dict | None) -> dict:
    """Same keys as the server's MetricsReport (crates/core/src/metrics/accumulator.rs)."""
    a = summarize(e3, True)
    r = {
        "count_3d": a["count"],
        "skipped_3d": a["skipped"],
        "oks_acc_3d": a["oks_acc"],
        "mean_oks_3d": a["mean_oks"],
        "mpjpe_3d_m": a["mpjpe"],
        "pck_3d_10cm": a["pck_10cm"],
        "pck_3d_20cm": a["pck_20cm"],
        "pem_3d_m": a["pem"],
        "per_keypoint_oks_3d": a["per_keypoint_oks"],
    }
    if e2 is not None:
        b = summarize(e2, False)
        r.update(
            {
                "count_2d": b["count"],
                "skipped_2d": b["skipped"],
                "oks_acc_2d": b["oks_acc"],
                "mean_oks_2d": b["mean_oks"],
                "mpjpe_2d_px": b["mpjpe"],
                "per_keypoint_oks_2d": b["per_keypoint_oks"],
            }
        )
    return r


# --- geometry for OKS@2D ---------------------------------------------------------------------


def local_to_vehicle(local: np.ndarray, box3d: np.ndarray, frame_yaw: np.ndarray) -> np.ndarray:
    """Model-input coordinates [M,K,3] -> vehicle frame (inverse of: subtract the box centre,
    rotate by -frame_yaw; the shards' `frame_yaw` is the model frame's yaw, docs/DATA.md)."""
    q = np.asarray(local, np.float64)
    b = np.asarray(box3d, np.float64)
    h = np.asarray(frame_yaw, np.float64).reshape(len(b))
    c, s = np.cos(h)[:, None], np.sin(h)[:, None]
    x = b[:, None, 0] + c * q[..., 0] - s * q[..., 1]
    y = b[:, None, 1] + s * q[..., 0] + c * q[..., 1]
    z = b[:, None, 2] + q[..., 2]
    return np.stack([x, y, z], axis=2)


def vehicle_to_local(vehicle: np.ndarray, box3d: np.ndarray, frame_yaw: np.ndarray) -> np.ndarray:
    """Vehicle frame [M,K,3] -> model-input coordinates (local_to_vehicle's inverse)."""
    q = np.asarray(vehicle, np.float64) - np.asarray(box3d, np.float64)[:, None, :3]
    h = np.asarray(frame_yaw, np.float64).reshape(len(q))
    c, s = np.cos(h)[:, None], np.sin(h)[:, None]
    return np.stack([c * q[..., 0] + s * q[..., 1], -s * q[..., 0] + c * q[..., 1], q[..., 2]], axis=2)


# Waymo's camera model trusts a projection only inside these radial distortion factors
# (crates/core/src/geometry/camera.rs, RADIAL_FACTOR_RANGE).
RADIAL_FACTOR_RANGE = (0.8, 1.2)


def project(vehicle: np.ndarray, intrinsic: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """Waymo camera model: [M,K,3] vehicle points -> [M,K,2] pixels; NaN without a valid
    projection: behind the camera, or where the radial distortion factor leaves
    RADIAL_FACTOR_RANGE (the lens polynomial folds back there), as the server's camera model."""
    p = np.asarray(vehicle, np.float64)
    ext = np.asarray(extrinsic, np.float64).reshape(-1, 4, 4)
    r, t = ext[:, :3, :3], ext[:, :3, 3]
    # camera->vehicle is [R|t]; vehicle->camera is R^T (p - t)
    cam = np.einsum("mji,mkj->mki", r, p - t[:, None, :])
    i = np.asarray(intrinsic, np.float64)
    fu, fv, cu, cv, k1, k2, p1, p2, k3 = (i[:, j][:, None] for j in range(9))
    x = cam[..., 0]
    front = x > 1e-6
    xs = np.where(front, x, 1.0)
    un, vn = -cam[..., 1] / xs, -cam[..., 2] / xs
    ud, vd, radial = _distort(un, vn, k1, k2, p1, p2, k3)
    uv = np.stack([fu * ud + cu, fv * vd + cv], axis=2)
    valid = front & (radial >= RADIAL_FACTOR_RANGE[0]) & (radial <= RADIAL_FACTOR_RANGE[1])
    return np.where(valid[..., None], uv, np.nan)


def _distort(un, vn, k1, k2, p1, p2, k3):
    """Waymo's lens polynomial: normalised -> distorted coordinates, and the radial factor."""
    r2 = un * un + vn * vn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    ud = un * radial + 2.0 * p1 * un * vn + p2 * (r2 + 2.0 * un * un)
    vd = vn * radial + p1 * (r2 + 2.0 * vn * vn) + 2.0 * p2 * un * vn
    return ud, vd, radial


def unproject(px: np.ndarray, depth: np.ndarray, intrinsic: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """`project`'s inverse: [M,K,2] pixels at [M,K] depths (metres along the camera's optical axis)
    -> [M,K,3] vehicle points. The lens is inverted by Newton's method, as the server's
    `Camera::undistort` (crates/core/src/geometry/camera.rs)."""
    uv = np.asarray(px, np.float64)
    i = np.asarray(intrinsic, np.float64)
    fu, fv, cu, cv, k1, k2, p1, p2, k3 = (i[:, j][:, None] for j in range(9))
    lens = (k1, k2, p1, p2, k3)
    ud, vd = (uv[..., 0] - cu) / fu, (uv[..., 1] - cv) / fv
    un, vn = ud.copy(), vd.copy()
    h = 1e-7
    for _ in range(20):
        fu0, fv0, _ = _distort(un, vn, *lens)
        ru, rv = fu0 - ud, fv0 - vd
        a1, b1, _ = _distort(un + h, vn, *lens)
        a2, b2, _ = _distort(un, vn + h, *lens)
        j11, j21, j12, j22 = (a1 - fu0) / h, (b1 - fv0) / h, (a2 - fu0) / h, (b2 - fv0) / h
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) < 1e-12, 1.0, det)
        un, vn = un - (j22 * ru - j12 * rv) / det, vn - (-j21 * ru + j11 * rv) / det
    x = np.asarray(depth, np.float64)
    cam = np.stack([x, -un * x, -vn * x], axis=2)
    ext = np.asarray(extrinsic, np.float64).reshape(-1, 4, 4)
    return np.einsum("mij,mkj->mki", ext[:, :3, :3], cam) + ext[:, None, :3, 3]


def camera_depth(vehicle: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """[M,...,3] vehicle points -> [M,...] depth along each person's camera's optical axis."""
    ext = np.asarray(extrinsic, np.float64).reshape(-1, 4, 4)
    p = np.asarray(vehicle, np.float64)
    t = ext[:, :3, 3].reshape((len(ext),) + (1,) * (p.ndim - 2) + (3,))
    return np.einsum("mj,m...j->m...", ext[:, :3, 0], p - t)
