"""One frame through a posefuse server's Open Inference Protocol (KServe v2) endpoints with Triton's
own client (`pip install "tritonclient[http,grpc]"`), three ways: HTTP with binary tensors, HTTP
with JSON tensors, and gRPC (on the same port as HTTP). Each answer's keypoints are checked equal
to those of `POST /v1/poses` for the same frame, to float32 rounding (the v2 outputs are FP32).
The model's Triton-style configuration is read too (`get_model_config`, HTTP and gRPC).

    python examples/tritonclient_infer.py --url localhost:8080 --frame examples/frame.json

The first person is sent without its 2D box (`--drop-box-2d 1`): its `boxes_2d` row is four NaN,
which means "no box" (the server derives the box from the projected 3D box, as /v1/poses does for
a person without `box_2d`); in JSON tensors tritonclient writes those as `NaN` tokens. The tensor
contract is docs/KSERVE.md. Exit status 0 when every answer matches, 1 otherwise.

models-export/tests/test_kserve_client.py imports the helpers below and runs this script.
"""

from __future__ import annotations

import argparse
import base64
import json
import sys
import urllib.request
from pathlib import Path

import numpy as np
import tritonclient.grpc as grpcclient
import tritonclient.http as httpclient
from tritonclient.utils import InferenceServerException

K = 13  # keypoints per person
OUTPUTS = ("keypoints_3d", "keypoints_2d", "scores", "mode", "status")
# Float32 rounding of the native answer's numbers: metres, pixels, 0..1 scores.
TOLERANCE = {"keypoints_3d": 1e-5, "keypoints_2d": 1e-3, "scores": 1e-6}
DATATYPES = {np.dtype(np.float32): "FP32", np.dtype(np.float64): "FP64", np.dtype(np.int32): "INT32",
             np.dtype(object): "BYTES"}


def v1_poses(addr: str, frame: dict) -> dict:
    """The native answer: POST /v1/poses."""
    req = urllib.request.Request(f"http://{addr}/v1/poses", data=json.dumps(frame).encode(),
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.loads(r.read())


def expected_outputs(frame: dict, resp: dict) -> dict:
    """The native response as the v2 outputs: one row per requested person, NaN where absent."""
    m = len(frame["persons"])
    kp3 = np.full((m, K, 3), np.nan, np.float32)
    kp2 = np.full((m, K, 2), np.nan, np.float32)
    scores = np.full((m, K), np.nan, np.float32)
    modes, status = ["none"] * m, [""] * m
    for s in resp.get("skipped", []):
        status[s["index"]] = s["error"]["code"]
    rows = iter(i for i in range(m) if not status[i])
    for p in resp["persons"]:
        i = next(rows)
        modes[i], status[i] = p["mode"], "ok"
        for k, kp in enumerate(p["keypoints"]):
            kp3[i, k] = kp["xyz"]
            if kp["uv"] is not None:
                kp2[i, k] = kp["uv"]
            if kp["score"] is not None:
                scores[i, k] = kp["score"]
    return {"keypoints_3d": kp3, "keypoints_2d": kp2, "scores": scores, "mode": modes, "status": status}


def frame_tensors(frame: dict, *, image_as_base64: bool) -> list[tuple[str, np.ndarray]]:
    """The frame (native JSON form) as the v2 inputs (docs/KSERVE.md). A person without `box_2d`
    gets a row of NaN in `boxes_2d`. The image is base64 text where it travels as a JSON string
    (HTTP JSON tensors), else the file's bytes; a frame without one is sent LiDAR only."""
    c = frame["calibration"]
    points = frame["points"]
    if isinstance(points, dict):
        pts = np.frombuffer(base64.b64decode(points["b64"]), dtype="<f4").reshape(-1, 3)
    else:
        pts = np.asarray(points, np.float32).reshape(-1, 3)
    persons = frame["persons"]
    b3 = np.array([[p["box_3d"][k] for k in ("center_x", "center_y", "center_z", "length", "width", "height",
                                             "heading")] for p in persons], np.float64)
    b2 = np.array([[p["box_2d"][k] for k in ("center_x", "center_y", "width", "height")] if p.get("box_2d")
                   else [np.nan] * 4 for p in persons], np.float64)
    tensors = []
    if frame.get("image"):
        image = frame["image"] if image_as_base64 else base64.b64decode(frame["image"])
        tensors.append(("image", np.array([image], dtype=object)))
    return tensors + [
        ("points", np.ascontiguousarray(pts)),
        ("calibration_intrinsic", np.array(c["intrinsic"], np.float64)),
        ("calibration_extrinsic", np.array(c["extrinsic"], np.float64)),
        ("image_size", np.array([c["width"], c["height"]], np.int32)),
        ("boxes_3d", b3),
        ("boxes_2d", b2),
        ("person_ids", np.array([p["id"].encode() for p in persons], dtype=object)),
        ("mode", np.array([frame.get("mode", "auto").encode()], dtype=object)),
    ]


def infer_inputs(module, frame: dict, *, binary: bool) -> list:
    """tritonclient InferInputs of `module` (tritonclient.http or tritonclient.grpc); `binary`:
    HTTP's binary tensor data extension, else JSON tensors (gRPC is always binary)."""
    out = []
    for name, arr in frame_tensors(frame, image_as_base64=not binary):
        t = module.InferInput(name, list(arr.shape), DATATYPES[arr.dtype])
        if module is httpclient:
            t.set_data_from_numpy(arr, binary_data=binary)
        else:
            t.set_data_from_numpy(arr)
        out.append(t)
    return out


def _text(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in values.tolist()]


def differences(result, expected: dict) -> list[str]:
    """What in a tritonclient InferResult differs from the native answer (empty: it matches)."""
    out = []
    for name in ("mode", "status"):
        got = _text(result.as_numpy(name))
        if got != expected[name]:
            out.append(f"{name}: {got} != {expected[name]}")
    for name, atol in TOLERANCE.items():
        got, want = result.as_numpy(name), expected[name]
        if got is None or got.shape != want.shape:
            out.append(f"{name}: shape {None if got is None else got.shape} != {want.shape}")
        elif not np.array_equal(np.isnan(got), np.isnan(want)):
            out.append(f"{name}: NaN where /v1/poses has a number, or the other way round")
        elif np.nan_to_num(np.abs(got - want)).max(initial=0.0) > atol:
            out.append(f"{name}: differs by {np.nanmax(np.abs(got - want)):.3g} (> {atol})")
    return out


def max_difference(result, expected: dict) -> float:
    got, want = result.as_numpy("keypoints_3d"), expected["keypoints_3d"]
    return float(np.nan_to_num(np.abs(got - want)).max(initial=0.0))


def without_boxes_2d(frame: dict, count: int) -> dict:
    """The frame with its first `count` persons' `box_2d` removed."""
    persons = [{k: v for k, v in p.items() if k != "box_2d" or i >= count} for i, p in enumerate(frame["persons"])]
    return dict(frame, persons=persons)


def _check_config(http, model: str) -> str:
    """Triton's model configuration (REST GET /v2/models/{name}/config): names the model."""
    config = http.get_model_config(model)
    if config.get("name") != model:
        raise ValueError(f"the model config names {config.get('name')!r}, not {model!r}")
    return f"{len(config.get('input', []))} inputs, {len(config.get('output', []))} outputs"


def _check_grpc_config(grpc, model: str) -> str:
    """The same over gRPC (Triton's ModelConfig call)."""
    config = grpc.get_model_config(model).config
    if config.name != model:
        raise ValueError(f"the model config names {config.name!r}, not {model!r}")
    return f"{len(config.input)} inputs, {len(config.output)} outputs"


def _check_answer(result, expected: dict) -> str:
    wrong = differences(result, expected)
    if wrong:
        raise ValueError("DIFFERENT from /v1/poses: " + "; ".join(wrong))
    return (f"keypoints_3d {result.as_numpy('keypoints_3d').shape}, max |difference| "
            f"{max_difference(result, expected):.2g} m: equal to /v1/poses")


def run(url: str, frame: dict, model: str = "default") -> bool:
    """Sends the frame three ways and prints, for the model config and each answer, what it found
    (an answer: its comparison with /v1/poses) or why it failed; True when everything passed."""
    expected = expected_outputs(frame, v1_poses(url, frame))
    print(f"/v1/poses: modes {expected['mode']}, status {expected['status']}")
    http = httpclient.InferenceServerClient(url=url)
    if not (http.is_server_ready() and http.is_model_ready(model)):
        print(f"{url}: model {model} is not ready")
        return False
    meta = http.get_model_metadata(model)
    print(f"model {meta['name']} versions {meta['versions']}: inputs {[t['name'] for t in meta['inputs']]}")

    grpc = grpcclient.InferenceServerClient(url=url)
    json_outputs = [httpclient.InferRequestedOutput(n, binary_data=False) for n in OUTPUTS]
    checks = {
        "http model config": lambda: _check_config(http, model),
        "grpc model config": lambda: _check_grpc_config(grpc, model),
        "http binary tensors": lambda: _check_answer(
            http.infer(model, infer_inputs(httpclient, frame, binary=True), request_id="binary"), expected),
        # JSON tensors: a NaN boxes_2d row goes out as NaN tokens (json.dumps of a float nan).
        "http json tensors": lambda: _check_answer(
            http.infer(model, infer_inputs(httpclient, frame, binary=False), outputs=json_outputs,
                       request_id="json"), expected),
        "grpc": lambda: _check_answer(
            grpc.infer(model, infer_inputs(grpcclient, frame, binary=True), request_id="grpc"), expected),
    }
    ok = True
    for name, check in checks.items():
        try:
            print(f"{name}: {check()}")
        except (InferenceServerException, ValueError) as e:
            ok = False
            why = f"{e.status()} {e.message()}" if isinstance(e, InferenceServerException) else str(e)
            print(f"{name}: FAILED: {why}")
    return ok


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="localhost:8080", help="the server's host:port (HTTP and gRPC)")
    parser.add_argument("--frame", type=Path, default=Path(__file__).with_name("frame.json"),
                        help="a frame in the native JSON form (default: examples/frame.json)")
    parser.add_argument("--model", default="default", help="the model (bundle) name")
    parser.add_argument("--drop-box-2d", type=int, default=1, metavar="N",
                        help="send the first N persons without their 2D box (NaN rows in boxes_2d)")
    args = parser.parse_args(argv)
    frame = without_boxes_2d(json.loads(args.frame.read_text()), args.drop_box_2d)
    ok = run(args.url, frame, args.model)
    print("all answers equal /v1/poses" if ok else "FAILED: see above")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
