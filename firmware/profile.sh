#!/usr/bin/env bash
# Instruction-count profile of the Cortex-M7 firmware query (a development tool, not run by
# CI): builds the image with the `pc-profile` feature and debug info, runs it under QEMU with
# -icount shift=0 (SysTick samples the PC every 100,000 instructions) and prints where the
# instructions go, by the innermost function of the core's own code and by pipeline stage,
# with llvm-symbolizer (Debian package `llvm`). The same variables as qemu.sh apply
# (GOMATCH_FIRMWARE_VIEW_FEATURES for the view-features image).
#
#   bash firmware/profile.sh [TOP]
set -euo pipefail
cd "$(dirname "$0")"
repo=$(cd .. && pwd)
top=${1:-25}
target=thumbv7em-none-eabihf
export CARGO_TARGET_DIR="$PWD/target/profile"
CARGO_PROFILE_RELEASE_DEBUG=true GOMATCH_FIRMWARE_MODEL="$repo/models/gomatch-int8.bin" \
  cargo build --release --target "$target" --features pc-profile
image="$CARGO_TARGET_DIR/$target/release/gomatch-firmware"
log="$CARGO_TARGET_DIR/profile.log"
timeout "${QEMU_TIMEOUT:-1200}" qemu-system-arm -M mps2-an500 -semihosting-config enable=on,target=native \
  -icount shift=0 -nographic -monitor none -serial none -kernel "$image" >"$log" 2>&1 || {
  tail -5 "$log"
  echo "the profiled image did not exit 0" >&2
  exit 1
}
grep -E "^instructions|^pc-samples" "$log"
sed -n 's/^pc //p' "$log" | python3 "$PWD/profile_report.py" "$image" "$top"
