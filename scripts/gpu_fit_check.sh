#!/usr/bin/env bash
# The paper recipe (ResNet-50, 256 px, bf16, channels-last) on NVIDIA GPUs for a bounded number of
# steps: training samples/s and peak GPU memory per stage, the held-out OKS@2D of the camera net,
# written to OUT/summary.json (docs/TRAINING.md, "GPUs"; BENCHMARKS.md, "Training"). Sized to run in
# under 10 minutes on one H100/H200-class GPU. Nothing in the test suite depends on it.
#
#   bash scripts/gpu_fit_check.sh [OUT]
#   env: NPROC=8 (GPUs, through torchrun), CAMERA_STEPS=400, POINT_STEPS=2000,
#        TRAIN=DIR TEST=DIR (256 px shards; default: synthetic stick figures, no binary needed),
#        PY=python with torch (default .venv/bin/python, else python3),
#        DEVICE=cpu CAMERA_BATCH=8 POINT_BATCH=16 SAMPLES=64 (a dry run of the script on a CPU)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-${OUT:-/tmp/posefuse-gpu-fit}}
PY=${PY:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
NPROC=${NPROC:-1}
CAMERA_STEPS=${CAMERA_STEPS:-400}
POINT_STEPS=${POINT_STEPS:-2000}
DEVICE=${DEVICE:-cuda}
SAMPLES=${SAMPLES:-8192}
batch=()
[ -n "${CAMERA_BATCH:-}" ] && batch+=(--set camera.batch_size="$CAMERA_BATCH")
[ -n "${POINT_BATCH:-}" ] && batch+=(--set point.batch_size="$POINT_BATCH")
export PYTHONPATH="$PWD/models-export${PYTHONPATH:+:$PYTHONPATH}"
if [ "$DEVICE" = cuda ]; then
  "$PY" -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else "no CUDA device visible to PyTorch")'
  "$PY" -c 'import torch; print("GPU:", torch.cuda.get_device_name(0), "x", torch.cuda.device_count(), "| torch", torch.__version__)'
fi
mkdir -p "$OUT"
if [ -z "${TRAIN:-}" ]; then
  TRAIN="$OUT/train" TEST="$OUT/test"
  [ -d "$TRAIN" ] || "$PY" models-export/tests/synthetic.py "$TRAIN" "$SAMPLES" 1 256
  [ -d "$TEST" ] || "$PY" models-export/tests/synthetic.py "$TEST" $(( SAMPLES / 8 )) 2 256
fi
rm -rf "$OUT/bundle" "$OUT/bundle.work"
launcher=("$PY" -m)
if [ "$NPROC" -gt 1 ]; then launcher=("$PY" -m torch.distributed.run --standalone --nproc-per-node "$NPROC" -m); fi
start=$(date +%s)
"${launcher[@]}" posefuse_train fit --recipe paper --device "$DEVICE" --train "$TRAIN" --test "$TEST" \
  --out "$OUT/bundle" --memory-mb 24000 \
  --set camera.steps="$CAMERA_STEPS" --set point.steps="$POINT_STEPS" --set run.checkpoint_every=0 "${batch[@]}"
wall=$(( $(date +%s) - start ))
"$PY" - "$OUT" "$wall" <<'PY'
import json, statistics, sys
from pathlib import Path
out, wall = Path(sys.argv[1]), int(sys.argv[2])
log = [json.loads(l) for l in (out / "bundle.work" / "log.jsonl").read_text().splitlines()]
m = json.loads((out / "bundle" / "manifest.json").read_text())
stages = {}
rates = [r for r in log if "samples_per_s" in r]
# past the first record's warm-up (cuDNN autotuning, the first shards) where a stage has more
later = [r for r in rates if r["step"] > 50]
for r in later + [r for r in rates if r["stage"] not in {x["stage"] for x in later}]:
    s = stages.setdefault(r["stage"], {"samples_per_s": [], "cuda_max_memory_gb": 0.0})
    s["samples_per_s"].append(r["samples_per_s"])
    s["cuda_max_memory_gb"] = max(s["cuda_max_memory_gb"], r.get("cuda_max_memory_gb", 0.0))
summary = {
    "wall_s": wall,
    "processes": m["training"]["processes"],
    "steps": {k: m["training"]["recipe"][k]["steps"] for k in ("camera", "point")},
    "stages": {k: {"samples_per_s_median": statistics.median(v["samples_per_s"]),
                   "cuda_max_memory_gb": v["cuda_max_memory_gb"]} for k, v in stages.items()},
    "time_s": m["training"]["time_s"],
    "held_out": {k: {x: v[x] for x in ("oks_acc_2d", "oks_acc_3d", "mpjpe_3d_m")}
                 for k, v in m["metrics"]["held_out"].items()},
}
(out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
print(json.dumps(summary, indent=2))
PY
