"""Reading the simulator's shards (docs/DATA.md) into one dict of numpy arrays."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .config import PipelineConfig

KEYS = (
    "image",
    "points_xyz",
    "points_uv",
    "points_count",
    "serve_xyz",
    "serve_uv",
    "kp2d",
    "kp2d_visible",
    "kp2d_occluded",
    "kp2d_image_true",
    "kp3d",
    "kp3d_vehicle",
    "kp3d_visible",
    "kp3d_occluded",
    "box3d",
    "box2d",
    "crop",
    "intrinsic",
    "extrinsic",
    "image_size_wh",
    "sensor_xyz",
    "frame_yaw",
    "range_m",
    "frame_index",
)


def read_meta(root: str | Path) -> tuple[dict, PipelineConfig]:
    meta = json.loads((Path(root) / "dataset.json").read_text())
    return meta, PipelineConfig.from_dict(meta["preprocessing"])


def shard_paths(root: str | Path) -> list[Path]:
    paths = sorted((Path(root) / "shards").glob("shard-*.npz"))
    if not paths:
        raise FileNotFoundError(f"no shards under {Path(root) / 'shards'}")
    return paths


def load(root: str | Path, limit: int | None = None) -> tuple[dict, PipelineConfig, dict]:
    """All samples of a data set (at most `limit`): (arrays, preprocessing, dataset.json).

    The point arrays are trimmed to the largest `points_count` so padding costs no memory."""
    meta, cfg = read_meta(root)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in KEYS}
    total = 0
    for path in shard_paths(root):
        with np.load(path) as z:
            missing = [k for k in KEYS if k not in z.files]
            if missing:
                raise KeyError(f"{path}: missing keys {missing} (from an older posefuse)")
            m = len(z["points_count"])
            take = m if limit is None else min(m, limit - total)
            for k in KEYS:
                parts[k].append(z[k][:take])
            total += take
        if limit is not None and total >= limit:
            break
    p = max(int(max(a.max(initial=0) for a in parts["points_count"])), 1)
    data = {}
    for k, arrs in parts.items():
        if k in ("points_xyz", "points_uv"):
            arrs = [a[:, :p] for a in arrs]
            width = max(a.shape[1] for a in arrs)
            arrs = [np.pad(a, ((0, 0), (0, width - a.shape[1]), (0, 0))) for a in arrs]
        data[k] = np.concatenate(arrs, axis=0)
    check(data, cfg)
    return data, cfg, meta


def check(data: dict, cfg: PipelineConfig) -> None:
    m = len(data["points_count"])
    s, n = cfg.image_size, cfg.num_points
    want = {
        "image": (m, s, s, 3),
        "serve_xyz": (m, n, 3),
        "serve_uv": (m, n, 2),
        "kp2d": (m, 13, 2),
        "kp3d": (m, 13, 3),
        "box3d": (m, 7),
        "box2d": (m, 4),
    }
    for k, shape in want.items():
        if data[k].shape != shape:
            raise ValueError(f"{k}: shape {data[k].shape}, expected {shape} (image_size {s}, num_points {n})")


def subset(data: dict, idx: np.ndarray) -> dict:
    return {k: v[idx] for k, v in data.items()}
