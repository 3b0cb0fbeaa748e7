"""Starts the repository's `posefuse serve` on a free loopback port for end-to-end tests.

The binary is this checkout's, fresh: [`binary`] asks cargo to build it (after `cargo test` that
is only a check) and takes the path cargo reports; POSEFUSE_BIN names another. ONNX Runtime is
ORT_DYLIB_PATH or .ort/lib/libonnxruntime.so (scripts/setup.sh). When either is missing the tests
that need them skip with the reason, and under CI=true such a skip fails the run
(scripts/pytest_ci_skips.py).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
import urllib.request
from dataclasses import dataclass
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


@dataclass
class LiveServer:
    process: subprocess.Popen
    port: int
    log: Path

    @property
    def http_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def grpc_target(self) -> str:
        return f"127.0.0.1:{self.port}"


class BinaryMissing(RuntimeError):
    """No posefuse binary can be had here (the message says why)."""


# The features `cargo test` builds the workspace with (the serving crate's test hooks), so that
# after the Rust tests the build below reuses their binary instead of compiling another.
CARGO_FEATURES = "posefuse-serve/test-hooks"


@cache
def binary() -> Path:
    """This checkout's `posefuse` binary, built if it is stale: POSEFUSE_BIN when set, else the
    executable `cargo build --bin posefuse` reports."""
    if "POSEFUSE_BIN" in os.environ:
        named = Path(os.environ["POSEFUSE_BIN"])
        if not named.is_file():
            raise BinaryMissing(f"POSEFUSE_BIN={named} is not a file")
        return named
    cargo = os.environ.get("CARGO") or shutil.which("cargo")
    if cargo is None:
        raise BinaryMissing("cargo is not on PATH to build posefuse (or set POSEFUSE_BIN)")
    p = subprocess.run(
        [cargo, "build", "--locked", "--bin", "posefuse", "--features", CARGO_FEATURES,
         "--message-format=json-render-diagnostics"],
        cwd=ROOT, capture_output=True, text=True,
    )
    if p.returncode != 0:
        raise BinaryMissing(f"`cargo build --bin posefuse` failed: {p.stderr[-2000:]}")
    for line in p.stdout.splitlines():
        msg = json.loads(line)
        if msg.get("reason") == "compiler-artifact" and msg["target"]["name"] == "posefuse" and msg.get("executable"):
            return Path(msg["executable"])
    raise BinaryMissing("cargo built no `posefuse` executable")


def missing_reason() -> str | None:
    """Why the server cannot start here, or None."""
    try:
        binary()
    except BinaryMissing as e:
        return str(e)
    ort = Path(os.environ.get("ORT_DYLIB_PATH", ROOT / ".ort/lib/libonnxruntime.so"))
    if not ort.is_file():
        return f"ONNX Runtime {ort} is missing (bash scripts/setup.sh --runtime-only)"
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(log_dir: Path, timeout_s: float = 60.0, flags: tuple[str, ...] = ()) -> LiveServer:
    env = {**os.environ, "ORT_DYLIB_PATH": os.environ.get("ORT_DYLIB_PATH", str(ROOT / ".ort/lib/libonnxruntime.so"))}
    env.setdefault("RUST_LOG", "warn")
    port = free_port()
    log = log_dir / f"posefuse-{port}.log"
    process = subprocess.Popen(
        [str(binary()), "serve", "--addr", f"127.0.0.1:{port}", "--model-dir", str(ROOT / "models/default"), *flags],
        env=env,
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
    )
    server = LiveServer(process, port, log)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"posefuse serve exited with {process.returncode}: {log.read_text()[-2000:]}")
        try:
            with urllib.request.urlopen(f"{server.http_url}/readyz", timeout=1) as r:
                if r.status == 200:
                    return server
        except OSError:
            pass
        time.sleep(0.1)
    stop(server)
    raise RuntimeError(f"posefuse serve not ready after {timeout_s} s: {log.read_text()[-2000:]}")


def stop(server: LiveServer) -> None:
    if server.process.poll() is None:
        server.process.send_signal(signal.SIGTERM)
        try:
            server.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.process.kill()
            server.process.wait()
