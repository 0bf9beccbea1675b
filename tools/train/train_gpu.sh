#!/usr/bin/env bash
# A short training run on one GPU: writes the training data, then trains one or more models side by side on
# the GPU with --batched, each for MINUTES of wall time, and copies their exports, histories and logs to OUT
# (every 20 s, so a run cut short still leaves its last checkpointed exports).
#
#   tools/train/train_gpu.sh GOMATCH_SIM DATA OUT MINUTES RUN...
#
# GOMATCH_SIM: a built `gomatch-sim`; DATA: the ../shared/data folder; OUT: where results go.
# RUN: NAME:INIT:WIDTH:ENCODER_BLOCKS:CLASSIFIER_BLOCKS[:OPTIONS]; INIT is an export to fine-tune (path relative to
# the repository root) or empty for a new model; OPTIONS, comma-separated, are added to (and override) the trainer
# options below. Example, the paper's configuration from scratch, the shipped one fine-tuned, and the shipped one
# at a tenth of the learning rate:
#   paper::128:12:4 paper3:models/gomatch.safetensors:128:12:4 low:models/gomatch.safetensors:128:12:4:--lr,1e-4
# Every run: at most 1024 points per set, batch 32, Adam 1e-3, outlier rate 0.5. Training data: every real
# training scene of DATA (COLMAP, OpenSfM, BAL, Bundler; REAL_QUERIES queries each, default 100) plus, per
# synthetic seed 0, 2, 3, 4 (seed 1 is the firmware query's), 30 scenes of the four layouts and 30 photo
# collections, each file written by its own process; validation: 20 queries of each validation scene. DEVICE=cpu tries it on a machine without a GPU,
# SYNTHETIC_SCENES=N writes N instead of 30 scenes per synthetic seed (the test's short version).
set -euo pipefail
sim=$(realpath "$1"); data=$(realpath "$2"); out=$(realpath -m "$3"); minutes=$4
shift 4
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$out"
py=${PYTHON:-python3}

start=$(date +%s)
validation=" colmap/mouse colmap/sceaux colmap/mamechun colmap/softmurata opensfm/projcv_cc9d27 "
real=() val=()
for dir in "$data"/colmap/* "$data"/opensfm/*; do
    kind=$(basename "$(dirname "$dir")") name=$(basename "$dir")
    if [[ $validation == *" $kind/$name "* ]]; then val+=(--"$kind" "$dir"); else real+=(--"$kind" "$dir"); fi
done
for file in "$data"/bal/*.txt; do real+=(--bal "$file"); done
for file in "$data"/bundler/*/bundle.out; do real+=(--bundler "$file"); done
"$sim" dataset --output "$work/real.safetensors" "${real[@]}" --queries-per-scene "${REAL_QUERIES:-100}" \
    >"$work/gen-real.log" &
for seed in 0 2 3 4; do
    "$sim" dataset --output "$work/synthetic-$seed.safetensors" --synthetic "${SYNTHETIC_SCENES:-30}" \
        --synthetic-collection "${SYNTHETIC_SCENES:-30}" --synthetic-seed "$seed" >"$work/gen-$seed.log" &
done
"$sim" dataset --output "$work/val.safetensors" "${val[@]}" --queries-per-scene 20 >"$work/gen-val.log" &
wait
head -qn1 "$work"/gen-*.log
echo "data written in $(($(date +%s) - start)) s"

common=(--train "$work"/real.safetensors "$work"/synthetic-*.safetensors --val "$work/val.safetensors"
    --device "${DEVICE:-cuda}" --batched --batch 32 --lr 1e-3 --max-points 1024 --epochs 100 --threads 2
    --max-minutes "$minutes" --ckpt-minutes 2 --log-every 50)
cd "$here"
names=() pids=()
for spec in "$@"; do
    IFS=: read -r name init width encoder classifier extra <<<"$spec"
    options=(--feature-dim "$width" --encoder-blocks "$encoder" --classifier-blocks "$classifier")
    if [ -n "$init" ]; then options+=(--init "$repo/$init"); fi
    if [ -n "$extra" ]; then IFS=, read -r -a extra_options <<<"$extra" && options+=("${extra_options[@]}"); fi
    "$py" -m gomatch_train.train "${common[@]}" --out "$work/$name" "${options[@]}" >"$work/$name.log" 2>&1 &
    names+=("$name") pids+=($!)
done

collect() {  # the latest exports, histories and logs of every run into OUT
    for name in "${names[@]}"; do
        cp "$work/$name.log" "$out/$name.log"
        for file in last.safetensors best.safetensors history.jsonl; do
            if [ -f "$work/$name/$file" ]; then cp "$work/$name/$file" "$out/$name-$file"; fi
        done
    done
}
running() {
    for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && return 0; done
    return 1
}
while running; do
    sleep 20
    collect
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=$?; done
collect
for name in "${names[@]}"; do
    echo "== $name"; grep -E "model|validation|stopping|Error|error" "$work/$name.log" | tail -n 12
    tail -n 2 "$work/$name.log"
done
exit $status
