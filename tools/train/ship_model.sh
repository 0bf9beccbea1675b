#!/usr/bin/env bash
# Ships a trained checkpoint into models/ and measures it the way the model card reports it.
#
#   tools/train/ship_model.sh RUN/last.safetensors [QUERIES]
#   SEEDS="1 2 3" (default): further protocol seeds evaluated beside seed 0 (RANSAC's sampling and, on
#   scenes with more queries than asked for, the query draw change with the seed; their mean is
#   steadier than one seed on 56 queries)
#
# 1. copies the f32 export to models/gomatch.safetensors;
# 2. converts it with `gomatch-tools convert` to models/gomatch-{f32,f16,int8}.bin;
# 3. refits the acceptance rules for the new int8 blob (tools/train/refit_acceptance.sh: every capacity, the rules
#    into core/src/acceptance/fitted.rs) and rebuilds, so every report below is made with the new blob's rules;
# 4. runs `gomatch-sim eval --k 10` (the paper's protocol, Sinkhorn cost in f16 as on the
#    device) on mouse and sceaux for each precision, writing
#    models/eval/<scene>-<precision>.json and .png (QUERIES: queries per scene, default all),
#    and with each seed S of SEEDS models/eval/<scene>-<precision>-seed<S>.json;
# 5. writes models/SHA256SUMS, the firmware replies (firmware/data/reply.hex, reply-1024.hex) and prints the model
#    card's tables (tools/train/eval_table.py).
# Then the validation tables (tools/train/eval_all.sh into models/eval-all and models/eval-small/nN-kK,
# docs/embedded.md) and the firmware images' instruction counts (firmware/qemu.sh).
set -euo pipefail
checkpoint=$(realpath "$1")
queries=${2:-500}
seeds=${SEEDS-1 2 3}
repo=$(cd "$(dirname "$0")/../.." && pwd)
cd "$repo"
data="$repo/../shared/data"
[ -d "$data" ] || { echo "no ../shared/data beside the checkout" >&2; exit 1; }

cargo build --release -q -p gomatch-sim -p gomatch-tools
bin="$repo/target/release"
mkdir -p models/eval
[ "$checkpoint" -ef models/gomatch.safetensors ] || cp "$checkpoint" models/gomatch.safetensors
for p in f32 f16 int8; do
  "$bin/gomatch-tools" convert --input models/gomatch.safetensors --precision "$p" \
    --output "models/gomatch-$p.bin"
done
tools/train/refit_acceptance.sh
cargo build --release -q -p gomatch-sim
threads=$(nproc)
for scene in mouse sceaux; do
  for p in f32 f16 int8; do
    "$bin/gomatch-sim" eval --colmap "$data/colmap/$scene" --k 10 --queries "$queries" \
      --model "models/gomatch-$p.bin" --threads "$threads" \
      --json "models/eval/$scene-$p.json" --plot "models/eval/$scene-$p.png"
    for seed in $seeds; do
      "$bin/gomatch-sim" eval --colmap "$data/colmap/$scene" --k 10 --queries "$queries" \
        --model "models/gomatch-$p.bin" --threads "$threads" --seed "$seed" \
        --json "models/eval/$scene-$p-seed$seed.json"
    done
  done
done
(cd models && sha256sum gomatch.safetensors gomatch-f32.bin gomatch-f16.bin gomatch-int8.bin > SHA256SUMS)
"$bin/gomatch-sim" firmware-reply --out firmware/data/reply.hex >/dev/null
"$bin/gomatch-sim" firmware-reply --capacity 1024 --out firmware/data/reply-1024.hex >/dev/null
python3 tools/train/eval_table.py models/eval
