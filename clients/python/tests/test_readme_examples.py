"""The Python examples of the READMEs, run as written against a live `posefuse serve` (the default
bundle, the committed examples/ frames), from the repository root: only their address
(localhost:8080) is changed to the test server's. A README example that stops working fails here."""

import re
import subprocess
import sys

import pytest
from live_server import ROOT

# (README, index of its ```python block): lines its output must contain. Every block is listed
# (test_every_python_block_is_run), so a new example is run too.
EXPECTED = {
    ("clients/python/README.md", 0): [
        r"^p0 (fusion|lidar|camera) \[",
        r"^p1 (fusion|lidar|camera) \[",
        r"^p2 (fusion|lidar|camera) \[",
        r"^walker fusion \[",
        r"^invalid_field calibration\.intrinsic 422$",
        r"^\[\[",  # the gRPC answer's keypoints_2d rows
    ],
    ("examples/README.md", 0): [r"^p0 (fusion|lidar|camera) \[", r"^0 True$", r"^\[\["],
    ("examples/README.md", 1): [r"^\{.*'name': 'nose'"],
}


def python_blocks(readme: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```$", (ROOT / readme).read_text(), re.S | re.M)


def test_every_python_block_is_run():
    for readme in {r for r, _ in EXPECTED}:
        count = len(python_blocks(readme))
        assert sorted(i for r, i in EXPECTED if r == readme) == list(range(count)), readme


@pytest.mark.parametrize(("readme", "index"), sorted(EXPECTED))
def test_readme_python_example_runs_as_written(server, readme, index):
    code = python_blocks(readme)[index]
    assert "localhost:8080" in code, "the example talks to the documented address"
    run = subprocess.run(
        [sys.executable, "-c", code.replace("localhost:8080", f"127.0.0.1:{server.port}")],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert run.returncode == 0, f"{readme} example {index} failed:\n{run.stdout}\n{run.stderr}"
    lines = run.stdout.splitlines()
    for pattern in EXPECTED[readme, index]:
        assert any(re.search(pattern, line) for line in lines), f"no line matches {pattern!r}:\n{run.stdout}"
