#!/usr/bin/env bash
# Builds the firmware image for an ARM board and runs it under QEMU with instruction counting.
#
#   bash firmware/qemu.sh cortex-m7   # thumbv7em-none-eabihf, qemu-system-arm -M mps2-an500
#   bash firmware/qemu.sh aarch64     # aarch64-unknown-none, qemu-system-aarch64 -M virt -cpu cortex-a53
#
# The image (same data and grading as build.sh's x86_64 one) prints its instruction counts over
# semihosting (exact under -icount shift=0: one instruction per virtual nanosecond) and exits
# with its status through semihosting; this script requires 0 (pose right). Needs the shipped
# models/gomatch-int8.bin; QEMU_TIMEOUT (seconds, default 1200) bounds the run. With
# GOMATCH_FIRMWARE_MAX_INSTRUCTIONS set, a query counting more instructions fails the script
# (a deterministic budget under -icount, not a timing).
set -euo pipefail
cd "$(dirname "$0")"
repo=$(cd .. && pwd)
board=${1:?usage: qemu.sh cortex-m7|aarch64}

model="${GOMATCH_FIRMWARE_MODEL:-$repo/models/gomatch-int8.bin}"
if [ ! -f "$model" ]; then
  echo "SKIPPED: no shipped model $model to embed"
  exit 0
fi

semihosting=(-semihosting-config enable=on,target=native -icount shift=0 -nographic -monitor none -serial none)
case "$board" in
  cortex-m7)
    target=thumbv7em-none-eabihf
    qemu=(qemu-system-arm -M mps2-an500)
    ;;
  aarch64)
    target=aarch64-unknown-none
    qemu=(qemu-system-aarch64 -M virt -cpu cortex-a53 -nic none)
    ;;
  *)
    echo "unknown board $board (cortex-m7 or aarch64)" >&2
    exit 1
    ;;
esac

GOMATCH_FIRMWARE_MODEL="$model" cargo build --release --target "$target"
image="target/$target/release/gomatch-firmware"
ls -l "$image"

set +e
start=$(date +%s)
# The output (semihosting writes to QEMU's stderr) is kept in target/<board>.log for firmware/cross_isa.sh.
timeout "${QEMU_TIMEOUT:-1200}" "${qemu[@]}" "${semihosting[@]}" -kernel "$image" 2>&1 | tee "target/$board.log"
status=${PIPESTATUS[0]}
set -e
echo "$board image exited with status $status after $(( $(date +%s) - start )) s of QEMU wall time"
if [ "$status" != 0 ]; then
  echo "$board image: expected status 0 (pose right)" >&2
  exit 1
fi
if [ -n "${GOMATCH_FIRMWARE_MAX_INSTRUCTIONS:-}" ]; then
  count=$(sed -n 's/^instructions, whole query: \([0-9]*\).*/\1/p' "target/$board.log")
  if [ -z "$count" ] || [ "$count" -gt "$GOMATCH_FIRMWARE_MAX_INSTRUCTIONS" ]; then
    echo "$board image: ${count:-no} instructions per query, over the budget of $GOMATCH_FIRMWARE_MAX_INSTRUCTIONS" >&2
    exit 1
  fi
  echo "$board image: $count instructions per query, within the budget of $GOMATCH_FIRMWARE_MAX_INSTRUCTIONS"
fi
