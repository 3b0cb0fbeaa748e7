#!/usr/bin/env bash
# Builds the server image and checks it end to end: it becomes healthy, answers a simulated frame
# on the published port, runs as a non-root user, serves a bundle from an overriding model dir,
# refuses a broken one with a message, and stops cleanly on SIGTERM.
# Usage: scripts/container-check.sh [IMAGE]   (CONTAINER=podman to use podman instead of docker)
# CONTAINER_BUILD_FLAGS: more flags for the build, split at spaces (scripts/container-ci.sh passes
# `--build-context`s that stand in for the base images where no registry serves them).
set -euo pipefail
cd "$(dirname "$0")/.."
IMAGE=${1:-posefuse:check}
PORT=${PORT:-18080}
. scripts/container-lib.sh

step "build $IMAGE"
start=$(date +%s)
read -r -a flags <<<"${CONTAINER_BUILD_FLAGS:-}"
# podman writes OCI images by default, and those drop HEALTHCHECK.
[ "$C" = podman ] && flags+=(--format docker)
"$C" build "${flags[@]}" -t "$IMAGE" .
echo "built in $(($(date +%s) - start)) s; size: $("$C" image inspect --format '{{.Size}}' "$IMAGE") bytes"

step "simulate request frames with the image's own binary"
simulate_frame "$IMAGE"

step "serve the baked-in bundle"
name=posefuse-check-$$
names+=("$name")
"$C" run -d --name "$name" -p "127.0.0.1:$PORT:8080" "$IMAGE" >/dev/null
wait_ready "$PORT" "$name"
echo ready

step "a frame over the published port"
curl -fsS "http://127.0.0.1:$PORT/v1/poses" -H 'content-type: application/json' -d @"$frame" >"$work/response.json" \
  || fail "POST /v1/poses failed"
curl -fsS "http://127.0.0.1:$PORT/v1/models" >"$work/models.json"
python3 - "$work/response.json" "$work/models.json" <<'EOF'
import json
import sys

response = json.load(open(sys.argv[1]))
manifest = json.load(open(sys.argv[2]))
persons = response["persons"]
assert persons, "no person answered"
for person in persons:
    assert len(person["keypoints"]) == 13, person
    assert person["mode"] in ("fusion", "lidar", "camera"), person["mode"]
assert response["model"]["version"] == manifest["version"], (response["model"], manifest["version"])
first = persons[0]
print(f"{len(persons)} person(s); first: mode {first['mode']}, {first['keypoints'][0]}")
EOF

step "non-root user"
uid=$("$C" exec "$name" id -u)
[ "$uid" != 0 ] || fail "the server runs as root"
echo "uid $uid"

step "HEALTHCHECK"
if [ "$C" = podman ]; then
  # podman runs health checks from systemd timers; without systemd, run the check itself.
  podman healthcheck run "$name" || fail "the image's HEALTHCHECK fails"
fi
for _ in $(seq 60); do
  health=$("$C" inspect --format '{{.State.Health.Status}}' "$name")
  [ "$health" = healthy ] && break
  sleep 1
done
[ "$health" = healthy ] || fail "health status: $health"
echo "$health"

step "SIGTERM stops it cleanly"
"$C" stop -t 20 "$name" >/dev/null
code=$("$C" inspect --format '{{.State.ExitCode}}' "$name")
[ "$code" = 0 ] || fail "exit code after SIGTERM: $code"
echo "exit code $code"

step "an overriding model dir"
mkdir -p "$work/models"
cp -r models/default "$work/models/mine"
name2=posefuse-check-override-$$
names+=("$name2")
"$C" run -d --name "$name2" -p "127.0.0.1:$((PORT + 1)):8080" -v "$work/models:/models:ro" \
  -e POSEFUSE_MODEL_DIR=/models/mine "$IMAGE" >/dev/null
wait_ready "$((PORT + 1))" "$name2"
"$C" logs "$name2" >"$work/override.log" 2>&1
grep -q /models/mine "$work/override.log" || fail "the log does not name /models/mine: $(tail -n 3 "$work/override.log")"
curl -fsS "http://127.0.0.1:$((PORT + 1))/v1/poses" -H 'content-type: application/json' -d @"$frame" >/dev/null \
  || fail "the overriding bundle does not serve"
echo "served from /models/mine"

step "a broken bundle is refused with a message"
rm "$work/models/mine/manifest.json"
if "$C" run --rm -v "$work/models:/models:ro" -e POSEFUSE_MODEL_DIR=/models/mine "$IMAGE" >"$work/broken.log" 2>&1; then
  fail "started on a bundle without a manifest"
fi
grep -q manifest "$work/broken.log" || fail "the refusal does not name the manifest: $(tail -n 3 "$work/broken.log")"
tail -n 1 "$work/broken.log"

echo "container check passed"
