"""Held-out metrics when the 3D box's heading is wrong. Point networks trained in the
heading-aligned box frame (±20° rotation) take the body's facing from the box; the paper's recipe
([0, 2π) rotation) has to read it from the points (and the camera). A perception stack's boxes
carry detector headings, so this is what serving with either kind costs when they are off.

    python -m experiments.heading_error --test data/test --errors 0,15,45,90,180 \\
        --models runs/ablation:lidar_reg_seg,runs/ablation:fusion_reg_seg,runs/rot180:lidar_reg_seg
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from posefuse_train import data as data_mod
from posefuse_train import evaluate

from .report import heading_error_table
from .runs import run_heatmaps, run_predictions


def with_heading_error(test: dict, error_rad: float) -> dict:
    """The held-out set as the pipeline would have prepared it had every box's heading been off by
    `error_rad`: the model-input frame turns by -error about z (points and truth alike), the image
    side is unchanged, and the box's heading carries the error back out to the vehicle frame."""
    c, s = np.cos(-error_rad), np.sin(-error_rad)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], np.float32)
    out = dict(test)
    for key in ("points_xyz", "serve_xyz", "kp3d", "sensor_xyz"):
        if key in test:
            out[key] = (test[key] @ rot.T).astype(test[key].dtype)
    out["box3d"] = test["box3d"].copy()
    out["box3d"][:, 6] += error_rad
    return out


def main(argv=None):
    p = argparse.ArgumentParser(
        prog="python -m experiments.heading_error", description=__doc__.split("\n")[0]
    )
    p.add_argument("--test", required=True)
    p.add_argument("--models", required=True, help="comma-separated RUN_DIR:ROW (an ablation's checkpoints)")
    p.add_argument("--errors", default="0,15,45,90,180", help="heading errors in degrees")
    p.add_argument("--json", help="also write the table here")
    a = p.parse_args(argv)
    test, cfg, _ = data_mod.load(a.test)
    models = [tuple(m.split(":", 1)) for m in a.models.split(",")]
    raw = {run: run_heatmaps(Path(run), test, cfg) for run in dict.fromkeys(run for run, _ in models)}
    errors = [float(e) for e in a.errors.split(",")]
    table = []
    for deg in errors:
        shifted = with_heading_error(test, np.radians(deg))
        cells = {"error_deg": deg}
        for run, row in models:
            pred = run_predictions(Path(run), [row], shifted, cfg, raw[run])[row]
            m = evaluate.evaluate(pred, shifted, cfg)
            cells[f"{run}:{row}"] = {
                k: m[k] for k in ("oks_acc_3d", "mpjpe_3d_m", "oks_acc_2d", "left_right_swap_rate")
            }
        table.append(cells)
    print(heading_error_table(table))
    if a.json:
        Path(a.json).write_text(json.dumps(table, indent=2))


if __name__ == "__main__":
    main()
