#!/usr/bin/env bash
# Refits the acceptance rule at every capacity the project ships (128, 256, 1024) for the shipped int8 model, in
# one command: per capacity N, the validation reports (`gomatch-sim eval` on the five validation scenes, every
# query, k = 10, seed 0, with the reconstruction's keypoints and with --fresh-keypoints: <scene>-fresh.json) in
# models/acceptance/N/validation, the training reports (both kinds, FRESH=1) and the fit
# (tools/train/acceptance_reports.sh, checked on those validation reports) in models/acceptance/N/{train,rule.json,
# rule.txt}; then tools/train/render_acceptance.py writes the rules into the core
# (core/src/acceptance/fitted.rs) and the operating points into docs/evaluation.md.
#
#   tools/train/refit_acceptance.sh
#
# Reports of a capacity are reused while models/acceptance/N/model.sha256 names the current model blob and
# deleted (re-run) when it does not, so run this after every model change and commit models/acceptance and the
# two generated files; REFRESH=1 re-runs them all (after a change of the localizer's code, e.g. guided
# re-matching). Environment: CAPACITIES (default "128 256 1024"), MAX_WRONG (per capacity the share of wrong poses
# the threshold allows among the accepted training poses, default "128:0.005 256:0.0075 1024:0.01": smaller
# capacities keep a margin for the unseen scenes, docs/acceptance.md), FIT_ARGS (fit-acceptance flags, default
# "--max-wrong" with that share), MODEL, THREADS and QUERIES (training queries per scene, default 50) as in
# acceptance_reports.sh, VAL_QUERIES (default 500: every query the protocol offers).
set -euo pipefail
repo=$(cd "$(dirname "$0")/../.." && pwd)
model=${MODEL:-$repo/models/gomatch-int8.bin}
data="$repo/../shared/data"
[ -d "$data" ] || { echo "no ../shared/data beside the checkout" >&2; exit 1; }
cargo build --release -q -p gomatch-sim --manifest-path "$repo/Cargo.toml"
bin="$repo/target/release/gomatch-sim"
digest=$(sha256sum "$model" | cut -d' ' -f1)
# The share of MAX_WRONG for capacity $1.
max_wrong() {
  for entry in ${MAX_WRONG:-128:0.005 256:0.0075 1024:0.01}; do
    [ "${entry%%:*}" = "$1" ] && { echo "${entry#*:}"; return; }
  done
  echo "no share for capacity $1 in MAX_WRONG" >&2
  exit 1
}
for n in ${CAPACITIES:-128 256 1024}; do
  share=$(max_wrong "$n")
  dir="$repo/models/acceptance/$n"
  if [ -n "${REFRESH:-}" ] || [ "$(cat "$dir/model.sha256" 2>/dev/null)" != "$digest" ]; then
    rm -rf "$dir/train" "$dir/validation"
  fi
  mkdir -p "$dir/validation"
  echo "$digest" >"$dir/model.sha256"
  for scene in colmap/mouse colmap/sceaux colmap/mamechun colmap/softmurata opensfm/projcv_cc9d27; do
    name=${scene#*/}
    for variant in "" -fresh; do
      report="$dir/validation/$name$variant.json"
      [ -s "$report" ] && continue
      flags=()
      [ -n "$variant" ] && flags=(--fresh-keypoints)
      "$bin" eval --"${scene%%/*}" "$data/$scene" --model "$model" --k 10 --capacity "$n" \
        --queries "${VAL_QUERIES:-500}" --seed 0 --threads "${THREADS:-$(nproc)}" "${flags[@]}" \
        --json "$report" >/dev/null
    done
  done
  FRESH=1 BIN="$bin" MODEL="$model" CAPACITY="$n" CHECK="$dir/validation/*.json" RULE="$dir/rule.json" \
    FIT_ARGS="--capacity $n ${FIT_ARGS:---max-wrong $share}" THREADS="${THREADS:-$(nproc)}" \
    "$repo/tools/train/acceptance_reports.sh" "$dir/train"
done
python3 "$repo/tools/train/render_acceptance.py"
rustfmt --edition 2021 "$repo/core/src/acceptance/fitted.rs"  # the generated constants as cargo fmt lays them out
