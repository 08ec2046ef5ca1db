#!/usr/bin/env bash
# Ship a trained expert: its policy alone (no optimiser state) as src/pomil/experts/NAME.pt, with its
# evaluation and training log beside it.  Usage: bash scripts/ship_expert.sh RUN_DIR NAME
set -euo pipefail
cd "$(dirname "$0")/.."
run=$1 name=$2
mkdir -p src/pomil/experts
.venv/bin/python -c "import sys; from pomil import TrainedPolicy; TrainedPolicy.load(sys.argv[1]).save(sys.argv[2])" \
  "$run/checkpoint.pt" "src/pomil/experts/$name.pt"
cp "$run/evaluation.json" "src/pomil/experts/$name-evaluation.json"
cp "$run/metrics.csv" "src/pomil/experts/$name-metrics.csv"
