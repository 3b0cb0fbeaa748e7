#!/usr/bin/env bash
# One set-up for developers, CI and the container: a project-local Python environment with the
# trainer's dependencies, and ONNX Runtime's shared library copied to .ort/lib for the server.
# `--runtime-only` stops after ONNX Runtime (the container's builder needs no PyTorch); CI runs
# every line before that point too, so the container's set-up is the one CI exercises.
# `--gpu` then swaps in ONNX Runtime's GPU build (onnxruntime-gpu, same version, with its CUDA 13
# and cuDNN 9 libraries from PyPI) for `posefuse serve --device cuda`: its providers go beside the
# library in .ort/lib, the CUDA libraries in .ort/lib/cuda, and .ort/cuda.env sets the loader path
# to them (docs/OPERATIONS.md, "Devices"). `--runtime-only --gpu` is the CUDA container's set-up.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${POSEFUSE_VENV:-.venv}
gpu=0
runtime_only=0
for arg in "$@"; do
  case "$arg" in
    --runtime-only) runtime_only=1 ;;
    --gpu) gpu=1 ;;
    *) echo "usage: $0 [--runtime-only] [--gpu]" >&2; exit 2 ;;
  esac
done

# nasm assembles the JPEG decoder's SIMD code at build time; without it the build uses its C code
# (slower). Installed from Debian's packages where this runs as root (containers, CI).
if ! command -v nasm >/dev/null 2>&1; then
  if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends nasm; } || true
  fi
  command -v nasm >/dev/null 2>&1 || echo "note: no nasm (apt-get install nasm): the JPEG decoder builds without SIMD" >&2
fi

if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
# The pin lives in requirements.txt (and its lock) only, so the server and the trainer's checks use
# one version.
ort_pin=$(grep -E '^onnxruntime==' models-export/requirements.txt)
if [ "$gpu" = 0 ] && "$VENV/bin/python" -m pip show -q onnxruntime-gpu >/dev/null 2>&1; then
  # Back from --gpu: the GPU build's files would shadow the CPU build's (one package directory).
  "$VENV/bin/python" -m pip uninstall -q -y onnxruntime-gpu
  "$VENV/bin/python" -m pip install -q --force-reinstall --no-deps "$ort_pin"
fi
"$VENV/bin/python" -m pip install -q "$ort_pin"

capi() {
  "$VENV/bin/python" -c 'import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), "capi"))'
}
lib=$(ls "$(capi)"/libonnxruntime.so.* | head -n 1)
rm -rf .ort/lib .ort/cuda.env
mkdir -p .ort/lib
cp -f "$lib" .ort/lib/libonnxruntime.so
echo "ONNX Runtime: .ort/lib/libonnxruntime.so (from $(basename "$lib"))"

# ONNX Runtime's GPU build in place of the CPU build: the library and its providers in .ort/lib, and
# the CUDA and cuDNN libraries of its wheels in .ort/lib/cuda, so that .ort/lib alone serves
# `--device cuda` (the CUDA container copies just that folder).
use_gpu_build() {
  # Both wheels install the `onnxruntime` package: remove the CPU build's files first.
  local version=${ort_pin#onnxruntime==} nvidia
  "$VENV/bin/python" -m pip uninstall -q -y onnxruntime
  "$VENV/bin/python" -m pip install -q "onnxruntime-gpu[cuda,cudnn]==$version"
  cp -f "$(capi)"/libonnxruntime.so.* .ort/lib/libonnxruntime.so
  cp -f "$(capi)"/libonnxruntime_providers_*.so .ort/lib/
  # The CUDA provider finds CUDA and cuDNN by the loader path (it has no RUNPATH). Hard links where
  # the file system allows: the wheels' files are not copied twice.
  nvidia=$("$VENV/bin/python" -c 'import nvidia, os; print(os.path.dirname(nvidia.__path__[0] + "/"))')
  mkdir -p .ort/lib/cuda
  find "$nvidia" -name 'lib*.so*' -type f -exec sh -c 'cp -l -f "$@" .ort/lib/cuda/ 2>/dev/null || cp -f "$@" .ort/lib/cuda/' sh {} +
  echo "export LD_LIBRARY_PATH=\"$PWD/.ort/lib/cuda\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}\"" > .ort/cuda.env
  echo "ONNX Runtime GPU build $version: .ort/lib (providers: $(cd .ort/lib && ls libonnxruntime_providers_*.so | tr '\n' ' ')), CUDA libraries: .ort/lib/cuda ($(ls .ort/lib/cuda | wc -l) files)"
  echo "before 'posefuse serve --device cuda': . .ort/cuda.env"
}

if [ "$runtime_only" = 1 ]; then
  [ "$gpu" = 1 ] && use_gpu_build
  exit 0
fi

# The exact versions (requirements.lock, resolved from requirements.txt by scripts/lock.sh): the
# same command gives the same weights on another machine of the same kind.
"$VENV/bin/python" -m pip install -q -r models-export/requirements.lock
"$VENV/bin/python" -m pip install -q --no-deps -e models-export
"$VENV/bin/python" -m pip install -q --no-deps -e clients/python
[ "$gpu" = 1 ] && use_gpu_build
echo "set-up done: $VENV (python, the trainer, the Python client), .ort/lib/libonnxruntime.so"
