"""Circles throughput, measured in one run on this machine.

Prints env-steps/s of the batched torch environment against the Gymnasium
face of the same dynamics (one episode at a time), the time to record the
default demonstrations, and BC gradient steps/s for both policies.

    .venv/bin/python benchmarks/circles_speed.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import pomil  # noqa: F401
from pomil.algos.bc import BCConfig, train_bc
from pomil.demos import record_circles_demos
from pomil.envs.circles import CirclesVecEnv, make_spec


def batched_steps_per_s(num_envs: int, episodes: int = 20) -> float:
    spec = make_spec()
    env = CirclesVecEnv(spec, num_envs)
    actions = torch.randn(spec.episode_length, num_envs, 2)
    t0 = time.perf_counter()
    for _ in range(episodes):
        env.reset()
        for a in actions:
            env.step(a)
    return episodes * spec.episode_length * num_envs / (time.perf_counter() - t0)


def gym_steps_per_s(episodes: int = 100) -> float:
    env = gym.make("pomil/Circles-v0")
    rng = np.random.default_rng(0)
    steps = 0
    t0 = time.perf_counter()
    for _ in range(episodes):
        env.reset()
        done = False
        while not done:
            _, _, term, trunc, _ = env.step(rng.standard_normal(2).astype(np.float32))
            steps += 1
            done = term or trunc
    return steps / (time.perf_counter() - t0)


def main() -> None:
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    g = gym_steps_per_s()
    print(f"gymnasium CirclesEnv (1 env, with wrappers):   {g:12,.0f} env-steps/s")
    for n in (64, 1024, 8192):
        b = batched_steps_per_s(n)
        print(f"batched CirclesVecEnv, {n:5d} envs:            {b:12,.0f} env-steps/s  ({b / g:7.1f}x gymnasium)")
    t0 = time.perf_counter()
    demos = record_circles_demos(make_spec(), 400, seed=0)
    print(f"record 400 expert episodes:                     {time.perf_counter() - t0:8.2f} s")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "d.npz"
        demos.save(path)
        for policy in ("mlp", "gru"):
            iters = 200
            t0 = time.perf_counter()
            train_bc(BCConfig(demos=str(path), out=f"{tmp}/{policy}", policy=policy, iterations=iters, progress=False))
            dt = time.perf_counter() - t0
            print(f"BC {policy}, batch 64 episodes x 33 steps:        {iters / dt:8.1f} it/s ({dt:.1f} s for {iters})")


if __name__ == "__main__":
    main()
