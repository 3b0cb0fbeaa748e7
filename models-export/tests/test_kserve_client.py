"""The server's Open Inference Protocol (KServe v2) endpoints, called through tritonclient, the
client Triton ships on PyPI: health, metadata and inference over HTTP (JSON tensors and binary
tensors) and gRPC, whose keypoints equal those of POST /v1/poses for the same simulated frame
(to float32 rounding: the v2 outputs are FP32).

Needs the debug binary (`cargo build`, which the Rust tests build first); skipped without it.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
BINARY = ROOT / "target" / "debug" / "posefuse"
MODEL_DIR = ROOT / "models" / "default"
MANIFEST = json.loads((MODEL_DIR / "manifest.json").read_text())
MODEL = MANIFEST["name"]

if not BINARY.is_file():
    pytest.skip(f"{BINARY} is not built (run `cargo build`)", allow_module_level=True)

import tritonclient.grpc as grpcclient  # noqa: E402
import tritonclient.http as httpclient  # noqa: E402
from tritonclient.utils import InferenceServerException  # noqa: E402

K = 13


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str) -> int:
    try:
        with urllib.request.urlopen(url, timeout=2) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code
    except OSError:
        return 0


@pytest.fixture(scope="module")
def frame(tmp_path_factory) -> dict:
    """A simulator request fixture (camera image, LiDAR points, several persons)."""
    out = tmp_path_factory.mktemp("sim")
    subprocess.run(
        [str(BINARY), "simulate", "--count", "6", "--seed", "3", "--image-size", "64", "--requests", "3",
         "--out", str(out)],
        check=True, capture_output=True, timeout=300,
    )
    frames = [json.loads(p.read_text()) for p in sorted((out / "requests").glob("*.json"))]
    return max(frames, key=lambda f: len(f["persons"]))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """`posefuse serve` on a free loopback port, ready; yields its host:port."""
    port = _free_port()
    env = dict(os.environ)
    env.setdefault("ORT_DYLIB_PATH", str(ROOT / ".ort" / "lib" / "libonnxruntime.so"))
    log_path = tmp_path_factory.mktemp("serve") / "serve.log"
    log = log_path.open("wb")
    proc = subprocess.Popen(
        [str(BINARY), "serve", "--addr", f"127.0.0.1:{port}", "--model-dir", str(MODEL_DIR)],
        env=env, stdout=log, stderr=subprocess.STDOUT,
    )
    addr = f"127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while _get(f"http://{addr}/v2/health/ready") != 200:
            if proc.poll() is not None:
                raise RuntimeError(f"the server exited: {log_path.read_text(errors='replace')[-2000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError("the server did not become ready within 120 s")
            time.sleep(0.1)
        yield addr
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def _v1_poses(addr: str, frame: dict) -> dict:
    body = json.dumps(frame).encode()
    headers = {"Content-Type": "application/json"}
    req = urllib.request.Request(f"http://{addr}/v1/poses", data=body, headers=headers)
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.loads(r.read())


def _expected(frame: dict, resp: dict) -> dict:
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


def _tensors(frame: dict, *, image_as_base64: bool) -> list[tuple[str, np.ndarray]]:
    """The frame as the v2 inputs (docs/KSERVE.md)."""
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
    image = frame["image"] if image_as_base64 else base64.b64decode(frame["image"])
    return [
        ("image", np.array([image], dtype=object)),
        ("points", np.ascontiguousarray(pts)),
        ("calibration_intrinsic", np.array(c["intrinsic"], np.float64)),
        ("calibration_extrinsic", np.array(c["extrinsic"], np.float64)),
        ("image_size", np.array([c["width"], c["height"]], np.int32)),
        ("boxes_3d", b3),
        ("boxes_2d", b2),
        ("person_ids", np.array([p["id"].encode() for p in persons], dtype=object)),
        ("mode", np.array([frame.get("mode", "auto").encode()], dtype=object)),
    ]


DATATYPES = {np.dtype(np.float32): "FP32", np.dtype(np.float64): "FP64", np.dtype(np.int32): "INT32",
             np.dtype(object): "BYTES"}


def _inputs(module, frame: dict, *, binary: bool) -> list:
    out = []
    for name, arr in _tensors(frame, image_as_base64=not binary):
        t = module.InferInput(name, list(arr.shape), DATATYPES[arr.dtype])
        if module is httpclient:
            t.set_data_from_numpy(arr, binary_data=binary)
        else:
            t.set_data_from_numpy(arr)
        out.append(t)
    return out


def _check(result, expected: dict) -> None:
    as_text = [v.decode() if isinstance(v, bytes) else str(v) for v in result.as_numpy("mode").tolist()]
    assert as_text == expected["mode"]
    status = [v.decode() if isinstance(v, bytes) else str(v) for v in result.as_numpy("status").tolist()]
    assert status == expected["status"]
    # The same numbers as /v1/poses, rounded to float32 (NaN where that answer has null).
    np.testing.assert_allclose(result.as_numpy("keypoints_3d"), expected["keypoints_3d"], rtol=0, atol=1e-5)
    np.testing.assert_allclose(result.as_numpy("keypoints_2d"), expected["keypoints_2d"], rtol=0, atol=1e-3)
    np.testing.assert_allclose(result.as_numpy("scores"), expected["scores"], rtol=0, atol=1e-6)


def test_health_and_metadata_over_http(server):
    c = httpclient.InferenceServerClient(url=server)
    assert c.is_server_live() and c.is_server_ready() and c.is_model_ready(MODEL)
    assert c.is_model_ready(MODEL, model_version=MANIFEST["version"])
    assert not c.is_model_ready("no-such-model")
    assert "binary_tensor_data" in c.get_server_metadata()["extensions"]
    meta = c.get_model_metadata(MODEL)
    assert meta["versions"] == [MANIFEST["version"]]
    inputs = {t["name"]: (t["datatype"], t["shape"]) for t in meta["inputs"]}
    assert inputs["points"] == ("FP32", [-1, 3]) and inputs["image"] == ("BYTES", [1])
    outputs = {t["name"]: (t["datatype"], t["shape"]) for t in meta["outputs"]}
    assert outputs["keypoints_3d"] == ("FP32", [-1, K, 3]) and outputs["mode"] == ("BYTES", [-1])
    with pytest.raises(InferenceServerException) as e:
        c.get_model_metadata("no-such-model")
    assert e.value.status() == "404"


def test_health_and_metadata_over_grpc(server):
    c = grpcclient.InferenceServerClient(url=server)
    assert c.is_server_live() and c.is_server_ready() and c.is_model_ready(MODEL)
    assert "binary_tensor_data" in c.get_server_metadata().extensions
    meta = c.get_model_metadata(MODEL)
    assert list(meta.versions) == [MANIFEST["version"]]
    shapes = {t.name: (t.datatype, list(t.shape)) for t in meta.outputs}
    assert shapes["keypoints_2d"] == ("FP32", [-1, K, 2]) and shapes["status"] == ("BYTES", [-1])
    with pytest.raises(InferenceServerException) as e:
        c.get_model_metadata("no-such-model")
    assert "NOT_FOUND" in str(e.value.status())


def test_http_json_tensors_give_the_v1_keypoints(server, frame):
    expected = _expected(frame, _v1_poses(server, frame))
    c = httpclient.InferenceServerClient(url=server)
    outputs = [httpclient.InferRequestedOutput(n, binary_data=False)
               for n in ("keypoints_3d", "keypoints_2d", "scores", "mode", "status")]
    result = c.infer(MODEL, _inputs(httpclient, frame, binary=False), outputs=outputs, request_id="r-json")
    assert result.get_response()["id"] == "r-json"
    _check(result, expected)


def test_http_binary_tensors_give_the_v1_keypoints(server, frame):
    expected = _expected(frame, _v1_poses(server, frame))
    c = httpclient.InferenceServerClient(url=server)
    result = c.infer(MODEL, _inputs(httpclient, frame, binary=True))
    assert all("binary_data_size" in o["parameters"] for o in result.get_response()["outputs"])
    _check(result, expected)


def test_grpc_gives_the_v1_keypoints(server, frame):
    expected = _expected(frame, _v1_poses(server, frame))
    c = grpcclient.InferenceServerClient(url=server)
    result = c.infer(MODEL, _inputs(grpcclient, frame, binary=True))
    _check(result, expected)


def test_a_bad_tensor_is_an_error_naming_it(server, frame):
    bad = httpclient.InferInput("points", [4, 2], "FP32")
    bad.set_data_from_numpy(np.zeros((4, 2), np.float32))
    inputs = [t for t in _inputs(httpclient, frame, binary=True) if t.name() != "points"] + [bad]
    with pytest.raises(InferenceServerException) as e:
        httpclient.InferenceServerClient(url=server).infer(MODEL, inputs)
    assert e.value.status() == "400" and "points" in e.value.message()
    gbad = grpcclient.InferInput("points", [4, 2], "FP32")
    gbad.set_data_from_numpy(np.zeros((4, 2), np.float32))
    ginputs = [t for t in _inputs(grpcclient, frame, binary=True) if t.name() != "points"] + [gbad]
    with pytest.raises(InferenceServerException) as e:
        grpcclient.InferenceServerClient(url=server).infer(MODEL, ginputs)
    assert "INVALID_ARGUMENT" in str(e.value.status()) and "points" in e.value.message()
