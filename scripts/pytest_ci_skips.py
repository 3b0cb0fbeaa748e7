"""A pytest plugin: under CI=true a skipped test fails the run, unless its reason matches a
pattern of .ci/allowed-skips (one regular expression a line, each with the why in a comment).

A suite that cannot run (no binary, no browser, no ONNX Runtime) skips and says why on a
developer's machine; in CI the same skip would read as green, so there it is a failure.
scripts/test.sh loads it (`-p pytest_ci_skips`, with scripts/ on PYTHONPATH).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

# POSEFUSE_ALLOWED_SKIPS names another list (the plugin's own test).
ALLOWED = Path(os.environ.get("POSEFUSE_ALLOWED_SKIPS", Path(__file__).resolve().parents[1] / ".ci" / "allowed-skips"))

_refused: list[str] = []


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("true", "1", "yes")


def allowed_patterns(text: str) -> list[re.Pattern[str]]:
    """The patterns of an allow-list: blank lines and `#` comments ignored."""
    lines = (line.split("#", 1)[0].strip() for line in text.splitlines())
    return [re.compile(line) for line in lines if line]


def skip_reason(report) -> str:
    """The reason of a skipped report (pytest keeps it as `(file, line, "Skipped: reason")`)."""
    longrepr = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        return str(longrepr[2]).removeprefix("Skipped: ")
    return str(longrepr)


def _check(report) -> None:
    if not (in_ci() and report.skipped) or hasattr(report, "wasxfail"):
        return
    reason = skip_reason(report)
    patterns = allowed_patterns(ALLOWED.read_text()) if ALLOWED.is_file() else []
    if not any(p.search(reason) for p in patterns):
        _refused.append(f"{report.nodeid}: {reason}")


def pytest_runtest_logreport(report) -> None:
    _check(report)


def pytest_collectreport(report) -> None:
    _check(report)


def pytest_terminal_summary(terminalreporter) -> None:
    if _refused:
        terminalreporter.section("skips refused under CI (.ci/allowed-skips)", red=True)
        for line in _refused:
            terminalreporter.line(line)


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session, exitstatus) -> None:
    if _refused and exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
