#!/usr/bin/env bash
# The project's test command: every Rust test of the workspace (release build), the core's unit
# tests without its `link` feature, the C API's host test in C (capi/test/run.sh: under valgrind
# when it is installed), then the trainer's PyTorch tests (reference-fixture
# conformance, agreement with the Rust core through the release gomatch-sim binary, losses, a
# short training smoke run).
# Tests that need ../shared skip with a message when it is absent.
set -euo pipefail
cd "$(dirname "$0")"
# The trainer's venv (tools/train/setup_venv.sh) also holds pycolmap, which the end-to-end test on freshly
# detected keypoints runs (tests/tests/localize.rs).
GOMATCH_PYTHON="$(tools/train/setup_venv.sh)/bin/python"
export GOMATCH_PYTHON
cargo test --workspace --release
# The core without its default `link` feature (no device link) builds and passes on its own.
cargo test -p gomatch --release --no-default-features --lib
cargo test -p gomatch --release --lib --features f32-statistics  # single-precision FPUs
cargo build --release -p gomatch-sim -p gomatch-tools
bash capi/test/run.sh  # the C API from C, against the x86-64 static library
tools/train/run_tests.sh
