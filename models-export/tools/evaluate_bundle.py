"""Evaluate an exported bundle (the ONNX files, through ONNX Runtime) on simulator shards, each
person in the mode the server would run: `posefuse eval` on the same data set's request fixtures
must give the same persons, modes and keypoints. This is the train/serve skew check
(tests/eval_parity.rs).

    python -m tools.evaluate_bundle --bundle models/default --data data/test --fixtures-only --mode auto

--mode auto, fusion, lidar or camera (comma-separated for several), as a request's "mode". With
--fixtures-only only the persons of DATA/requests/frame-*.json are evaluated, and the fixtures say
which frames carry an image (frames without one get LiDAR-only in auto mode and are refused in
fusion and camera mode, as the server refuses them). Without it every shard person counts and
has an image. --predictions-out writes each person's 3D keypoints (vehicle frame), keyed by
fixture file and person id.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from posefuse_train import data as data_mod
from posefuse_train.bundle_eval import predictions, sessions
from posefuse_train.config import MODEL_FIELDS, PipelineConfig
from posefuse_train.evaluate import evaluate
from posefuse_train.metrics import local_to_vehicle

MODES = ("auto", "fusion", "lidar", "camera")


def same_config(a: PipelineConfig, b: PipelineConfig) -> bool:
    """Equal up to f32 rounding (the Rust side stores mean/std as f32) in what prepares the data;
    the heatmap grid, smoothing, sampling, the lifting temperature and min_points are the bundle's,
    not the data's (MODEL_FIELDS)."""
    da, db = a.to_dict(), b.to_dict()
    for d in (da, db):
        for k in MODEL_FIELDS:
            d.pop(k, None)
    return da.keys() == db.keys() and all(
        np.allclose(da[k], db[k], rtol=1e-6) if isinstance(da[k], (list, float)) else da[k] == db[k]
        for k in da
    )


def person_modes(requested: str, d: dict, has_image: np.ndarray, cfg: PipelineConfig) -> np.ndarray:
    """The mode the server runs per person (crates/serve/src/server/predict.rs): auto picks fusion with the
    image and at least min_points in-box points, camera lifting with the image and fewer points,
    LiDAR-only without an image (every simulated person has a 2D box in view)."""
    if requested != "auto":
        return np.full(len(has_image), requested)
    fusion = np.where(d["points_count"] >= cfg.min_points, "fusion", "camera")
    return np.where(has_image, fusion, "lidar")


def skipped(modes: np.ndarray, d: dict) -> np.ndarray:
    """Persons the server answers with no pose: no point in the box, or camera lifting without a
    point in front of the camera."""
    no_uv = ~np.isfinite(d["serve_uv"]).all(axis=2).any(axis=1)
    return (d["points_count"] == 0) | ((modes == "camera") & no_uv)


def read_fixtures(root: Path, d: dict) -> dict:
    """Per shard person: its fixture file, person id, whether the frame has an image, and its
    3D box (the fixture's f64 values); the shard's persons of frame f are, in order, the persons
    of requests/frame-f.json."""
    files = {int(p.stem.split("-")[1]): p for p in sorted((root / "requests").glob("frame-*.json"))}
    if not files:
        raise SystemExit(f"no request fixtures under {root / 'requests'}")
    keep = np.isin(d["frame_index"], list(files))
    out = {"keep": keep, "file": [], "id": [], "image": [], "box3d": []}
    for f, path in files.items():
        frame = json.loads(path.read_text())
        persons = frame["persons"]
        n = int((d["frame_index"] == f).sum())
        if n != len(persons):
            raise SystemExit(f"{path.name}: {len(persons)} persons, the shards hold {n}")
        for p in persons:
            if p.get("box_2d") is None:
                raise SystemExit(f"{path.name}: person {p['id']} has no box_2d (not supported here)")
            b = p["box_3d"]
            out["file"].append(path.name)
            out["id"].append(p["id"])
            out["image"].append(bool(frame.get("image")))
            keys = ("center_x", "center_y", "center_z", "length", "width", "height", "heading")
            out["box3d"].append([b[k] for k in keys])
    # persons were appended frame by frame: put them in shard order
    order = np.argsort(d["frame_index"][keep], kind="stable")
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    for k in ("file", "id", "image", "box3d"):
        out[k] = [out[k][i] for i in inverse]
    return out


def evaluate_bundle(
    bundle: Path,
    root: Path,
    fixtures_only: bool,
    modes=("auto",),
    threads: int = 1,
    precision: str | None = None,
):
    """(report per mode, per-person predictions per mode). A report holds the persons scored,
    those skipped, the frames the server refuses and the metrics over all persons and per mode
    that ran; predictions map fixture file -> person id -> {mode, num_points, xyz (vehicle)}."""
    cfg = PipelineConfig.from_dict(json.loads((bundle / "manifest.json").read_text())["preprocessing"])
    d, data_cfg, _ = data_mod.load(root)
    if not same_config(data_cfg, cfg):
        raise SystemExit(f"{root}: data preprocessing differs from the bundle's")
    m = len(d["points_count"])
    fx = None
    if fixtures_only:
        fx = read_fixtures(root, d)
        d = data_mod.subset(d, np.flatnonzero(fx["keep"]))
        m = len(d["points_count"])
        d["box3d"] = np.asarray(fx["box3d"], np.float64)
    has_image = np.ones(m, bool) if fx is None else np.asarray(fx["image"], bool)
    pred = predictions(sessions(bundle, threads, precision), d, cfg)
    reports, per_person = {}, {}
    for requested in modes:
        mode = person_modes(requested, d, has_image, cfg)
        skip = skipped(mode, d)
        # A forced camera or fusion mode refuses a frame without an image (once a person of it
        # reaches the mode decision, i.e. has a point in its box).
        refused = np.zeros(m, bool)
        if fx is not None and requested in ("fusion", "camera"):
            files = np.asarray(fx["file"])
            bad = {f for f in files[~has_image & (d["points_count"] > 0)]}
            refused = np.isin(files, list(bad))
        scored = np.flatnonzero(~refused & ~skip)
        local = np.stack([pred[str(k)][i] for i, k in enumerate(mode)]) if m else np.zeros((0, 13, 3))
        sub = data_mod.subset(d, scored)
        report = {
            "persons": int(len(scored)),
            "skipped_persons": int((~refused & skip).sum()),
            "failed_frames": 0 if fx is None else len({fx["file"][i] for i in np.flatnonzero(refused)}),
            "metrics": {"all": evaluate(local[scored], sub, cfg)},
        }
        for name in ("fusion", "lidar", "camera"):
            sel = scored[mode[scored] == name]
            if len(sel):
                report["metrics"][name] = evaluate(local[sel], data_mod.subset(d, sel), cfg)
        reports[requested] = report
        if fx is not None:
            vehicle = local_to_vehicle(local, d["box3d"], d["frame_yaw"])
            frames: dict = {}
            for i in range(m):
                frame = frames.setdefault(
                    fx["file"][i], {"refused": bool(refused[i]), "persons": {}, "skipped": []}
                )
                if refused[i]:
                    continue
                if skip[i]:
                    frame["skipped"].append(fx["id"][i])
                    continue
                frame["persons"][fx["id"][i]] = {
                    "mode": str(mode[i]),
                    "num_points": int(d["points_count"][i]),
                    "xyz": vehicle[i].tolist(),
                }
            per_person[requested] = frames
    return reports, per_person


def main(argv=None):
    p = argparse.ArgumentParser(
        prog="python -m tools.evaluate_bundle",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--bundle", default="models/default")
    p.add_argument("--data", required=True)
    p.add_argument(
        "--fixtures-only", action="store_true", help="only persons of frames with a request fixture"
    )
    p.add_argument("--mode", default="auto", help="comma-separated modes among " + ", ".join(MODES))
    p.add_argument("--predictions-out", help="write per-person predictions here (needs --fixtures-only)")
    p.add_argument("--json", action="store_true", help="print {mode: report} as JSON")
    p.add_argument("--precision", help="the camera network's precision, as `posefuse serve --precision`")
    a = p.parse_args(argv)
    modes = [x for x in a.mode.split(",") if x]
    if not modes or any(x not in MODES for x in modes):
        p.error(f"--mode: one or more of {', '.join(MODES)}")
    if a.predictions_out and not a.fixtures_only:
        p.error("--predictions-out needs --fixtures-only (predictions are keyed by fixture)")
    reports, per_person = evaluate_bundle(
        Path(a.bundle), Path(a.data), a.fixtures_only, modes, precision=a.precision
    )
    if a.predictions_out:
        Path(a.predictions_out).write_text(json.dumps(per_person))
    if a.json:
        json.dump(reports, sys.stdout)
        print()
    else:
        for requested, r in reports.items():
            print(f"--mode {requested}: {r['persons']} persons, {r['skipped_persons']} skipped")
            for name, mm in r["metrics"].items():
                print(
                    f"  {name:8s} n={mm['count_3d']:5d}  OKS/ACC@3D {100 * (mm['oks_acc_3d'] or 0):6.2f}%  "
                    f"MPJPE {100 * (mm['mpjpe_3d_m'] or 0):6.2f} cm  "
                    f"OKS/ACC@2D {100 * (mm['oks_acc_2d'] or 0):6.2f}%"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
