#!/usr/bin/env bash
# One stage of a staged training run (gomatch_train/stage.py): data, training from the run's committed state,
# export, evaluation on every validation scene at N = 1024 and 256, a row in the run's log.
#
#   tools/train/stage.sh RUN MINUTES
#
# RUN is a folder of tools/train/stages with its run.json. COMMIT=1 commits the run folder (state.pt, log.md)
# afterwards, so the next stage, here or on another machine, continues from it. DEVICE=cuda trains on a GPU
# (--batched) and counts in the same log. The stage owns both cores while it trains: a build beside it halves it.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
cargo build --release -q -p gomatch-sim -p gomatch-tools --manifest-path "$repo/Cargo.toml"
venv="$("$here/setup_venv.sh")"
cd "$here"
"$venv/bin/python" -m gomatch_train.stage "$1" "$2"
if [ "${COMMIT:-0}" = 1 ]; then
  git -C "$repo" add "tools/train/stages/$1"
  git -C "$repo" commit -q -m "Training stage of run $1: $(tail -n 1 "$here/stages/$1/log.md" | cut -c1-200)" \
    -- "tools/train/stages/$1"
fi
