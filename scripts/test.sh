#!/usr/bin/env bash
# Every test of the project: set-up (idempotent), lints, Rust tests, Python tests, and the
# container check where a container engine is usable.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-$PWD/.ort/lib/libonnxruntime.so}"

echo "== rustfmt / clippy"
cargo fmt --all -- --check
cargo clippy --workspace --all-targets --locked -- -D warnings

echo "== ruff"
.venv/bin/ruff check models-export clients/python deploy scripts examples fuzz tests/ros_logs tests/ci

echo "== Rust tests"
cargo test --workspace --locked --all-targets

echo "== Python tests"
# The trainer's tests, then the Python client's (end to end against this checkout's posefuse, which
# clients/python/tests/live_server.py has cargo build: after the Rust tests, only a check) and the
# deploy/ manifests' (two pytest runs: the trainer's tests import their conftest by name); -rs
# prints the reason of any skip, and under CI=true a skip not in .ci/allowed-skips fails the run
# (scripts/pytest_ci_skips.py). tests/ros_logs reads the ROS 2 logs posefuse writes with the
# official MCAP, ROS 2 and Foxglove readers.
# Each run's temporary files live in this checkout's target/ (--basetemp, emptied at the start of
# the run): two checkouts tested at once on one machine would otherwise share, and prune,
# /tmp/pytest-of-$USER.
export PYTHONPATH="$PWD/scripts${PYTHONPATH:+:$PYTHONPATH}"
mkdir -p target/pytest
.venv/bin/python -m pytest -q -rs -p pytest_ci_skips --basetemp target/pytest/trainer models-export
.venv/bin/python -m pytest -q -rs -p pytest_ci_skips --basetemp target/pytest/clients clients/python deploy tests/ros_logs tests/ci

echo "== container"
bash scripts/container-ci.sh
