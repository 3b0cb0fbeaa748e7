"""The paper's ablation in one command: camera-only; LiDAR-only reg / reg+seg; multi-modal reg /
reg+seg; multi-modal reg+seg with depth-corrected pseudo labels. Trains on one simulated set,
evaluates on another; with --bundle also writes the default bundle, with --results the markdown
report (nothing is written outside --out unless asked).

    python -m experiments.ablation --train data/train --test data/test --out runs/ablation \
        --bundle models/default --results docs/RESULTS.md

Runs a fixed number of epochs per network, so a second run with the same arguments trains the
same models; --budget-min (opt-in) fits the run into a wall-clock budget instead.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from posefuse_train import __version__, evaluate, labels
from posefuse_train import data as data_mod
from posefuse_train.camera_net import as_served, check_heatmap_size, deconv_layers_for, predicted_heatmap_size
from posefuse_train.config import CameraNetConfig, PointNetConfig
from posefuse_train.export import camera_from_checkpoint, export_bundle, export_onnx, measure_latency
from posefuse_train.fusion import smoothed
from posefuse_train.keypoints import K
from posefuse_train.metrics import labelled
from posefuse_train.train import (
    TrainCameraConfig,
    TrainPointConfig,
    checkpoint,
    predict_heatmaps,
    predict_points,
    train_camera,
    train_point,
)

from . import report

# name -> (fusion, seg, depth_correction)
ROWS = {
    "lidar_reg": (False, False, False),
    "lidar_reg_seg": (False, True, False),
    "fusion_reg": (True, False, False),
    "fusion_reg_seg": (True, True, False),
    "fusion_reg_seg_depth": (True, True, True),
    "lidar_reg_seg_depth": (False, True, True),
}


def label_quality(lab: dict, d: dict) -> dict:
    """Diagnostics only (never used for training): pseudo-label error against the 3D truth."""
    ok = lab["visible"] & labelled(d, 3)
    err = np.linalg.norm(lab["kp3d"] - d["kp3d"], axis=2)[ok]
    return {"mean_error_m": float(err.mean()) if err.size else None, "labels": int(ok.sum())}


def degrade_lidar(train: dict, test: dict, sigma: float, seed: int = 0) -> None:
    """A harsher LiDAR for diagnosis: noise on every point the trainer and the evaluation see.
    The points' pixels stay: range noise moves a return along its ray, not across the image."""
    rng = np.random.default_rng(seed)
    for d, key in ((train, "points_xyz"), (test, "points_xyz"), (test, "serve_xyz")):
        d[key] = (d[key] + rng.normal(0.0, sigma, d[key].shape)).astype(d[key].dtype)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.ablation", description=__doc__.split("\n")[0])
    p.add_argument("--train", required=True)
    p.add_argument("--test", required=True)
    p.add_argument("--out", default="runs/ablation")
    p.add_argument("--bundle", help="also write the default bundle here (best fusion + LiDAR rows)")
    p.add_argument(
        "--bundle-version", default=__version__, help="the bundle's version, which every response names"
    )
    p.add_argument(
        "--results", default="", help="also write the markdown report to this file (e.g. docs/RESULTS.md)"
    )
    p.add_argument("--backbones", help="backbones.json of `experiments.backbones` to include in the report")
    p.add_argument("--rows", default=",".join(ROWS), help="comma-separated subset of " + ",".join(ROWS))
    p.add_argument("--limit-train", type=int)
    p.add_argument("--limit-test", type=int)
    p.add_argument("--backbone", default=CameraNetConfig.backbone)
    p.add_argument("--deconv-channels", type=int, default=CameraNetConfig.deconv_channels)
    p.add_argument(
        "--heatmap-size",
        type=int,
        help="heatmap side H, the model's choice like the smoothing (default: the data's S/4); "
        "the camera net gets the deconvolutions that make it",
    )
    p.add_argument(
        "--sampling",
        choices=["nearest", "bilinear"],
        help="how points read the smoothed heatmaps (the model's choice; default the data's, nearest)",
    )
    p.add_argument(
        "--final-shuffle",
        type=int,
        default=CameraNetConfig.final_shuffle,
        help="sub-cells per heatmap cell side from the last 1x1 conv (pixel shuffle); 2 with "
        "--heatmap-size S/2 keeps the three deconvolutions",
    )
    p.add_argument("--camera-epochs", type=float, default=TrainCameraConfig.epochs)
    p.add_argument("--camera-lr", type=float, default=TrainCameraConfig.lr)
    p.add_argument(
        "--camera-facing-weight",
        type=float,
        default=TrainCameraConfig.facing_weight,
        help="> 0: train the camera net with a facing target of this weight (docs/TRAINING.md)",
    )
    p.add_argument("--camera-checkpoint", help="reuse a trained camera net instead of training one")
    p.add_argument(
        "--flip-test",
        action="store_true",
        help="the camera net answers with the mean of the crop's and its mirror's heatmaps "
        "(docs/TRAINING.md, 'Flip test'): the point nets train on those, the report and the bundle use them",
    )
    p.add_argument(
        "--point-epochs",
        type=float,
        default=8.0,
        help="epochs of every point-net row (docs/RESULTS.md's runs: 7.95)",
    )
    p.add_argument("--point-lr", type=float, default=TrainPointConfig.lr)
    p.add_argument("--point-optimizer", default=TrainPointConfig.optimizer, choices=["sgd", "adam"])
    p.add_argument("--rotate-deg", type=float, default=TrainPointConfig.rotate_deg)
    p.add_argument(
        "--seed", type=int, default=TrainPointConfig.seed, help="point nets' initialisation and sampling"
    )
    p.add_argument(
        "--seg-weight",
        type=float,
        default=TrainPointConfig.seg_weight,
        help="lambda; the segmentation loss is a mean over points (x N = the paper's sum)",
    )
    p.add_argument(
        "--budget-min",
        type=float,
        default=0.0,
        help="opt-in wall-clock budget of the whole run (minutes): the camera net gets --camera-share of "
        "it and the point rows the rest, so the epochs run depend on the machine; 0 (default): train "
        "for the given epochs",
    )
    p.add_argument(
        "--camera-share", type=float, default=0.25, help="share of the training budget for the camera net"
    )
    p.add_argument(
        "--smoothing-sigma",
        type=float,
        help="heatmap smoothing sigma in heatmap cells (default: the data's); the kernel is the odd "
        "size 2*ceil(sigma)+1 (7 for the paper's sigma = 3)",
    )
    p.add_argument("--t-r", type=float, default=200.0, help="reliability temperature T_r (S units)")
    p.add_argument(
        "--lidar-noise",
        type=float,
        default=0.0,
        help="diagnostic: extra isotropic Gaussian noise (metres) on every LiDAR point, train and test",
    )
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    rows = [r for r in a.rows.split(",") if r]
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        p.error(f"unknown rows {unknown}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log_lines: list[str] = []

    def log(msg):
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        print(line, flush=True)
        log_lines.append(line)

    t_start = time.time()
    timings = {}
    train, cfg, train_meta = data_mod.load(a.train, a.limit_train)
    test, test_cfg, test_meta = data_mod.load(a.test, a.limit_test)
    if cfg != test_cfg:
        raise SystemExit(f"train and test preprocessing differ:\n{cfg}\n{test_cfg}")
    if a.lidar_noise > 0:
        degrade_lidar(train, test, a.lidar_noise)
    if a.heatmap_size is not None:
        cfg = dataclasses.replace(cfg, heatmap_size=a.heatmap_size)
    if a.sampling is not None:
        cfg = dataclasses.replace(cfg, sampling=a.sampling)
    if a.smoothing_sigma is not None:
        # Smoothing is the model's, not the data's: it goes into the bundle's manifest.
        kernel = 2 * int(np.ceil(a.smoothing_sigma)) + 1
        cfg = dataclasses.replace(cfg, smoothing_sigma=a.smoothing_sigma, smoothing_kernel=kernel)
    log(
        f"data: {len(train['kp2d'])} train, {len(test['kp2d'])} test persons, "
        f"S={cfg.image_size}, N={cfg.num_points}"
    )
    timings["load_s"] = time.time() - t_start

    t = time.time()
    plain = labels.pseudo_labels(train, cfg, a.t_r)
    corrected = (
        labels.pseudo_labels(train, cfg, a.t_r, depth_correction=True)
        if any(ROWS[r][2] for r in rows)
        else None
    )
    quality = {"eq1": label_quality(plain, train)}
    if corrected is not None:
        quality["eq1_depth_corrected"] = label_quality(corrected, train)
    timings["labels_s"] = time.time() - t
    log(f"pseudo labels in {timings['labels_s']:.0f}s; quality (diagnostic, 3D truth): {quality}")

    # Time left for training, after a reserve for heatmap inference, evaluation and export.
    train_s = max(60.0, a.budget_min * 60 - (time.time() - t_start) - 150) if a.budget_min > 0 else 0.0
    cam_budget = 0.0 if a.camera_checkpoint else train_s * a.camera_share
    row_budget = 0.0

    # camera network
    t = time.time()
    cam_cfg = TrainCameraConfig(
        epochs=a.camera_epochs,
        lr=a.camera_lr,
        time_budget_s=cam_budget,
        facing_weight=a.camera_facing_weight,
        flip_test=a.flip_test,
    )
    if a.camera_checkpoint:
        cam_ckpt = torch.load(a.camera_checkpoint, map_location="cpu", weights_only=False)
        camera = camera_from_checkpoint(cam_ckpt).to(a.device)
        if a.heatmap_size is None:
            # the reused net's heatmaps decide the grid the fusion samples
            cfg = dataclasses.replace(cfg, heatmap_size=predicted_heatmap_size(cfg.image_size, camera.cfg))
        check_heatmap_size(cfg.image_size, cfg.heatmap_size, camera.cfg)
        cam_cfg = TrainCameraConfig(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in cam_ckpt["train_config"].items()}
        )
        cam_cfg = dataclasses.replace(cam_cfg, flip_test=a.flip_test)
        log(f"camera: reusing {a.camera_checkpoint}")
        # the run directory stays self-contained for by_range / heading_error
        if Path(a.camera_checkpoint).resolve() != (out / "camera.pt").resolve():
            shutil.copyfile(a.camera_checkpoint, out / "camera.pt")
    else:
        net_cfg = CameraNetConfig(
            backbone=a.backbone,
            deconv_channels=a.deconv_channels,
            deconv_layers=deconv_layers_for(cfg.image_size, cfg.heatmap_size, a.final_shuffle),
            final_shuffle=a.final_shuffle,
            facing_head=a.camera_facing_weight > 0,
        )
        camera = train_camera(train, cfg, net_cfg, cam_cfg, a.device, log=log)
        torch.save(checkpoint(camera, cfg, cam_cfg, str(a.train)), out / "camera.pt")
    timings["camera_train_s"] = time.time() - t
    plain_camera, camera = camera, as_served(camera, a.flip_test)
    t = time.time()
    raw_train = predict_heatmaps(camera, train["image"], cfg, a.device)
    raw_test = predict_heatmaps(camera, test["image"], cfg, a.device)
    sm_train, sm_test = smoothed(raw_train, cfg), smoothed(raw_test, cfg)
    del raw_train
    timings["heatmaps_s"] = time.time() - t
    camera = camera.cpu().eval()
    with tempfile.TemporaryDirectory() as tmp:
        lat_path = Path(tmp) / "camera.onnx"
        export_onnx(
            camera, torch.zeros(1, 3, cfg.image_size, cfg.image_size), lat_path, "image", ["heatmaps"]
        )
        cam_latency = measure_latency(lat_path, (1, 3, cfg.image_size, cfg.image_size))
    cam_pred = evaluate.camera_only(raw_test, test, cfg)
    results = {
        "camera": {
            "config": {
                "backbone": camera.cfg.backbone,
                "deconv_channels": camera.cfg.deconv_channels,
                "deconv_layers": camera.cfg.deconv_layers,
                "final_shuffle": camera.cfg.final_shuffle,
                **dataclasses.asdict(cam_cfg),
            },
            "metrics": evaluate.evaluate(cam_pred, test, cfg),
            "train_s": timings["camera_train_s"],
            "ort_latency_ms_b1": cam_latency,
            "params": sum(p.numel() for p in camera.parameters()),
            "epochs": getattr(plain_camera, "trained_epochs", 0.0),
        }
    }
    if a.flip_test:
        raw_plain = predict_heatmaps(plain_camera, test["image"], cfg, a.device)
        results["camera"]["metrics_without_flip_test"] = evaluate.evaluate(
            evaluate.camera_only(raw_plain, test, cfg), test, cfg
        )
    m = results["camera"]["metrics"]
    log(
        f"camera-only: OKS@3D {m['oks_acc_3d']:.4f} MPJPE {m['mpjpe_3d_m']:.4f} "
        f"OKS@2D {m['oks_acc_2d']:.4f}, "
        f"ORT {cam_latency:.2f} ms"
    )

    # point networks. Every row gets the same number of steps, the first row's (--point-epochs).
    # Under the opt-in budget the most expensive row present (fusion + seg) runs first under its
    # share and fixes the count for the others, which are capped at 1.3x the budget in case the
    # shared CPU gets busier.
    if a.budget_min > 0:
        row_budget = max(30.0, (a.budget_min * 60 - 120 - (time.time() - t_start)) / max(1, len(rows)))
    nets, epochs, steps = {}, a.point_epochs, 0
    order = sorted(rows, key=lambda r: (not ROWS[r][0], not ROWS[r][1], ROWS[r][2]))
    for name in order:
        fusion, seg, depth = ROWS[name]
        t = time.time()
        first = name == order[0]
        pcfg = TrainPointConfig(
            fusion=fusion,
            seg=seg,
            epochs=epochs,
            steps=steps,
            lr=a.point_lr,
            optimizer=a.point_optimizer,
            rotate_deg=a.rotate_deg,
            seed=a.seed,
            seg_weight=a.seg_weight,
            depth_correction=depth,
            time_budget_s=row_budget * (1.0 if first else 1.3),
        )
        net_cfg = PointNetConfig(in_features=3 + K if fusion else 3)
        lab = corrected if depth else plain
        net = train_point(train, lab, sm_train if fusion else None, cfg, net_cfg, pcfg, a.device, name, log)
        net = net.cpu()
        if first:
            epochs, steps = net.trained_epochs, len(net.loss_history)
        train_s = time.time() - t
        pred = predict_points(net, test["serve_xyz"], test["serve_uv"], sm_test if fusion else None, cfg)
        pred = evaluate.with_fallback(pred, cam_pred, test, cfg)
        metrics = evaluate.evaluate(pred, test, cfg)
        results[name] = {
            "config": {
                **dataclasses.asdict(pcfg),
                "depth_correction": depth,
                "net": dataclasses.asdict(net_cfg),
            },
            "metrics": metrics,
            "train_s": train_s,
            "steps": len(net.loss_history),
        }
        nets[name] = net
        torch.save(checkpoint(net, cfg, pcfg, str(a.train)), out / f"{name}.pt")
        log(
            f"{name}: OKS@3D {metrics['oks_acc_3d']:.4f} MPJPE {metrics['mpjpe_3d_m']:.4f} "
            f"OKS@2D {metrics['oks_acc_2d']:.4f} ({train_s:.0f}s)"
        )
        (out / "results.json").write_text(json.dumps(results, indent=2))

    results = {k: results[k] for k in ["camera", *ROWS] if k in results}
    wall = time.time() - t_start
    summary = {
        "command": "python -m experiments.ablation "
        + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:])),
        "wall_s": wall,
        "timings": timings,
        "train": {
            "path": str(a.train),
            "count": len(train["kp2d"]),
            "meta": {k: v for k, v in train_meta.items() if k != "preprocessing"},
        },
        "test": {
            "path": str(a.test),
            "count": len(test["kp2d"]),
            "meta": {k: v for k, v in test_meta.items() if k != "preprocessing"},
        },
        "preprocessing": cfg.to_dict(),
        "label_quality": quality,
        "t_r": a.t_r,
        "machine": f"{platform.machine()}, {torch.get_num_threads()} torch threads, device {a.device}",
        "point_epochs": epochs,
        "rows": results,
    }
    (out / "results.json").write_text(json.dumps(summary, indent=2))
    log(f"ablation done in {wall / 60:.1f} min -> {out / 'results.json'}")

    if a.bundle:
        fusion_rows = [r for r in nets if ROWS[r][0]]
        lidar_rows = [r for r in nets if not ROWS[r][0]]
        if fusion_rows and lidar_rows:
            best_f = max(fusion_rows, key=lambda r: results[r]["metrics"]["oks_acc_3d"])
            best_l = max(lidar_rows, key=lambda r: results[r]["metrics"]["oks_acc_3d"])
            manifest = export_bundle(
                a.bundle,
                camera,
                nets[best_f],
                nets[best_l],
                cfg,
                trained=True,
                training={
                    "data": {"train": str(a.train), "test": str(a.test), "train_count": len(train["kp2d"])},
                    "config": {
                        "camera": results["camera"]["config"],
                        "fusion": results[best_f]["config"],
                        "lidar": results[best_l]["config"],
                        "fusion_row": best_f,
                        "lidar_row": best_l,
                    },
                },
                metrics={
                    "fusion": results[best_f]["metrics"],
                    "lidar": results[best_l]["metrics"],
                    "camera": results["camera"]["metrics"],
                },
                version=a.bundle_version,
            )
            summary["bundle"] = {
                "path": a.bundle,
                "fusion_row": best_f,
                "lidar_row": best_l,
                "size_mb": sum(
                    (Path(a.bundle) / mm["file"]).stat().st_size for mm in manifest["models"].values()
                )
                / 1e6,
            }
            log(
                f"bundle -> {a.bundle} (fusion: {best_f}, LiDAR: {best_l}, "
                f"{summary['bundle']['size_mb']:.1f} MB)"
            )
        else:
            log("bundle skipped: needs at least one fusion and one LiDAR row")
        (out / "results.json").write_text(json.dumps(summary, indent=2))

    if a.results:
        Path(a.results).parent.mkdir(parents=True, exist_ok=True)
        backbones = json.loads(Path(a.backbones).read_text()) if a.backbones else None
        Path(a.results).write_text(report.results_markdown(summary, backbones))
        log(f"wrote {a.results}")
    (out / "ablation.log").write_text("\n".join(log_lines) + "\n")


if __name__ == "__main__":
    main()
