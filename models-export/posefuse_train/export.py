"""ONNX export of the camera and point networks plus the bundle manifest (docs/BUNDLE.md).

Every model is checked against ONNX Runtime on random inputs (batch 1 and 3, so the dynamic batch
axis is exercised) before anything is written; a mismatch above `tol` aborts the export.

    python -m posefuse_train.export --untrained --out models/default --image-size 64
    python -m posefuse_train.export --camera runs/x/camera.pt --fusion runs/x/fusion.pt \
        --lidar runs/x/lidar.pt --out models/default
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import hashlib
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from . import __version__
from .camera_net import CameraNet, FlipTest, as_served, check_heatmap_size, deconv_layers_for
from .config import CameraNetConfig, PipelineConfig, PointNetConfig
from .facing_net import FacingPointNet
from .keypoints import NAMES, WAYMO_TYPES, K
from .metrics import CONVENTION
from .point_net import Blend, PointNet, PointNetExport

OPSET = 17
FORMAT_VERSION = 1


class ParityError(RuntimeError):
    pass


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def export_onnx(model: torch.nn.Module, example: torch.Tensor, path: Path, input_name: str, output_names):
    model.eval()
    dynamic = {input_name: {0: "batch"}}
    for name in output_names:
        dynamic[name] = {0: "batch"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            (example,),
            str(path),
            input_names=[input_name],
            output_names=list(output_names),
            dynamic_axes=dynamic,
            opset_version=OPSET,
            dynamo=False,
        )
    onnx.checker.check_model(onnx.load(str(path)))


def check_parity(model: torch.nn.Module, path: Path, make_input, tol: float) -> float:
    """Max abs difference between PyTorch and ONNX Runtime over batches of 1 and 3."""
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    in_name = sess.get_inputs()[0].name
    worst = 0.0
    model.eval()
    for b in (1, 3):
        x = make_input(b)
        with torch.no_grad():
            ref = model(x)
        ref = ref if isinstance(ref, (tuple, list)) else (ref,)
        got = sess.run(None, {in_name: x.numpy()})
        for r, g in zip(ref, got, strict=True):
            if tuple(r.shape) != tuple(g.shape):
                raise ParityError(f"{path.name}: shape {tuple(g.shape)} != torch {tuple(r.shape)}")
            worst = max(worst, float(np.max(np.abs(r.numpy() - g))))
    if not worst <= tol:
        raise ParityError(f"{path.name}: ONNX Runtime differs from PyTorch by {worst:.3g} > {tol}")
    return worst


def export_bundle(
    out_dir: str | os.PathLike,
    camera: CameraNet | FlipTest,
    fusion: PointNet | FacingPointNet | Blend,
    lidar: PointNet | FacingPointNet,
    pipeline: PipelineConfig,
    *,
    trained: bool,
    training: dict | None = None,
    metrics: dict | None = None,
    name: str = "default",
    version: str = __version__,
    tol: float = 1e-4,
) -> dict:
    """Exports the three networks and manifest.json into out_dir; returns the manifest.

    Files are written to a temporary directory first and only moved into place when every parity
    check passed, so a failed export never leaves a half-written bundle behind."""
    s, h, n = pipeline.image_size, pipeline.heatmap_size, pipeline.num_points
    check_heatmap_size(s, h, camera.cfg)
    if fusion.cfg.in_features != 3 + K or lidar.cfg.in_features != 3:
        raise ValueError("fusion net must take 3+K features and lidar net 3")
    out_dir = Path(out_dir)
    gen = torch.Generator().manual_seed(0)

    def image_input(b):
        return torch.randn(b, 3, s, s, generator=gen)

    def points_input(c):
        def make(b):
            xyz = torch.randn(b, n, 3, generator=gen) * 0.5
            feats = torch.rand(b, n, c - 3, generator=gen)
            return torch.cat([xyz, feats], dim=2)

        return make

    flip_test = {"flip_test": True} if isinstance(camera, FlipTest) else {}
    blend = {"blend": fusion.names} if isinstance(fusion, Blend) else {}
    specs = {
        "camera": dict(
            file="camera.onnx",
            model=camera.cpu().eval(),
            make=image_input,
            input="image",
            inputs={"image": [-1, 3, s, s]},
            outputs={"heatmaps": [-1, K, h, h]},
            extra={"backbone": camera.cfg.backbone, **flip_test},
        ),
        "point_fusion": dict(
            file="point_fusion.onnx",
            model=PointNetExport(fusion.cpu()).eval(),
            make=points_input(3 + K),
            input="points",
            inputs={"points": [-1, n, 3 + K]},
            outputs={"keypoints": [-1, K, 3], "segmentation": [-1, n, K]},
            extra=blend,
        ),
        "point_lidar": dict(
            file="point_lidar.onnx",
            model=PointNetExport(lidar.cpu()).eval(),
            make=points_input(3),
            input="points",
            inputs={"points": [-1, n, 3]},
            outputs={"keypoints": [-1, K, 3], "segmentation": [-1, n, K]},
            extra={},
        ),
    }
    models, parity = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for key, sp in specs.items():
            path = tmp / sp["file"]
            export_onnx(sp["model"], sp["make"](1), path, sp["input"], list(sp["outputs"]))
            parity[key] = check_parity(sp["model"], path, sp["make"], tol)
            models[key] = {
                "file": sp["file"],
                "sha256": sha256(path),
                **sp["extra"],
                "inputs": sp["inputs"],
                "outputs": sp["outputs"],
            }
        manifest = {
            "format_version": FORMAT_VERSION,
            "name": name,
            "version": version,
            "created": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "keypoints": {"names": list(NAMES), "waymo_types": list(WAYMO_TYPES)},
            "preprocessing": pipeline.to_dict(),
            "models": models,
            "training": {
                "data": (training or {}).get("data"),
                "config": {**(training or {}).get("config", {}), "onnx_parity_max_abs_diff": parity},
                "trained": bool(trained),
            },
            "metrics": {
                "held_out": metrics or {"fusion": {}, "lidar": {}, "camera": {}},
                "convention": CONVENTION,
            },
        }
        with open(tmp / "manifest.json", "w") as f:
            json.dump(manifest, f, indent=2)
            f.write("\n")
        out_dir.mkdir(parents=True, exist_ok=True)
        for sp in specs.values():
            shutil.move(str(tmp / sp["file"]), out_dir / sp["file"])
        shutil.move(str(tmp / "manifest.json"), out_dir / "manifest.json")
    return manifest


def untrained_models(pipeline: PipelineConfig, camera_cfg: CameraNetConfig | None = None, seed: int = 0):
    torch.manual_seed(seed)
    camera = CameraNet(camera_cfg or CameraNetConfig())
    fusion = PointNet(PointNetConfig(in_features=3 + K))
    lidar = PointNet(PointNetConfig(in_features=3))
    return camera, fusion, lidar


def load_checkpoint(path: str | os.PathLike) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def camera_from_checkpoint(ckpt: dict) -> CameraNet:
    net = CameraNet(CameraNetConfig(**ckpt["config"]))
    net.load_state_dict(ckpt["state_dict"])
    return net.eval()


def point_from_checkpoint(ckpt: dict) -> PointNet:
    cfg = dict(ckpt["config"])
    cfg = {k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items()}
    net = PointNet(PointNetConfig(**cfg))
    net.load_state_dict(ckpt["state_dict"])
    return net.eval()


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m posefuse_train.export", description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True, help="bundle directory to write")
    p.add_argument("--untrained", action="store_true", help="random weights (for server tests only)")
    p.add_argument("--image-size", type=int, default=64, help="crop side S (untrained bundles)")
    p.add_argument("--backbone", default=CameraNetConfig.backbone, help="camera backbone (untrained)")
    p.add_argument("--heatmap-size", type=int, help="heatmap side H (untrained; default S/4)")
    p.add_argument(
        "--final-shuffle", type=int, default=1, help="the camera net's sub-cells per cell side (untrained)"
    )
    p.add_argument("--camera", help="camera checkpoint (.pt) of a trained model")
    p.add_argument("--fusion", help="fusion point-net checkpoint (.pt)")
    p.add_argument("--lidar", help="LiDAR-only point-net checkpoint (.pt)")
    p.add_argument(
        "--facing-fusion",
        help="a fusion point net trained with rotation over [0, 2π) (.pt) that reads the facing for --fusion",
    )
    p.add_argument("--facing-lidar", help="the same for --lidar (both or neither)")
    p.add_argument(
        "--facing-passes", type=int, default=1, help="refinement passes inside the graph (with --facing-*)"
    )
    p.add_argument("--facing-turns", type=int, default=1, help="turns of the input the facing nets answer at")
    p.add_argument(
        "--facing-agree-deg",
        type=float,
        default=0.0,
        help="keep the box frame where the facing net agrees with it within this many degrees (0: never)",
    )
    flip = p.add_mutually_exclusive_group()
    flip.add_argument(
        "--flip-test",
        action="store_true",
        help="export the camera net with its mirror pass inside the graph (docs/TRAINING.md, 'Flip test'); "
        "a camera checkpoint trained with flip_test gets it without the flag",
    )
    flip.add_argument(
        "--no-flip-test",
        action="store_true",
        help="export a camera net trained with flip_test without its mirror pass: half the camera's cost, "
        "for what the mirror pass adds (docs/TRAINING.md, 'Flip test')",
    )
    p.add_argument(
        "--blend",
        action="store_true",
        help="the fusion graph answers the mean of the fusion and the LiDAR-only networks "
        "(docs/TRAINING.md, 'Blending the point networks')",
    )
    p.add_argument("--metrics", help="JSON file with held-out metrics {fusion, lidar, camera}")
    p.add_argument("--name", default="default")
    p.add_argument("--version", default=__version__, help="the bundle's version, which every response names")
    p.add_argument("--tol", type=float, default=1e-4)
    a = p.parse_args(argv)
    if a.untrained:
        pipeline = PipelineConfig.with_image_size(a.image_size)
        if a.heatmap_size:
            pipeline = dataclasses.replace(pipeline, heatmap_size=a.heatmap_size)
        layers = deconv_layers_for(pipeline.image_size, pipeline.heatmap_size, a.final_shuffle)
        cam_cfg = CameraNetConfig(backbone=a.backbone, deconv_layers=layers, final_shuffle=a.final_shuffle)
        camera, fusion, lidar = untrained_models(pipeline, cam_cfg)
        training, metrics = {"data": None, "config": {"camera": dataclasses.asdict(camera.cfg)}}, None
        trained = False
    else:
        if not (a.camera and a.fusion and a.lidar):
            p.error("either --untrained or all of --camera, --fusion, --lidar")
        cam_ckpt, fus_ckpt, lid_ckpt = (load_checkpoint(x) for x in (a.camera, a.fusion, a.lidar))
        pipeline = PipelineConfig.from_dict(cam_ckpt["pipeline"])
        camera = camera_from_checkpoint(cam_ckpt)
        # Checkpoints from before the trainer recorded its config have none.
        trained_with_flip = (cam_ckpt.get("train_config") or {}).get("flip_test", False)
        camera = as_served(camera, (a.flip_test or trained_with_flip) and not a.no_flip_test)
        fusion, lidar = point_from_checkpoint(fus_ckpt), point_from_checkpoint(lid_ckpt)
        training = {
            "data": cam_ckpt.get("data"),
            "config": {
                "camera": cam_ckpt.get("train_config"),
                "fusion": fus_ckpt.get("train_config"),
                "lidar": lid_ckpt.get("train_config"),
            },
        }
        if bool(a.facing_fusion) != bool(a.facing_lidar):
            p.error("--facing-fusion and --facing-lidar go together")
        if a.facing_fusion:
            first_f, first_l = (load_checkpoint(x) for x in (a.facing_fusion, a.facing_lidar))
            shape = dict(passes=a.facing_passes, turns=a.facing_turns, agree_deg=a.facing_agree_deg)
            fusion = FacingPointNet(point_from_checkpoint(first_f), fusion, **shape)
            lidar = FacingPointNet(point_from_checkpoint(first_l), lidar, **shape)
            training["config"]["facing"] = {
                "passes": a.facing_passes,
                "turns": a.facing_turns,
                "agree_deg": a.facing_agree_deg,
                "fusion": first_f.get("train_config"),
                "lidar": first_l.get("train_config"),
            }
        if a.blend:
            fusion = Blend([fusion, lidar], ["fusion", "lidar"])
        metrics = json.loads(Path(a.metrics).read_text()) if a.metrics else None
        trained = True
    manifest = export_bundle(
        a.out,
        camera,
        fusion,
        lidar,
        pipeline,
        trained=trained,
        training=training,
        metrics=metrics,
        name=a.name,
        version=a.version,
        tol=a.tol,
    )
    size = sum((Path(a.out) / m["file"]).stat().st_size for m in manifest["models"].values())
    parity = manifest["training"]["config"]["onnx_parity_max_abs_diff"]
    print(f"wrote {a.out} ({size / 1e6:.2f} MB), ONNX Runtime parity {parity}")


def measure_latency(path: str | os.PathLike, shape, runs: int = 50, threads: int = 1) -> float:
    """Median ONNX Runtime CPU latency (ms) of one call with a random float32 input."""
    import time

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    x = {sess.get_inputs()[0].name: np.random.default_rng(0).standard_normal(shape).astype(np.float32)}
    for _ in range(5):
        sess.run(None, x)
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        sess.run(None, x)
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e3)


if __name__ == "__main__":
    main()
