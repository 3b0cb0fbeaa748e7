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
from posefuse_train.config import PipelineConfig

from .report import heading_error_table
from .runs import run_heatmaps, run_predictions


def person_errors(count: int, spec: str, seed: int = 0) -> np.ndarray:
    """Heading errors (radians) for `count` persons, as `posefuse eval --heading-noise` draws
    them: DEG gives that error with a random sign per person, `uniform` one from [-180°, 180°)."""
    rng = np.random.default_rng(seed)
    if spec == "uniform":
        return rng.uniform(-np.pi, np.pi, count)
    return np.radians(float(spec)) * rng.choice([-1.0, 1.0], count)


def with_heading_error(test: dict, errors_rad: np.ndarray, cfg: PipelineConfig) -> dict:
    """The held-out set as the pipeline would have prepared it had each box's heading been off by
    its error. In the box-heading frame the model-input frame turns by -error about z (points and
    truth alike; the image side is unchanged) and the frame's yaw carries the error back out to the
    vehicle frame; the view and centred frames do not follow the heading, so only the box changes."""
    err = np.broadcast_to(np.asarray(errors_rad, np.float64), (len(test["box3d"]),))
    out = dict(test)
    out["box3d"] = test["box3d"].copy()
    out["box3d"][:, 6] += err.astype(np.float32)
    if cfg.point_frame() != "box_heading":
        return out
    c, s = np.cos(-err), np.sin(-err)
    rot = np.zeros((len(err), 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    for key in ("points_xyz", "serve_xyz", "kp3d", "sensor_xyz"):
        if key in test:
            v = test[key].reshape(len(err), -1, 3).astype(np.float64)
            out[key] = np.einsum("mij,mkj->mki", rot, v).reshape(test[key].shape).astype(test[key].dtype)
    out["frame_yaw"] = (test["frame_yaw"] + err).astype(test["frame_yaw"].dtype)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(
        prog="python -m experiments.heading_error", description=__doc__.split("\n")[0]
    )
    p.add_argument("--test", required=True)
    p.add_argument("--models", required=True, help="comma-separated RUN_DIR:ROW (an ablation's checkpoints)")
    p.add_argument(
        "--errors", default="0,15,45,90,180,uniform", help="heading errors: degrees (random sign) or uniform"
    )
    p.add_argument("--noise-seed", type=int, default=0)
    p.add_argument("--json", help="also write the table here")
    a = p.parse_args(argv)
    test, cfg, _ = data_mod.load(a.test)
    models = [tuple(m.split(":", 1)) for m in a.models.split(",")]
    raw = {run: run_heatmaps(Path(run), test, cfg) for run in dict.fromkeys(run for run, _ in models)}
    table = []
    for spec in a.errors.split(","):
        shifted = with_heading_error(test, person_errors(len(test["box3d"]), spec, a.noise_seed), cfg)
        cells = {"error_deg": spec if spec == "uniform" else float(spec)}
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
