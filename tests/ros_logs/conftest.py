"""Fixtures of the ROS 2 log tests: a small simulated drive recorded as MCAP (`posefuse waymo
simulate`, then `posefuse mcap record`), and a live `posefuse serve` to score it against."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "clients/python/tests"))

import live_server  # noqa: E402


def _require_binary():
    if reason := live_server.missing_reason():
        pytest.skip(reason)


def posefuse(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "ORT_DYLIB_PATH": os.environ.get("ORT_DYLIB_PATH", str(ROOT / ".ort/lib/libonnxruntime.so"))}
    env.setdefault("RUST_LOG", "warn")
    p = subprocess.run([str(live_server.binary()), *args], env=env, capture_output=True, text=True, timeout=600)
    if check and p.returncode != 0:
        raise AssertionError(f"posefuse {' '.join(args)} exited {p.returncode}: {p.stderr[-3000:]}")
    return p


@pytest.fixture(scope="session")
def drive(tmp_path_factory) -> Path:
    """Five frames of one simulated segment (five cameras at a quarter of Waymo's size, every
    laser), as a ROS 2 log."""
    _require_binary()
    d = tmp_path_factory.mktemp("drive")
    posefuse(
        "waymo",
        "simulate",
        "--out",
        str(d / "waymo"),
        "--segments",
        "1",
        "--frames",
        "5",
        "--seed",
        "11",
        "--profile",
        "clean",
        "--image-scale",
        "0.25",
        "--top-cols",
        "660",
        "--short-rows",
        "50",
        "--short-cols",
        "150",
    )
    posefuse("mcap", "record", "--dataset", str(d / "waymo"), "--out", str(d / "drive.mcap"))
    return d / "drive.mcap"


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    _require_binary()
    s = live_server.start(tmp_path_factory.mktemp("server"))
    yield s
    live_server.stop(s)
