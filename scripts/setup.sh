#!/usr/bin/env bash
# One set-up for developers, CI and the container: a project-local Python environment with the
# trainer's dependencies, and ONNX Runtime's shared library copied to .ort/lib for the server.
# `--runtime-only` stops after ONNX Runtime (the container's builder needs no PyTorch); CI runs
# every line before that point too, so the container's set-up is the one CI exercises.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${POSEFUSE_VENV:-.venv}
case "${1:-}" in
  "") runtime_only=0 ;;
  --runtime-only) runtime_only=1 ;;
  *) echo "usage: $0 [--runtime-only]" >&2; exit 2 ;;
esac

if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
# The pin lives in requirements.txt (and its lock) only, so the server and the trainer's checks use
# one version.
"$VENV/bin/python" -m pip install -q "$(grep -E '^onnxruntime==' models-export/requirements.txt)"

capi=$("$VENV/bin/python" -c 'import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), "capi"))')
lib=$(ls "$capi"/libonnxruntime.so.* | head -n 1)
mkdir -p .ort/lib
cp -f "$lib" .ort/lib/libonnxruntime.so
echo "ONNX Runtime: .ort/lib/libonnxruntime.so (from $(basename "$lib"))"
if [ "$runtime_only" = 1 ]; then
  exit 0
fi

# The exact versions (requirements.lock, resolved from requirements.txt by scripts/lock.sh): the
# same command gives the same weights on another machine of the same kind.
"$VENV/bin/python" -m pip install -q -r models-export/requirements.lock
"$VENV/bin/python" -m pip install -q --no-deps -e models-export
"$VENV/bin/python" -m pip install -q --no-deps -e clients/python
echo "set-up done: $VENV (python, the trainer, the Python client), .ort/lib/libonnxruntime.so"
