#!/usr/bin/env bash
# The main job: set up, then the circles reproduction (extra arguments go to `pomil reproduce circles`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/pomil reproduce circles "$@"
