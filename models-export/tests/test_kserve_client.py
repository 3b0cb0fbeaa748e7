"""The server's Open Inference Protocol (KServe v2) endpoints, called through tritonclient, the
client Triton ships on PyPI: health, metadata and inference over HTTP (JSON tensors and binary
tensors) and gRPC, whose keypoints equal those of POST /v1/poses for the same simulated frame
(to float32 rounding: the v2 outputs are FP32).

The helpers (frame to tensors, native answer to outputs, comparison) are examples/tritonclient_infer.py's,
and that script is run here too. Needs the debug binary (`cargo build`, which the Rust tests build
first); skipped without it, except under CI=true, where a missing binary fails.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "clients" / "python" / "tests"))
import live_server  # noqa: E402

MODEL_DIR = ROOT / "models" / "default"
MANIFEST = json.loads((MODEL_DIR / "manifest.json").read_text())
MODEL = MANIFEST["name"]

if reason := live_server.missing_reason():
    pytest.skip(reason, allow_module_level=True)
BINARY = live_server.binary()

import tritonclient.grpc as grpcclient  # noqa: E402
import tritonclient.http as httpclient  # noqa: E402
from tritonclient.utils import InferenceServerException  # noqa: E402

sys.path.insert(0, str(ROOT / "examples"))
from tritonclient_infer import K, differences, infer_inputs, v1_poses  # noqa: E402
from tritonclient_infer import expected_outputs as _expected  # noqa: E402

EXAMPLE = ROOT / "examples" / "tritonclient_infer.py"


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
         "--profile", "clean", "--out", str(out)],
        check=True, capture_output=True, timeout=300,
    )
    frames = [json.loads(p.read_text()) for p in sorted((out / "requests").glob("*.json"))]
    return max(frames, key=lambda f: len(f["persons"]))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """`posefuse serve` on a free loopback port, ready; yields its host:port."""
    yield from _serve(tmp_path_factory, [])


@pytest.fixture(scope="module")
def shm_server(tmp_path_factory):
    """As `server`, with the system shared-memory extension on."""
    yield from _serve(tmp_path_factory, ["--system-shared-memory"])


def _serve(tmp_path_factory, flags: list[str]):
    port = _free_port()
    env = dict(os.environ)
    env.setdefault("ORT_DYLIB_PATH", str(ROOT / ".ort" / "lib" / "libonnxruntime.so"))
    log_path = tmp_path_factory.mktemp("serve") / "serve.log"
    log = log_path.open("wb")
    proc = subprocess.Popen(
        [str(BINARY), "serve", "--addr", f"127.0.0.1:{port}", "--model-dir", str(MODEL_DIR), *flags],
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


def _check(result, expected: dict) -> None:
    # The same numbers as /v1/poses, rounded to float32 (NaN where that answer has null).
    assert differences(result, expected) == []


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
    expected = _expected(frame, v1_poses(server, frame))
    c = httpclient.InferenceServerClient(url=server)
    outputs = [httpclient.InferRequestedOutput(n, binary_data=False)
               for n in ("keypoints_3d", "keypoints_2d", "scores", "mode", "status")]
    inputs = infer_inputs(httpclient, frame, binary=False)
    result = c.infer(MODEL, inputs, outputs=outputs, request_id="r-json")
    assert result.get_response()["id"] == "r-json"
    _check(result, expected)


def test_http_binary_tensors_give_the_v1_keypoints(server, frame):
    expected = _expected(frame, v1_poses(server, frame))
    c = httpclient.InferenceServerClient(url=server)
    result = c.infer(MODEL, infer_inputs(httpclient, frame, binary=True))
    assert all("binary_data_size" in o["parameters"] for o in result.get_response()["outputs"])
    _check(result, expected)


def test_grpc_gives_the_v1_keypoints(server, frame):
    expected = _expected(frame, v1_poses(server, frame))
    c = grpcclient.InferenceServerClient(url=server)
    result = c.infer(MODEL, infer_inputs(grpcclient, frame, binary=True))
    _check(result, expected)


def test_a_bad_tensor_is_an_error_naming_it(server, frame):
    bad = httpclient.InferInput("points", [4, 2], "FP32")
    bad.set_data_from_numpy(np.zeros((4, 2), np.float32))
    inputs = [t for t in infer_inputs(httpclient, frame, binary=True) if t.name() != "points"] + [bad]
    with pytest.raises(InferenceServerException) as e:
        httpclient.InferenceServerClient(url=server).infer(MODEL, inputs)
    assert e.value.status() == "400" and "points" in e.value.message()
    gbad = grpcclient.InferInput("points", [4, 2], "FP32")
    gbad.set_data_from_numpy(np.zeros((4, 2), np.float32))
    ginputs = [t for t in infer_inputs(grpcclient, frame, binary=True) if t.name() != "points"] + [gbad]
    with pytest.raises(InferenceServerException) as e:
        grpcclient.InferenceServerClient(url=server).infer(MODEL, ginputs)
    assert "INVALID_ARGUMENT" in str(e.value.status()) and "points" in e.value.message()


def test_the_tritonclient_example_gets_the_v1_keypoints_three_ways(server):
    """examples/tritonclient_infer.py as its docstring runs it, on the committed example frame:
    the model config (`get_model_config`, HTTP and gRPC), then HTTP binary tensors, HTTP JSON
    tensors (with a row of NaN tokens in boxes_2d: "no box") and gRPC, each equal to /v1/poses."""
    run = subprocess.run(
        [sys.executable, str(EXAMPLE), "--url", server, "--frame", str(ROOT / "examples" / "frame.json")],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )
    lines = run.stdout.splitlines()
    checks = ("http model config", "grpc model config", "http binary tensors", "http json tensors", "grpc")
    results = {c: next((x for x in lines if x.startswith(f"{c}: ")), "(not run)") for c in checks}
    failed = {c: r for c, r in results.items() if "FAILED" in r or r == "(not run)"}
    assert not failed, run.stdout + run.stderr
    for answer in (results[c] for c in checks[2:]):
        assert "keypoints_3d (3, 13, 3)" in answer and answer.endswith(": equal to /v1/poses"), answer
    assert run.returncode == 0 and lines[-1] == "all answers equal /v1/poses", run.stdout + run.stderr


SHM_EXAMPLE = ROOT / "examples" / "tritonclient_shared_memory.py"


def test_shared_memory_is_refused_unless_turned_on(server):
    """The default server offers no shared memory: registration is 403 / PERMISSION_DENIED, and
    server metadata does not list the extension."""
    http = httpclient.InferenceServerClient(url=server)
    assert "system_shared_memory" not in http.get_server_metadata()["extensions"]
    with pytest.raises(InferenceServerException) as e:
        http.register_system_shared_memory("r", "/posefuse-nothing", 16)
    assert "403" in str(e.value.status()) and "--system-shared-memory" in e.value.message()
    with pytest.raises(InferenceServerException) as e:
        grpcclient.InferenceServerClient(url=server).get_system_shared_memory_status()
    assert "PERMISSION_DENIED" in str(e.value.status())


def test_the_shared_memory_example_gets_the_v1_keypoints_over_http_and_grpc(shm_server):
    """examples/tritonclient_shared_memory.py as its docstring runs it: pixels and points in a
    region made by tritonclient.utils.shared_memory, three outputs written by the server into
    another, over HTTP and gRPC, each equal to /v1/poses for the same pixels; nothing is left
    registered."""
    run = subprocess.run(
        [sys.executable, str(SHM_EXAMPLE), "--url", shm_server,
         "--frame", str(ROOT / "examples" / "frame.json")],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )
    lines = run.stdout.splitlines()
    for label in ("http", "grpc"):
        line = next((x for x in lines if x.startswith(f"{label} shared memory: ")), "(not run)")
        assert line.endswith("equal to /v1/poses"), run.stdout + run.stderr
    assert run.returncode == 0 and lines[-1] == "all answers equal /v1/poses", run.stdout + run.stderr
    http = httpclient.InferenceServerClient(url=shm_server)
    assert "system_shared_memory" in http.get_server_metadata()["extensions"]
    assert http.get_system_shared_memory_status() == []
