import sys
from pathlib import Path

import pytest

# The Python client tests' live_server module: one way to start `posefuse serve`.
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "clients" / "python" / "tests"))

import live_server  # noqa: E402


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A running `posefuse serve` on a free loopback port (skipped, with the reason, without one)."""
    reason = live_server.missing_reason()
    if reason:
        pytest.skip(f"no live server: {reason}")
    s = live_server.start(tmp_path_factory.mktemp("server"))
    yield s
    live_server.stop(s)
