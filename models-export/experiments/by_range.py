"""Held-out metrics of an ablation's checkpoints per LiDAR range band: where do camera features
help? (The paper's argument: where the points are sparse.)

    python -m experiments.by_range --run runs/ablation --test data/test \
        --rows camera,lidar_reg_seg,fusion_reg_seg,fusion_reg_seg_depth
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from posefuse_train import data as data_mod
from posefuse_train import evaluate

from .report import cm, pct
from .runs import run_predictions

BANDS = ((3.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0))


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.by_range", description=__doc__.split("\n")[0])
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
