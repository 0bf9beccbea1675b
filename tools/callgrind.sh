#!/usr/bin/env bash
# Instruction counts of the matcher and the localizer, per stage, with valgrind's callgrind
# (noise-free: the same build counts the same instructions whatever the machine's load).
#
#   tools/callgrind.sh [OUT_DIR [RUN...]]   (default target/callgrind, every run)
#
# RUN: match-N-WEIGHTS (N 256 or 1024, WEIGHTS int8, f32 or int8-unfolded: the reference's residual
# blocks, `gomatch-tools convert --fold-blocks=false`), localize-1024-int8 or
# localize-1024-int8-features (the same localization with the map's view features).
# Runs `cargo run --example workload` under callgrind for one match at N = 256 and 1024
# (reference fixture weights; int8 weights with an f16 cost, and f32 weights with an f32
# cost) and one full k = 10 localization of a colmap/mouse query at N = 1024 (shipped int8
# model, f16 cost), counting only the network and localizer calls (preparation excluded),
# and prints per run the total and each stage's inclusive count (`callgrind_annotate
# --inclusive=yes`). Needs valgrind and ../shared (reference fixtures, data/colmap/mouse).
# WORKLOAD=path runs a prebuilt `workload` binary instead (to compare two builds).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-target/callgrind}
shift || true
runs=("$@")
if [ ${#runs[@]} -eq 0 ]; then
  runs=(match-256-int8 match-256-f32 match-1024-int8 match-1024-f32 localize-1024-int8 localize-1024-int8-features)
fi
mkdir -p "$out"
bin=${WORKLOAD:-target/release/examples/workload}
if [ -z "${WORKLOAD:-}" ]; then
  cargo build --release -q -p gomatch-sim --example workload
fi

# Stage functions (inclusive counts), in forward order.
stages=(
  "gomatch::encoder::encode"
  "gomatch::attention::self_layer"
  "gomatch::attention::cross_layer"
  "gomatch::sinkhorn::cost_matrix"
  "gomatch::sinkhorn::sinkhorn"
  "gomatch::sinkhorn::mutual_assignment"
  "gomatch::classifier::classify"
  "gomatch::ransac::estimate_pose"
)

# count NAME TOGGLE WORKLOAD_ARGS...: callgrind counting only inside functions matching TOGGLE
# (a pattern list separated by '|').
count() {
  local name=$1 toggle=$2
  shift 2
  local toggles=()
  IFS='|' read -ra patterns <<<"$toggle"
  for p in "${patterns[@]}"; do toggles+=("--toggle-collect=$p"); done
  valgrind --tool=callgrind --callgrind-out-file="$out/$name.out" "${toggles[@]}" \
    "$bin" "$@" >"$out/$name.log" 2>&1 || {
    cat "$out/$name.log"
    exit 1
  }
  callgrind_annotate --inclusive=yes --threshold=100 "$out/$name.out" >"$out/$name.txt" 2>/dev/null
  local total
  total=$(grep -m1 'PROGRAM TOTALS' "$out/$name.txt" | awk '{print $1}')
  echo "$name: total $total instructions ($(grep -v '^==' "$out/$name.log" | tail -1))"
  local stage line
  for stage in "${stages[@]}"; do
    # The function's largest entry (callgrind_annotate lists a function once per source
    # file its debug info names, sorted by count; the largest is its inclusive count).
    line=$(grep -F ":$stage" "$out/$name.txt" | grep -v -F '{closure' | head -1 || true)
    if [ -n "$line" ]; then awk -v s="$stage" '{printf "  %-40s %15s\n", s, $1}' <<<"$line"; fi
  done
}

for run in "${runs[@]}"; do
  case $run in
  match-*-*)
    IFS=- read -r _ n precision <<<"$run"
    count "$run" '*workload::run_match' match "$n" "$precision"
    ;;
  localize-1024-int8) count "$run" '*Localizer*::localize' localize ;;
  localize-1024-int8-features) count "$run" '*Localizer*::localize' localize features ;;
  *) echo "unknown run $run" >&2 && exit 2 ;;
  esac
done
