"""MuJoCo Warp physics (``--sim warp``) against the CPU path, measured in one run on this machine.

Prints, for a MuJoCo locomotion task (Hopper-v5 by default, the paper setting):

1. agreement of :class:`pomil.envs.warp.WarpSim` on ``--device`` with MuJoCo on the
   CPU (gymnasium): max |difference| of observations and rewards after one env step
   from the same states, and along whole episodes from the same seeds, with the
   number of episode ends (terminations / truncations) compared, and as a yardstick
   MuJoCo against itself from the same start rounded to float32 (chaos alone);
2. physics-only env-steps/s of ``WarpSim`` for each ``--num-envs`` (random actions
   drawn on the device; ``--steps`` env steps timed after ``--warmup`` untimed ones,
   which include Warp's kernel compilation and, on CUDA, the graph capture), and of
   the CPU simulator (``HopperSim``, all usable cores) for the same env counts;
3. with ``--train-envs``: InfoGAIL-POMDP training env-steps/s on the shipped Hopper
   demonstrations (as ``benchmarks/hopper_speed.py``: warm start and policy warm-up
   off, everything else timed) with ``sim=warp`` and ``sim=cpu``.

    python benchmarks/warp_speed.py --device cpu --num-envs 64,256             # Warp's CPU device: slow, a check
    python benchmarks/warp_speed.py --device cuda --num-envs 1024,4096,16384,65536 \
        --train-envs 4096,16384,65536 --train-sims warp

Needs the gpu extra (``pip install 'pomil[gpu]'``).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from any_task_speed import batched_speed  # this script's folder is on sys.path

from pomil.envs.locomotion import HOPPER_ID, HopperSim, locomotion_kwargs, usable_cpus
from pomil.envs.warp import SPECS, WarpSim


def agreement(env_id: str, kwargs: dict, device: str, num_envs: int, one_step_states: int,
              seed: int = 0) -> dict[str, float]:
    """Max |WarpSim - gymnasium| of observations and rewards: one step from the same
    states, and along one episode per env from the same seeds (random actions in the
    control range's scale); the episode ends compared must all agree."""
    rng = np.random.default_rng(seed)
    # One step from gymnasium's states: episodes that never end (an ended WarpSim copy stays frozen).
    endless = {**kwargs, "max_episode_steps": 10**9}
    if "terminate_when_unhealthy" in SPECS[env_id].defaults:
        endless["terminate_when_unhealthy"] = False
    envs = [gym.make(env_id, **endless) for _ in range(num_envs)]
    for i, e in enumerate(envs):
        e.reset(seed=seed + i)
    sim = WarpSim(env_id, num_envs, endless, device)
    sim.reset(seed)
    one_obs = one_rew = 0.0
    for _ in range(one_step_states):
        sim.set_state(torch.as_tensor(np.stack([e.unwrapped.data.qpos for e in envs])),
                      torch.as_tensor(np.stack([e.unwrapped.data.qvel for e in envs])))
        act = rng.uniform(-1, 1, (num_envs, sim.act_dim))
        obs, rew, _, _ = sim.step(torch.as_tensor(act, device=sim.device))
        ref = [e.step(a) for e, a in zip(envs, act, strict=True)]
        one_obs = max(one_obs, float(np.abs(obs.cpu().numpy() - np.stack([r[0] for r in ref])).max()))
        one_rew = max(one_rew, float(np.abs(rew.cpu().numpy() - np.array([r[1] for r in ref])).max()))
    # Whole episodes from the same seeds.
    envs = [gym.make(env_id, **kwargs) for _ in range(num_envs)]
    sim = WarpSim(env_id, num_envs, kwargs, device)
    for i, e in enumerate(envs):
        e.reset(seed=seed + 100 + i)
    sim.reset(seed + 100)
    traj_obs = traj_rew = 0.0
    done = np.zeros(num_envs, dtype=bool)
    ends = mismatched = steps = 0
    while not done.all():
        act = rng.uniform(-1, 1, (num_envs, sim.act_dim))
        obs, rew, term, trunc = (x.cpu().numpy() for x in sim.step(torch.as_tensor(act, device=sim.device)))
        steps += 1
        for i, e in enumerate(envs):
            if done[i]:
                continue
            o, r, te, tr, _ = e.step(act[i])
            traj_obs = max(traj_obs, float(np.abs(obs[i] - o).max()))
            traj_rew = max(traj_rew, abs(float(rew[i]) - r))
            mismatched += int((bool(term[i]), bool(trunc[i])) != (te, tr))
            if te or tr:
                done[i] = True
                ends += 1
    return {"float64_chaos": float64_chaos(env_id, kwargs, num_envs, seed + 100),
            "one_step_obs": one_obs, "one_step_reward": one_rew, "states": one_step_states * num_envs,
            "episode_obs": traj_obs, "episode_reward": traj_rew, "episode_steps": steps, "ends": ends,
            "mismatched": mismatched}


def float64_chaos(env_id: str, kwargs: dict, num_envs: int, seed: int) -> float:
    """The yardstick for whole episodes: max |obs difference| between MuJoCo (float64) and
    itself started from the same state rounded to float32, over episodes from the seeds of
    :func:`agreement`'s with random actions of the same scale (how far chaos alone carries a
    float32-sized difference)."""
    rng = np.random.default_rng(seed)
    worst = 0.0
    for i in range(num_envs):
        a, b = gym.make(env_id, **kwargs), gym.make(env_id, **kwargs)
        a.reset(seed=seed + i)
        b.reset(seed=seed + i)
        d = b.unwrapped.data
        rounded = [x.astype(np.float32).astype(np.float64) for x in (d.qpos, d.qvel)]
        b.unwrapped.set_state(*rounded)
        done = False
        while not done:
            act = rng.uniform(-1, 1, a.action_space.shape)
            oa, _, te, tr, _ = a.step(act)
            ob, _, te_b, tr_b, _ = b.step(act)
            worst = max(worst, float(np.abs(oa - ob).max()))
            done = te or tr or te_b or tr_b
    return worst


def warp_speed(env_id: str, kwargs: dict, device: str, num_envs: int, steps: int, warmup: int) -> tuple[float, float]:
    """(env-steps/s of WarpSim with random actions, seconds of the untimed warm-up steps)."""
    sim = WarpSim(env_id, num_envs, kwargs, device)
    gen = torch.Generator(sim.device).manual_seed(0)
    sim.reset(0)

    def run(k: int) -> None:
        for _ in range(k):
            if bool(sim.done.all()):
                sim.reset()
            sim.step(2 * torch.rand(num_envs, sim.act_dim, device=sim.device, generator=gen) - 1)

    t0 = time.perf_counter()
    run(warmup)
    sync(sim.device)
    t1 = time.perf_counter()
    run(steps)
    sync(sim.device)
    return steps * num_envs / (time.perf_counter() - t1), t1 - t0


def cpu_speed(kwargs: dict, num_envs: int, steps: int) -> float:
    return batched_speed(HopperSim(num_envs, kwargs), steps)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def training_speed(demos: str, device: str, num_envs: int, iterations: int, sim: str) -> tuple[float, str]:
    """(InfoGAIL-POMDP training env-steps/s over ``iterations``, each phase's share of the time)."""
    from pomil.algos.adversarial import AdversarialConfig, train_adversarial
    from pomil.config import from_dict

    with tempfile.TemporaryDirectory() as tmp:
        values = {"learner": "infogail-pomdp", "demos": demos, "out": tmp, "iterations": iterations,
                  "warm_start_iterations": 0, "policy_warmup_iterations": 0, "eval_every": 0, "log_every": 1,
                  "progress": False, "device": device, "num_envs": num_envs, "sim": sim,
                  "max_iteration_steps": num_envs * 1000}  # every env an episode, whatever its length
        train_adversarial(from_dict(AdversarialConfig, values, "benchmark"))
        import csv

        with open(Path(tmp) / "metrics.csv", newline="") as f:
            last = list(csv.DictReader(f))[-1]
        shares = ", ".join(f"{k.removeprefix('time/share_')} {float(v):.0%}" for k, v in last.items()
                           if k.startswith("time/share_"))
        return float(last["time/env_steps_per_s"]), shares


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", help="Warp/torch device: cpu, cuda, cuda:N")
    ap.add_argument("--env-id", default=HOPPER_ID, help="Hopper-v5, Walker2d-v5 or HalfCheetah-v5")
    ap.add_argument("--setting", default="paper", choices=["paper", "standard"])
    ap.add_argument("--num-envs", default="64,256", help="comma-separated env counts for the physics rows ('': none)")
    ap.add_argument("--steps", type=int, default=32, help="env steps timed per env count")
    ap.add_argument("--warmup", type=int, default=2, help="untimed env steps first (kernel compilation, graph capture)")
    ap.add_argument("--no-cpu", action="store_true", help="skip the CPU simulator rows")
    ap.add_argument("--agreement-envs", type=int, default=8, help="envs of the agreement check (0: skip it)")
    ap.add_argument("--train-envs", default="", help="comma-separated env counts for InfoGAIL-POMDP training rows")
    ap.add_argument("--train-sims", default="warp,cpu", help="comma-separated sims of the training rows")
    ap.add_argument("--iterations", type=int, default=3, help="training iterations timed per training row")
    ap.add_argument("--demos", default="data/hopper-paper.npz")
    args = ap.parse_args()
    import mujoco
    import mujoco_warp
    import warp as wp

    kwargs = locomotion_kwargs(args.env_id, "forward", args.setting)
    gpu = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or platform.machine()
    print(f"torch {torch.__version__}, warp {wp.__version__}, mujoco_warp {mujoco_warp.__version__}, "
          f"mujoco {mujoco.__version__}; "
          f"{usable_cpus()} usable CPU cores, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; "
          f"device {args.device} ({gpu}); {args.env_id}, {args.setting} setting")
    if args.agreement_envs > 0:
        t0 = time.perf_counter()
        a = agreement(args.env_id, kwargs, args.device, args.agreement_envs, one_step_states=25)
        print(f"agreement with MuJoCo (float64) on {args.device}, {time.perf_counter() - t0:.0f} s: "
              f"one step from the same state, {a['states']} states: max |obs diff| {a['one_step_obs']:.2e}, "
              f"max |reward diff| {a['one_step_reward']:.2e}; {args.agreement_envs} episodes from the same seeds "
              f"({a['episode_steps']} steps): max |obs diff| {a['episode_obs']:.2e}, "
              f"max |reward diff| {a['episode_reward']:.2e}, {a['ends']} episode ends compared, "
              f"{a['mismatched']} mismatched (yardstick: MuJoCo against itself from the float32-rounded start, "
              f"{a['float64_chaos']:.2e})")
    rows = []
    for n in [int(v) for v in args.num_envs.split(",") if v.strip()]:
        rate, warm = warp_speed(args.env_id, kwargs, args.device, n, args.steps, args.warmup)
        rows.append((f"physics, WarpSim on {args.device} ({n} envs; warm-up {warm:.1f} s)", rate))
        print(f"{rows[-1][0]}: {rate:,.0f} env-steps/s", flush=True)
        if not args.no_cpu and args.env_id == HOPPER_ID:
            name = f"physics, HopperSim on {usable_cpus()} CPU cores ({n} envs)"
            rows.append((name, cpu_speed(kwargs, n, args.steps)))
            print(f"{name}: {rows[-1][1]:,.0f} env-steps/s", flush=True)
    for n in [int(v) for v in args.train_envs.split(",")] if args.train_envs else []:
        for sim in args.train_sims.split(","):
            rate, shares = training_speed(args.demos, args.device, n, args.iterations, sim)
            rows.append((f"InfoGAIL-POMDP training, sim {sim}, device {args.device} ({n} envs, all updates)", rate))
            print(f"InfoGAIL-POMDP training, sim {sim}, {n} envs: {rate:,.0f} env-steps/s; time shares: {shares}",
                  flush=True)
    print(f"{'what':78s} {'env-steps/s':>12s}")
    for name, v in rows:
        print(f"{name:78s} {v:12,.0f}")


if __name__ == "__main__":
    main()
