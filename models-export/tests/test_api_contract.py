"""The server's HTTP API against its own OpenAPI document, property-based (schemathesis): random
requests from the document's schemas, every answer checked for a documented status, a matching
content type and body schema, and no 5xx. Fixed seed and a bounded number of cases per route.
Starts `target/debug/posefuse serve`; skipped (with the reason) when the binary is missing."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis")
hypothesis = pytest.importorskip("hypothesis")

from schemathesis.checks import (  # noqa: E402
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "clients" / "python" / "tests"))
import live_server  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ready(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=2) as c:
            c.sendall(b"GET /readyz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            return c.recv(64).startswith(b"HTTP/1.1 200")
    except OSError:
        return False


@pytest.fixture(scope="module")
def server_url():
    if reason := live_server.missing_reason():
        pytest.skip(reason)
    port = _free_port()
    env = {**os.environ}
    env.setdefault("ORT_DYLIB_PATH", str(ROOT / ".ort" / "lib" / "libonnxruntime.so"))
    proc = subprocess.Popen(
        [str(live_server.binary()), "serve", "--addr", f"127.0.0.1:{port}",
         "--model-dir", str(ROOT / "models" / "default")],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 120
    while not _ready(port):
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail("posefuse serve did not become ready")
        time.sleep(0.1)
    yield f"http://127.0.0.1:{port}"
    proc.terminate()
    proc.wait(timeout=60)


@pytest.fixture(scope="module")
def api_schema(server_url):
    # utoipa writes OpenAPI 3.1, which schemathesis 3 supports behind this switch.
    schemathesis.experimental.OPEN_API_3_1.enable()
    return schemathesis.from_uri(f"{server_url}/openapi.json", base_url=server_url)


schema = schemathesis.from_pytest_fixture("api_schema")
CHECKS = (not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance)


# The reload route swaps bundles (it is tested on its own); /metrics and /openapi.json are text
# and the document itself.
@schema.parametrize(endpoint=r"^/(v1/poses|v1/poses:batch|v1/evaluate|v1/models|healthz|readyz)$")
@hypothesis.settings(
    max_examples=8,
    derandomize=True,
    deadline=None,
    suppress_health_check=list(hypothesis.HealthCheck),
)
def test_the_api_answers_as_its_openapi_document_says(case):
    case.call_and_validate(checks=CHECKS)
