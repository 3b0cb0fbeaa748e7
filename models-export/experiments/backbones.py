"""Camera backbone study: accuracy vs ONNX Runtime CPU latency (batch 1) at the data's crop size.
Each candidate trains for its epochs (`BACKBONE:WIDTH:EPOCHS`, or --epochs), then is scored on
held-out crops: 2D keypoints decoded from its heatmaps against the exact 2D projections, and the
camera-only 3D baseline (decode + eq. 1 over the serve points).

    python -m experiments.backbones --train data/train --test data/test \
        --candidates resnet18-w16:64:3.7,resnet18-w32:128:1.4,resnet18:256:0.4 --out runs/backbones

--minutes (opt-in) trains every candidate for the same wall-clock time instead (at most 100
epochs); the epochs that fit then depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from posefuse_train import data as data_mod
from posefuse_train import metrics
from posefuse_train.camera_net import CameraNet
from posefuse_train.config import CameraNetConfig
from posefuse_train.evaluate import camera_only, evaluate
from posefuse_train.export import export_onnx, measure_latency
from posefuse_train.fusion import decode_heatmaps
from posefuse_train.train import TrainCameraConfig, predict_heatmaps, train_camera


def pck_2d(pred_uv, data, frac: float) -> float:
    """Fraction of visible keypoints whose decoded model-px position is within frac*S of the label."""
    s = data["image"].shape[1]
    d = np.linalg.norm(pred_uv - data["kp2d"], axis=2)
    vis = metrics.labelled(data, 2)
    return float((d[vis] <= frac * s).mean())


def latency_of(net: CameraNet, s: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "camera.onnx"
        export_onnx(net.cpu().eval(), torch.zeros(1, 3, s, s), path, "image", ["heatmaps"])
        return measure_latency(path, (1, 3, s, s))


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.backbones", description=__doc__.split("\n")[0])
    p.add_argument("--train", required=True)
    p.add_argument("--test", required=True)
    p.add_argument("--out", default="runs/backbones")
    p.add_argument(
        "--candidates",
        default="resnet18-w16:64,resnet18-w32:128,resnet18:256",
        help="comma-separated BACKBONE:DECONV_WIDTH[:EPOCHS]",
    )
    p.add_argument("--epochs", type=float, default=2.0, help="epochs of a candidate that names none")
    p.add_argument(
        "--minutes",
        type=float,
        default=0.0,
        help="opt-in: train every candidate for this wall-clock time instead (at most 100 epochs)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--latency-only", default="resnet50:256", help="candidates only timed (too slow to train here)"
    )
    p.add_argument("--limit-train", type=int)
    p.add_argument("--limit-test", type=int, default=2000)
    a = p.parse_args(argv)
    train, cfg, _ = data_mod.load(a.train, a.limit_train)
    test, _, _ = data_mod.load(a.test, a.limit_test)
    s = cfg.image_size
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for cand in [c for c in a.candidates.split(",") if c]:
        name, width, *epochs = cand.split(":")
        epochs = 100.0 if a.minutes > 0 else float(epochs[0]) if epochs else a.epochs
        net_cfg = CameraNetConfig(backbone=name, deconv_channels=int(width))
        t = time.time()
        train_cfg = TrainCameraConfig(epochs=epochs, time_budget_s=a.minutes * 60, seed=a.seed)
        net = train_camera(train, cfg, net_cfg, train_cfg)
        train_s = time.time() - t
        raw = predict_heatmaps(net, test["image"], cfg)
        uv, _ = decode_heatmaps(raw, s)
        m = evaluate(camera_only(raw, test, cfg), test, cfg)
        row = {
            "backbone": name,
            "deconv_channels": int(width),
            "params_m": sum(x.numel() for x in net.parameters()) / 1e6,
            "train_s": train_s,
            "epochs": net.trained_epochs,
            "pck2d_5pct": pck_2d(uv, test, 0.05),
            "pck2d_10pct": pck_2d(uv, test, 0.10),
            "camera_only_oks3d": m["oks_acc_3d"],
            "camera_only_mpjpe_m": m["mpjpe_3d_m"],
            "camera_only_oks2d": m["oks_acc_2d"],
            "ort_ms_b1": latency_of(net, s),
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
        (out / "backbones.json").write_text(json.dumps({"image_size": s, "rows": rows}, indent=2))
    for cand in [c for c in a.latency_only.split(",") if c]:
        name, width = cand.split(":")[:2]
        net = CameraNet(CameraNetConfig(backbone=name, deconv_channels=int(width)))
        row = {
            "backbone": name,
            "deconv_channels": int(width),
            "params_m": sum(x.numel() for x in net.parameters()) / 1e6,
            "ort_ms_b1": latency_of(net, s),
            "ort_ms_b1_at_256": latency_of(net, 256),
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    command = "python -m experiments.backbones " + " ".join(argv if argv is not None else sys.argv[1:])
    summary = {"image_size": s, "minutes": a.minutes, "command": command, "rows": rows}
    (out / "backbones.json").write_text(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
