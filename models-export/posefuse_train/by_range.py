"""Held-out metrics of an ablation's checkpoints per LiDAR range band: where do camera features
help? (The paper's argument: where the points are sparse.)

    python -m posefuse_train.by_range --run runs/ablation --test data/test \
        --rows camera,lidar_reg_seg,fusion_reg_seg,fusion_reg_seg_depth
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from . import data as data_mod
from . import evaluate
from .ablation import smoothed
from .config import PipelineConfig
from .export import camera_from_checkpoint, load_checkpoint, point_from_checkpoint
from .report import cm, pct
from .train_camera import predict_heatmaps
from .train_point import predict_points

BANDS = ((3.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0))


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
        sm = smoothed(raw, PipelineConfig.from_dict(ckpt["pipeline"])) if fusion else None
        pred = predict_points(net, test["serve_xyz"], test["serve_uv"], sm, cfg.image_size)
        preds[row] = evaluate.with_fallback(pred, cam_pred, test, cfg)
    return preds


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m posefuse_train.by_range", description=__doc__.split("\n")[0])
    p.add_argument("--run", required=True, help="an ablation --out directory (camera.pt, <row>.pt)")
    p.add_argument("--test", required=True)
    p.add_argument("--rows", default="camera,lidar_reg_seg,fusion_reg_seg")
    p.add_argument("--json", help="also write the table here")
    a = p.parse_args(argv)
    test, cfg, _ = data_mod.load(a.test)
    preds = run_predictions(Path(a.run), a.rows.split(","), test, cfg)
    table = []
    for lo, hi in BANDS:
        sel = np.flatnonzero((test["range_m"] >= lo) & (test["range_m"] < hi))
        if not len(sel):
            continue
        sub = data_mod.subset(test, sel)
        cells = {"range_m": f"{lo:g}-{hi:g}", "persons": int(len(sel))}
        cells["mean_points"] = float(sub["points_count"].mean())
        for row, pred in preds.items():
            m = evaluate.evaluate(pred[sel], sub, cfg)
            cells[row] = {"oks_acc_3d": m["oks_acc_3d"], "mpjpe_3d_m": m["mpjpe_3d_m"]}
        table.append(cells)
    header = ["range (m)", "persons", "in-box points", *[f"{r} OKS@3D / MPJPE" for r in preds]]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for c in table:
        vals = [f"{pct(c[r]['oks_acc_3d'])} / {cm(c[r]['mpjpe_3d_m'])}" for r in preds]
        print(f"| {c['range_m']} | {c['persons']} | {c['mean_points']:.0f} | " + " | ".join(vals) + " |")
    if a.json:
        Path(a.json).write_text(json.dumps(table, indent=2))


if __name__ == "__main__":
    main()
