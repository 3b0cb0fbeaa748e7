#!/usr/bin/env bash
# Every test of the project: set-up (idempotent), lints, Rust tests, Python tests, and the
# container check where a container engine is usable.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-$PWD/.ort/lib/libonnxruntime.so}"

echo "== rustfmt / clippy"
cargo fmt --all -- --check
cargo clippy --all-targets --locked -- -D warnings

echo "== ruff"
.venv/bin/ruff check models-export clients/python deploy scripts examples fuzz tests/ros_logs

echo "== Rust tests"
cargo test --locked --all-targets

echo "== Python tests"
# The trainer's tests, then the Python client's (end to end against target/debug/posefuse, built
# above) and the deploy/ manifests' (two pytest runs: the trainer's tests import their conftest by
# name); -rs prints the reason of any skip. tests/ros_logs reads the ROS 2 logs posefuse writes with
# the official MCAP, ROS 2 and Foxglove readers.
.venv/bin/python -m pytest -q -rs models-export
.venv/bin/python -m pytest -q -rs clients/python deploy tests/ros_logs

echo "== container"
bash scripts/container-ci.sh
