#!/usr/bin/env bash
# Cortex-M7 instructions per query of a model configuration, before training it: an untrained model of that
# configuration (seed 0) exported, converted to int8 and embedded in the Cortex-M7 image, which localizes the
# firmware query under QEMU (firmware/qemu.sh, counted under -icount). Random weights find no pose, so RANSAC runs
# its full budget: the count bounds a trained model's (whose pose stage is ~2 M instructions, not ~100 M).
#
#   tools/train/device_instructions.sh WIDTH ENCODER_BLOCKS CLASSIFIER_BLOCKS HEADS SINKHORN_ITERS
#
# With VIEW_FEATURES=1 the image carries the map's view features for that model (`gomatch-sim map features`, as
# the firmware check of .ci/run does for the shipped model): the views' encoder and first self-attention are read,
# not computed.
#
# Prints `instructions, whole query: N` and the per-stage counts. It overwrites firmware/target/cortex-m7.log: run
# `bash firmware/qemu.sh cortex-m7` again before `firmware/cross_isa.sh`. Needs what firmware/qemu.sh needs
# (qemu-system-arm, the thumbv7em-none-eabihf target) and the trainer's venv (setup_venv.sh).
set -euo pipefail
[ $# -eq 5 ] || { sed -n 2,9p "$0" >&2; exit 2; }
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
venv="$("$here/setup_venv.sh")"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
(cd "$here" && "$venv/bin/python" - "$work/model.safetensors" "$@" <<'PY'
import sys

import torch

from gomatch_train.config import ModelConfig
from gomatch_train.export import save_export
from gomatch_train.model import GoMatch

path, width, encoder, classifier, heads, iters = sys.argv[1], *map(int, sys.argv[2:])
torch.manual_seed(0)
config = ModelConfig(feature_dim=width, encoder_blocks=encoder, classifier_blocks=classifier, heads=heads,
                     sinkhorn_iters=iters)
save_export(GoMatch(config), path)
PY
)
cargo build --release -q -p gomatch-tools -p gomatch-sim --manifest-path "$repo/Cargo.toml"
"$repo/target/release/gomatch-tools" convert --input "$work/model.safetensors" --precision int8 \
  --output "$work/model-int8.bin"
features=()
if [ -n "${VIEW_FEATURES:-}" ]; then
  "$repo/target/release/gomatch-sim" map features "$repo/firmware/data/map.bin" --model "$work/model-int8.bin" \
    --capacity 256 --output "$work/view-features.bin" >/dev/null
  features=(GOMATCH_FIRMWARE_VIEW_FEATURES="$work/view-features.bin")
fi
# The image exits 4 (pose refused) with random weights; the count is what matters here.
env "${features[@]}" GOMATCH_FIRMWARE_MODEL="$work/model-int8.bin" bash "$repo/firmware/qemu.sh" cortex-m7 \
  >/dev/null 2>&1 || true
grep -E '^instructions' "$repo/firmware/target/cortex-m7.log"
