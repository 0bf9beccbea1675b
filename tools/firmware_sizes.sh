#!/usr/bin/env bash
# Flash/RAM layout of the linked firmware images (firmware/build.sh, firmware/qemu.sh build
# them): one row per target with the bytes of each section, read from the ELF files with
# llvm-size (on PATH, or from `rustup component add llvm-tools`). Images not built are skipped.
#
#   bash tools/firmware_sizes.sh
#
# flash = code and read-only data in the image (.vector_table, .text, .rodata, .data's load
# copy; AArch64's QEMU image is loaded into RAM, so its "flash" is the loaded part of RAM);
# RAM = .data + .bss + .psram (the Cortex-M7 workspace, in PSRAM) + .stack (AArch64; on
# Cortex-M the stack is the rest of RAM).
set -euo pipefail
cd "$(dirname "$0")/../firmware"

size_tool=$(command -v llvm-size || true)
if [ -z "$size_tool" ]; then
  sysroot=$(rustc --print sysroot)
  size_tool=$(find "$sysroot" -name llvm-size -type f | head -n 1)
fi
if [ -z "$size_tool" ]; then
  echo "llvm-size not found: rustup component add llvm-tools" >&2
  exit 1
fi

sections=(.vector_table .text .rodata .data .bss .psram .stack)
printf '%-26s' target
printf '%14s' "${sections[@]}" flash RAM
echo
for target in x86_64-unknown-linux-gnu thumbv7em-none-eabihf aarch64-unknown-none; do
  image="target/$target/release/gomatch-firmware"
  [ -f "$image" ] || continue
  declare -A bytes=()
  while read -r name size _; do
    [ -n "$name" ] && bytes[$name]=$size
  done < <("$size_tool" -A "$image" | tail -n +3)
  printf '%-26s' "$target"
  for s in "${sections[@]}"; do
    printf '%14s' "${bytes[$s]:-0}"
  done
  flash=$(( ${bytes[.vector_table]:-0} + ${bytes[.text]:-0} + ${bytes[.rodata]:-0} + ${bytes[.data]:-0} ))
  ram=$(( ${bytes[.data]:-0} + ${bytes[.bss]:-0} + ${bytes[.psram]:-0} + ${bytes[.stack]:-0} ))
  printf '%14s%14s\n' "$flash" "$ram"
  unset bytes
done
