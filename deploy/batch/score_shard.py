"""Scores one shard of an NDJSON frame set through a posefuse server's `/v1/poses:batch`.

Run by each pod of deploy/batch/job.yaml (a Kubernetes Indexed Job): pod JOB_COMPLETION_INDEX of
NUM_SHARDS takes every NUM_SHARDS-th frame line (counted over the sorted `*.ndjson` files of
INPUT_DIR), streams them to POSEFUSE_URL in chunks of CHUNK_FRAMES (each tried up to TRIES times
on 429, 5xx or a connection error), and writes one result line per
frame to OUTPUT_DIR/shard-<index>-of-<count>.ndjson:
  {"file": ..., "line": ..., "response": {...}}  or  {"file": ..., "line": ..., "error": {...}}
The file appears only when the shard is complete (written aside, then renamed), so a retried pod
starts over cleanly. Standard library only: it runs on any Python 3.10+ image.
Exit status: 0 when every frame has a response, 1 when some frames got an error item, 2 on a
transport failure after retries.
"""

from __future__ import annotations

import json
import os
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path


def shard_lines(input_dir: Path, index: int, count: int):
    """(file name, line number from 1, line) of this shard's frames, in a stable order."""
    position = 0
    for path in sorted(input_dir.glob("*.ndjson")):
        with path.open("rb") as f:
            for number, raw in enumerate(f, start=1):
                if not raw.strip():
                    continue
                if position % count == index:
                    yield path.name, number, raw.rstrip(b"\r\n")
                position += 1


def post_chunk(url: str, lines: list[bytes], timeout: float, tries: int = 4) -> list[dict]:
    """The batch endpoint's items for `lines`, in order; retries 429, 5xx and connection errors."""
    body = b"\n".join(lines) + b"\n"
    for attempt in range(tries):
        request = urllib.request.Request(
            url, data=body, method="POST", headers={"Content-Type": "application/x-ndjson"}
        )
        try:
            with urllib.request.urlopen(request, timeout=timeout) as response:
                items = [json.loads(line) for line in response if line.strip()]
            if len(items) != len(lines):
                raise RuntimeError(f"{len(items)} result lines for {len(lines)} frames")
            return sorted(items, key=lambda item: item["index"])
        except urllib.error.HTTPError as e:
            if (e.code != 429 and e.code < 500) or attempt + 1 == tries:
                raise RuntimeError(f"HTTP {e.code}: {e.read()[:500]!r}") from e
        except (urllib.error.URLError, ConnectionError, TimeoutError) as e:
            if attempt + 1 == tries:
                raise RuntimeError(f"{url}: {e}") from e
        time.sleep(min(2**attempt, 10))
    raise AssertionError("unreachable")


def main() -> int:
    index = int(os.environ["JOB_COMPLETION_INDEX"])
    count = int(os.environ["NUM_SHARDS"])
    if not 0 <= index < count:
        print(f"JOB_COMPLETION_INDEX {index} outside 0..{count - 1}", file=sys.stderr)
        return 2
    url = os.environ.get("POSEFUSE_URL", "http://posefuse:8080").rstrip("/") + "/v1/poses:batch"
    input_dir = Path(os.environ.get("INPUT_DIR", "/data/frames"))
    output_dir = Path(os.environ.get("OUTPUT_DIR", "/data/results"))
    chunk_frames = int(os.environ.get("CHUNK_FRAMES", "64"))
    timeout = float(os.environ.get("REQUEST_TIMEOUT_S", "300"))
    tries = int(os.environ.get("TRIES", "4"))

    output_dir.mkdir(parents=True, exist_ok=True)
    final = output_dir / f"shard-{index:05d}-of-{count:05d}.ndjson"
    partial = final.with_suffix(".partial")
    frames = errors = 0
    started = time.monotonic()

    def flush(chunk, out):
        nonlocal frames, errors
        items = post_chunk(url, [line for _, _, line in chunk], timeout, tries)
        for (name, number, _), item in zip(chunk, items, strict=True):
            record = {"file": name, "line": number}
            if "response" in item:
                record["response"] = item["response"]
            else:
                record["error"] = item.get("error")
                errors += 1
            out.write(json.dumps(record, separators=(",", ":")) + "\n")
        frames += len(chunk)

    try:
        with partial.open("w") as out:
            chunk = []
            for entry in shard_lines(input_dir, index, count):
                chunk.append(entry)
                if len(chunk) == chunk_frames:
                    flush(chunk, out)
                    chunk = []
            if chunk:
                flush(chunk, out)
    except RuntimeError as e:
        print(f"shard {index}/{count}: {e}", file=sys.stderr)
        return 2
    partial.replace(final)
    seconds = time.monotonic() - started
    print(f"shard {index}/{count}: {frames} frames, {errors} errors, {seconds:.1f} s -> {final}")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
