"""Latency of the Open Inference Protocol endpoints against POST /v1/poses on the same frame.

Sends one simulator request fixture to a running `posefuse serve`, interleaved, N times each:
/v1/poses (the fixture's JSON), /v2 infer with JSON tensors, /v2 infer with binary tensors (the
binary tensor data extension, binary outputs) and gRPC ModelInfer with raw contents. Bodies are
encoded once beforehand and responses are read but not parsed, so the numbers are the server's
work plus one loopback round trip on a kept-alive connection. Prints p50 and p99 per endpoint.

    python scripts/bench_kserve.py --addr 127.0.0.1:8080 --frame data/test/requests/frame-000000.json -n 200

Needs numpy, grpcio and tritonclient (models-export/requirements.txt) for the gRPC message.
"""

from __future__ import annotations

import argparse
import base64
import http.client
import json
import time
from pathlib import Path

import grpc
import numpy as np
from tritonclient.grpc import service_pb2

BOX3 = ("center_x", "center_y", "center_z", "length", "width", "height", "heading")
BOX2 = ("center_x", "center_y", "width", "height")


def tensors(frame: dict) -> list[tuple[str, str, list[int], bytes, list]]:
    """(name, datatype, shape, raw little-endian bytes, JSON data) for each input."""
    c = frame["calibration"]
    pts = frame["points"]
    pts = (np.frombuffer(base64.b64decode(pts["b64"]), "<f4") if isinstance(pts, dict)
           else np.asarray(pts, "<f4")).reshape(-1, 3)
    persons = frame["persons"]
    b3 = np.array([[p["box_3d"][k] for k in BOX3] for p in persons], "<f8")
    no_box = [np.nan] * 4
    b2 = np.array([[p["box_2d"][k] for k in BOX2] if p.get("box_2d") else no_box for p in persons], "<f8")
    out = []
    if frame.get("image"):
        img = base64.b64decode(frame["image"])
        out.append(("image", "BYTES", [1], len(img).to_bytes(4, "little") + img, [frame["image"]]))
    for name, dt, arr in [
        ("points", "FP32", pts),
        ("calibration_intrinsic", "FP64", np.array(c["intrinsic"], "<f8")),
        ("calibration_extrinsic", "FP64", np.array(c["extrinsic"], "<f8")),
        ("image_size", "INT32", np.array([c["width"], c["height"]], "<i4")),
        ("boxes_3d", "FP64", b3),
        ("boxes_2d", "FP64", b2),
    ]:
        data = [None if isinstance(v, float) and np.isnan(v) else v for v in arr.ravel().tolist()]
        out.append((name, dt, list(arr.shape), arr.tobytes(), data))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addr", default="127.0.0.1:8080")
    ap.add_argument("--frame", required=True, help="a frame JSON file (body of POST /v1/poses)")
    ap.add_argument("--model", default="default")
    ap.add_argument("-n", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=10)
    a = ap.parse_args()

    frame = json.loads(Path(a.frame).read_text())
    ts = tensors(frame)
    v1_body = json.dumps(frame).encode()
    v2_json = json.dumps(
        {"inputs": [{"name": n, "datatype": d, "shape": s, "data": j} for n, d, s, _, j in ts]}
    ).encode()
    head = json.dumps({
        "inputs": [{"name": n, "datatype": d, "shape": s, "parameters": {"binary_data_size": len(r)}}
                   for n, d, s, r, _ in ts],
        "parameters": {"binary_data_output": True},
    }).encode()
    v2_binary = head + b"".join(r for _, _, _, r, _ in ts)
    Input = service_pb2.ModelInferRequest.InferInputTensor
    grpc_req = service_pb2.ModelInferRequest(
        model_name=a.model,
        inputs=[Input(name=n, datatype=d, shape=s) for n, d, s, _, _ in ts],
        raw_input_contents=[r for _, _, _, r, _ in ts],
    ).SerializeToString()

    host, port = a.addr.rsplit(":", 1)
    conn = http.client.HTTPConnection(host, int(port))
    infer = f"/v2/models/{a.model}/infer"
    json_h = {"Content-Type": "application/json"}
    bin_h = {"Content-Type": "application/octet-stream", "Inference-Header-Content-Length": str(len(head))}
    channel = grpc.insecure_channel(a.addr)
    model_infer = channel.unary_unary("/inference.GRPCInferenceService/ModelInfer")

    def post(path: str, body: bytes, headers: dict) -> None:
        conn.request("POST", path, body=body, headers=headers)
        r = conn.getresponse()
        r.read()
        if r.status != 200:
            raise SystemExit(f"{path}: HTTP {r.status}")

    calls = {
        "POST /v1/poses (JSON)": lambda: post("/v1/poses", v1_body, json_h),
        "POST /v2 infer, JSON tensors": lambda: post(infer, v2_json, json_h),
        "POST /v2 infer, binary tensors": lambda: post(infer, v2_binary, bin_h),
        "gRPC ModelInfer, raw contents": lambda: model_infer(grpc_req),
    }
    times: dict[str, list[float]] = {k: [] for k in calls}
    for i in range(a.warmup + a.n):
        for name, call in calls.items():
            t0 = time.perf_counter()
            call()
            if i >= a.warmup:
                times[name].append((time.perf_counter() - t0) * 1e3)
    print(
        f"{a.frame}: {len(frame['persons'])} persons, bodies: v1 {len(v1_body)} B, v2 JSON {len(v2_json)} B,"
        f" v2 binary {len(v2_binary)} B, gRPC {len(grpc_req)} B; n = {a.n} each, interleaved"
    )
    for name, t in times.items():
        print(f"{name:34s} p50 {np.percentile(t, 50):7.2f} ms   p99 {np.percentile(t, 99):7.2f} ms")


if __name__ == "__main__":
    main()
