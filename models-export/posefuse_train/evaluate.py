"""Held-out evaluation, exactly on the server's inputs (serve_xyz / serve_uv): the camera-only
baseline (decode + eq. 1 lifting) and point-network predictions, scored in 3D and, after projection
into the image, in 2D."""

from __future__ import annotations

import numpy as np

from . import metrics
from .config import PipelineConfig
from .fusion import decode_heatmaps
from .keypoints import FLIP
from .labels import lift


def camera_only(heatmaps: np.ndarray, data: dict, cfg: PipelineConfig) -> np.ndarray:
    """Raw heatmaps [M,K,H,W] -> keypoints [M,K,3] (model-input coords; NaN where no serve point
    has a projection): argmax decoding, then eq. 1 over the N serve points."""
    kp_uv, _ = decode_heatmaps(heatmaps, cfg.image_size)
    return lift(kp_uv, data["serve_uv"], data["serve_xyz"], None, cfg.image_size, cfg.lift_temperature)


def with_fallback(pred: np.ndarray, camera_pred: np.ndarray, data: dict, cfg: PipelineConfig) -> np.ndarray:
    """Persons with fewer than min_points in-box points get the camera-only answer, as on the server."""
    few = data["points_count"] < cfg.min_points
    return np.where(few[:, None, None], camera_pred, pred)


def evaluate(pred_local: np.ndarray, data: dict, cfg: PipelineConfig) -> dict:
    """MetricsReport-shaped dict for predictions in model-input coordinates, every labelled
    keypoint counted (Waymo's convention), with `breakdown`: the same on the visible keypoints
    only and on the occluded ones only."""
    vehicle = metrics.local_to_vehicle(pred_local, data["box3d"], data["frame_yaw"])
    px = metrics.project(vehicle, data["intrinsic"], data["extrinsic"])
    s3, s2 = metrics.box_scale_3d(data["box3d"]), metrics.box_scale_2d(data["box2d"])

    def scored(mask3, mask2) -> dict:
        e3 = metrics.evaluate_persons(pred_local, data["kp3d"], mask3, s3)
        e2 = metrics.evaluate_persons(px, data["kp2d_image_true"], mask2, s2)
        return metrics.report(e3, e2)

    report = scored(metrics.labelled(data, 3), metrics.labelled(data, 2))
    report["breakdown"] = {
        "visible": scored(data["kp3d_visible"] > 0, data["kp2d_visible"] > 0),
        "occluded": scored(data["kp3d_occluded"] > 0, data["kp2d_occluded"] > 0),
    }
    report["left_right_swap_rate"] = left_right_swap_rate(pred_local, data["kp3d"], metrics.labelled(data, 3))
    return report


def with_points(pred_local: np.ndarray, data: dict, cfg: PipelineConfig) -> dict:
    """evaluate() over the persons with at least min_points in-box points only: the persons that
    `posefuse eval --mode fusion|lidar` scores (it skips the others, which the held-out figures
    answer by camera lifting, as the server's auto mode does)."""
    keep = data["points_count"] >= cfg.min_points
    return evaluate(pred_local[keep], {k: v[keep] for k, v in data.items()}, cfg)


def left_right_swap_rate(pred, gt, visible, min_visible: int = 4) -> float | None:
    """Diagnostic (not a Waymo metric): the share of persons whose prediction is closer to the
    truth with left and right exchanged than to the truth itself, i.e. the body's facing was read
    the wrong way round. Persons with fewer than `min_visible` visible keypoints are skipped."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    vis = np.asarray(visible, bool)
    both = vis & vis[:, FLIP] & np.isfinite(pred).all(axis=2)
    keep = both.sum(axis=1) >= min_visible
    if not keep.any():
        return None
    direct = np.where(both, np.linalg.norm(pred - gt, axis=2), 0.0).sum(axis=1)
    mirrored = np.where(both, np.linalg.norm(pred - gt[:, FLIP], axis=2), 0.0).sum(axis=1)
    return float((mirrored[keep] < direct[keep]).mean())
