"""The real-data path end to end, with exactly the commands docs/TRAINING.md and docs/WAYMO.md
show: Waymo v2 segments (the simulator's, tiny) -> `posefuse waymo convert` -> `python -m
posefuse_train fit` (the cpu recipe, a few steps) -> the bundle served by `posefuse serve` ->
`posefuse waymo score --server` + `posefuse waymo eval`, and `posefuse eval` on the converted
fixtures. Both evaluations score the same 12 persons with the same bundle and must agree.

Needs this checkout's binary (`live_server.binary()` builds it); skipped with the reason without
it, which under CI=true fails the run.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "clients" / "python" / "tests"))
import live_server  # noqa: E402

if reason := live_server.missing_reason():
    pytest.skip(reason, allow_module_level=True)
BINARY = live_server.binary()

TINY_SEGMENT = (
    "--segments 1 --frames 6 --top-rows 48 --top-cols 1200 --short-rows 24 --short-cols 80 "
    "--image-scale 0.25 --keypoint-fraction 1 --profile clean"
).split()
FEW_STEPS = ["--set", "camera.steps=4", "--set", "point.steps=4", "--set", "point.warmup_steps=2"]


def env() -> dict:
    return {**os.environ, "ORT_DYLIB_PATH": str(ROOT / ".ort" / "lib" / "libonnxruntime.so")}


def posefuse(*args, cwd: Path) -> str:
    p = subprocess.run([str(BINARY), *args], cwd=cwd, env=env(), capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, f"posefuse {' '.join(args)}:\n{p.stderr[-3000:]}"
    return p.stdout


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_convert_fit_serve_score_and_evaluate(tmp_path):
    for name, seed in (("wod_train", "5"), ("wod_test", "6")):
        posefuse("waymo", "simulate", "--out", name, "--seed", seed, *TINY_SEGMENT, cwd=tmp_path)
    # 1. convert
    posefuse(
        "waymo",
        "convert",
        "--dataset",
        "wod_train",
        "--out",
        "train",
        "--image-size",
        "64",
        "--no-requests",
        cwd=tmp_path,
    )
    posefuse("waymo", "convert", "--dataset", "wod_test", "--out", "test", "--image-size", "64", cwd=tmp_path)
    # 2. fit
    fit = subprocess.run(
        [sys.executable, "-m", "posefuse_train", "fit", "--train", "train", "--test", "test",
         "--out", "bundle", "--version", "0.0.1-e2e", *FEW_STEPS],
        cwd=tmp_path, env=env(), capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert fit.returncode == 0, fit.stderr[-3000:]
    manifest = json.loads((tmp_path / "bundle" / "manifest.json").read_text())
    assert manifest["version"] == "0.0.1-e2e" and manifest["training"]["recipe"]["recipe"]["name"] == "cpu"
    assert manifest["training"]["data"]["train"]["meta"]["segments"] == ["sim5_0000_0000_000_0000"]
    fit_persons = manifest["metrics"]["held_out"]["fusion"]["count_3d"]
    assert fit_persons > 0

    # 3. the bundle in-process: `posefuse eval` on the converted fixtures
    report = json.loads(posefuse("eval", "--data", "test", "--model-dir", "bundle", "--json", cwd=tmp_path))
    assert report["model"]["version"] == "0.0.1-e2e" and report["failed_frames"] == 0
    in_process = report["metrics"]["all"]
    assert in_process["count_3d"] > 0

    # 4. the bundle served: batch scoring through the server, scored by Waymo's rules
    addr = f"127.0.0.1:{free_port()}"
    server = subprocess.Popen(
        [str(BINARY), "serve", "--model-dir", "bundle", "--addr", addr],
        cwd=tmp_path, env=env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while subprocess.run(
            [str(BINARY), "health", "--addr", addr], env=env(), capture_output=True
        ).returncode:
            assert time.monotonic() < deadline and server.poll() is None, "the server did not become ready"
            time.sleep(0.3)
        posefuse(
            "waymo",
            "score",
            "--dataset",
            "wod_test",
            "--out",
            "pred",
            "--server",
            f"http://{addr}",
            cwd=tmp_path,
        )
    finally:
        server.terminate()
        server.wait(timeout=30)
    waymo = json.loads(
        posefuse("waymo", "eval", "--dataset", "wod_test", "--predictions", "pred", "--json", cwd=tmp_path)
    )
    assert waymo["missing"] == 0
    served = waymo["metrics"]
    # the same persons, the same bundle, the same answers
    assert served["count_3d"] == in_process["count_3d"]
    for k in ("mpjpe_3d_m", "mean_oks_3d", "pem_3d_m"):
        assert served[k] == pytest.approx(in_process[k], abs=1e-6), k
