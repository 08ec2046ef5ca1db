"""Batched simulators on several Gymnasium tasks, measured in one run on this machine.

For each task, N copies with random actions in 128-step episodes, env-steps/s of:

1. ``GymSim`` (``pomil.envs.batch``): the general path every id takes, N
   gymnasium envs stepped one after another, ended copies frozen;
2. gymnasium's ``SyncVectorEnv`` (the peer);
3. for Hopper-v5 also ``HopperSim``, pomil's dedicated simulator.

    .venv/bin/python benchmarks/any_task_speed.py [--num-envs 64] [--steps 256]
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

from pomil.envs.batch import GymSim
from pomil.envs.locomotion import HopperSim

TASKS = {"Hopper-v5": {"terminate_when_unhealthy": False}, "Walker2d-v5": {"terminate_when_unhealthy": False},
         "HalfCheetah-v5": {}, "Pendulum-v1": {}}


def batched_speed(sim, steps: int) -> float:
    """env-steps/s of a NumPy batched simulator (HopperSim, GymSim) with uniform random actions."""
    rng = np.random.default_rng(0)
    sim.reset(0)
    t0 = time.perf_counter()
    for _ in range(steps):
        if sim.done.all():
            sim.reset()
        sim.step(rng.uniform(-1, 1, (sim.num_envs, sim.act_dim)))
    dt = time.perf_counter() - t0
    sim.close()
    return steps * sim.num_envs / dt


def gym_vector_speed(env_id: str, kwargs: dict, num_envs: int, steps: int) -> float:
    env = gym.vector.SyncVectorEnv([lambda: gym.make(env_id, **kwargs) for _ in range(num_envs)])
    env.reset(seed=0)
    env.action_space.seed(0)
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(env.action_space.sample())
    dt = time.perf_counter() - t0
    env.close()
    return steps * num_envs / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--steps", type=int, default=256, help="batched steps timed per simulator")
    args = ap.parse_args()
    print(f"{'task':16s} {'simulator':22s} {'env-steps/s':>12s} {'vs SyncVectorEnv':>17s}")
    for env_id, extra in TASKS.items():
        kw = {"max_episode_steps": 128, **extra}
        base = gym_vector_speed(env_id, kw, args.num_envs, args.steps // 2)
        rows = [("SyncVectorEnv", base), ("GymSim", batched_speed(GymSim(env_id, args.num_envs, kw), args.steps))]
        if env_id == "Hopper-v5":
            rows.append(("HopperSim", batched_speed(HopperSim(args.num_envs, kw), args.steps)))
        for name, v in rows:
            print(f"{env_id:16s} {name:22s} {v:12,.0f} {v / base:16.2f}x")


if __name__ == "__main__":
    main()
