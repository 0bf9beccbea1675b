#!/usr/bin/env bash
# The C API's host test: builds the x86-64 static library (profile `capi`: panic = "abort",
# as in the images), compiles capi/test/host_test.c with the system `cc` against it and runs it
# on the shipped model, the firmware's map and the host's reply bytes. Under valgrind
# (memcheck, every error an exit status) when it is installed, unless GOMATCH_VALGRIND=0;
# GOMATCH_VALGRIND=1 requires it (CI).
set -euo pipefail
cd "$(dirname "$0")/../.."

model=models/gomatch-int8.bin
if [ ! -f "$model" ]; then
  echo "SKIPPED: capi host test: no shipped model $model"
  exit 0
fi

# The README's C example compiles against the header.
snippet=$(awk '/^## Using the localizer from C/ {on = 1} on && /^```c$/ {code = 1; next}
  code && /^```$/ {exit} code {print}' README.md)
[ -n "$snippet" ] || { echo "README.md: no C example under 'Using the localizer from C'" >&2; exit 1; }
cc -std=c11 -Wall -Wextra -Werror -Icapi/include -fsyntax-only -x c - <<<"$snippet"
echo "README's C example: compiles"

cargo build -q -p gomatch-capi --profile capi
out=target/capi/host_test
cc -std=c11 -O2 -g -Wall -Wextra -Werror -Icapi/include capi/test/host_test.c \
  target/capi/libgomatch_capi.a -Wl,--gc-sections -lgcc_s -lutil -lrt -lpthread -lm -ldl -o "$out"

run=("$out" "$model" firmware/data/map.bin firmware/data/reply.hex firmware/data/reply-1024.hex)
case "${GOMATCH_VALGRIND:-}" in
  0) valgrind=no ;;
  1) command -v valgrind >/dev/null || { echo "GOMATCH_VALGRIND=1 but valgrind is not installed" >&2; exit 1; }
     valgrind=yes ;;
  *) if command -v valgrind >/dev/null; then valgrind=yes; else valgrind=no; fi ;;
esac
if [ "$valgrind" = yes ]; then
  echo "capi host test under valgrind (memcheck)"
  valgrind --quiet --error-exitcode=99 --leak-check=full --errors-for-leak-kinds=definite \
    "${run[@]}"
else
  "${run[@]}"
fi
