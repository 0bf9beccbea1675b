#!/usr/bin/env bash
# Bit-identical across machines: compares the reply bytes (stage timings cleared) and the digest of
# the merged correspondences (every classifier probability, bit for bit) that the firmware images
# printed on x86_64 (build.sh), Cortex-M7 and AArch64 (qemu.sh), and by the C example on the
# Cortex-M7 (board c-cortex-m7: capi/example/qemu.sh, through the C API), kept in
# firmware/target/<board>.log, with the host's at the board's capacity: firmware/data/reply.hex for the
# capacity-256 images (x86_64, Cortex-M7, C example), firmware/data/reply-1024.hex for AArch64 (each
# capacity applies its own acceptance rule), written by
# `cargo run --release -p gomatch-sim -- firmware-reply --out firmware/data/reply.hex` and
# `... firmware-reply --capacity 1024 --out firmware/data/reply-1024.hex`.
#
#   bash firmware/cross_isa.sh                # after build.sh, both qemu.sh runs and capi/example/qemu.sh
#   bash firmware/cross_isa.sh x86_64         # only the boards named
#
# Fails with a diff when a board's bytes differ from the host's or its log is absent.
set -euo pipefail
cd "$(dirname "$0")"

boards=("$@")
[ ${#boards[@]} -gt 0 ] || boards=(x86_64 cortex-m7 aarch64 c-cortex-m7)

if [ ! -f ../models/gomatch-int8.bin ]; then
  echo "SKIPPED: no shipped model ../models/gomatch-int8.bin (the images were not run)"
  exit 0
fi

hex_digits=$(grep '^reply bytes' data/reply.hex | grep -o '[0-9a-f]*$' | tr -d '\n' | wc -c)
failed=0
for board in "${boards[@]}"; do
  log="target/$board.log"
  if [ ! -f "$log" ]; then
    echo "$board: no log $log (run build.sh for x86_64, qemu.sh $board for an ARM board, capi/example/qemu.sh for c-cortex-m7)" >&2
    failed=1
    continue
  fi
  host=data/reply.hex
  [ "$board" = aarch64 ] && host=data/reply-1024.hex
  if diff -u --label "host ($host)" --label "$board ($log)" \
    "$host" <(grep -E '^(reply bytes|correspondences digest)' "$log"); then
    echo "$board: reply bytes ($((hex_digits / 2))) and correspondences digest identical to the host's"
  else
    echo "$board: reply bytes differ from the host's" >&2
    failed=1
  fi
done
exit "$failed"
