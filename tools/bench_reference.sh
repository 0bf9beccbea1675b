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
# SIZES (default "256 1024"), ROUNDS (default 3), REF_RUNS (default 5) and RUNS (default 9) set the work.
# Each round times the reference and then ours at each size, so that a machine whose load drifts (other
# tenants: the same binary's time moved 1.5x from minute to minute here) weighs on both sides of a
# round's ratio alike. Reported per size and weights: each round's ratio of medians, the median of those
# ratios, and the ratio of the fastest runs over all rounds (min over min: the least disturbed runs of
# each side).
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

rounds=${ROUNDS:-3}
for round in $(seq "$rounds"); do
  for n in $sizes; do
    echo "== round $round, N = $n: reference (1 thread, ${REF_RUNS:-5} runs)"
    GOMATCH_SRC=$GOMATCH_SRC "$venv/bin/python" "$reference" bench --sizes "$n" --threads 1 \
      --runs "${REF_RUNS:-5}" --stage-runs 0 --json "$work/ref-$n-$round.json" >"$work/ref-$n-$round.log"
    for precision in int8 f32 int8-unfolded; do
      echo "== round $round, N = $n: ours, $precision (${RUNS:-9} runs)"
      "$workload" time "$n" "$precision" "${RUNS:-9}" | sed -n 's/^RESULT //p' \
        >"$work/ours-$n-$precision-$round.json"
    done
  done
done

"$venv/bin/python" - "$work" "$out" "$rounds" $sizes <<'EOF'
import json, statistics, sys
work, out, rounds, sizes = sys.argv[1], sys.argv[2], int(sys.argv[3]), [int(n) for n in sys.argv[4:]]
precisions = ("int8", "f32", "int8-unfolded")
rows = []
for n in sizes:
    refs = [json.load(open(f"{work}/ref-{n}-{r}.json")) for r in range(1, rounds + 1)]
    ref_ms = [ref["results"][0]["median_ms"] for ref in refs]
    ref_min = min(ref["results"][0]["min_ms"] for ref in refs)
    row = {"n": n, "rounds": rounds, "reference_ms": statistics.median(ref_ms), "reference_round_ms": ref_ms,
           "reference_min_ms": ref_min, "reference": refs[0]["versions"], "machine": refs[0]["machine"]}
    for precision in precisions:
        ours = [json.load(open(f"{work}/ours-{n}-{precision}-{r}.json")) for r in range(1, rounds + 1)]
        key = precision.replace("-", "_")
        ms = [o["median_ms"] for o in ours]
        ratios = [ref / mine for ref, mine in zip(ref_ms, ms)]
        row[f"ours_{key}_ms"] = statistics.median(ms)
        row[f"ours_{key}_round_ms"] = ms
        row[f"ratio_{key}_rounds"] = ratios
        row[f"ratio_{key}"] = statistics.median(ratios)
        row[f"ours_{key}_min_ms"] = min(o["min_ms"] for o in ours)
        row[f"ratio_{key}_min"] = ref_min / row[f"ours_{key}_min_ms"]
    rows.append(row)
print("Median of the rounds' ratios (each round: reference median / ours median), each round's ratio, and the "
      "ratio of the fastest runs (min / min).")
print("| N | reference (ms) | int8 weights + f16 cost (ms) | ratio | rounds | min/min "
      "| f32 (ms) | ratio | rounds | min/min | int8, unfolded blocks (ms) | ratio | rounds | min/min |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for r in rows:
    cells = [f"{r['n']}", f"{r['reference_ms']:.1f}"]
    for precision in precisions:
        key = precision.replace("-", "_")
        cells += [f"{r[f'ours_{key}_ms']:.1f}", f"{r[f'ratio_{key}']:.1f}x",
                  " / ".join(f"{x:.1f}" for x in r[f"ratio_{key}_rounds"]), f"{r[f'ratio_{key}_min']:.1f}x"]
    print("| " + " | ".join(cells) + " |")
json.dump({"what": "forward time of one query-view pair of N points, one thread; per round the reference and "
                   "then ours, median over runs; ratio = median over rounds of the rounds' ratios, ratio_*_min = "
                   "fastest reference run / fastest run of ours (tools/bench_reference.sh)", "results": rows},
          open(out, "w"), indent=1)
print(f"written {out}")
EOF
