#!/usr/bin/env bash
# `posefuse mcap score` against `posefuse waymo score` on the same simulated frames, with each
# command's wall time and peak RSS (GNU time), at two log lengths to show the RSS does not grow
# with the log (BENCHMARKS.md, "ROS 2 logs").
#
#   bash scripts/bench_mcap.sh [DIR] [FRAMES]      (default /tmp/posefuse-mcap-bench, 200)
set -euo pipefail
cd "$(dirname "$0")/.."
DIR="${1:-/tmp/posefuse-mcap-bench}"
FRAMES="${2:-200}"
BIN="${POSEFUSE_BIN:-target/release/posefuse}"
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-$PWD/.ort/lib/libonnxruntime.so}"
export RUST_LOG="${RUST_LOG:-warn}"
mkdir -p "$DIR"

if [ ! -d "$DIR/waymo" ]; then
  "$BIN" waymo simulate --out "$DIR/waymo" --segments 1 --frames "$FRAMES" --seed 5 --profile clean
fi
"$BIN" mcap record --dataset "$DIR/waymo" --out "$DIR/drive.mcap" > /dev/null
"$BIN" mcap record --dataset "$DIR/waymo" --out "$DIR/short.mcap" --frames $((FRAMES / 4)) > /dev/null
ls -l "$DIR/drive.mcap" "$DIR/short.mcap"

measure() { # NAME, then the command
  local name="$1"; shift
  /usr/bin/time -f "%e %M" -o "$DIR/$name.time" "$@" > "$DIR/$name.out" 2> "$DIR/$name.err"
  read -r secs kib < "$DIR/$name.time"
  echo "$name: ${secs} s, peak RSS $((kib / 1024)) MiB"
}

rm -rf "$DIR/pred"
measure waymo-score "$BIN" waymo score --dataset "$DIR/waymo" --out "$DIR/pred"
grep -o "scored.*" "$DIR/waymo-score.err" || true
measure mcap-score "$BIN" mcap score --in "$DIR/drive.mcap" --out "$DIR/poses.mcap"
python3 -c 'import json,sys; s=json.load(open(sys.argv[1])); print({k: s[k] for k in ("frames","frames_answered","persons","modes","seconds","frames_per_second")})' "$DIR/mcap-score.out"
measure mcap-score-short "$BIN" mcap score --in "$DIR/short.mcap" --out "$DIR/poses-short.mcap"
python3 -c 'import json,sys; s=json.load(open(sys.argv[1])); print({k: s[k] for k in ("frames","persons","seconds","frames_per_second")})' "$DIR/mcap-score-short.out"
