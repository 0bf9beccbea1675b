#!/usr/bin/env bash
# Create (or reuse) the trainer's virtualenv and install requirements.txt only when something is missing.
# The venv path defaults to ~/.cache/gomatch-venv and can be overridden with GOMATCH_VENV.
# GOMATCH_TORCH_INDEX=URL installs torch from that wheel index (e.g. PyTorch's CPU-only index, ~200 MB instead of
# PyPI's ~5 GB wheel with CUDA libraries) when the machine reaches it; PyPI stays the index of everything else.
# Idempotent and silent when everything is already installed; prints the venv path on stdout.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="${GOMATCH_VENV:-$HOME/.cache/gomatch-venv}"
req="$here/requirements.txt"

if [ ! -x "$venv/bin/python" ]; then
    echo "setup_venv: creating $venv" >&2
    python3 -m venv "$venv" >&2
fi

# Each pinned "name==version" line must be importable metadata at exactly that version.
missing="$("$venv/bin/python" - "$req" <<'PY'
import sys
from importlib import metadata
missing = []
for line in open(sys.argv[1]):
    line = line.split("#", 1)[0].strip()
    if not line:
        continue
    name, _, version = line.partition("==")
    try:
        installed = metadata.version(name)
    except metadata.PackageNotFoundError:
        installed = None
    if installed is None or installed.split("+", 1)[0] != version:
        missing.append(line)
print(" ".join(missing))
PY
)"

if [ -n "$missing" ]; then
    echo "setup_venv: installing $missing" >&2
    if [ -n "${GOMATCH_TORCH_INDEX:-}" ]; then
        "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --index-url "$GOMATCH_TORCH_INDEX" \
            "$(grep -E '^torch==' "$req")" >&2
    fi
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req" >&2
fi
echo "$venv"
