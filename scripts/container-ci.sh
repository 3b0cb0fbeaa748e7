#!/usr/bin/env bash
# CI's container step: builds the server image from the Dockerfile and checks it end to end
# (scripts/container-check.sh). The Dockerfile's base images come one of two ways:
#
# - registry: the engine pulls rust:*-bookworm and debian:bookworm-slim (or has them) and builds
#   the whole Dockerfile, the release build in its builder stage included.
# - local, with no registry: scripts/container-base.sh makes the runtime base from Debian's
#   packages (mmdebstrap), the builder stage is replaced by an image of the server this run built
#   (target/debug/posefuse as `cargo test` left it, debug info stripped; POSEFUSE_CONTAINER_BINARY
#   names another) and ONNX Runtime's library (.ort/lib), and podman builds the unchanged
#   Dockerfile with a `--build-context` for each (podman then skips the builder stage). Needs root
#   (under CI, password-less sudo will do) and Debian's podman, mmdebstrap, runc, netavark,
#   aardvark-dns and iptables; under CI they are installed with apt-get when missing. podman runs
#   with scripts/containers-ci.conf.
#
# Under CI (CI=true, as .ci/run sets) the local way is taken, and a check that cannot run fails.
# Elsewhere the registry way is tried first, then the local way where root and its tools are
# already there; otherwise the step prints why it is skipped and succeeds.
# POSEFUSE_CONTAINER_BASE=local|registry picks the way; CONTAINER=docker|podman the engine of the
# registry way (default: the first found); POSEFUSE_SKIP_CONTAINER=1 skips.
set -euo pipefail
cd "$(dirname "$0")/.."
in_ci=false
case "${CI:-}" in true | 1 | yes) in_ci=true ;; esac
skip() {
  echo "container check skipped: $*"
  exit 0
}
# Under CI a check that cannot run is a failure, not a skip.
unavailable() {
  if $in_ci; then
    echo "FAIL: the container check cannot run: $*" >&2
    exit 1
  fi
  skip "$*"
}
[ "${POSEFUSE_SKIP_CONTAINER:-0}" = 1 ] && skip "POSEFUSE_SKIP_CONTAINER=1"
way=${POSEFUSE_CONTAINER_BASE:-}
case "$way" in
  "" | local | registry) ;;
  *) echo "POSEFUSE_CONTAINER_BASE must be local or registry, not $way" >&2; exit 2 ;;
esac
[ -z "$way" ] && $in_ci && way=local
step_start=$(date +%s)
since() { echo "$(($(date +%s) - $1)) s"; }

# The Dockerfile's base images, with ARG defaults substituted (e.g. rust:${RUST_VERSION}-bookworm).
images=$(awk '
  /^ARG [A-Za-z_]+=/ { split(substr($0, 5), kv, "="); arg[kv[1]] = kv[2] }
  /^FROM / { img = $2; for (k in arg) gsub("\\$\\{" k "\\}", arg[k], img); print img }
' Dockerfile)

# Prints "ready ENGINE" when the registry way can run, else why not.
registry_probe() {
  local engine=${CONTAINER:-} candidate info image pulled
  if [ -z "$engine" ]; then
    for candidate in docker podman; do
      if command -v "$candidate" >/dev/null 2>&1; then engine=$candidate; break; fi
    done
  fi
  [ -n "$engine" ] || { echo "no container engine (docker or podman) on PATH"; return; }
  command -v "$engine" >/dev/null 2>&1 || { echo "CONTAINER=$engine is not on PATH"; return; }
  if ! info=$(timeout 30 "$engine" info 2>&1); then
    echo "$engine is installed but does not answer: $(printf '%s\n' "$info" | grep -v '^ *$' | tail -n 1)"
    return
  fi
  for image in $images; do
    if ! "$engine" image inspect "$image" >/dev/null 2>&1; then
      if ! pulled=$(timeout 600 "$engine" pull -q "$image" 2>&1); then
        echo "base image $image is not present and cannot be pulled: $(printf '%s\n' "$pulled" | tail -n 1)"
        return
      fi
    fi
  done
  echo "ready $engine"
}

if [ "$way" != local ]; then
  why=$(registry_probe)
  if [ "${why%% *}" = ready ]; then
    engine=${why#ready }
    echo "container check: $engine, base images ${images//$'\n'/ }"
    CONTAINER=$engine bash scripts/container-check.sh
    echo "container step: $(since "$step_start")"
    exit 0
  fi
  [ "$way" = registry ] && unavailable "$why"
  echo "registry way: $why; trying without a registry"
fi

# The local way. Debian's packages it needs (rootful podman: no uidmap, slirp4netns or
# fuse-overlayfs), and what scripts/container-check.sh calls on the host.
packages=(podman mmdebstrap runc netavark aardvark-dns iptables curl python3)
# The server binary (built as the invoking user when missing: `cargo test` normally left it here).
binary=${POSEFUSE_CONTAINER_BINARY:-target/debug/posefuse}
if [ ! -x "$binary" ] && [ -z "${POSEFUSE_CONTAINER_BINARY:-}" ]; then
  cargo build --locked --bin posefuse
fi
[ -x "$binary" ] || unavailable "no server binary at $binary"
[ -f .ort/lib/libonnxruntime.so ] || unavailable "no .ort/lib/libonnxruntime.so (run scripts/setup.sh)"
if [ "$(id -u)" != 0 ]; then
  # Under CI, as .ci/run does for its packages, a user with password-less sudo continues as root.
  if $in_ci && command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    exec sudo -n -E POSEFUSE_CONTAINER_BASE=local POSEFUSE_CONTAINER_BINARY="$binary" bash "$PWD/scripts/container-ci.sh"
  fi
  unavailable "the build without a registry needs root (mmdebstrap, rootful podman)"
fi
command -v dpkg-query >/dev/null 2>&1 || unavailable "the build without a registry needs Debian's packages (no dpkg here)"
missing=()
install_s="0 s"
for p in "${packages[@]}"; do
  dpkg-query -W -f '${Status}\n' "$p" 2>/dev/null | grep -q 'ok installed' || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  $in_ci || skip "registry way: ${why:-not tried}; without a registry: missing packages ${missing[*]} (CI installs them)"
  command -v apt-get >/dev/null 2>&1 || unavailable "missing packages ${missing[*]} and no apt-get"
  t=$(date +%s)
  echo "installing ${missing[*]}"
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null; } \
    || unavailable "apt-get could not install ${missing[*]}"
  install_s=$(since "$t")
  echo "packages installed in $install_s"
fi
export CONTAINERS_CONF=${CONTAINERS_CONF:-$PWD/scripts/containers-ci.conf}

# The stand-ins: the runtime stage's base, and the builder stage the runtime stage copies from.
runtime_image=$(printf '%s\n' "$images" | tail -n 1)
case "$runtime_image" in
  debian:*-slim) suite=${runtime_image#debian:}; suite=${suite%-slim} ;;
  *) unavailable "the runtime base $runtime_image is not a Debian slim image that scripts/container-base.sh can make" ;;
esac
grep -q -- '--from=builder ' Dockerfile || unavailable "the Dockerfile's runtime stage no longer copies from a stage named builder"
base=localhost/posefuse-debian:$suite
prebuilt=localhost/posefuse-prebuilt:ci
t=$(date +%s)
SUITE=$suite bash scripts/container-base.sh "$base" || unavailable "the base image could not be made from Debian's packages"
base_s=$(since "$t")

t=$(date +%s)
stage=$(mktemp -d "${TMPDIR:-/var/tmp}/posefuse-prebuilt.XXXXXX")
trap 'rm -rf "$stage"; podman rmi -f "$prebuilt" >/dev/null 2>&1 || true' EXIT
mkdir -p "$stage/usr/local/bin" "$stage/src/.ort"
objcopy --strip-debug "$binary" "$stage/usr/local/bin/posefuse" 2>/dev/null || cp "$binary" "$stage/usr/local/bin/posefuse"
cp -r .ort/lib "$stage/src/.ort/lib"
tar -C "$stage" -c --numeric-owner --owner=0 --group=0 . | podman import -q - "$prebuilt" >/dev/null
stand_in_s=$(since "$t")
echo "builder stand-in $prebuilt: $binary ($(stat -c %s "$stage/usr/local/bin/posefuse") bytes) and .ort/lib, in $stand_in_s"

# The previous check image, removed once the new one has its tag (layers unchanged are kept).
old=$(podman image inspect --format '{{.Id}}' localhost/posefuse:check 2>/dev/null || true)
t=$(date +%s)
echo "container check: podman $(podman version --format '{{.Client.Version}}'), base $base for $runtime_image, builder stage from $prebuilt"
CONTAINER=podman CONTAINER_BUILD_FLAGS="--build-context builder=container-image://$prebuilt --build-context $runtime_image=container-image://$base" \
  bash scripts/container-check.sh posefuse:check
check_s=$(since "$t")
new=$(podman image inspect --format '{{.Id}}' localhost/posefuse:check)
[ -n "$old" ] && [ "$old" != "$new" ] && { podman rmi "$old" >/dev/null 2>&1 || true; }
echo "container step: $(since "$step_start") (packages $install_s, base image $base_s, builder stand-in $stand_in_s, build and check $check_s)"
