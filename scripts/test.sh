#!/usr/bin/env bash
# Set up with test tools, then the linter and the default test suite (slow tests excluded; add `-m slow` for them).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh test,minari,ray,diffusion   # the optional extras are tested too
.venv/bin/ruff check src tests benchmarks scripts setup.py
# One pytest worker per CPU core (pytest-xdist), a test file to a worker; POMIL_TEST_WORKERS=0 runs them in this process.
exec .venv/bin/python -m pytest -q -n "${POMIL_TEST_WORKERS:-auto}" --dist loadfile --durations 15 "$@"
