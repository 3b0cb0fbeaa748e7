#!/usr/bin/env bash
# One set-up for developers, CI and the container: a project-local Python environment with the
# trainer's dependencies, and ONNX Runtime's shared library copied to .ort/lib for the server.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${POSEFUSE_VENV:-.venv}

if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -r models-export/requirements.txt
"$VENV/bin/python" -m pip install -q --no-deps -e models-export

capi=$("$VENV/bin/python" -c 'import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), "capi"))')
lib=$(ls "$capi"/libonnxruntime.so.* | head -n 1)
mkdir -p .ort/lib
cp -f "$lib" .ort/lib/libonnxruntime.so
echo "set-up done: $VENV (python), .ort/lib/libonnxruntime.so (from $(basename "$lib"))"
