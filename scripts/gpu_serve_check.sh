#!/usr/bin/env bash
# Serving on one NVIDIA GPU: latency and throughput of the default bundle and of a paper-size camera
# net (ResNet-50 at 256 px, exported with random weights, which cost what trained ones do) on ONNX
# Runtime's CUDA provider (float32, as the server picks on a GPU), through `posefuse bench --device
# cuda` at each --max-batch of BATCHES; then the default bundle on the same machine's CPU (INT8
# camera, as its manifest says) for comparison. Each run's table goes to OUT/bench-*.txt and its
# numbers (`posefuse bench --json`) to OUT/bench-*.json, all of them to OUT/summary.json
# (BENCHMARKS.md, "Serving on a GPU").
# Sized to run in under 10 minutes on one H100-class GPU. Nothing in the test suite depends on it.
#
#   bash scripts/gpu_serve_check.sh [OUT]
#   needs: target/release/posefuse (cargo build --release); ONNX Runtime's GPU build with its
#     providers (bash scripts/setup.sh --gpu puts it in .ort/lib; ORT_LIB=.../libonnxruntime.so names
#     another); the CUDA 13 and cuDNN 9 libraries from .ort/lib/cuda, else from the nvidia-* wheels
#     that PY has (PyTorch's own, for one); PY with torch for the ResNet-50 bundle's export.
#   env: DEVICE=cuda (cpu: a dry run of the script on a CPU), CLIENTS=1,16,64, DURATION=6,
#        BATCHES=16,64, FRAMES=40, IMAGE=jpeg420, WORKERS (the server's own sizing if unset),
#        CPU_BASELINE=1, PY (default .venv/bin/python, else python3)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-${OUT:-/tmp/posefuse-gpu-serve}}
BIN=${BIN:-target/release/posefuse}
ORT_LIB=${ORT_LIB:-$PWD/.ort/lib/libonnxruntime.so}
PY=${PY:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
DEVICE=${DEVICE:-cuda}
CLIENTS=${CLIENTS:-1,16,64}
DURATION=${DURATION:-6}
BATCHES=${BATCHES:-16,64}
FRAMES=${FRAMES:-40}
IMAGE=${IMAGE:-jpeg420}
CPU_BASELINE=${CPU_BASELINE:-1}
[ -x "$BIN" ] || { echo "no $BIN: cargo build --release" >&2; exit 2; }
[ -f "$ORT_LIB" ] || { echo "no ONNX Runtime at $ORT_LIB: bash scripts/setup.sh --gpu" >&2; exit 2; }
mkdir -p "$OUT"
rm -f "$OUT"/bench-*.txt "$OUT"/bench-*.json "$OUT/summary.json"

if [ "$DEVICE" != cpu ]; then
  cuda_dir=$(dirname "$ORT_LIB")/cuda
  if [ -d "$cuda_dir" ]; then
    dirs=$cuda_dir
  else
    # The CUDA libraries of an installed PyTorch (the nvidia-* wheels) serve ONNX Runtime as well.
    nvidia=$("$PY" -c 'import nvidia, os; print(os.path.dirname(nvidia.__path__[0] + "/"))')
    dirs=$(find "$nvidia" -name 'lib*.so*' -printf '%h\n' | sort -u | paste -sd:)
  fi
  export LD_LIBRARY_PATH="$dirs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
fi
nproc | sed 's/^/CPU cores: /'

step_start=$(date +%s)
if [ ! -d "$OUT/requests/requests" ]; then
  "$BIN" simulate --profile street-hard --count 100 --seed 2 --image-size 64 --requests 100 \
    --out "$OUT/requests" >"$OUT/simulate.log" 2>&1
fi
if [ ! -f "$OUT/bundle_r50/manifest.json" ]; then
  PYTHONPATH="$PWD/models-export${PYTHONPATH:+:$PYTHONPATH}" "$PY" -m posefuse_train.export --untrained \
    --out "$OUT/bundle_r50" --image-size 256 --backbone resnet50 >/dev/null
fi
echo "fixtures and the ResNet-50 bundle: $(($(date +%s) - step_start)) s"

# bench NAME DEVICE BUNDLE MAX_BATCH: one `posefuse bench`, its table into OUT/bench-NAME.txt and
# its numbers into OUT/bench-NAME.json.
bench() {
  local name=$1 device=$2 bundle=$3 batch=$4 t
  local workers=()
  [ -n "${WORKERS:-}" ] && workers=(--workers "$WORKERS")
  t=$(date +%s)
  echo "== $name: --device $device --max-batch $batch --model-dir $bundle"
  "$BIN" bench --data "$OUT/requests" --frames "$FRAMES" --concurrency "$CLIENTS" --duration "$DURATION" \
    --image "$IMAGE" --device "$device" --max-batch "$batch" "${workers[@]}" \
    --model-dir "$bundle" --ort-lib "$ORT_LIB" --json "$OUT/bench-$name.json" 2>"$OUT/bench-$name.log" | tee "$OUT/bench-$name.txt" \
    || { tail -n 5 "$OUT/bench-$name.log" >&2; exit 1; }
  echo "($(($(date +%s) - t)) s)"
}

for batch in ${BATCHES//,/ }; do
  bench "default-$DEVICE-b$batch" "$DEVICE" models/default "$batch"
  bench "r50-$DEVICE-b$batch" "$DEVICE" "$OUT/bundle_r50" "$batch"
done
if [ "$CPU_BASELINE" = 1 ] && [ "$DEVICE" != cpu ]; then
  bench "default-cpu-b16" cpu models/default 16
fi
python3 -c 'import json, pathlib, sys
runs = {pathlib.Path(p).stem.removeprefix("bench-"): json.loads(pathlib.Path(p).read_text()) for p in sys.argv[1:]}
print(json.dumps(runs, indent=2))' "$OUT"/bench-*.json >"$OUT/summary.json"
echo "summary: $OUT/summary.json ($(($(date +%s) - step_start)) s in all)"
