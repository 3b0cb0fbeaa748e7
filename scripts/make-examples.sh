#!/usr/bin/env bash
# Regenerates examples/frame.json, examples/frames.ndjson and examples/frames.json, reproducibly:
# `posefuse simulate` (fixed seed) writes request fixtures, examples/make_frames.rs shrinks each to
# the image region and the points around its persons, and the smallest ones are kept.
# Usage: scripts/make-examples.sh   (POSEFUSE_BIN=path to use an already built binary)
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --quiet --bin posefuse --example make_frames
BIN=${POSEFUSE_BIN:-target/debug/posefuse}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$BIN" simulate --count 24 --seed 3 --image-size 64 --requests 24 --profile street \
  --out "$work/sim" >/dev/null
target/debug/examples/make_frames "$work/sim/requests" "$work/small"
python3 - "$work/small" examples <<'EOF_PY'
import json
import sys
from pathlib import Path

small, out = Path(sys.argv[1]), Path(sys.argv[2])
frames = [(p.name, p.stat().st_size, json.loads(p.read_text())) for p in sorted(small.glob("*.json"))]
with_truth = [f for f in frames if all("ground_truth" in p for p in f[2]["persons"])]
# frame.json: the most persons (at least 2) within 150 KB, then the smallest.
name, _, frame = max(
    (f for f in with_truth if len(f[2]["persons"]) >= 2 and f[1] <= 150_000), key=lambda f: (len(f[2]["persons"]), -f[1])
)
(out / "frame.json").write_text(json.dumps(frame, indent=1) + "\n")
# frames.ndjson / frames.json: the four smallest other frames, in simulation order.
rest = sorted(sorted((f for f in with_truth if f[0] != name), key=lambda f: f[1])[:4])
(out / "frames.ndjson").write_text("".join(json.dumps(f[2], separators=(",", ":")) + "\n" for f in rest))
(out / "frames.json").write_text(json.dumps([f[2] for f in rest], separators=(",", ":")) + "\n")
persons = sum(len(f[2]["persons"]) for f in rest)
print(f"frame.json: {name}, {len(frame['persons'])} persons; frames.ndjson: {len(rest)} frames, {persons} persons")
EOF_PY
ls -l examples/frame.json examples/frames.ndjson examples/frames.json
