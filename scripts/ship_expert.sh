#!/usr/bin/env bash
# Ship a trained expert: its policy alone (no optimiser state) as data/experts/NAME.pt, with its
# evaluation and training log beside it.  Usage: bash scripts/ship_expert.sh RUN_DIR NAME
set -euo pipefail
cd "$(dirname "$0")/.."
run=$1 name=$2
mkdir -p data/experts
.venv/bin/python -c "import sys; from pomil import TrainedPolicy; TrainedPolicy.load(sys.argv[1]).save(sys.argv[2])" \
  "$run/checkpoint.pt" "data/experts/$name.pt"
cp "$run/evaluation.json" "data/experts/$name-evaluation.json"
cp "$run/metrics.csv" "data/experts/$name-metrics.csv"
