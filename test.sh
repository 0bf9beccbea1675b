#!/usr/bin/env bash
# The project's test command: every Rust test of the workspace (release build), then the trainer's
# PyTorch tests (reference-fixture conformance, losses, a short training smoke run).
# Tests that need ../shared skip with a message when it is absent.
set -euo pipefail
cd "$(dirname "$0")"
cargo test --workspace --release
tools/train/run_tests.sh
