#!/usr/bin/env bash
# Fuzz smoke: builds every target of fuzz/ with libFuzzer's instrumentation and runs each for
# FUZZ_SECONDS (default 40) from its committed seeds and regressions, with a memory limit per
# allocation and in total, so a crash, a timeout or an over-reservation fails.
#
# Toolchain: nightly when installed, else stable with RUSTC_BOOTSTRAP=1; if neither builds the
# targets, the smoke is skipped with a message. The build uses the flags `cargo fuzz build -O -s
# none` passes (cargo-fuzz itself is not needed; with it: `cd fuzz && cargo +nightly fuzz run
# <target> -s none -O`). New corpus entries go to fuzz/target/smoke-corpus (ignored).
set -euo pipefail
cd "$(dirname "$0")"
seconds=${FUZZ_SECONDS:-40}
host=$(rustc -vV | sed -n 's/^host: //p')
rustflags="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 \
-Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table \
-Cllvm-args=-sanitizer-coverage-trace-compares --cfg fuzzing"

build() {
  RUSTFLAGS="$rustflags" "$@" build --release --target "$host" --bins
}
if rustup toolchain list 2>/dev/null | grep -q '^nightly' && build cargo +nightly; then
  echo "fuzz smoke: built with nightly"
elif RUSTC_BOOTSTRAP=1 build cargo; then
  echo "fuzz smoke: built with stable and RUSTC_BOOTSTRAP=1"
else
  echo "SKIPPED: fuzz smoke: neither a nightly toolchain nor stable with RUSTC_BOOTSTRAP=1 builds the libFuzzer targets"
  exit 0
fi

targets=$(sed -n 's/^name = "\(.*\)"$/\1/p' Cargo.toml | grep -v '^gomatch-fuzz$')
for target in $targets; do
  corpus=target/smoke-corpus/$target
  mkdir -p "$corpus" "target/artifacts/$target"
  inputs=("seeds/$target")
  [ -d "regressions/$target" ] && inputs+=("regressions/$target")
  echo "== fuzz smoke: $target, $seconds s"
  log=target/smoke-$target.log
  set +e
  "target/$host/release/$target" "$corpus" "${inputs[@]}" \
    -max_total_time="$seconds" -timeout=20 -max_len=16384 \
    -malloc_limit_mb=512 -rss_limit_mb=2048 \
    -artifact_prefix="target/artifacts/$target/" -print_final_stats=1 >"$log" 2>&1
  status=$?
  set -e
  grep -E '^stat::(number_of_executed_units|peak_rss_mb)' "$log" || true
  if [ "$status" != 0 ]; then
    tail -n 40 "$log" >&2
    echo "fuzz smoke: $target failed (exit $status); the input is in fuzz/target/artifacts/$target/" >&2
    exit 1
  fi
done
echo "fuzz smoke: all targets ran $seconds s without a crash, timeout or out-of-memory"
