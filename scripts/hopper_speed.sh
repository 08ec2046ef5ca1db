#!/usr/bin/env bash
# Speed modes: where the belief should matter.  Three PPO experts hop forward at three target
# speeds (pomil/HopperSpeed-v0: Hopper-v5 paid -|v_x - target| instead of v_x), 256-step episodes
# that do not end when unhealthy.  Their positions-only demonstrations are merged without labels,
# and the hopper-speed spec (`pomil reproduce hopper-speed`) trains BC-MLP, BC-GRU, InfoGAIL (MLP) and InfoGAIL-POMDP on them and
# scores every code by speed (on-task share, purity, speed error) and normalised return.
# Positions alone do not show a speed: a policy has to infer it from the history.
# Usage: bash scripts/hopper_speed.sh [extra `pomil reproduce` flags, e.g. --seeds 1 --ray]
# Writes runs/results/hopper-speed (the committed copy: results/hopper-speed, with --out results/hopper-speed).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
pomil=.venv/bin/pomil
SPEEDS="0.6 1.2 1.8"
STEPS=256
for v in $SPEEDS; do
  if [ ! -f "src/pomil/experts/hopper-speed-$v.pt" ]; then
    $pomil experts train --env-id pomil/HopperSpeed-v0 --task none --setting paper \
      --env-kwargs "target_velocity=$v,max_episode_steps=$STEPS" --iterations 150 --out "runs/experts/hopper-speed-$v"
    bash scripts/ship_expert.sh "runs/experts/hopper-speed-$v" "hopper-speed-$v"
  fi
done
demos=data/hopper-speed.npz
if [ ! -f "$demos" ]; then
  recordings=()
  for v in $SPEEDS; do
    $pomil demos record --expert "src/pomil/experts/hopper-speed-$v.pt" --episodes 200 --observation-mask positions-only \
      --seed 0 --out "runs/demos/hopper-speed-$v.npz"
    recordings+=("runs/demos/hopper-speed-$v.npz")
  done
  $pomil demos merge "${recordings[@]}" --out "$demos"
fi
$pomil reproduce hopper-speed "$@"
