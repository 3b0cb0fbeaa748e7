"""Tiny synthetic data sets in the simulator's shard format (docs/DATA.md), for tests and smoke
runs: a stick-figure person, LiDAR-like points on limb surfaces facing the sensor, a pinhole
camera, crops with coloured keypoint dots."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from posefuse_train.config import PipelineConfig  # noqa: E402
from posefuse_train.keypoints import SKELETON, K  # noqa: E402

# standing person, box frame (x forward, y left, z up, box centre at hip height ~0.9 m)
TEMPLATE = np.array(
    [
        [0.10, 0.00, 0.72],
        [0.00, 0.20, 0.52],
        [0.00, -0.20, 0.52],
        [0.02, 0.25, 0.24],
        [0.02, -0.25, 0.24],
        [0.06, 0.25, -0.02],
        [0.06, -0.25, -0.02],
        [0.00, 0.11, 0.02],
        [0.00, -0.11, 0.02],
        [0.02, 0.11, -0.42],
        [0.02, -0.11, -0.42],
        [0.00, 0.11, -0.84],
        [0.00, -0.11, -0.84],
    ],
    np.float64,
)
FU, CU, CV, W, H = 1000.0, 960.0, 640.0, 1920, 1280


def _project(p):
    """Identity extrinsic, no distortion: camera frame == vehicle frame."""
    x = p[..., 0]
    return np.stack([FU * (-p[..., 1] / x) + CU, FU * (-p[..., 2] / x) + CV], axis=-1)


def make_sample(rng, cfg: PipelineConfig, cap: int):
    s, n = cfg.image_size, cfg.num_points
    kp_local = TEMPLATE + rng.normal(0, 0.03, TEMPLATE.shape)
    heading = rng.uniform(-np.pi, np.pi)
    centre = np.array([rng.uniform(6, 14), rng.uniform(-2, 2), 0.9])
    c, sn = np.cos(heading), np.sin(heading)

    def to_vehicle(q):
        return np.stack(
            [
                centre[0] + c * q[..., 0] - sn * q[..., 1],
                centre[1] + sn * q[..., 0] + c * q[..., 1],
                centre[2] + q[..., 2],
            ],
            axis=-1,
        )

    def to_local(p):
        d = p - centre
        return np.stack([c * d[..., 0] + sn * d[..., 1], -sn * d[..., 0] + c * d[..., 1], d[..., 2]], axis=-1)

    sensor_local = to_local(np.zeros(3))
    # points: on limb segments, pushed 5 cm towards the sensor (the visible surface)
    count = int(rng.integers(40, cap + 1))
    bones = rng.integers(0, len(SKELETON), count)
    t = rng.uniform(0, 1, count)[:, None]
    a = kp_local[[SKELETON[b][0] for b in bones]]
    b = kp_local[[SKELETON[b][1] for b in bones]]
    pts = a + t * (b - a)
    towards = sensor_local - pts
    towards /= np.linalg.norm(towards, axis=1, keepdims=True)
    pts = pts + 0.05 * towards + rng.normal(0, 0.01, pts.shape)
    kp_vehicle = to_vehicle(kp_local)
    kp_img = _project(kp_vehicle)
    lo, hi = kp_img.min(axis=0) - 5, kp_img.max(axis=0) + 5
    box2d = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[0] - lo[0], hi[1] - lo[1]])
    side = max(box2d[2], box2d[3]) * cfg.crop_scale
    x0, y0 = box2d[0] - side / 2, box2d[1] - side / 2
    scale = s / side
    pts_uv = (_project(to_vehicle(pts)) - [x0, y0]) * scale
    kp_uv = (kp_img - [x0, y0]) * scale
    image = np.zeros((s, s, 3), np.uint8)
    yy, xx = np.mgrid[0:s, 0:s] + 0.5
    for k in range(K):
        blob = np.exp(-((xx - kp_uv[k, 0]) ** 2 + (yy - kp_uv[k, 1]) ** 2) / 2.0)
        colour = np.array([(37 * k) % 256, (91 * k + 60) % 256, (151 * k + 120) % 256])
        image = np.maximum(image, (blob[..., None] * colour).astype(np.uint8))
    pts_xyz = np.zeros((cap, 3), np.float32)
    pts_uv_full = np.zeros((cap, 2), np.float32)
    pts_xyz[:count], pts_uv_full[:count] = pts, pts_uv
    sel = np.concatenate([np.arange(min(count, n)), rng.integers(0, count, max(0, n - count))])[:n]
    vis = (rng.uniform(size=K) > 0.1).astype(np.uint8)
    occluded = (1 - vis).astype(np.uint8)  # every keypoint labelled, as the simulator labels 3D
    return {
        "image": image,
        "points_xyz": pts_xyz,
        "points_uv": pts_uv_full,
        "points_count": np.int32(count),
        "serve_xyz": pts_xyz[sel],
        "serve_uv": pts_uv_full[sel],
        "kp2d": (kp_uv + rng.normal(0, 0.3, kp_uv.shape)).astype(np.float32),
        "kp2d_visible": vis,
        "kp2d_occluded": occluded,
        "kp2d_image_true": kp_img.astype(np.float32),
        "kp3d": kp_local.astype(np.float32),
        "kp3d_vehicle": kp_vehicle.astype(np.float32),
        "kp3d_visible": vis,
        "kp3d_occluded": occluded,
        "box3d": np.array([*centre, 0.6, 0.7, 1.9, heading], np.float32),
        "box2d": box2d.astype(np.float32),
        "crop": np.array([x0, y0, scale], np.float32),
        "intrinsic": np.array([FU, FU, CU, CV, 0, 0, 0, 0, 0], np.float32),
        "extrinsic": np.eye(4, dtype=np.float32).reshape(16),
        "image_size_wh": np.array([W, H], np.int32),
        "sensor_xyz": sensor_local.astype(np.float32),
        "frame_yaw": np.float32(heading),
        "range_m": np.float32(np.hypot(centre[0], centre[1])),
        "frame_index": np.int32(0),
    }


def write_dataset(
    root,
    count: int,
    seed: int = 0,
    image_size: int = 32,
    num_points: int = 64,
    cap: int = 96,
    shard_size: int = 64,
) -> Path:
    root = Path(root)
    (root / "shards").mkdir(parents=True, exist_ok=True)
    cfg = PipelineConfig.with_image_size(image_size)
    cfg.num_points = num_points
    rng = np.random.default_rng(seed)
    samples = [make_sample(rng, cfg, cap) for _ in range(count)]
    for i, a in enumerate(range(0, count, shard_size)):
        chunk = samples[a : a + shard_size]
        arrays = {k: np.stack([sm[k] for sm in chunk]) for k in chunk[0]}
        np.savez(root / "shards" / f"shard-{i:05d}.npz", **arrays)
    meta = {
        "seed": seed,
        "count": count,
        "simulator": "synthetic-test",
        "points_cap": cap,
        "preprocessing": cfg.to_dict(),
    }
    (root / "dataset.json").write_text(json.dumps(meta, indent=2))
    return root


if __name__ == "__main__":
    out, n, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 0
    size = int(sys.argv[4]) if len(sys.argv) > 4 else 32
    print(write_dataset(out, n, seed, image_size=size, num_points=256 if size >= 64 else 64, cap=512))
