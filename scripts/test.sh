#!/usr/bin/env bash
# Set up with test tools, then the linter and the default test suite (slow tests excluded; add `-m slow` for them).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh test,minari,ray,diffusion   # the optional extras are tested too
.venv/bin/ruff check src tests benchmarks scripts setup.py
# One pytest worker per CPU core (pytest-xdist), each pinned to its core (tests/conftest.py); a worker that runs out of
# tests takes some of the other's; POMIL_TEST_WORKERS=0 runs them in this process.
exec .venv/bin/python -m pytest -q -n "${POMIL_TEST_WORKERS:-auto}" --dist worksteal --durations 15 "$@"
