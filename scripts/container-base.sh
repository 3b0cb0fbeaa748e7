#!/usr/bin/env bash
# Builds the Dockerfile's runtime base without a registry: a minimal Debian root file system made
# from Debian's packages by mmdebstrap (the minbase variant, merged /usr, the security and
# updates suites; no documentation, man pages or locales, like Debian's slim images), imported into
# podman as IMAGE. An image of that name made by the same recipe less than MAX_AGE_DAYS ago is
# reused, so a machine that keeps its podman storage builds it once a week.
# Usage: scripts/container-base.sh [IMAGE]   (default localhost/posefuse-debian:bookworm)
# Needs root, mmdebstrap and podman (scripts/container-ci.sh installs them from Debian's packages).
# SUITE (bookworm), DEBIAN_MIRROR, DEBIAN_SECURITY_MIRROR and MAX_AGE_DAYS (7) can be set.
set -euo pipefail
cd "$(dirname "$0")/.."
IMAGE=${1:-localhost/posefuse-debian:bookworm}
SUITE=${SUITE:-bookworm}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
SECURITY=${DEBIAN_SECURITY_MIRROR:-http://deb.debian.org/debian-security}
MAX_AGE_DAYS=${MAX_AGE_DAYS:-7}

sources=(
  "deb $MIRROR $SUITE main"
  "deb $MIRROR $SUITE-updates main"
  "deb $SECURITY $SUITE-security main"
)
args=(
  --variant=minbase
  # Merged /usr without the usrmerge package (which would bring perl into the image).
  --hook-dir=/usr/share/mmdebstrap/hooks/merged-usr
  # Kept in the image's /etc/dpkg/dpkg.cfg.d/, so packages added later are slim too. No fsync per
  # file while unpacking, as in Debian's own container images (a third faster here).
  --dpkgopt=force-unsafe-io
  --dpkgopt='path-exclude=/usr/share/doc/*'
  --dpkgopt='path-include=/usr/share/doc/*/copyright'
  --dpkgopt='path-exclude=/usr/share/man/*'
  --dpkgopt='path-exclude=/usr/share/groff/*'
  --dpkgopt='path-exclude=/usr/share/info/*'
  --dpkgopt='path-exclude=/usr/share/lintian/*'
  --dpkgopt='path-exclude=/usr/share/locale/*'
)
recipe=$(printf '%s\n' "$SUITE" "${sources[@]}" "${args[@]}" | sha256sum | cut -c1-16)

if created=$(podman image inspect --format '{{.Created.Unix}} {{index .Labels "posefuse.base.recipe"}}' "$IMAGE" 2>/dev/null); then
  age=$(($(date +%s) - ${created%% *}))
  if [ "${created#* }" = "$recipe" ] && [ "$age" -lt $((MAX_AGE_DAYS * 86400)) ]; then
    echo "base image $IMAGE: reused (made $((age / 3600)) h ago, recipe $recipe)"
    exit 0
  fi
fi

work=$(mktemp -d "${TMPDIR:-/var/tmp}/posefuse-base.XXXXXX")
trap 'rm -rf "$work"' EXIT
start=$(date +%s)
if ! mmdebstrap --quiet "${args[@]}" "$SUITE" "$work/rootfs.tar" "${sources[@]}" >"$work/log" 2>&1; then
  tail -n 20 "$work/log" >&2
  echo "mmdebstrap failed" >&2
  exit 1
fi
podman import -q \
  --change 'CMD ["bash"]' \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change "LABEL posefuse.base.recipe=$recipe" \
  --change "LABEL org.opencontainers.image.description=\"Debian $SUITE minbase from $MIRROR (scripts/container-base.sh)\"" \
  "$work/rootfs.tar" "$IMAGE" >/dev/null
echo "base image $IMAGE: built from Debian's packages in $(($(date +%s) - start)) s," \
  "$(podman image inspect --format '{{.Size}}' "$IMAGE") bytes (recipe $recipe)"
