#!/usr/bin/env bash
# Training throughput: whole trainer steps on full sets of POINTS keypoints and POINTS 3D points.
#
#   tools/train/bench_train.sh WIDTH ENCODER_BLOCKS POINTS [trainer options ...]
#
# e.g. `tools/train/bench_train.sh 128 12 256` (the paper's configuration) or `... 64 6 256 --bf16`. Runs
# `python -m gomatch_train.bench_train` in the trainer's virtualenv (setup_venv.sh) with a stage's defaults
# (--workers 2 --threads 1 --compile --batch 32; later options override them); the last line is `samples/s: X`.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="$("$here/setup_venv.sh")"
cd "$here"
exec "$venv/bin/python" -m gomatch_train.bench_train "$@"
