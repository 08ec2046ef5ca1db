#!/usr/bin/env bash
# The main job: set up, then the circles reproduction over 3 seeds (extra arguments go to `pomil reproduce circles`;
# `--seeds 10` runs the committed table's 10).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh diffusion   # the Diffusion Policy peer rows need the extra diffusion
exec .venv/bin/pomil reproduce circles --seeds 3 "$@"
