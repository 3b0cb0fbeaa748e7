"""How good the camera must be for fusion to pay. No camera net: the fusion net trains and is
scored on heatmaps drawn from the 2D labels with an error of a chosen size (a Gaussian of the
training targets' width at each labelled keypoint, moved by isotropic noise of `sigma` x S pixels;
with `--swap`, that share of persons has left and right exchanged), against one LiDAR-only net
trained once, on the same data, the same steps and the server's pre-processing. Each level reports
the synthetic camera's own camera-only score, so that the fusion margin can be read against the
camera-only OKS@2D that a real camera net reaches.

    python -m experiments.camera_quality --train ../data/hard64_train --test ../data/hard64_test \
        --levels 0:0,0.02:0,0.04:0 --out ../runs/camera_quality
    python -m experiments.camera_quality ... --calibrate 0.01,0.02,0.04   # camera-only scores only

The errors are independent of the LiDAR's and of each other, unlike a real camera's, which fails
on the same far, dark and occluded persons as the points do: read the margins as what a camera of
that score could give at best (docs/RESULTS.md, "How good the camera must be")."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from posefuse_train import data as data_mod
from posefuse_train import evaluate, labels
from posefuse_train.config import PointNetConfig
from posefuse_train.fusion import smoothed
from posefuse_train.keypoints import FLIP, K
from posefuse_train.losses import heatmap_targets
from posefuse_train.metrics import labelled
from posefuse_train.train import TrainPointConfig, next_round_labels, predict_points, train_point

from .report import part_oks

PARTS = ("wrist", "elbow", "hip")


def synthetic_heatmaps(
    data: dict, image_size: int, heatmap_size: int, sigma: float, swap: float, seed: int, chunk: int = 2048
) -> np.ndarray:
    """Raw heatmaps [M,K,H,H]: a unit Gaussian (one cell wide, as the camera net's targets) at each
    labelled 2D keypoint moved by N(0, (sigma * S)^2) per axis; `swap` of the persons mirrored."""
    rng = np.random.default_rng(seed)
    kp = np.asarray(data["kp2d"], np.float32).copy()
    known = labelled(data, 2).astype(np.float32)
    mirrored = rng.random(len(kp)) < swap
    kp[mirrored] = kp[mirrored][:, FLIP]
    known[mirrored] = known[mirrored][:, FLIP]
    kp += rng.normal(0.0, sigma * image_size, kp.shape).astype(np.float32)
    out = np.empty((len(kp), K, heatmap_size, heatmap_size), np.float32)
    for a in range(0, len(kp), chunk):
        t, _ = heatmap_targets(
            torch.from_numpy(kp[a : a + chunk]),
            torch.from_numpy(known[a : a + chunk]),
            image_size,
            heatmap_size,
            1.0,
        )
        out[a : a + chunk] = t.numpy()
    return out


def truth_labels(data: dict, where: np.ndarray | None = None) -> dict:
    """The simulator's 3D keypoints as training labels, in the shape of `labels.pseudo_labels`:
    every labelled keypoint (or those of them `where` says), weight 1."""
    known = labelled(data, 3) & np.isfinite(data["kp3d"]).all(axis=2)
    if where is not None:
        known &= where
    kp3d = np.where(known[..., None], np.nan_to_num(data["kp3d"]), 0.0).astype(np.float32)
    return {"kp3d": kp3d, "weight": known.astype(np.float32), "visible": known}


def summary(m: dict) -> dict:
    return {
        "oks_3d": m["oks_acc_3d"],
        "mpjpe_m": m["mpjpe_3d_m"],
        "oks_2d": m.get("oks_acc_2d"),
        "swaps": m.get("left_right_swap_rate"),
        **{p: part_oks(m, p, "per_keypoint_oks_3d") for p in PARTS},
        **{
            f"{b}_{key}": m["breakdown"][b][metric]
            for b in ("visible", "occluded")
            for key, metric in (("oks_3d", "oks_acc_3d"), ("mpjpe_m", "mpjpe_3d_m"))
            if "breakdown" in m
        },
    }


def parse_levels(text: str) -> list[tuple[float, float]]:
    return [(float(s), float(w)) for s, w in (lv.split(":") for lv in text.split(",") if lv)]


def main(argv=None):
    p = argparse.ArgumentParser(
        prog="python -m experiments.camera_quality", description=__doc__.split("\n")[0]
    )
    p.add_argument("--train", required=True)
    p.add_argument("--test", required=True)
    p.add_argument("--out", default="runs/camera_quality")
    p.add_argument("--levels", default="0:0", help="comma-separated sigma:swap pairs (sigma in units of S)")
    p.add_argument("--calibrate", help="comma-separated sigmas: print the camera-only scores and stop")
    p.add_argument("--swap", type=float, default=0.0, help="with --calibrate: the mirrored share")
    p.add_argument("--heatmap-size", type=int, default=32)
    p.add_argument("--smoothing-sigma", type=float, default=1.5)
    p.add_argument("--sampling", choices=["nearest", "bilinear"], default="bilinear")
    p.add_argument("--point-steps", type=int, default=1153, help="the recipe cpu128-flip's")
    p.add_argument("--seed", type=int, default=0, help="point nets' initialisation and sampling")
    p.add_argument("--t-r", type=float, default=200.0)
    p.add_argument(
        "--supervision",
        choices=["pseudo", "truth", "truth-where-pseudo"],
        default="pseudo",
        help="pseudo: the depth-corrected pseudo labels from the 2D labels (the project's way); truth: "
        "the simulator's 3D keypoints, a diagnostic of what full 3D supervision would allow; "
        "truth-where-pseudo: the 3D keypoints only where a pseudo label exists (error without gaps)",
    )
    p.add_argument(
        "--occluded-weight",
        type=float,
        default=0.0,
        help="with pseudo supervision: occluded 2D labels with no point near them get a label on "
        "their camera ray at the box centre's depth, at this weight (labels.occluded_labels)",
    )
    p.add_argument(
        "--snap-to-rays",
        action="store_true",
        help="with pseudo supervision: each pseudo label moved onto its 2D label's camera ray at the "
        "depth it had (labels.snapped_to_label_rays)",
    )
    p.add_argument(
        "--self-train",
        type=float,
        default=0.0,
        help="> 0: a second round of both point nets on labels.relabelled() from the first round's "
        "blend, its labels without a first-round label at this weight",
    )
    p.add_argument("--limit-train", type=int)
    p.add_argument("--threads", type=int, default=0)
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    train, cfg, _ = data_mod.load(a.train, a.limit_train)
    test, test_cfg, _ = data_mod.load(a.test)
    if cfg != test_cfg:
        raise SystemExit("train and test preprocessing differ")
    kernel = 2 * int(np.ceil(a.smoothing_sigma)) + 1
    cfg = dataclasses.replace(
        cfg,
        heatmap_size=a.heatmap_size,
        sampling=a.sampling,
        smoothing_sigma=a.smoothing_sigma,
        smoothing_kernel=kernel,
    )

    def camera(data: dict, sigma: float, swap: float, seed: int) -> np.ndarray:
        return synthetic_heatmaps(data, cfg.image_size, cfg.heatmap_size, sigma, swap, seed)

    if a.calibrate:
        for sigma in (float(s) for s in a.calibrate.split(",")):
            raw = camera(test, sigma, a.swap, 2)
            m = evaluate.evaluate(evaluate.camera_only(raw, test, cfg), test, cfg)
            print(json.dumps({"sigma": sigma, "swap": a.swap, "camera_only": summary(m)}), flush=True)
        return

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)

    lab = labels.pseudo_labels(
        train,
        cfg,
        a.t_r,
        True,
        occluded_weight=a.occluded_weight,
        snap_to_rays=a.snap_to_rays,
    )
    if a.supervision == "truth":
        lab = truth_labels(train)
    elif a.supervision == "truth-where-pseudo":
        lab = truth_labels(train, lab["visible"])

    def point_net(fusion: bool, heatmaps, lab: dict = lab) -> torch.nn.Module:
        pcfg = TrainPointConfig(
            fusion=fusion, seg=True, steps=a.point_steps, seed=a.seed, depth_correction=True
        )
        net_cfg = PointNetConfig(in_features=3 + K if fusion else 3)
        name = "fusion" if fusion else "lidar"
        return train_point(train, lab, heatmaps, cfg, net_cfg, pcfg, "cpu", name, log, t_r=a.t_r).cpu()

    t = time.time()
    lidar = point_net(False, None)
    pred_lidar = predict_points(lidar, test["serve_xyz"], test["serve_uv"], None, cfg)
    results = {
        "command": " ".join(sys.argv[1:] if argv is None else argv),
        "supervision": a.supervision,
        "occluded_weight": a.occluded_weight,
        "snap_to_rays": a.snap_to_rays,
        "self_train": a.self_train,
        "lidar_train_s": time.time() - t,
        "levels": [],
    }
    for sigma, swap in parse_levels(a.levels):
        t = time.time()
        raw_test = camera(test, sigma, swap, 2)
        sm_train, sm_test = smoothed(camera(train, sigma, swap, 1), cfg), smoothed(raw_test, cfg)
        cam_pred = evaluate.camera_only(raw_test, test, cfg)
        fusion = point_net(True, sm_train)
        pred_fusion = predict_points(fusion, test["serve_xyz"], test["serve_uv"], sm_test, cfg)

        def scored(pred: np.ndarray, cam_pred: np.ndarray = cam_pred) -> dict:
            return summary(evaluate.evaluate(evaluate.with_fallback(pred, cam_pred, test, cfg), test, cfg))

        level = {
            "sigma": sigma,
            "swap": swap,
            "camera_only": summary(evaluate.evaluate(cam_pred, test, cfg)),
            "fusion": scored(pred_fusion),
            "lidar": scored(pred_lidar),
            "blend": scored((pred_fusion + pred_lidar) / 2),
            "train_s": time.time() - t,
        }
        if a.self_train > 0:
            second = TrainPointConfig(self_train=a.self_train)
            lab2 = next_round_labels(train, lab, (fusion, lidar), sm_train, cfg, second)
            lidar2, fusion2 = point_net(False, None, lab2), point_net(True, sm_train, lab2)
            pred_lidar2 = predict_points(lidar2, test["serve_xyz"], test["serve_uv"], None, cfg)
            pred_fusion2 = predict_points(fusion2, test["serve_xyz"], test["serve_uv"], sm_test, cfg)
            level["round2"] = {
                "fusion": scored(pred_fusion2),
                "lidar": scored(pred_lidar2),
                "blend": scored((pred_fusion2 + pred_lidar2) / 2),
                "labels": int((lab2["weight"] > 0).sum()),
            }
        results["levels"].append(level)
        (out / "results.json").write_text(json.dumps(results, indent=2))
        f, li, c = level["fusion"], level["lidar"], level["camera_only"]
        log(
            f"sigma {sigma} swap {swap}: camera-only OKS@2D {c['oks_2d']:.4f}; fusion {f['oks_3d']:.4f} "
            f"vs LiDAR {li['oks_3d']:.4f} ({100 * (f['oks_3d'] - li['oks_3d']):+.2f} pt, wrists "
            f"{100 * (f['wrist'] - li['wrist']):+.1f}); blend {level['blend']['oks_3d']:.4f}"
        )
        if "round2" in level:
            r = level["round2"]
            log(
                f"round 2: fusion {r['fusion']['oks_3d']:.4f} vs LiDAR {r['lidar']['oks_3d']:.4f}; "
                f"blend {r['blend']['oks_3d']:.4f} / {r['blend']['mpjpe_m'] * 100:.2f} cm"
            )


if __name__ == "__main__":
    main()
