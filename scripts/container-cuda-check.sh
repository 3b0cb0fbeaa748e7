#!/usr/bin/env bash
# Builds the CUDA image (Dockerfile.cuda) on top of a CPU image and checks it end to end, as far as
# the host allows:
# - the image holds ONNX Runtime's GPU build: its CUDA provider and the CUDA libraries;
# - on the CPU (POSEFUSE_DEVICE=cpu) it answers a simulated frame as the CPU image does;
# - without a GPU, `--device cuda` (the image's default) stops at start-up with an error that
#   names what is missing, and never serves on the CPU in its place;
# - with a GPU (GPU_FLAGS set, e.g. "--gpus all" for docker or "--device nvidia.com/gpu=all" for
#   podman with CDI), it serves the frame on the GPU, within 5 mm of the CPU image's answer.
# The CUDA libraries come from PyPI (about 3 GB), so CI does not run this; docs/DEPLOY.md records
# its last run.
# Usage: scripts/container-cuda-check.sh [CPU_IMAGE] [CUDA_IMAGE]
#   CPU_IMAGE: built from ./Dockerfile (default posefuse:check, as scripts/container-check.sh
#   leaves it); CONTAINER=podman to use podman; CONTAINER_BUILD_FLAGS: more build flags, split at
#   spaces (e.g. --build-arg DEBIAN_IMAGE=... where no registry serves debian:bookworm-slim).
set -euo pipefail
cd "$(dirname "$0")/.."
CPU_IMAGE=${1:-posefuse:check}
IMAGE=${2:-posefuse:cuda-check}
PORT=${PORT:-18090}
read -r -a gpu_flags <<<"${GPU_FLAGS:-}"
. scripts/container-lib.sh
# Serves IMAGE with the extra run flags, answers the frame into FILE, stops the container.
answer() {
  local file=$1 port=$2 name=posefuse-cuda-check-$2-$$
  shift 2
  names+=("$name")
  "$C" run -d --name "$name" -p "127.0.0.1:$port:8080" "$@" >/dev/null
  wait_ready "$port" "$name"
  curl -fsS "http://127.0.0.1:$port/v1/poses" -H 'content-type: application/json' -d @"$frame" >"$file" \
    || fail "POST /v1/poses failed: $("$C" logs "$name" 2>&1 | tail -n 3)"
  "$C" logs "$name" >"$file.log" 2>&1
  "$C" rm -f "$name" >/dev/null
}
# The two answers' keypoints, person by person, at most TOL metres apart.
same_answer() {
  python3 - "$1" "$2" "$3" <<'EOF'
import json
import sys

a, b = (json.load(open(p))["persons"] for p in sys.argv[1:3])
tol = float(sys.argv[3])
assert a and len(a) == len(b), (len(a), len(b))
worst = 0.0
for pa, pb in zip(a, b):
    assert pa["mode"] == pb["mode"], (pa["mode"], pb["mode"])
    for ka, kb in zip(pa["keypoints"], pb["keypoints"]):
        worst = max(worst, max(abs(x - y) for x, y in zip(ka["xyz"], kb["xyz"])))
assert worst <= tol, f"answers {worst:.6f} m apart (allowed {tol} m)"
print(f"{len(a)} person(s), keypoints at most {worst * 1000:.3f} mm apart")
EOF
}

step "build $IMAGE on $CPU_IMAGE"
start=$(date +%s)
read -r -a flags <<<"${CONTAINER_BUILD_FLAGS:-}"
[ "$C" = podman ] && flags+=(--format docker)
"$C" build "${flags[@]}" -f Dockerfile.cuda --build-arg POSEFUSE_IMAGE="$CPU_IMAGE" -t "$IMAGE" .
echo "built in $(($(date +%s) - start)) s; size: $("$C" image inspect --format '{{.Size}}' "$IMAGE") bytes"

step "ONNX Runtime's GPU build in the image"
"$C" run --rm --entrypoint sh "$IMAGE" -c \
  'ls /app/.ort/lib/libonnxruntime_providers_cuda.so && ls /app/.ort/lib/cuda | grep -E "^lib(cudart|cublas|cudnn)\.so" | sort' \
  || fail "no CUDA provider or CUDA libraries in /app/.ort/lib"

step "simulate a request frame"
simulate_frame "$CPU_IMAGE"

step "the CUDA image on the CPU answers as the CPU image"
answer "$work/cpu.json" "$PORT" "$CPU_IMAGE"
answer "$work/cuda-on-cpu.json" "$((PORT + 1))" -e POSEFUSE_DEVICE=cpu "$IMAGE"
same_answer "$work/cpu.json" "$work/cuda-on-cpu.json" 1e-4
grep 'bundle loaded' "$work/cuda-on-cpu.json.log" | grep -q -E 'device[=":]+cpu' \
  || fail "POSEFUSE_DEVICE=cpu did not reach the server: $(grep 'bundle loaded' "$work/cuda-on-cpu.json.log")"

if [ ${#gpu_flags[@]} -gt 0 ]; then
  step "served on the GPU (${gpu_flags[*]})"
  answer "$work/gpu.json" "$((PORT + 2))" "${gpu_flags[@]}" "$IMAGE"
  grep 'bundle loaded' "$work/gpu.json.log" | grep -q -E 'device[=":]+cuda' \
    || fail "the log does not say the bundle runs on CUDA: $(grep 'bundle loaded' "$work/gpu.json.log")"
  same_answer "$work/cpu.json" "$work/gpu.json" 5e-3
else
  step "no GPU: --device cuda stops at start-up with a message"
  if timeout 120 "$C" run --rm "$IMAGE" >"$work/nogpu.log" 2>&1; then
    fail "served with --device cuda and no GPU"
  fi
  grep -q -i -E 'libcuda|cuda' "$work/nogpu.log" || fail "the error names nothing of CUDA: $(tail -n 3 "$work/nogpu.log")"
  grep -i -E 'error|cuda' "$work/nogpu.log" | tail -n 2
fi

echo "CUDA container check passed"
