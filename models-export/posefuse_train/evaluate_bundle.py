"""Evaluate an exported bundle (the ONNX files, through ONNX Runtime) on simulator shards, choosing
each person's mode the way the server's auto mode does. `posefuse eval` on the same data set's
request fixtures must give the same numbers: this is the train/serve skew check.

    python -m posefuse_train.evaluate_bundle --bundle models/default --data data/test --fixtures-only --json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from . import data as data_mod
from .config import PipelineConfig
from .evaluate import camera_only, evaluate
from .fusion import sample_features, smooth_heatmaps
from .keypoints import K


def normalize(images: np.ndarray, cfg: PipelineConfig) -> np.ndarray:
    """uint8 [M,S,S,3] -> float32 [M,3,S,S], as src/pipeline/crop.rs normalizes."""
    mean = np.asarray(cfg.mean, dtype=np.float32)
    std = np.asarray(cfg.std, dtype=np.float32)
    scale = (1.0 / (255.0 * std)).astype(np.float32)
    shift = (mean / std).astype(np.float32)
    x = images.astype(np.float32) * scale - shift
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))


def run(session: ort.InferenceSession, name: str, x: np.ndarray, batch: int = 256) -> list[np.ndarray]:
    outs = [session.run(None, {name: x[a : a + batch]}) for a in range(0, len(x), batch)]
    return [np.concatenate([o[i] for o in outs], axis=0) for i in range(len(outs[0]))]


def server_modes(d: dict, cfg: PipelineConfig) -> np.ndarray:
    """'fusion' or 'camera' per person, as the server's auto mode picks them for simulator
    fixtures (the image is present and every person has a 2D box)."""
    return np.where(d["points_count"] >= cfg.min_points, "fusion", "camera")


def answerable(d: dict, cfg: PipelineConfig) -> np.ndarray:
    """Per person: whether the server gives a pose. It skips a person with no point in the box,
    or one that needs camera lifting without a point in front of the camera."""
    no_points = d["points_count"] == 0
    no_uv = ~np.isfinite(d["serve_uv"]).all(axis=2).any(axis=1)
    return ~(no_points | ((d["points_count"] < cfg.min_points) & no_uv))


def same_config(a: PipelineConfig, b: PipelineConfig) -> bool:
    """Equal up to f32 rounding (the Rust side stores mean/std as f32), smoothing aside: that is
    the model's (the bundle's), not the data's."""
    da, db = a.to_dict(), b.to_dict()
    for d in (da, db):
        d.pop("smoothing_kernel"), d.pop("smoothing_sigma")
    return da.keys() == db.keys() and all(
        np.allclose(da[k], db[k], rtol=1e-6) if isinstance(da[k], (list, float)) else da[k] == db[k]
        for k in da
    )


def evaluate_bundle(bundle: Path, root: Path, fixtures_only: bool, threads: int = 1) -> dict:
    manifest = json.loads((bundle / "manifest.json").read_text())
    cfg = PipelineConfig.from_dict(manifest["preprocessing"])
    d, data_cfg, _ = data_mod.load(root)
    if not same_config(data_cfg, cfg):
        raise SystemExit(f"{root}: data preprocessing differs from the bundle's")
    keep = np.ones(len(d["points_count"]), dtype=bool)
    if fixtures_only:
        frames = len(list((root / "requests").glob("frame-*.json")))
        keep &= d["frame_index"] < frames
    d = data_mod.subset(d, np.flatnonzero(keep))
    ok = answerable(d, cfg)
    skipped = int((~ok).sum())
    d = data_mod.subset(d, np.flatnonzero(ok))

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    sess = {
        k: ort.InferenceSession(str(bundle / v["file"]), opts, providers=["CPUExecutionProvider"])
        for k, v in manifest["models"].items()
    }
    (heat,) = run(sess["camera"], "image", normalize(d["image"], cfg))[:1]
    smoothed = smooth_heatmaps(torch.from_numpy(heat), cfg.smoothing_kernel, cfg.smoothing_sigma)
    feats = sample_features(smoothed, torch.from_numpy(d["serve_uv"]), cfg.image_size).numpy()
    fused = np.concatenate([d["serve_xyz"], feats], axis=2).astype(np.float32)
    fusion_pred = run(sess["point_fusion"], "points", fused)[0]
    cam_pred = camera_only(heat, d, cfg)
    modes = server_modes(d, cfg)
    pred = np.where((modes == "fusion")[:, None, None], fusion_pred, cam_pred)
    out = {"persons": int(len(pred)), "skipped_persons": skipped, "metrics": {"all": evaluate(pred, d, cfg)}}
    for m in ("fusion", "camera"):
        sel = np.flatnonzero(modes == m)
        if len(sel):
            out["metrics"][m] = evaluate(pred[sel], data_mod.subset(d, sel), cfg)
    assert pred.shape[1] == K
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bundle", default="models/default")
    p.add_argument("--data", required=True)
    p.add_argument(
        "--fixtures-only", action="store_true", help="only persons of frames with a request fixture"
    )
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    r = evaluate_bundle(Path(a.bundle), Path(a.data), a.fixtures_only)
    if a.json:
        json.dump(r, sys.stdout)
        print()
    else:
        for name, m in r["metrics"].items():
            print(
                f"{name:8s} n={m['count_3d']:5d}  OKS/ACC@3D {100 * (m['oks_acc_3d'] or 0):6.2f}%  "
                f"MPJPE {100 * (m['mpjpe_3d_m'] or 0):6.2f} cm  "
                f"OKS/ACC@2D {100 * (m['oks_acc_2d'] or 0):6.2f}%"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
