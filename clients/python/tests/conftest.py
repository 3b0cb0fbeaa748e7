import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import live_server  # noqa: E402

EXAMPLES = live_server.ROOT / "examples"


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """A running `posefuse serve` on a free loopback port (skipped, with the reason, without one)."""
    reason = live_server.missing_reason()
    if reason:
        pytest.skip(f"no live server: {reason}")
    s = live_server.start(tmp_path_factory.mktemp("server"))
    yield s
    live_server.stop(s)


@pytest.fixture(scope="session")
def frame_json() -> dict:
    return json.loads((EXAMPLES / "frame.json").read_text())


@pytest.fixture(scope="session")
def frames_json() -> list[dict]:
    return [json.loads(line) for line in (EXAMPLES / "frames.ndjson").read_text().splitlines() if line.strip()]
