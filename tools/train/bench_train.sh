#!/usr/bin/env bash
# Training throughput: whole trainer steps on full sets of POINTS keypoints and POINTS 3D points.
#
#   tools/train/bench_train.sh WIDTH ENCODER_BLOCKS POINTS [trainer options ...]
#
# e.g. `tools/train/bench_train.sh 128 12 256` (the paper's configuration) or `... 48 4 256 --no-bf16`. Runs
# `python -m gomatch_train.bench_train` in the trainer's virtualenv (setup_venv.sh) with the paper-size stages'
# settings (--workers 2 --threads 1 --compile --bf16 --batch 32; later options override them); the last line is
# `samples/s: X`.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="$("$here/setup_venv.sh")"
cd "$here"
exec "$venv/bin/python" -m gomatch_train.bench_train "$@"
