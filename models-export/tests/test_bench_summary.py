"""scripts/bench_summary.py: `posefuse bench`'s printed tables read back as numbers, and a run that
printed no table refused (scripts/gpu_serve_check.sh keeps its runs this way)."""

from __future__ import annotations

import pytest
from bench_summary import main, parse_bench

HEADER = (
    "| image | clients | clients answered | frames/s | persons/s | p50 ms | p99 ms | p50 / raw "
    "| persons/s / raw | statuses | peak RSS MB |"
)
OUTPUT = f"""\
fixtures: 5 frames, 7 persons (1.40 per frame) from /tmp/gsc/requests
runtime: bundle models/default | workers 1 | intra-op threads 1 | max batch 16 | protocol Http | 1 s per step
raw ONNX Runtime (camera + point fusion): per frame p50 7.656 ms (110 frames timed) | ceiling 151 persons/s

{HEADER}
|---|---|---|---|---|---|---|---|---|---|---|
| Jpeg420 | 1 | 1 | 50.4 | 70.2 | 19.71 | 35.34 | 2.57 | 0.47 | 200: 51 | 82 |
| Jpeg420 | 64 | 60 | 85.2 | 120.1 | 44.39 | 82.72 | 5.80 | 0.80 | 200: 88, 429: 3 | 94 |

server VmHWM (lifetime peak RSS): 94 MB
"""


def test_the_reference_the_runtime_and_every_step_are_read_as_numbers():
    run = parse_bench(OUTPUT)
    assert run["fixtures"] == {"frames": 5, "persons": 7}
    assert run["runtime"] == {"bundle": "models/default", "workers": 1, "intra_threads": 1, "max_batch": 16}
    assert run["raw"] == {"frame_p50_ms": 7.656, "frames_timed": 110, "ceiling_persons_per_s": 151.0}
    assert run["server_peak_rss_mb"] == 94
    one, many = run["steps"]
    assert one == {
        "image": "Jpeg420",
        "clients": 1,
        "clients_answered": 1,
        "frames_per_s": 50.4,
        "persons_per_s": 70.2,
        "p50_ms": 19.71,
        "p99_ms": 35.34,
        "p50_per_raw": 2.57,
        "persons_per_s_per_raw": 0.47,
        "statuses": "200: 51",
        "peak_rss_mb": 82.0,
    }
    assert (many["clients"], many["clients_answered"], many["statuses"]) == (64, 60, "200: 88, 429: 3")


def test_a_run_without_the_raw_reference_has_none():
    text = "\n".join(line for line in OUTPUT.splitlines() if not line.startswith("raw "))
    run = parse_bench(text)
    assert "raw" not in run and len(run["steps"]) == 2


def test_a_bench_that_stopped_before_its_table_is_refused():
    cut = OUTPUT.split("\n| image")[0]
    with pytest.raises(ValueError, match="no table"):
        parse_bench(cut)


def test_a_row_that_does_not_fit_the_header_is_refused():
    with pytest.raises(ValueError):
        parse_bench(OUTPUT.replace("| 200: 51 | 82 |", "| 200: 51 |"))


def test_runs_are_named_by_their_files(tmp_path):
    for name in ("bench-default-cuda-b16.txt", "bench-r50-cuda-b64.txt"):
        (tmp_path / name).write_text(OUTPUT)
    runs = main(sorted(str(p) for p in tmp_path.iterdir()))
    assert sorted(runs) == ["default-cuda-b16", "r50-cuda-b64"]
