"""An ablation run directory's checkpoints (camera.pt, <row>.pt) back as held-out predictions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from posefuse_train import evaluate
from posefuse_train.config import PipelineConfig
from posefuse_train.export import camera_from_checkpoint, load_checkpoint, point_from_checkpoint
from posefuse_train.fusion import smoothed
from posefuse_train.train import predict_heatmaps, predict_points


def run_heatmaps(run: Path, test: dict, cfg: PipelineConfig) -> np.ndarray:
    camera = camera_from_checkpoint(load_checkpoint(run / "camera.pt")).eval()
    return predict_heatmaps(camera, test["image"], cfg)


def run_predictions(run: Path, rows: list[str], test: dict, cfg: PipelineConfig, raw=None) -> dict:
    """Held-out predictions (model-input coordinates, camera-only fallback for sparse persons) of
    an ablation run's checkpoints; row "camera" is the camera-only baseline. `raw`: the run's
    camera heatmaps of `test`, when already computed."""
    raw = run_heatmaps(run, test, cfg) if raw is None else raw
    cam_pred = evaluate.camera_only(raw, test, cfg)
    preds = {}
    for row in rows:
        if row == "camera":
            preds[row] = cam_pred
            continue
        ckpt = load_checkpoint(run / f"{row}.pt")
        net = point_from_checkpoint(ckpt).eval()
        fusion = ckpt["train_config"]["fusion"]
        row_cfg = PipelineConfig.from_dict(ckpt["pipeline"])
        sm = smoothed(raw, row_cfg) if fusion else None
        pred = predict_points(net, test["serve_xyz"], test["serve_uv"], sm, row_cfg)
        preds[row] = evaluate.with_fallback(pred, cam_pred, test, cfg)
    return preds
