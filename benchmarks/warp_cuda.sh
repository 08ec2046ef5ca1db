#!/usr/bin/env bash
# The CUDA check of --sim warp, in one go on a GPU machine (docs/gpu.md): install, versions, the Warp tests on
# CUDA, physics and training rates against the CPU simulator on the same machine, and a short paper-setting Hopper
# training run on the GPU. Prints everything; the committed copy is benchmarks/results/warp_speed_cuda.txt.
#
#   bash benchmarks/warp_cuda.sh                  # with a CUDA torch already installed in `python3`'s environment
#   PIP_NO_INDEX=1 PIP_FIND_LINKS=DIR bash ...    # offline: every wheel the extras need in DIR
#
# Each step has its own time limit and a failed step does not stop the next; the exit status is the number of
# failed steps. A fresh machine compiles Warp's kernels first (cached in ~/.cache/warp).
set -uo pipefail
cd "$(dirname "$0")/.."
py="${PYTHON:-python3}"
device="${WARP_DEVICE:-cuda}"  # cpu: the same steps on Warp's CPU device, small, to check the script itself
failed=0
t_script=$(date +%s)
step() {  # step NAME LIMIT_S COMMAND...: run one step under a time limit, timed
  local name=$1 limit=$2 t0 rc
  shift 2
  echo; echo "=== $name"
  t0=$(date +%s)
  timeout "$limit" "$@"
  rc=$?
  echo "--- $name: exit $rc after $(( $(date +%s) - t0 )) s"
  [ "$rc" = 0 ] || failed=$((failed + 1))
}

step "install: pip install -e '.[gpu,test]'" 300 "$py" -m pip install -q --disable-pip-version-check -e '.[gpu,test]'
step "versions" 120 "$py" - <<'EOF'
import mujoco, mujoco_warp, torch, warp as wp
wp.init()
print(f"torch {torch.__version__} (CUDA {torch.version.cuda}), warp {wp.__version__}, mujoco_warp "
      f"{mujoco_warp.__version__}, mujoco {mujoco.__version__}")
if torch.cuda.is_available():
    print(f"GPU: {torch.cuda.get_device_name()} ({torch.cuda.get_device_properties(0).total_memory / 2**30:.0f} GiB)")
EOF
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
nproc

step "benchmarks/warp_speed.py --device $device" 600 "$py" benchmarks/warp_speed.py --device "$device" \
  --num-envs "${WARP_NUM_ENVS:-1024,4096,16384,65536}" --train-envs "${WARP_TRAIN_ENVS:-4096,16384}" --train-sims warp

step "tests/envs/test_warp.py on $device (the slow training test included)" 400 \
  env POMIL_WARP_DEVICE="$device" "$py" -m pytest -q -p no:cacheprovider tests/envs/test_warp.py -m "slow or not slow"

run="${WARP_RUN_DIR:-$(mktemp -d)}"
envs="${WARP_RUN_ENVS:-4096}"
step "pomil train infogail-pomdp, paper-setting Hopper, --sim warp --device $device, $envs envs, 5 iterations" 600 \
  "$py" -m pomil train infogail-pomdp --demos data/hopper-paper.npz --sim warp --device "$device" --num-envs "$envs" \
  --max-iteration-steps $((envs * 128)) --iterations 5 --eval-every 5 --no-progress --out "$run"
"$py" - "$run/metrics.csv" <<'EOF'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1], newline="")))
keys = ["iteration", "time/elapsed_s", "time/env_steps_per_s", "time/share_rollout", "time/share_critic",
        "time/share_posterior", "time/share_ppo", "critic/wasserstein", "posterior/accuracy", "env/true_return"]
keys += sorted(k for k in rows[-1] if ("loss" in k or k.startswith("eval/")) and rows[-1][k] not in ("", None))


def cell(v):
    return f"{float(v):12.4g}" if v not in ("", None) else f"{'-':>12s}"


print("metrics.csv (a column per logged iteration):")
for k in keys:
    print(f"  {k:40s} " + " ".join(cell(row.get(k)) for row in rows))
EOF
echo; echo "=== the script: $(( $(date +%s) - t_script )) s, $failed failed step(s)"
exit "$failed"
