"""scripts/pytest_ci_skips.py: under CI=true a skip fails the run unless .ci/allowed-skips names
its reason; elsewhere a skip is a skip."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SUITE = '''
import pytest

def test_runs():
    assert True

def test_needs_a_browser():
    pytest.skip("no Chromium here")
'''


def run(tmp_path: Path, ci: str, allowed: str) -> subprocess.CompletedProcess:
    (tmp_path / "test_suite.py").write_text(SUITE)
    (tmp_path / "allowed").write_text(allowed)
    env = {
        **os.environ,
        "CI": ci,
        "POSEFUSE_ALLOWED_SKIPS": str(tmp_path / "allowed"),
        "PYTHONPATH": str(ROOT / "scripts"),
        "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1",
    }
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "pytest_ci_skips", "-p", "no:cacheprovider", str(tmp_path)],
        cwd=tmp_path, env=env, capture_output=True, text=True,
    )


def test_under_ci_a_skip_fails_the_run_and_is_named(tmp_path):
    p = run(tmp_path, "true", "# nothing allowed\n")
    assert p.returncode == 1, p.stdout
    assert "skips refused under CI" in p.stdout
    assert "test_needs_a_browser: no Chromium here" in p.stdout


def test_under_ci_an_allowed_reason_passes(tmp_path):
    p = run(tmp_path, "true", "^no Chromium  # this machine has no browser\n")
    assert p.returncode == 0, p.stdout
    assert "1 passed, 1 skipped" in p.stdout


def test_a_module_level_skip_counts_too(tmp_path):
    (tmp_path / "test_other.py").write_text('import pytest\npytest.skip("no binary", allow_module_level=True)\n')
    p = run(tmp_path, "true", "^no Chromium\n")
    assert p.returncode == 1, p.stdout
    assert "test_other.py: no binary" in p.stdout


def test_outside_ci_a_skip_is_a_skip(tmp_path):
    p = run(tmp_path, "false", "")
    assert p.returncode == 0, p.stdout
    assert "refused" not in p.stdout
