"""Held-out evaluation, exactly on the server's inputs (serve_xyz / serve_uv): the camera-only
baseline (decode + eq. 1 lifting) and point-network predictions, scored in 3D and, after projection
into the image, in 2D."""

from __future__ import annotations

import numpy as np

from . import metrics
from .config import PipelineConfig
from .fusion import decode_heatmaps
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
    """MetricsReport-shaped dict for predictions in model-input coordinates."""
    e3 = metrics.evaluate_persons(
        pred_local, data["kp3d"], data["kp3d_visible"] > 0, metrics.box_scale_3d(data["box3d"])
    )
    vehicle = metrics.local_to_vehicle(pred_local, data["box3d"], cfg.rotate_by_heading)
    px = metrics.project(vehicle, data["intrinsic"], data["extrinsic"])
    e2 = metrics.evaluate_persons(
        px, data["kp2d_image_true"], data["kp2d_visible"] > 0, metrics.box_scale_2d(data["box2d"])
    )
    return metrics.report(e3, e2)
