#!/usr/bin/env bash
# Fuzz campaign: runs each named target (default: all) for SECONDS on the long-lived corpus
# fuzz/corpus/<target> (ignored by git, cargo-fuzz's place for it) and appends one line per run
# to fuzz/ledger.tsv: date, commit, target, seconds (wall), executions, peak RSS (MB), "ok" and
# the number of processes, JOBS (a failing run stops the campaign and is not recorded; its input is in
# fuzz/target/artifacts/<target>/). `fuzz/campaign.sh --totals` sums the ledger per target (a
# markdown table).
#
#   bash fuzz/campaign.sh 600 device_link localize
#   JOBS=2 bash fuzz/campaign.sh 600 localize    # two processes on one corpus, one ledger line
set -euo pipefail
cd "$(dirname "$0")"
source ./common.sh
ledger=ledger.tsv
if [ "${1:-}" = --totals ]; then
  echo "| target | runs | seconds | executions |"
  echo "|---|---|---|---|"
  awk -F'\t' 'NR > 1 { runs[$3]++; execs[$3] += $5; secs[$3] += $4 }
    END { for (t in execs) printf "| `%s` | %d | %d | %d |\n", t, runs[t], secs[t], execs[t] }' "$ledger" | sort
  exit 0
fi
seconds=${1:?usage: fuzz/campaign.sh SECONDS [TARGET...] | --totals}
shift
[ "$#" -gt 0 ] && targets="$*"
build_targets
commit=$(git rev-parse --short HEAD)
[ -n "$(git status --porcelain -- . ':!ledger.tsv' ../core ../host-sim ../tools)" ] && commit="$commit+changes"
[ -f "$ledger" ] || printf 'date\tcommit\ttarget\tseconds\texecutions\tpeak_rss_mb\tresult\tjobs\n' >"$ledger"
jobs=${JOBS:-1}
for target in $targets; do
  echo "== fuzz campaign: $target, $seconds s, $jobs process(es)"
  pids=()
  for job in $(seq "$jobs"); do
    run_target "$target" "$seconds" "corpus/$target" "target/campaign-$target-$job.log" &
    pids+=("$!")
  done
  for pid in "${pids[@]}"; do wait "$pid"; done
  logs=$(seq -f "target/campaign-$target-%g.log" "$jobs")
  # shellcheck disable=SC2086 # one word per log
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' $logs | awk '{ s += $1 } END { print s }')
  # shellcheck disable=SC2086
  rss=$(sed -n 's/^stat::peak_rss_mb: *//p' $logs | sort -n | tail -n 1)
  printf '%s\t%s\t%s\t%s\t%s\t%s\tok\t%s\n' "$(date -u +%FT%TZ)" "$commit" "$target" "$seconds" \
    "$execs" "$rss" "$jobs" >>"$ledger"
done
