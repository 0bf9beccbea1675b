#!/usr/bin/env bash
# A short training session on one GPU: writes the training data, then trains two models side by side on the GPU
# with --batched, each for MINUTES of wall time, and copies their exports, histories and logs to OUT.
#
#   tools/train/train_gpu.sh GOMATCH_SIM DATA OUT MINUTES
#
# GOMATCH_SIM: a built `gomatch-sim`; DATA: the ../shared/data folder; OUT: where results go.
# Runs (both at most 1024 points per set, batch 32, Adam 1e-3, outlier rate 0.5):
#   paper  the paper's configuration (feature width 128, 12 encoder blocks, 4 classifier blocks), from scratch
#   m64    the shipped configuration (64, 6, 4), fine-tuned from models/gomatch.safetensors
# Training data: the real training scenes plus 4 x 30 synthetic scenes (seeds 0, 2, 3, 4; seed 1 is the
# firmware query's), each file written by its own process; validation: colmap/mouse and colmap/sceaux.
set -euo pipefail
sim=$(realpath "$1"); data=$(realpath "$2"); out=$(realpath -m "$3"); minutes=$4
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$out"
py=${PYTHON:-python3}  # DEVICE=cpu for a try on a machine without a GPU

start=$(date +%s)
"$sim" dataset --output "$work/real.safetensors" \
    --colmap "$data/colmap/wmv_video0" --colmap "$data/colmap/wmv_video3" \
    --bal "$data/bal/problem-49-7776-pre.txt" --bal "$data/bal/problem-21-11315-pre.txt" \
    --bundler "$data/bundler/kermit/bundle.out" >"$work/gen-real.log" &
for seed in 0 2 3 4; do
    "$sim" dataset --output "$work/synthetic-$seed.safetensors" --synthetic 30 --synthetic-seed "$seed" \
        >"$work/gen-$seed.log" &
done
"$sim" dataset --output "$work/val.safetensors" --colmap "$data/colmap/mouse" --colmap "$data/colmap/sceaux" \
    >"$work/gen-val.log" &
wait
head -qn1 "$work"/gen-*.log
echo "data written in $(($(date +%s) - start)) s"

common=(--train "$work"/real.safetensors "$work"/synthetic-*.safetensors --val "$work/val.safetensors"
    --device "${DEVICE:-cuda}" --batched --batch 32 --lr 1e-3 --max-points 1024 --epochs 100 --threads 2
    --max-minutes "$minutes" --ckpt-minutes 2 --log-every 50)
cd "$here"
"$py" -m gomatch_train.train "${common[@]}" --out "$work/paper" \
    --feature-dim 128 --encoder-blocks 12 --classifier-blocks 4 >"$work/paper.log" 2>&1 &
paper=$!
"$py" -m gomatch_train.train "${common[@]}" --out "$work/m64" --init "$repo/models/gomatch.safetensors" \
    --feature-dim 64 --encoder-blocks 6 --classifier-blocks 4 >"$work/m64.log" 2>&1 &
m64=$!
collect() {  # the latest exports, histories and logs of both runs into OUT
    for run in paper m64; do
        cp "$work/$run.log" "$out/$run.log"
        for file in last.safetensors best.safetensors history.jsonl; do
            if [ -f "$work/$run/$file" ]; then cp "$work/$run/$file" "$out/$run-$file"; fi
        done
    done
}
while kill -0 $paper 2>/dev/null || kill -0 $m64 2>/dev/null; do
    sleep 20
    collect
done
status=0
wait $paper || status=$?
wait $m64 || status=$?
collect
for run in paper m64; do
    echo "== $run"; grep -E "model|validation|stopping|Error|error" "$work/$run.log" | tail -n 12
    tail -n 2 "$work/$run.log"
done
exit $status
