"""The Indexed Job's scorer (deploy/batch/score_shard.py), run as the Job's pods would be, against a
live server: the shards together answer every frame line exactly once, in a stable order."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "deploy" / "batch" / "score_shard.py"


def run_shard(index: int, count: int, url: str, input_dir: Path, output_dir: Path, chunk: int = 2, tries: int = 4):
    env = {
        **os.environ,
        "JOB_COMPLETION_INDEX": str(index),
        "NUM_SHARDS": str(count),
        "POSEFUSE_URL": url,
        "INPUT_DIR": str(input_dir),
        "OUTPUT_DIR": str(output_dir),
        "CHUNK_FRAMES": str(chunk),
        "TRIES": str(tries),
    }
    return subprocess.run([sys.executable, str(SCRIPT)], env=env, capture_output=True, text=True, timeout=120)


def test_shards_score_every_frame_once(server, tmp_path):
    frames = ROOT / "examples" / "frames.ndjson"
    lines = [line for line in frames.read_text().splitlines() if line.strip()]
    inputs = tmp_path / "frames"
    inputs.mkdir()
    shutil.copy(frames, inputs / "a.ndjson")
    # A second file with a blank line and one frame the server refuses.
    bad = json.loads(lines[0])
    bad["calibration"]["width"] = "wide"
    (inputs / "b.ndjson").write_text(lines[-1] + "\n\n" + json.dumps(bad) + "\n")
    (inputs / "ignored.txt").write_text("not a frame\n")
    out = tmp_path / "results"

    count = 3
    runs = [run_shard(i, count, server.http_url, inputs, out) for i in range(count)]
    records = []
    for i, r in enumerate(runs):
        shard = out / f"shard-{i:05d}-of-{count:05d}.ndjson"
        assert shard.is_file(), r.stderr
        records += [json.loads(line) for line in shard.read_text().splitlines()]
        assert f"shard {i}/{count}" in r.stdout
    # Exactly the bad frame's shard exits 1 (error items), the others 0.
    seen = sorted((rec["file"], rec["line"]) for rec in records)
    expected = [("a.ndjson", n) for n in range(1, len(lines) + 1)] + [("b.ndjson", 1), ("b.ndjson", 3)]
    assert seen == expected
    errors = [rec for rec in records if "error" in rec]
    assert [(e["file"], e["line"]) for e in errors] == [("b.ndjson", 3)]
    assert errors[0]["error"]["field"] == "calibration.width"
    assert sorted(r.returncode for r in runs) == [0] * (count - 1) + [1]
    by_source = {(rec["file"], rec["line"]): rec for rec in records}
    for n, line in enumerate(lines, start=1):
        frame = json.loads(line)
        response = by_source[("a.ndjson", n)]["response"]
        assert response.get("frame_id") == frame.get("frame_id")
        assert len(response["persons"]) + len(response.get("skipped", [])) == len(frame["persons"])
    assert not list(out.glob("*.partial"))


def test_an_unreachable_server_fails_the_pod(tmp_path):
    inputs = tmp_path / "frames"
    inputs.mkdir()
    shutil.copy(ROOT / "examples" / "frames.ndjson", inputs / "a.ndjson")
    env_url = "http://127.0.0.1:9"
    r = run_shard(0, 1, env_url, inputs, tmp_path / "out", tries=2)
    assert r.returncode == 2 and "127.0.0.1:9" in r.stderr
    assert not (tmp_path / "out" / "shard-00000-of-00001.ndjson").exists()


def test_an_index_outside_the_shards_is_refused(tmp_path):
    r = run_shard(4, 4, "http://127.0.0.1:9", tmp_path, tmp_path / "out")
    assert r.returncode == 2 and "outside" in r.stderr
