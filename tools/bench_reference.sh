#!/usr/bin/env bash
# Speed against the reference in one run (issue #20's figure): the official PyTorch GoMatch forward
# (`../shared/reference/gomatch_ref.py bench`, one thread) and ours on the same machine, one size after the
# other, as a ratio (absolute times move 2x between machines of one kind; ratios measured together do not).
#
#   GOMATCH_SRC=path/to/gomatch tools/bench_reference.sh [OUT.json]   (default target/bench-reference.json)
#
# GOMATCH_SRC: a checkout of the public dvl-tum/gomatch repository (commit 3cd031d), which is not part of this
# repository. Python: the trainer's virtualenv (tools/train/setup_venv.sh) plus scipy, which the reference
# imports (installed into that virtualenv from tools/train/requirements-reference.txt on first use).
# Ours: `workload time N WEIGHTS RUNS` (host-sim/examples/workload.rs): one query-view pair of N points,
# the reference fixture's weights, int8 weights (residual blocks folded, the converter's default) with an
# f16 cost (the device configuration), f32 weights with an f32 cost, and int8 with the reference's unfolded
# blocks (`gomatch-tools convert --fold-blocks=false`).
# SIZES (default "256 1024"), REF_RUNS (default 5) and RUNS (default 9) set the work.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-target/bench-reference.json}
sizes=${SIZES:-256 1024}
if [ -z "${GOMATCH_SRC:-}" ] || [ ! -d "$GOMATCH_SRC/gomatch/models" ]; then
  echo "set GOMATCH_SRC to a checkout of https://github.com/dvl-tum/gomatch (commit 3cd031d)" >&2
  exit 2
fi
reference=../shared/reference/gomatch_ref.py
[ -f "$reference" ] || { echo "$reference not found (../shared beside the checkout)" >&2; exit 2; }
venv="$(tools/train/setup_venv.sh)"
if ! "$venv/bin/python" -c "import scipy" 2>/dev/null; then
  "$venv/bin/pip" install -q -r tools/train/requirements-reference.txt
fi
cargo build --release -q -p gomatch-sim --example workload
workload=target/release/examples/workload
mkdir -p "$(dirname "$out")"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

for n in $sizes; do
  echo "== N = $n: reference (1 thread, ${REF_RUNS:-5} runs)"
  GOMATCH_SRC=$GOMATCH_SRC "$venv/bin/python" "$reference" bench --sizes "$n" --threads 1 \
    --runs "${REF_RUNS:-5}" --stage-runs 0 --json "$work/ref-$n.json" >"$work/ref-$n.log"
  for precision in int8 f32 int8-unfolded; do
    echo "== N = $n: ours, $precision (${RUNS:-9} runs)"
    "$workload" time "$n" "$precision" "${RUNS:-9}" | sed -n 's/^RESULT //p' >"$work/ours-$n-$precision.json"
  done
done

"$venv/bin/python" - "$work" "$out" $sizes <<'EOF'
import json, sys
work, out, sizes = sys.argv[1], sys.argv[2], [int(n) for n in sys.argv[3:]]
rows = []
for n in sizes:
    ref = json.load(open(f"{work}/ref-{n}.json"))
    row = {"n": n, "reference_ms": ref["results"][0]["median_ms"], "reference": ref["versions"],
           "machine": ref["machine"]}
    for precision in ("int8", "f32", "int8-unfolded"):
        ours = json.load(open(f"{work}/ours-{n}-{precision}.json"))
        key = precision.replace("-", "_")
        row[f"ours_{key}_ms"] = ours["median_ms"]
        row[f"ratio_{key}"] = row["reference_ms"] / ours["median_ms"]
    rows.append(row)
print("| N | reference (ms) | ours, int8 weights + f16 cost (ms) | ratio | ours, f32 (ms) | ratio "
      "| ours, int8 with unfolded blocks (ms) | ratio |")
print("|---|---|---|---|---|---|---|---|")
for r in rows:
    print(f"| {r['n']} | {r['reference_ms']:.1f} | {r['ours_int8_ms']:.1f} | {r['ratio_int8']:.1f}x "
          f"| {r['ours_f32_ms']:.1f} | {r['ratio_f32']:.1f}x "
          f"| {r['ours_int8_unfolded_ms']:.1f} | {r['ratio_int8_unfolded']:.1f}x |")
json.dump({"what": "median forward time of one query-view pair of N points, one thread, reference and ours "
                   "measured one after the other in one run (tools/bench_reference.sh)", "results": rows},
          open(out, "w"), indent=1)
print(f"written {out}")
EOF
