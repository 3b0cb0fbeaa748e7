#!/usr/bin/env bash
# CI's container step: runs scripts/container-check.sh when a container engine is present and
# usable (its daemon or service answers, and the Dockerfile's base images are there or can be
# pulled); otherwise prints why it is skipped and succeeds. A check that runs and fails, fails.
# CONTAINER=docker|podman picks the engine (default: the first found); POSEFUSE_SKIP_CONTAINER=1 skips.
set -euo pipefail
cd "$(dirname "$0")/.."
skip() { echo "container check skipped: $*"; exit 0; }

[ "${POSEFUSE_SKIP_CONTAINER:-0}" = 1 ] && skip "POSEFUSE_SKIP_CONTAINER=1"
engine=${CONTAINER:-}
if [ -z "$engine" ]; then
  for candidate in docker podman; do
    if command -v "$candidate" >/dev/null 2>&1; then engine=$candidate; break; fi
  done
fi
[ -n "$engine" ] || skip "no container engine (docker or podman) on PATH"
command -v "$engine" >/dev/null 2>&1 || skip "CONTAINER=$engine is not on PATH"
if ! info=$(timeout 30 "$engine" info 2>&1); then
  skip "$engine is installed but does not answer: $(printf '%s\n' "$info" | grep -v '^ *$' | tail -n 1)"
fi

# The Dockerfile's base images, with ARG defaults substituted (e.g. rust:${RUST_VERSION}-bookworm).
images=$(awk '
  /^ARG [A-Za-z_]+=/ { split(substr($0, 5), kv, "="); arg[kv[1]] = kv[2] }
  /^FROM / { img = $2; for (k in arg) gsub("\\$\\{" k "\\}", arg[k], img); print img }
' Dockerfile)
for image in $images; do
  if ! "$engine" image inspect "$image" >/dev/null 2>&1; then
    if ! pulled=$(timeout 600 "$engine" pull -q "$image" 2>&1); then
      skip "base image $image is not present and cannot be pulled: $(printf '%s\n' "$pulled" | tail -n 1)"
    fi
  fi
done
echo "container check: $engine, base images $(echo $images)"
CONTAINER=$engine exec bash scripts/container-check.sh
