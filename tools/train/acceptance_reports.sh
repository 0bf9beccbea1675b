#!/usr/bin/env bash
# Evaluation reports for fitting the acceptance rule (docs/evaluation.md, "Acceptance rule"): runs
# `gomatch-sim eval --k 10 --seed 0` with the shipped int8 model on every training scene of ../shared/data
# that has real outlier keypoints (COLMAP and OpenSfM; the validation scenes are never used) and writes
# OUT_DIR/<name>.json (default models/acceptance/1024/train), prints the acceptance figures of the rule the
# reports were written with (tools/train/acceptance_table.py), then fits a rule on them, leaving out the
# scenes whose reference poses are unreliable (EXCLUDE), checks it on the validation reports of
# tools/train/eval_all.sh (models/eval-all/*-int8.json) and writes it to RULE (default
# OUT_DIR/../rule.json, the fit's log beside it as rule.txt; tools/train/refit_acceptance.sh runs this per capacity
# and writes the rules into the core):
#
#   tools/train/acceptance_reports.sh [OUT_DIR]
#
# Environment: FRESH=1 also writes OUT_DIR/<name>-fresh.json (`eval --fresh-keypoints`: the query keypoints made
# to look like a new detector run on the photo) and fits on both, QUERIES per scene (default 50: the threshold
# rests on the few wrong training poses, which 25 a scene left to a handful; docs/acceptance.md), THREADS
# (default 1), MODEL (default models/gomatch-int8.bin),
# BIN (a gomatch-sim binary to use instead of building target/release/gomatch-sim), CAPACITY (the localizer's
# keypoints per query and points per view, default 1024), CHECK (the validation reports the fitted rule is
# checked on, default models/eval-all/*-int8.json), EXCLUDE (an extended regular expression of report names
# left out of the fit, default the sub-models of one video whose per-frame focal lengths the data README
# calls unreliable: "pratikk_|wmv_video"; empty keeps all) and FIT_ARGS (more fit-acceptance flags, e.g.
# "--max-wrong 0.005"). A scene whose report exists is kept (delete it to re-run), so an interrupted run
# resumes.
set -euo pipefail
repo=$(cd "$(dirname "$0")/../.." && pwd)
out=${1:-$repo/models/acceptance/1024/train}
queries=${QUERIES:-50}
threads=${THREADS:-1}
model=${MODEL:-$repo/models/gomatch-int8.bin}
data="$repo/../shared/data"
[ -d "$data" ] || { echo "no ../shared/data beside the checkout" >&2; exit 1; }
validation="colmap/mouse colmap/sceaux colmap/mamechun colmap/softmurata opensfm/projcv_cc9d27"
bin=${BIN:-}
if [ -z "$bin" ]; then
  cargo build --release -q -p gomatch-sim --manifest-path "$repo/Cargo.toml"
  bin="$repo/target/release/gomatch-sim"
fi
mkdir -p "$out"
for dir in "$data"/colmap/* "$data"/opensfm/*; do
  kind=$(basename "$(dirname "$dir")")
  name=$(basename "$dir")
  case " $validation " in *" $kind/$name "*) continue ;; esac
  variants=("")
  [ "${FRESH:-0}" = 1 ] && variants+=("-fresh")
  for variant in "${variants[@]}"; do
    report="$out/$name$variant.json"
    [ -s "$report" ] && continue
    flags=()
    [ -n "$variant" ] && flags=(--fresh-keypoints)
    "$bin" eval --"$kind" "$dir" --model "$model" --k 10 --capacity "${CAPACITY:-1024}" --queries "$queries" \
      --seed 0 --threads "$threads" "${flags[@]}" --json "$report" >"${report%.json}.log" 2>&1 ||
      echo "eval failed on $kind/$name$variant (see ${report%.json}.log)"
  done
done
python3 "$repo/tools/train/acceptance_table.py" "$out"/*.json
rule=${RULE:-$(dirname "$out")/rule.json}
exclude=${EXCLUDE-pratikk_|wmv_video}
mapfile -t reports < <(ls "$out"/*.json | grep -v -E "${exclude:-^$}")
# shellcheck disable=SC2086 # CHECK is a glob, FIT_ARGS a list of flags
"$bin" fit-acceptance --reports "${reports[@]}" --check ${CHECK:-"$repo"/models/eval-all/*-int8.json} \
  ${FIT_ARGS:-} --out "$rule" | tee "${rule%.json}.txt"
