"""The LiDAR-only keypoint profile of ablation runs: each part's OKS as a ratio to the hips', in 3D
and in 2D (the 3D keypoints projected into the image), against the paper's Table 2.

    python -m experiments.profile ../runs/hard ../runs/hard_slim [--row lidar_reg_seg_depth]
    python -m experiments.profile ../runs/hard --test ../data/other_test   # the row scored on another set

The paper's two columns are measured on different sets (docs/DATA.md, "Realism against Waymo's
anchors"): OKS@3D on 986 Waymo pedestrians labelled in 3D, with nets trained on the authors'
internal dataset; OKS@2D on that internal dataset's own test set (42,199 pedestrians). Only the
second is the profile of a net on data like its training data, as every run here is."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from experiments.report import PAPER_T2, PAPER_T2_2D, PAPER_T3, md_table, part_oks
from experiments.runs import run_predictions
from posefuse_train import data as data_mod
from posefuse_train import evaluate

PROFILE_PARTS = ("wrist", "elbow", "knee", "ankle")
KEYS = {"3D": "per_keypoint_oks_3d", "2D": "per_keypoint_oks_2d"}


def ratios(per_part: dict) -> list[float | None]:
    """Each of PROFILE_PARTS over the hips."""
    hip = per_part.get("hip")
    return [per_part[p] / hip if hip and per_part.get(p) is not None else None for p in PROFILE_PARTS]


def run_profile(metrics: dict, dim: str) -> dict:
    return {p: part_oks(metrics, p, KEYS[dim]) for p in ("hip", *PROFILE_PARTS)}


def paper_profile(dim: str) -> dict:
    table = PAPER_T2 if dim == "3D" else PAPER_T2_2D
    return {p: table[p][1] / 100 for p in ("hip", *PROFILE_PARTS)}


def fmt(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def render(runs: dict[str, dict]) -> str:
    header = ["run", "dim", "OKS", "wrist", "hip"] + [f"{p} / hip" for p in PROFILE_PARTS]
    body = []
    for dim in KEYS:
        for name, m in runs.items():
            prof = run_profile(m, dim)
            overall = m["oks_acc_3d" if dim == "3D" else "oks_acc_2d"]
            body.append(
                [name, dim, fmt(100 * overall, 2), fmt(100 * prof["wrist"], 1), fmt(100 * prof["hip"], 1)]
                + [fmt(r) for r in ratios(prof)]
            )
        paper = paper_profile(dim)
        overall = PAPER_T3["lidar_reg_seg"][0 if dim == "3D" else 2]
        body.append(
            [
                "paper, LiDAR-only",
                dim,
                f"{overall:.2f}",
                fmt(100 * paper["wrist"], 1),
                fmt(100 * paper["hip"], 1),
            ]
            + [fmt(r) for r in ratios(paper)]
        )
    return md_table(header, body)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.profile", description=__doc__.split("\n")[0])
    p.add_argument("runs", type=Path, nargs="+", help="ablation run directories (results.json)")
    p.add_argument("--row", default="lidar_reg_seg_depth", help="the row whose profile to show")
    p.add_argument(
        "--test",
        type=Path,
        help="score the row's checkpoint on this held-out set instead of reading results.json",
    )
    a = p.parse_args(argv)
    runs = {}
    if a.test:
        test, cfg, _ = data_mod.load(a.test)
        for run in a.runs:
            pred = run_predictions(run, [a.row], test, cfg)[a.row]
            runs[f"{run.name} on {a.test.name}"] = evaluate.evaluate(pred, test, cfg)
        sys.stdout.write(render(runs) + "\n")
        return
    for run in a.runs:
        rows = json.loads((run / "results.json").read_text())["rows"]
        if a.row not in rows:
            raise SystemExit(f"{run}: no row {a.row} (rows: {', '.join(rows)})")
        runs[run.name] = rows[a.row]["metrics"]
    sys.stdout.write(render(runs) + "\n")


if __name__ == "__main__":
    main()
