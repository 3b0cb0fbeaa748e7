#!/usr/bin/env bash
# Re-resolves models-export/requirements.txt into models-export/requirements.lock, the exact
# versions scripts/setup.sh installs: a fresh virtual environment, the ranges installed, frozen.
# CUDA wheels (nvidia-*, triton) are pinned for Linux x86_64 only, where PyPI's torch needs them.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$PY" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -q --upgrade pip
"$tmp/venv/bin/python" -m pip install -q -r models-export/requirements.txt
lock=models-export/requirements.lock
{
  echo "# The exact versions scripts/setup.sh installs: the trainer's, the tests' and the tools' Python packages,"
  echo "# resolved from requirements.txt (the ranges a person edits) on $(uname -s) $(uname -m), $("$PY" -V), $(date +%Y-%m-%d)."
  echo "# Regenerate: bash scripts/lock.sh. torch from PyPI is its CUDA build on Linux x86_64: the same wheel"
  echo "# trains on the CPU and on an NVIDIA GPU (docs/TRAINING.md, \"GPUs\"); its CUDA libraries are the nvidia-* pins."
  "$tmp/venv/bin/python" -m pip freeze --exclude-editable \
    | sed -E 's/^((nvidia-[^=]+|triton)==[^ ]+)$/\1 ; sys_platform == "linux" and platform_machine == "x86_64"/'
  # pip freeze leaves setuptools out, but requirements.txt names it (tritonclient's pkg_resources).
  "$tmp/venv/bin/python" -m pip freeze --all | grep -E '^setuptools=='
  echo 'tomli==2.2.1 ; python_version < "3.11"'
} > "$lock"
echo "wrote $lock ($(grep -c '==' "$lock") pins)"
