#!/usr/bin/env bash
# One evaluation table over every validation scene of ../shared/data: the model and the ground-truth oracle
# on the same queries (protocol seed 0, k = 10 and N = 1024 unless K and CAPACITY say otherwise, Sinkhorn cost in
# f16 as on the device).
#
#   tools/train/eval_all.sh MODEL_DIR [OUT_DIR]
#
# MODEL_DIR holds gomatch-{f32,f16,int8}.bin (models/ for the shipped model). Per validation scene it runs
# `gomatch-sim eval --oracle` once (the oracle does not depend on the weights) and `gomatch-sim eval
# --model MODEL_DIR/gomatch-<p>.bin` per precision, writing OUT_DIR/<scene>-oracle.json and
# OUT_DIR/<scene>-<p>.json (OUT_DIR defaults to MODEL_DIR/eval-all), then prints the tables of
# tools/train/eval_table.py, whose validation table gives per scene and precision AUC @1/5/10 px beside the
# oracle's, failures, and the true matches among merged matches and inliers.
# Environment: QUERIES (default 500: every query the protocol offers on these scenes), PRECISIONS (default
# "f32 f16 int8"), SCENES (default: all five validation scenes, as kind/name), K (views per query, default 10),
# CAPACITY (keypoints per query and points per view, 128, 256 or 1024 (default): the small-part configurations
# of docs/embedded.md).
set -euo pipefail
model_dir=$(realpath "$1")
out=${2:-$model_dir/eval-all}
queries=${QUERIES:-500}
precisions=${PRECISIONS:-f32 f16 int8}
scenes=${SCENES:-colmap/mouse colmap/sceaux colmap/mamechun colmap/softmurata opensfm/projcv_cc9d27}
repo=$(cd "$(dirname "$0")/../.." && pwd)
data="$repo/../shared/data"
[ -d "$data" ] || { echo "no ../shared/data beside the checkout" >&2; exit 1; }
cargo build --release -q -p gomatch-sim --manifest-path "$repo/Cargo.toml"
bin="$repo/target/release/gomatch-sim"
mkdir -p "$out"
threads=$(nproc)
for scene in $scenes; do
  kind=${scene%%/*}
  name=${scene#*/}
  source=(--"$kind" "$data/$scene")
  common=("${source[@]}" --k "${K:-10}" --capacity "${CAPACITY:-1024}" --queries "$queries" --seed 0
    --threads "$threads")
  "$bin" eval "${common[@]}" --oracle --json "$out/$name-oracle.json"
  for p in $precisions; do
    "$bin" eval "${common[@]}" --model "$model_dir/gomatch-$p.bin" --json "$out/$name-$p.json"
  done
done
python3 "$repo/tools/train/eval_table.py" "$out"
