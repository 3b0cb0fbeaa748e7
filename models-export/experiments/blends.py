"""Where the camera's evidence goes: the point networks of one or more bundles (same camera net,
other point-net seeds), their errors split along and across the camera's line of sight, and the
means of pairs of them, scored on a held-out set as the server scores it (docs/RESULTS.md, "Where
the camera's evidence goes").

    python -m experiments.blends --bundle ../runs/fit128ft/bundle --bundle ../runs/fit128ft_seed2/bundle \\
        --test ../data/hard128_test --out ../runs/blends.json

Networks are named F0, L0 (fusion and LiDAR-only of the first bundle), F1, L1, ... A pair's mean
of one modality (L0 and L1) costs what a fusion/LiDAR-only pair (F0 and L0, `--blend`) costs, so
the difference between them is what the camera adds at equal compute."""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from posefuse_train import metrics
from posefuse_train.bundle_eval import EVAL_KEYS, predictions, sessions
from posefuse_train.config import PipelineConfig
from posefuse_train.evaluate import evaluate, with_fallback
from posefuse_train.keypoints import NAMES
from posefuse_train.shards import ShardSet

GROUPS = {
    "all": list(range(len(NAMES))),
    **{part: [i for i, n in enumerate(NAMES) if part in n] for part in ("wrist", "elbow", "hip")},
}


def line_of_sight(extrinsic: np.ndarray, box3d: np.ndarray, frame_yaw: np.ndarray) -> np.ndarray:
    """[M,3] unit vectors from each person's camera to its box centre, in model-input (box-frame)
    axes: the vehicle-frame ray turned by minus the frame's yaw (metrics.local_to_vehicle's inverse
    rotation)."""
    cam = np.asarray(extrinsic, np.float64).reshape(-1, 4, 4)[:, :3, 3]
    ray = np.asarray(box3d, np.float64)[:, :3] - cam
    h = np.asarray(frame_yaw, np.float64).reshape(-1)
    c, s = np.cos(h), np.sin(h)
    local = np.stack([c * ray[:, 0] + s * ray[:, 1], -s * ray[:, 0] + c * ray[:, 1], ray[:, 2]], axis=1)
    return local / np.linalg.norm(local, axis=1, keepdims=True)


def split_error(pred: np.ndarray, truth: np.ndarray, ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[M,K] |error along the ray| and |error across it| (metres)."""
    e = np.asarray(pred, np.float64) - np.asarray(truth, np.float64)
    along = np.einsum("mkc,mc->mk", e, ray)
    across = np.linalg.norm(e - along[..., None] * ray[:, None, :], axis=2)
    return np.abs(along), across


def axes_table(pred: np.ndarray, truth: np.ndarray, ray: np.ndarray, mask: np.ndarray) -> dict:
    """Per keypoint group: mean 3D error, its part along the line of sight and across it (m),
    over the labelled keypoints."""
    along, across = split_error(pred, truth, ray)
    norm = np.linalg.norm(np.asarray(pred, np.float64) - truth, axis=2)
    out = {}
    for g, idx in GROUPS.items():
        m = mask[:, idx]
        parts = (("error", norm), ("along", along), ("across", across))
        out[g] = {k: float(v[:, idx][m].mean()) for k, v in parts}
    return out


def pair_means(nets: dict) -> dict:
    """Every single network and the mean of every pair of them, by name ("mean(F0,L0)")."""
    rows = dict(nets)
    for a, b in itertools.combinations(nets, 2):
        rows[f"mean({a},{b})"] = 0.5 * (nets[a] + nets[b])
    return rows


def collect(
    bundles: list[Path], test: ShardSet, threads: int = 2
) -> tuple[dict, dict, np.ndarray, PipelineConfig]:
    """Every bundle's fusion and LiDAR-only answers (camera lifting below min_points, as served),
    the first bundle's camera-only answers, the evaluation data and the lines of sight."""
    manifests = [json.loads((b / "manifest.json").read_text()) for b in bundles]
    for b, m in zip(bundles, manifests, strict=True):
        if "blend" in m["models"]["point_fusion"]:
            raise SystemExit(f"{b}: its fusion graph is already a blend; export it without --blend")
    # the comparison is between point nets behind one camera net, on the same inputs
    cameras = {m["models"]["camera"]["sha256"] for m in manifests}
    if len(cameras) > 1:
        raise SystemExit(
            "the bundles have different camera nets (models.camera.sha256): "
            "train the others' point nets behind the first's camera"
        )
    cfgs = [m["preprocessing"] for m in manifests]
    if any(c != cfgs[0] for c in cfgs):
        raise SystemExit(
            "the bundles pre-process differently (manifest preprocessing): "
            "their nets do not see the same inputs"
        )
    cfg = PipelineConfig.from_dict(cfgs[0])
    sess = [sessions(b, threads, "fp32") for b in bundles]
    nets: dict[str, list] = {}
    kept, rays = [], []
    for i in range(test.num_shards):
        d = test.read(i, ("image", *EVAL_KEYS))
        for j, s in enumerate(sess):
            p = predictions(s, d, cfg, batch=32)
            for mode, tag in (("fusion", "F"), ("lidar", "L")):
                nets.setdefault(f"{tag}{j}", []).append(with_fallback(p[mode], p["camera"], d, cfg))
            if j == 0:
                nets.setdefault("camera", []).append(p["camera"])
        rays.append(line_of_sight(d["extrinsic"], d["box3d"], d["frame_yaw"]))
        del d["image"]
        kept.append(d)
    data = {k: np.concatenate([d[k] for d in kept], axis=0) for k in EVAL_KEYS}
    joined = {k: np.concatenate(v, axis=0).astype(np.float64) for k, v in nets.items()}
    return joined, data, np.concatenate(rays, axis=0), cfg


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bundle", type=Path, action="append", required=True, help="a bundle (repeat: seeds)")
    ap.add_argument("--test", type=Path, required=True, help="held-out shards")
    ap.add_argument("--out", type=Path, help="JSON file for the tables")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    nets, data, ray, cfg = collect(a.bundle, ShardSet(a.test), a.threads)
    mask = metrics.labelled(data, 3)
    axes = {n: axes_table(nets[n], data["kp3d"], ray, mask) for n in ("F0", "L0", "camera")}
    print("| network | keypoints | mean error cm | along the line of sight cm | across it cm |")
    print("|---|---|---|---|---|")
    for n, t in axes.items():
        for g, v in t.items():
            cm = [f"{100 * v[k]:.2f}" for k in ("error", "along", "across")]
            print(f"| {n} | {g} | {' | '.join(cm)} |")
    print("\n| answer | OKS@3D | MPJPE | wrist OKS@3D | OKS@2D |")
    print("|---|---|---|---|---|")
    scores = {}
    for name, pred in pair_means({k: v for k, v in nets.items() if k != "camera"}).items():
        r = evaluate(pred, data, cfg)
        wrist = float(np.mean([k["oks"] for k in r["per_keypoint_oks_3d"] if "wrist" in k["name"]]))
        scores[name] = {"oks_3d": r["oks_acc_3d"], "mpjpe_m": r["mpjpe_3d_m"], "wrist": wrist}
        scores[name]["oks_2d"] = r["oks_acc_2d"]
        print(
            f"| {name} | {100 * r['oks_acc_3d']:.2f} % | {100 * r['mpjpe_3d_m']:.2f} cm | "
            f"{100 * wrist:.1f} % | {100 * r['oks_acc_2d']:.2f} % |"
        )
    if a.out:
        out = {"bundles": [str(b) for b in a.bundle], "test": str(a.test), "axes": axes, "scores": scores}
        a.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
