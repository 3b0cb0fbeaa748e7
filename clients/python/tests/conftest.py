import base64
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import live_server  # noqa: E402

EXAMPLES = live_server.ROOT / "examples"


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """A running `posefuse serve` on a free loopback port (skipped, with the reason, without one;
    under CI=true that skip fails the run)."""
    if reason := live_server.missing_reason():
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


@pytest.fixture(scope="session")
def raw_frame_json(frame_json) -> dict:
    """examples/frame.json with its JPEG decoded (Pillow) into `image_rgb` pixels instead of `image`."""
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(base64.b64decode(frame_json["image"]))).convert("RGB"))
    assert rgb.shape == (frame_json["calibration"]["height"], frame_json["calibration"]["width"], 3)
    pixels = {"width": rgb.shape[1], "height": rgb.shape[0], "b64": base64.b64encode(rgb.tobytes()).decode()}
    return {k: v for k, v in frame_json.items() if k != "image"} | {"image_rgb": pixels}
