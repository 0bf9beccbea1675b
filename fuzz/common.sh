# Shared by fuzz/smoke.sh and fuzz/campaign.sh (sourced from fuzz/): builds every target with
# libFuzzer's instrumentation, the flags `cargo fuzz build -O -s none` passes, and runs one.
# Toolchain: nightly when installed, else stable with RUSTC_BOOTSTRAP=1; `build_targets` fails
# when neither builds them.
host=$(rustc -vV | sed -n 's/^host: //p')
rustflags="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 \
-Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table \
-Cllvm-args=-sanitizer-coverage-trace-compares --cfg fuzzing"
targets=$(sed -n 's/^name = "\(.*\)"$/\1/p' Cargo.toml | grep -v '^gomatch-fuzz$')

build_with() {
  RUSTFLAGS="$rustflags" "$@" build --release --target "$host" --bins
}

build_targets() {
  if rustup toolchain list 2>/dev/null | grep -q '^nightly' && build_with cargo +nightly; then
    echo "fuzz: built with nightly"
  elif RUSTC_BOOTSTRAP=1 build_with cargo; then
    echo "fuzz: built with stable and RUSTC_BOOTSTRAP=1"
  else
    return 1
  fi
}

# max_len TARGET: the longest input libFuzzer makes for TARGET. 16 KiB, except device_link:
# 1 KiB, about three of the longest request frames at its capacity 16 (link::rx_frame_len),
# enough for an overlong frame and several requests; longer inputs only carried more valid
# localization frames, each a full localization (the rate fell from ~1,050 to ~450 per second).
max_len() {
  case $1 in
    device_link) echo 1024 ;;
    *) echo 16384 ;;
  esac
}

# run_target TARGET SECONDS CORPUS LOG: fuzzes TARGET for SECONDS into CORPUS, starting from
# its seeds and regressions, with a 20 s timeout and memory limits per allocation and in
# total; prints libFuzzer's final stats and returns its exit status.
run_target() {
  local target=$1 seconds=$2 corpus=$3 log=$4 status
  mkdir -p "$corpus" "target/artifacts/$target"
  local inputs=("seeds/$target")
  [ -d "regressions/$target" ] && inputs+=("regressions/$target")
  set +e
  "target/$host/release/$target" "$corpus" "${inputs[@]}" \
    -max_total_time="$seconds" -timeout=20 -max_len="$(max_len "$target")" \
    -malloc_limit_mb=512 -rss_limit_mb=2048 \
    -artifact_prefix="target/artifacts/$target/" -print_final_stats=1 >"$log" 2>&1
  status=$?
  set -e
  grep -E '^stat::(number_of_executed_units|peak_rss_mb)' "$log" || true
  if [ "$status" != 0 ]; then
    tail -n 40 "$log" >&2
    echo "fuzz: $target failed (exit $status); the input is in fuzz/target/artifacts/$target/" >&2
  fi
  return "$status"
}
