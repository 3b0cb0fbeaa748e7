"""The Python peer of `posefuse serve`: the same bundle and the same `/v1/poses` request, served the
way a Python team would serve it (FastAPI + uvicorn, OpenCV's libjpeg-turbo decode and resize,
NumPy, ONNX Runtime). It exists only to be measured against (BENCHMARKS.md, "Against a Python
peer"); `scripts/peer_compare.py` starts it and checks that its keypoints agree with the server's.

    MODEL_DIR=models/default uvicorn --app-dir scripts/python_peer server:app --workers 2

What it does per request, as docs/ARCHITECTURE.md describes the server's pipeline:
- decodes the whole JPEG (cv2.imdecode), cuts each person's square crop (side = max(w, h) times
  `crop_scale`) and resizes it with area averaging;
- gathers the points inside each 3D box grown by `box_margin`, in the box-heading frame, and keeps
  `num_points` of them (a NumPy choice seeded from the points' bytes; the server seeds its own
  ChaCha choice the same way, so the two choose different but equally random points);
- projects the chosen points through the camera model of docs/DATA.md (Waymo's: x forward,
  OpenCV distortion);
- runs the camera net (the manifest's precision) on all crops at once, smooths the heatmaps
  (separable Gaussian, zero padding), samples them at the projected points as the manifest says
  (nearest cell or bilinear) and runs the fusion point net on all persons at once.

Persons with fewer than `min_points` points get the LiDAR-only net (the server lifts them from the
camera instead); frames without an image get the LiDAR-only net, as in the server's auto mode.
"""

from __future__ import annotations

import base64
import json
import os
import zlib
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import Response
from sampling import sample

BUNDLE = Path(os.environ.get("MODEL_DIR", "models/default"))
MANIFEST = json.loads((BUNDLE / "manifest.json").read_text())
CFG = MANIFEST["preprocessing"]
if not CFG.get("rotate_by_heading", True) or CFG.get("frame", "box_heading") != "box_heading":
    raise SystemExit("the peer serves box-heading bundles only")
cv2.setNumThreads(1)


def session(key: str) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(os.environ.get("PEER_ORT_THREADS", "1"))
    # the file the server serves: the manifest's precision picks a network's variant, if it has one
    # (docs/BUNDLE.md, "Precision")
    entry = MANIFEST["models"][key]
    variant = entry.get("variants", {}).get(MANIFEST.get("precision", "fp32"))
    path = BUNDLE / (variant or entry)["file"]
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


CAMERA, FUSION, LIDAR = session("camera"), session("point_fusion"), session("point_lidar")
S = int(CFG["image_size"])
MEAN = np.asarray(CFG["mean"], np.float32)
STD = np.asarray(CFG["std"], np.float32)


def gaussian_1d(size: int, sigma: float) -> np.ndarray:
    c = (size - 1) / 2.0
    g = np.exp(-((np.arange(size) - c) ** 2) / (2.0 * sigma**2))
    return (g / g.sum()).astype(np.float32)


KERNEL = gaussian_1d(int(CFG["smoothing_kernel"]), float(CFG["smoothing_sigma"]))
SAMPLING = CFG.get("sampling", "nearest")
if SAMPLING not in ("nearest", "bilinear"):
    raise SystemExit(f"the peer samples heatmaps nearest or bilinear, not {SAMPLING}")

app = FastAPI()


def crop(image: np.ndarray, box: dict) -> np.ndarray:
    """The S x S RGB crop of the BGR image around a 2D box; black outside the image."""
    side = max(box["width"], box["height"]) * CFG["crop_scale"]
    x0, y0 = box["center_x"] - side / 2, box["center_y"] - side / 2
    ix0, iy0 = int(np.floor(x0)), int(np.floor(y0))
    ix1, iy1 = int(np.ceil(x0 + side)), int(np.ceil(y0 + side))
    h, w = image.shape[:2]
    if ix1 <= 0 or iy1 <= 0 or ix0 >= w or iy0 >= h or side <= 0:
        return np.zeros((S, S, 3), np.uint8)
    window = image[max(iy0, 0) : min(iy1, h), max(ix0, 0) : min(ix1, w)]
    if ix0 < 0 or iy0 < 0 or ix1 > w or iy1 > h:
        window = cv2.copyMakeBorder(
            window, max(-iy0, 0), max(iy1 - h, 0), max(-ix0, 0), max(ix1 - w, 0), cv2.BORDER_CONSTANT
        )
    return cv2.cvtColor(cv2.resize(window, (S, S), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)


def box_points(points: np.ndarray, b: dict) -> np.ndarray:
    """The points inside the box grown by box_margin, in the box frame (metres from its centre)."""
    c, s = np.cos(b["heading"]), np.sin(b["heading"])
    d = points - np.array([b["center_x"], b["center_y"], b["center_z"]], np.float64)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    m = CFG["box_margin"]
    half = np.array([b["length"] / 2 + m, b["width"] / 2 + m, b["height"] / 2 + m])
    return local[(np.abs(local) <= half).all(axis=1)]


def choose(count: int, seed: int) -> np.ndarray:
    n = int(CFG["num_points"])
    rng = np.random.default_rng(seed)
    if count >= n:
        return np.sort(rng.choice(count, n, replace=False))
    return np.concatenate([np.arange(count), rng.integers(0, count, n - count)])


def project(vehicle: np.ndarray, cal: dict) -> np.ndarray:
    """Vehicle-frame points -> image pixels (NaN behind the camera or where the lens folds back)."""
    ext = np.asarray(cal["extrinsic"], np.float64).reshape(4, 4)
    cam = (vehicle - ext[:3, 3]) @ ext[:3, :3]
    fu, fv, cu, cv, k1, k2, p1, p2, k3 = cal["intrinsic"]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = -cam[:, 1] / cam[:, 0], -cam[:, 2] / cam[:, 0]
        r2 = u * u + v * v
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        ud = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
        vd = v * radial + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
    uv = np.stack([fu * ud + cu, fv * vd + cv], axis=1)
    uv[(cam[:, 0] <= 1e-6) | (radial < 0.8) | (radial > 1.2)] = np.nan
    return uv


def features(heatmaps: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Smoothed heatmaps [K,H,W] sampled at model pixels uv [N,2] -> [N,K]."""
    smooth = np.stack([cv2.sepFilter2D(m, -1, KERNEL, KERNEL, borderType=cv2.BORDER_CONSTANT) for m in heatmaps])
    finite = np.isfinite(uv).all(axis=1)
    safe = np.where(finite[:, None], uv, 0.0).astype(np.float32)
    return sample(smooth, safe, S, SAMPLING) * finite[:, None]


def to_vehicle(local: np.ndarray, b: dict) -> np.ndarray:
    c, s = np.cos(b["heading"]), np.sin(b["heading"])
    x, y = local[..., 0], local[..., 1]
    return np.stack(
        [c * x - s * y + b["center_x"], s * x + c * y + b["center_y"], local[..., 2] + b["center_z"]], axis=-1
    )


def predict(frame: dict) -> dict:
    points = np.frombuffer(base64.b64decode(frame["points"]["b64"]), "<f4").reshape(-1, 3).astype(np.float64)
    persons = frame.get("persons", [])
    image = None
    if frame.get("image"):
        image = cv2.imdecode(np.frombuffer(base64.b64decode(frame["image"]), np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise HTTPException(400, "image: not a decodable JPEG/PNG")
    seed = zlib.crc32(points.tobytes())
    chosen, fused_rows, lidar_rows = [], [], []
    for p in persons:
        local = box_points(points, p["box_3d"])
        if len(local) == 0:
            chosen.append(None)
            continue
        idx = choose(len(local), seed ^ len(local))
        xyz = local[idx].astype(np.float32)
        chosen.append(xyz)
        if image is not None and len(local) >= CFG["min_points"]:
            fused_rows.append(len(chosen) - 1)
        else:
            lidar_rows.append(len(chosen) - 1)
    out: dict[int, np.ndarray] = {}
    if fused_rows:
        crops = np.stack([crop(image, persons[r]["box_2d"]) for r in fused_rows]).astype(np.float32)
        x = ((crops / 255.0 - MEAN) / STD).transpose(0, 3, 1, 2)
        (heat,) = CAMERA.run(None, {"image": np.ascontiguousarray(x, np.float32)})[:1]
        batch = []
        for n, r in enumerate(fused_rows):
            b, box = persons[r]["box_3d"], persons[r]["box_2d"]
            xyz = chosen[r]
            vehicle = to_vehicle(xyz.astype(np.float64), b)
            side = max(box["width"], box["height"]) * CFG["crop_scale"]
            x0, y0 = box["center_x"] - side / 2, box["center_y"] - side / 2
            uv = (project(vehicle, frame["calibration"]) - [x0, y0]) * (S / side)
            batch.append(np.concatenate([xyz, features(heat[n], uv)], axis=1))
        (kp,) = FUSION.run(["keypoints"], {"points": np.stack(batch).astype(np.float32)})
        out.update(zip(fused_rows, kp, strict=True))
    if lidar_rows:
        (kp,) = LIDAR.run(["keypoints"], {"points": np.stack([chosen[r] for r in lidar_rows])})
        out.update(zip(lidar_rows, kp, strict=True))
    answers = []
    for r, p in enumerate(persons):
        kp = out.get(r)
        answers.append(
            {
                "id": p.get("id"),
                "mode": "fusion" if r in fused_rows else "lidar" if r in lidar_rows else None,
                "keypoints_3d": None if kp is None else to_vehicle(kp.astype(np.float64), p["box_3d"]).tolist(),
            }
        )
    return {"frame_id": frame.get("frame_id"), "persons": answers}


@app.post("/v1/poses")
def poses(frame: dict) -> dict:
    return predict(frame)


@app.get("/readyz")
def readyz(_: Request) -> Response:
    return Response("ready")
