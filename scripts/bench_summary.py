"""What `posefuse bench` printed, as JSON: its raw ONNX Runtime reference and one record per step
(image form, clients), for scripts that run it several times and keep the numbers
(scripts/gpu_serve_check.sh).

    python scripts/bench_summary.py OUT/bench-*.txt > OUT/summary.json

Each file becomes one run, named by its file name without `.txt`; a file whose bench printed no
table is an error, so a run that failed shows.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

RUNTIME = re.compile(
    r"^runtime: bundle (?P<bundle>\S+) \| workers (?P<workers>\d+) \| intra-op threads (?P<intra>\d+)"
    r" \| max batch (?P<max_batch>\d+)"
)
RAW = re.compile(
    r"^raw ONNX Runtime .*: per frame p50 (?P<p50>[\d.]+) ms \((?P<frames>\d+) frames timed\)"
    r" \| ceiling (?P<ceiling>[\d.]+) persons/s"
)
FIXTURES = re.compile(r"^fixtures: (?P<frames>\d+) frames, (?P<persons>\d+) persons")
PEAK = re.compile(r"^server VmHWM \(lifetime peak RSS\): (?P<mb>\d+) MB")
NUMBERS = {
    "clients": int,
    "clients answered": int,
    "frames/s": float,
    "persons/s": float,
    "p50 ms": float,
    "p99 ms": float,
    "p50 / raw": float,
    "persons/s / raw": float,
    "peak RSS MB": float,
}


def parse_bench(text: str) -> dict:
    """The reference and the steps of one `posefuse bench` output."""
    run: dict = {"steps": []}
    header: list[str] | None = None
    for line in text.splitlines():
        line = line.strip()
        if m := RUNTIME.match(line):
            run["runtime"] = {
                "bundle": m["bundle"],
                "workers": int(m["workers"]),
                "intra_threads": int(m["intra"]),
                "max_batch": int(m["max_batch"]),
            }
        elif m := RAW.match(line):
            run["raw"] = {
                "frame_p50_ms": float(m["p50"]),
                "frames_timed": int(m["frames"]),
                "ceiling_persons_per_s": float(m["ceiling"]),
            }
        elif m := FIXTURES.match(line):
            run["fixtures"] = {"frames": int(m["frames"]), "persons": int(m["persons"])}
        elif m := PEAK.match(line):
            run["server_peak_rss_mb"] = int(m["mb"])
        elif line.startswith("|") and not set(line) <= set("|-: "):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if header is None:
                header = cells
                continue
            step = {}
            for name, cell in zip(header, cells, strict=True):
                key = name.replace(" / ", "_per_").replace("/", "_per_").replace(" ", "_").lower()
                step[key] = NUMBERS[name](cell) if name in NUMBERS and cell not in ("", "-") else cell
            run["steps"].append(step)
    if not run["steps"]:
        raise ValueError("no table: the bench did not run to its end")
    return run


def main(paths: list[str]) -> dict:
    return {Path(p).name.removesuffix(".txt").removeprefix("bench-"): parse_bench(Path(p).read_text()) for p in paths}


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    print(json.dumps(main(sys.argv[1:]), indent=2))
