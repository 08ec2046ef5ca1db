#!/usr/bin/env bash
# The second locomotion task: HalfCheetah-v5 Forward/Backward with positions only,
# end to end with the generic commands (any Gymnasium id works the same way):
# two PPO experts, their demonstrations merged into one unlabeled set, and the
# spec halfcheetah (pomil reproduce halfcheetah): InfoGAIL-POMDP, 3 seeds (about 21 min on 2 cores).
# Usage: bash scripts/halfcheetah.sh [extra `pomil reproduce` flags, e.g. --seeds 1]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
pomil=.venv/bin/pomil
for task in forward backward; do
  if [ ! -f "src/pomil/experts/halfcheetah-$task.pt" ]; then
    $pomil experts train --env-id HalfCheetah-v5 --task "$task" --setting paper --out "runs/experts/halfcheetah-$task"
    bash scripts/ship_expert.sh "runs/experts/halfcheetah-$task" "halfcheetah-$task"
  fi
done
if [ ! -f data/halfcheetah-paper.npz ]; then
  for task in forward backward; do
    $pomil demos record --expert "src/pomil/experts/halfcheetah-$task.pt" --task "$task" --episodes 200 \
      --observation-mask positions-only --seed 0 --out "runs/demos/halfcheetah-$task.npz"
  done
  $pomil demos merge runs/demos/halfcheetah-forward.npz runs/demos/halfcheetah-backward.npz --out data/halfcheetah-paper.npz
fi
$pomil reproduce halfcheetah "$@"
