#!/usr/bin/env bash
# Fuzz smoke: builds every target of fuzz/ and runs each for FUZZ_SECONDS (default 40) from its
# committed seeds and regressions (fuzz/common.sh), so a crash, a timeout or an
# over-reservation fails. Skips with a message when no toolchain builds the targets. New corpus
# entries go to fuzz/target/smoke-corpus (ignored).
set -euo pipefail
cd "$(dirname "$0")"
source ./common.sh
seconds=${FUZZ_SECONDS:-40}
if ! build_targets; then
  echo "SKIPPED: fuzz smoke: neither a nightly toolchain nor stable with RUSTC_BOOTSTRAP=1 builds the libFuzzer targets"
  exit 0
fi
for target in $targets; do
  echo "== fuzz smoke: $target, $seconds s"
  run_target "$target" "$seconds" "target/smoke-corpus/$target" "target/smoke-$target.log"
done
echo "fuzz smoke: all targets ran $seconds s without a crash, timeout or out-of-memory"
