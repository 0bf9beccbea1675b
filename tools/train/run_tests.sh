#!/usr/bin/env bash
# CI entry point for the trainer: set up the venv (setup_venv.sh) and run the pytest suite quietly.
# Extra arguments are passed to pytest.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="$("$here/setup_venv.sh")"
cd "$here"
exec "$venv/bin/python" -m pytest -q -rs -p no:cacheprovider tests "$@"
