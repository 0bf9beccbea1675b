#!/usr/bin/env bash
# Builds the C example (capi/example: main.c linked against the Cortex-M7 static library) with
# CMake and Debian's arm-none-eabi toolchain, and runs it under QEMU's mps2-an500 with
# instruction counting, as firmware/qemu.sh runs the Rust image.
#
#   bash capi/example/qemu.sh
#
# Needs gcc-arm-none-eabi, libnewlib-arm-none-eabi, cmake, qemu-system-arm and
# `rustup target add thumbv7em-none-eabihf`, and the shipped models/gomatch-int8.bin. The output
# (semihosting) is kept in firmware/target/c-cortex-m7.log for firmware/cross_isa.sh; the script
# requires exit status 0 (localized) within QEMU_TIMEOUT seconds (default 1200).
set -euo pipefail
cd "$(dirname "$0")"
repo=$(cd ../.. && pwd)

model="$repo/models/gomatch-int8.bin"
if [ ! -f "$model" ]; then
  echo "SKIPPED: no shipped model $model to embed"
  exit 0
fi

cmake --no-warn-unused-cli -S . -B build -DCMAKE_TOOLCHAIN_FILE=arm-none-eabi.cmake -DCMAKE_BUILD_TYPE=MinSizeRel \
  -DGOMATCH_MODEL="$model" >/dev/null
cmake --build build
image=build/gomatch-c-example.elf
arm-none-eabi-size -A "$image" | grep -E '^\.(vector_table|text|rodata|data|bss|psram) '

mkdir -p "$repo/firmware/target"
log="$repo/firmware/target/c-cortex-m7.log"
set +e
start=$(date +%s)
# Semihosting writes to QEMU's stderr.
timeout "${QEMU_TIMEOUT:-1200}" qemu-system-arm -M mps2-an500 -nographic -monitor none -serial none \
  -semihosting-config enable=on,target=native -icount shift=0 -kernel "$image" 2>&1 | tee "$log"
status=${PIPESTATUS[0]}
set -e
echo "C example exited with status $status after $(( $(date +%s) - start )) s of QEMU wall time"
if [ "$status" != 0 ]; then
  echo "C example: expected status 0 (localized)" >&2
  exit 1
fi
