"""Writes the fuzz targets' seed inputs into fuzz/corpus/<target>/ (small, valid requests of
each kind, so the fuzzer starts from inputs that reach deep into the parsers):
`.venv/bin/python fuzz/make_seeds.py`. The corpus the fuzzer grows from them is kept too."""

import base64
import io
import json
import struct
from pathlib import Path

import numpy as np
from PIL import Image
from posefuse_client import Frame

ROOT = Path(__file__).resolve().parent
CORPUS = ROOT / "corpus"

CAL = {
    "intrinsic": [500.0, 500.0, 32.0, 24.0, -0.05, 0.01, 0.0, 0.0, 0.0],
    "extrinsic": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 1.5, 0, 0, 0, 1],
    "width": 64,
    "height": 48,
}
BOX3D = {"center_x": 8.0, "center_y": 0.5, "center_z": 0.9, "length": 0.5, "width": 0.7, "height": 1.8, "heading": 0.3}


def jpeg(w, h, **kw) -> bytes:
    x = np.linspace(0, 255, w, dtype=np.uint8)[None, :, None]
    y = np.linspace(0, 255, h, dtype=np.uint8)[:, None, None]
    img = np.concatenate([np.broadcast_to(x, (h, w, 1)), np.broadcast_to(y, (h, w, 1)), (x ^ y)], axis=2)
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img)).save(out, **kw)
    return out.getvalue()


def points(n=8):
    rng = np.random.default_rng(1)
    return (np.array([8.0, 0.5, 0.9]) + rng.uniform(-0.3, 0.3, (n, 3))).astype("<f4")


def frames():
    pts = points()
    b64 = base64.b64encode(pts.tobytes()).decode()
    image = base64.b64encode(jpeg(64, 48, format="JPEG", quality=80)).decode()
    person = {"id": "a", "box_3d": BOX3D}
    yield {"calibration": CAL, "points": {"b64": b64}, "persons": [person]}
    yield {"calibration": CAL, "image": image, "points": pts.ravel().tolist(),
           "persons": [person, {"id": "b", "box_3d": BOX3D,
                                "box_2d": {"center_x": 30, "center_y": 20, "width": 10, "height": 30}}],
           "mode": "fusion"}
    yield {"cameras": [{"name": "FRONT", "calibration": CAL, "image": image},
                       {"name": "LEFT", "calibration": CAL, "image_rgb": {"width": 64, "height": 48,
                        "b64": base64.b64encode(bytes(64 * 48 * 3)).decode()}}],
           "points": {"b64": b64}, "persons": [dict(person, camera="LEFT")]}


def kserve_bodies():
    pts = points()
    inputs = [
        {"name": "points", "datatype": "FP32", "shape": [len(pts), 3], "data": pts.ravel().tolist()},
        {"name": "calibration_intrinsic", "datatype": "FP64", "shape": [9], "data": CAL["intrinsic"]},
        {"name": "calibration_extrinsic", "datatype": "FP64", "shape": [16], "data": CAL["extrinsic"]},
        {"name": "image_size", "datatype": "INT32", "shape": [2], "data": [64, 48]},
        {"name": "boxes_3d", "datatype": "FP64", "shape": [1, 7], "data": list(BOX3D.values())},
    ]
    # JSON tensors, with a NaN box_2d row written as Python's json writes it
    body = json.dumps({"id": "s", "inputs": [*inputs, {"name": "boxes_2d", "datatype": "FP64", "shape": [1, 4],
                                                       "data": [float("nan")] * 4}],
                       "outputs": [{"name": "keypoints_3d"}]}).encode()
    yield struct.pack("<H", 0xFFFF) + body
    # binary tensor data: the JSON part, then the raw points and the image as a BYTES element
    img = jpeg(64, 48, format="JPEG", quality=70)
    raw_pts = pts.tobytes()
    raw_img = struct.pack("<I", len(img)) + img
    bin_inputs = [dict(inputs[0], data=None, parameters={"binary_data_size": len(raw_pts)}), *inputs[1:],
                  {"name": "image", "datatype": "BYTES", "shape": [1],
                   "parameters": {"binary_data_size": len(raw_img)}}]
    for i in bin_inputs:
        if i.get("data") is None:
            i.pop("data", None)
    head = json.dumps({"inputs": bin_inputs, "parameters": {"binary_data_output": True}}).encode()
    yield struct.pack("<H", len(head)) + head + raw_pts + raw_img


def main():
    for name in ["frame_json", "kserve_request", "proto_frame", "points_b64", "jpeg_decode"]:
        (CORPUS / name).mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames()):
        (CORPUS / "frame_json" / f"seed-{i}").write_text(json.dumps(f))
        (CORPUS / "proto_frame" / f"seed-{i}").write_bytes(Frame.from_json(f).to_proto().SerializeToString())
    for i, b in enumerate(kserve_bodies()):
        (CORPUS / "kserve_request" / f"seed-{i}").write_bytes(b)
    for i, n in enumerate([1, 4, 9]):
        (CORPUS / "points_b64" / f"seed-{i}").write_text(base64.b64encode(points(n).tobytes()).decode())
    kinds = [dict(format="JPEG", quality=80), dict(format="JPEG", quality=60, subsampling=0),
             dict(format="JPEG", quality=90, progressive=True), dict(format="JPEG", quality=75, subsampling=2),
             dict(format="PNG")]
    for i, kw in enumerate(kinds):
        (CORPUS / "jpeg_decode" / f"seed-{i}").write_bytes(jpeg(40 + 8 * i, 24 + 8 * i, **kw))
    gray = io.BytesIO()
    Image.fromarray(np.full((33, 17), 120, np.uint8)).save(gray, format="JPEG")
    (CORPUS / "jpeg_decode" / "seed-gray").write_bytes(gray.getvalue())


if __name__ == "__main__":
    main()
