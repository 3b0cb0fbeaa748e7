"""Held-out metrics per LiDAR range band: where do camera features help? (The paper's argument:
where the points are sparse.) Either an ablation's checkpoints (`--run`) or an exported bundle run
as the server runs it (`--bundle`: its fusion, LiDAR-only and camera modes, and per band the
fusion net's lead over the LiDAR-only one with its standard error over the band's persons).

    python -m experiments.by_range --run runs/ablation --test data/test \\
        --rows camera,lidar_reg_seg,fusion_reg_seg,fusion_reg_seg_depth
    python -m experiments.by_range --bundle models/default --test data/hard128_test \\
        --bands 3-10,10-20,20-30,30-40,40-60
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from posefuse_train import bundle_eval, evaluate, metrics
from posefuse_train import data as data_mod
from posefuse_train.keypoints import PARTS
from posefuse_train.shards import ShardSet

from .report import cm, pct
from .runs import run_predictions

BANDS = ((3.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0))


def parse_bands(text: str) -> tuple[tuple[float, float], ...]:
    """ "3-10,10-20" -> ((3, 10), (10, 20))."""
    bands = tuple(tuple(float(x) for x in b.split("-")) for b in text.split(","))
    if any(len(b) != 2 or not b[0] < b[1] for b in bands):
        raise SystemExit(f"--bands: ranges as LO-HI with LO < HI, comma-separated (got {text!r})")
    return bands


def person_oks_acc(pred: np.ndarray, data: dict) -> np.ndarray:
    """Each person's share of OKS thresholds met in 3D (NaN: no labelled keypoint): the mean of
    these over persons is OKS@3D, so differences between two answers pair person by person."""
    e = metrics.evaluate_persons(
        pred, data["kp3d"], metrics.labelled(data, 3), metrics.box_scale_3d(data["box3d"])
    )
    acc = (e["oks"][:, None] >= metrics.THRESHOLDS[None, :]).mean(axis=1)
    return np.where(np.isfinite(e["oks"]), acc, np.nan)


def part_oks(report: dict, part: str) -> float | None:
    """OKS@3D of one of the paper's Table 2 parts (left and right averaged) from a report."""
    vals = [report["per_keypoint_oks_3d"][k]["oks"] for k in PARTS[part]]
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else None


def lead(a: np.ndarray, b: np.ndarray) -> dict:
    """Mean of a − b over the persons both score, and its standard error."""
    d = (a - b)[np.isfinite(a) & np.isfinite(b)]
    se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else None
    return {"oks_acc_3d": float(d.mean()) if len(d) else None, "se": se}


def per_band(data: dict, preds: dict, cfg, bands) -> list[dict]:
    """One row per range band with persons: each answer's OKS@3D, MPJPE and wrists there, and
    where both a fusion and a LiDAR-only answer are given, the fusion one's paired lead."""
    table = []
    for lo, hi in bands:
        sel = np.flatnonzero((data["range_m"] >= lo) & (data["range_m"] < hi))
        if not len(sel):
            continue
        sub = data_mod.subset(data, sel)
        cells = {"range_m": f"{lo:g}-{hi:g}", "persons": int(len(sel))}
        cells["mean_points"] = float(sub["points_count"].mean())
        for name, p in preds.items():
            m = evaluate.evaluate(p[sel], sub, cfg)
            cells[name] = {
                "oks_acc_3d": m["oks_acc_3d"],
                "mpjpe_3d_m": m["mpjpe_3d_m"],
                "wrist": part_oks(m, "wrist"),
            }
        if {"fusion", "lidar"} <= preds.keys():
            cells["fusion_lead"] = lead(
                person_oks_acc(preds["fusion"][sel], sub), person_oks_acc(preds["lidar"][sel], sub)
            )
            f, li = cells["fusion"]["wrist"], cells["lidar"]["wrist"]
            cells["fusion_lead"]["wrist"] = f - li if f is not None and li is not None else None
        table.append(cells)
    return table


def bundle_table(bundle: Path, test: str, bands, threads: int) -> list[dict]:
    pred, data, cfg = bundle_eval.served_answers(bundle, ShardSet(test), threads, keys=("range_m",))
    return per_band(data, pred, cfg, bands)


def print_bundle_table(table: list[dict]) -> None:
    modes = "fusion | LiDAR-only | camera-only"
    print(f"| range (m) | persons | in-box points | {modes} | fusion − LiDAR-only | wrists |")
    print("|---|---|---|---|---|---|---|---|")
    for c in table:
        modes = [
            f"{pct(c[m]['oks_acc_3d'])} / {cm(c[m]['mpjpe_3d_m'])}" for m in ("fusion", "lidar", "camera")
        ]
        lead_ = c["fusion_lead"]
        se = f" ± {100 * lead_['se']:.2f}" if lead_["se"] is not None else ""
        wrist = f"{100 * lead_['wrist']:+.1f}" if lead_["wrist"] is not None else "–"
        print(
            f"| {c['range_m']} | {c['persons']} | {c['mean_points']:.0f} | "
            + " | ".join(modes)
            + f" | {100 * lead_['oks_acc_3d']:+.2f}{se} | {wrist} |"
        )


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.by_range", description=__doc__.split("\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--run", help="an ablation --out directory (camera.pt, <row>.pt)")
    src.add_argument("--bundle", help="an exported bundle (manifest.json and its ONNX files)")
    p.add_argument("--test", required=True)
    p.add_argument("--rows", default="camera,lidar_reg_seg,fusion_reg_seg", help="--run only")
    p.add_argument(
        "--bands", default=",".join(f"{lo:g}-{hi:g}" for lo, hi in BANDS), help="LO-HI,... in metres"
    )
    p.add_argument("--threads", type=int, default=1, help="--bundle only: ONNX Runtime threads")
    p.add_argument("--json", help="also write the table here")
    a = p.parse_args(argv)
    bands = parse_bands(a.bands)
    if a.bundle:
        table = bundle_table(Path(a.bundle), a.test, bands, a.threads)
        print_bundle_table(table)
    else:
        table = run_table(Path(a.run), a.test, a.rows.split(","), bands)
    if a.json:
        Path(a.json).write_text(json.dumps(table, indent=2))


def run_table(run: Path, test_dir: str, rows: list[str], bands) -> list[dict]:
    test, cfg, _ = data_mod.load(test_dir)
    preds = run_predictions(run, rows, test, cfg)
    table = per_band(test, preds, cfg, bands)
    header = ["range (m)", "persons", "in-box points", *[f"{r} OKS@3D / MPJPE" for r in preds]]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for c in table:
        vals = [f"{pct(c[r]['oks_acc_3d'])} / {cm(c[r]['mpjpe_3d_m'])}" for r in preds]
        print(f"| {c['range_m']} | {c['persons']} | {c['mean_points']:.0f} | " + " | ".join(vals) + " |")
    return table


if __name__ == "__main__":
    main()
