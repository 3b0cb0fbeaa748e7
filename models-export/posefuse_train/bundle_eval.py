"""An exported bundle run as the server runs it: the ONNX files through ONNX Runtime, the crops
normalized as crates/core/src/pipeline/crop.rs does, the heatmaps smoothed and sampled as
crates/core/src/pipeline/fusion.rs does. `tools.evaluate_bundle` checks this path against `posefuse eval`
(tests/eval_parity.rs); `fit` scores the bundle it wrote with it, one test shard at a time."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from .config import PipelineConfig
from .evaluate import camera_only, evaluate, with_fallback, with_points
from .fusion import sample_features, smooth_heatmaps
from .shards import ShardSet

# What the held-out evaluation reads of a test shard besides the image.
EVAL_KEYS = (
    "serve_xyz",
    "serve_uv",
    "points_count",
    "kp3d",
    "kp3d_visible",
    "kp3d_occluded",
    "box3d",
    "box2d",
    "frame_yaw",
    "intrinsic",
    "extrinsic",
    "kp2d_image_true",
    "kp2d_visible",
    "kp2d_occluded",
)


def normalize(images: np.ndarray, cfg: PipelineConfig) -> np.ndarray:
    """uint8 [M,S,S,3] -> float32 [M,3,S,S], as crates/core/src/pipeline/crop.rs normalizes."""
    mean = np.asarray(cfg.mean, dtype=np.float32)
    std = np.asarray(cfg.std, dtype=np.float32)
    scale = (1.0 / (255.0 * std)).astype(np.float32)
    shift = (mean / std).astype(np.float32)
    x = images.astype(np.float32) * scale - shift
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))


def run(session: ort.InferenceSession, name: str, x: np.ndarray, batch: int = 256) -> list[np.ndarray]:
    outs = [session.run(None, {name: x[a : a + batch]}) for a in range(0, len(x), batch)]
    return [np.concatenate([o[i] for o in outs], axis=0) for i in range(len(outs[0]))]


def model_file(spec: dict, precision: str | None) -> str:
    """The file a model runs from at `precision` (None or fp32: its own; else its variant)."""
    if precision in (None, "fp32"):
        return spec["file"]
    variants = spec.get("variants", {})
    if precision not in variants:
        raise SystemExit(
            f"no {precision} variant of this network in the bundle (python -m posefuse_train.quantize)"
        )
    return variants[precision]["file"]


def sessions(bundle: Path, threads: int = 1, precision: str | None = None) -> dict:
    """One session per network; `precision` picks the camera's variant (as `posefuse serve
    --precision`: without it, the manifest's own `precision`), the point networks have none."""
    manifest = json.loads((Path(bundle) / "manifest.json").read_text())
    precision = precision or manifest.get("precision")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    return {
        k: ort.InferenceSession(
            str(Path(bundle) / model_file(v, precision if k == "camera" else None)),
            opts,
            providers=["CPUExecutionProvider"],
        )
        for k, v in manifest["models"].items()
    }


def predictions(sess: dict, d: dict, cfg: PipelineConfig, batch: int = 256) -> dict:
    """Every person through every network: fusion, LiDAR-only and camera lifting (model-input
    coordinates), `batch` persons a call."""
    (heat,) = run(sess["camera"], "image", normalize(d["image"], cfg), batch)[:1]
    smoothed = smooth_heatmaps(torch.from_numpy(heat), cfg.smoothing_kernel, cfg.smoothing_sigma)
    feats = sample_features(smoothed, torch.from_numpy(d["serve_uv"]), cfg.image_size, cfg.sampling).numpy()
    fused = np.concatenate([d["serve_xyz"], feats], axis=2).astype(np.float32)
    return {
        "fusion": run(sess["point_fusion"], "points", fused, batch)[0],
        "lidar": run(sess["point_lidar"], "points", np.ascontiguousarray(d["serve_xyz"]), batch)[0],
        "camera": camera_only(heat, d, cfg),
    }


def served_answers(
    bundle: Path, test: ShardSet, threads: int = 1, progress=None, precision: str | None = None, keys=()
) -> tuple[dict, dict, PipelineConfig]:
    """(answers, data, cfg): every test person's answer in each forced mode {fusion, lidar,
    camera}, persons with fewer than min_points in-box points answered by camera lifting in the
    point modes (as the server does); `data` holds EVAL_KEYS and `keys` of the test set. Read one
    shard at a time so the test set need not fit in memory."""
    cfg = PipelineConfig.from_dict(json.loads((Path(bundle) / "manifest.json").read_text())["preprocessing"])
    sess = sessions(bundle, threads, precision)
    preds: dict[str, list] = {"fusion": [], "lidar": [], "camera": []}
    kept: list[dict] = []
    for i in range(test.num_shards):
        d = test.read(i, ("image", *EVAL_KEYS, *keys))
        # 32 persons a call: a point net's activations are [persons x N, channels]
        p = predictions(sess, d, cfg, batch=32)
        preds["camera"].append(p["camera"])
        for mode in ("fusion", "lidar"):
            preds[mode].append(with_fallback(p[mode], p["camera"], d, cfg))
        del d["image"]
        kept.append(d)
        if progress is not None:
            progress(i + 1, test.num_shards)
    data = {k: np.concatenate([d[k] for d in kept], axis=0) for k in kept[0]}
    return {mode: np.concatenate(v, axis=0) for mode, v in preds.items()}, data, cfg


def held_out(
    bundle: Path, test: ShardSet, threads: int = 1, progress=None, precision: str | None = None
) -> dict:
    """{fusion, lidar, camera}: metrics of every test person in each forced mode (served_answers)."""
    pred, data, cfg = served_answers(bundle, test, threads, progress, precision)
    reports = {mode: evaluate(p, data, cfg) for mode, p in pred.items()}
    for mode in ("fusion", "lidar"):
        reports[mode]["breakdown"]["with_points"] = with_points(pred[mode], data, cfg)
    return reports
