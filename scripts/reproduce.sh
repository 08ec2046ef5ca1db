#!/usr/bin/env bash
# The main job: set up, then the circles reproduction of the paper's five learners over 3 seeds (about 3 minutes on
# 2 cores). Extra arguments go to `pomil reproduce circles` and win over these: `--seeds 10` for the committed table's
# seeds; `.venv/bin/pomil reproduce circles --seeds 10` runs every row of the committed table, the Diffusion Policy
# peer's too (the set-up installs the extra diffusion they need).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh diffusion
exec .venv/bin/pomil reproduce circles --seeds 3 --rows bc-mlp,bc-gru,gail,infogail,infogail-pomdp "$@"
