#!/usr/bin/env bash
# Every test of the project: set-up (idempotent), lints, Rust tests, Python tests.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-$PWD/.ort/lib/libonnxruntime.so}"

echo "== rustfmt / clippy"
cargo fmt --all -- --check
cargo clippy --all-targets --locked -- -D warnings

echo "== ruff"
.venv/bin/ruff check models-export

echo "== Rust tests"
cargo test --locked --all-targets

echo "== Python tests"
.venv/bin/python -m pytest -q models-export
