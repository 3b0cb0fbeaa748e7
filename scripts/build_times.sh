#!/usr/bin/env bash
# Build times and binary size (BENCHMARKS.md, "Builds"): a cold release build of the binary in an
# empty target folder, then the rebuilds after touching the simulator and after touching the
# service, and the release binary's size. Run it on an otherwise idle machine.
#   bash scripts/build_times.sh [TREE]   (TREE: a checkout, default this one)
set -euo pipefail
tree=$(cd "${1:-$(dirname "$0")/..}" && pwd)
cd "$tree"
target=$(mktemp -d)
trap 'rm -rf "$target"' EXIT
export CARGO_TARGET_DIR=$target
# The same two files in either layout (before and after the workspace's crates).
first() { for f in "$@"; do [ -f "$f" ] && { echo "$f"; return; }; done; echo "none of $*" >&2; exit 1; }
sim=$(first crates/data/src/sim/raycast.rs src/sim/raycast.rs)
service=$(first crates/serve/src/service/predict.rs src/service/predict.rs)
timed() {
  local s=$SECONDS
  cargo build --release --locked --bin posefuse --quiet
  echo "$1: $((SECONDS - s)) s"
}
timed "cold release build"
echo "release binary: $(stat -c %s "$target/release/posefuse") bytes"
touch "$sim" && timed "rebuild after touching $sim"
touch "$service" && timed "rebuild after touching $service"
