"""Starts the repository's `posefuse serve` on a free loopback port for end-to-end tests.

The binary is target/debug/posefuse (built by `cargo test`/`cargo build`; POSEFUSE_BIN overrides)
and ONNX Runtime is ORT_DYLIB_PATH or .ort/lib/libonnxruntime.so (scripts/setup.sh). When either is
missing the tests that need the server are skipped with the reason.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
import urllib.request
from dataclasses import dataclass
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


def missing_reason() -> str | None:
    """Why the server cannot start here, or None."""
    binary = Path(os.environ.get("POSEFUSE_BIN", ROOT / "target/debug/posefuse"))
    if not binary.is_file():
        return f"{binary} is missing (build it with `cargo build`)"
    ort = Path(os.environ.get("ORT_DYLIB_PATH", ROOT / ".ort/lib/libonnxruntime.so"))
    if not ort.is_file():
        return f"ONNX Runtime {ort} is missing (bash scripts/setup.sh --runtime-only)"
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(log_dir: Path, timeout_s: float = 60.0) -> LiveServer:
    binary = Path(os.environ.get("POSEFUSE_BIN", ROOT / "target/debug/posefuse"))
    env = {**os.environ, "ORT_DYLIB_PATH": os.environ.get("ORT_DYLIB_PATH", str(ROOT / ".ort/lib/libonnxruntime.so"))}
    env.setdefault("RUST_LOG", "warn")
    port = free_port()
    log = log_dir / f"posefuse-{port}.log"
    process = subprocess.Popen(
        [str(binary), "serve", "--addr", f"127.0.0.1:{port}", "--model-dir", str(ROOT / "models/default")],
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
