#!/usr/bin/env bash
# Builds the freestanding no_std/no_main image for x86_64 without the C runtime and runs it.
# Exit status 0 means the image ran the core and every check in it passed.
set -euo pipefail
cd "$(dirname "$0")"
RUSTFLAGS="-C link-arg=-nostartfiles -C link-arg=-static -C relocation-model=static" \
  cargo build --release --target x86_64-unknown-linux-gnu
image=target/x86_64-unknown-linux-gnu/release/gomatch-firmware
ls -l "$image"
"$image"
echo "firmware image ran and exited 0"
