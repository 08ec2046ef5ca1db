#!/usr/bin/env bash
# Set up with test tools, then the default test suite (slow tests excluded; add `-m slow` for them).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh test,minari,ray   # the optional extras are tested too
exec .venv/bin/python -m pytest -q "$@"
