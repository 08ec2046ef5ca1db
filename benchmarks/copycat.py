"""The copycat check: how well the previous action predicts a policy's action, against the experts'.

A least-squares fit of a_t from a_{t-1} (and a constant) over every step of a policy's own deterministic episodes on
each task of the demonstrations, R^2 pooled over the action's dimensions; the same fit over the demonstrations. A
clone that copies its previous action (de Haan et al. 2019) scores well above the experts.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/copycat.py --demos hv.npz runs/bc-gru/checkpoint.pt ...
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from pomil.api import TrainedPolicy
from pomil.data import Demonstrations
from pomil.envs import make_vec_env
from pomil.errors import PomilError


def r_squared(prev: np.ndarray, act: np.ndarray) -> float:
    """R^2 of the least-squares fit act ~ prev @ W + b, pooled over the action's dimensions."""
    x = np.concatenate([prev, np.ones((len(prev), 1))], 1)
    w, *_ = np.linalg.lstsq(x, act, rcond=None)
    return float(1 - ((act - x @ w) ** 2).sum() / ((act - act.mean(0)) ** 2).sum())


def demo_pairs(demos: Demonstrations) -> tuple[np.ndarray, np.ndarray]:
    """(a_{t-1}, a_t) over every step after the first of every demonstration episode."""
    ends = np.cumsum(demos.episode_lengths)
    episodes = [demos.actions[s:e] for s, e in zip(ends - demos.episode_lengths, ends, strict=True)]
    return np.concatenate([a[:-1] for a in episodes]), np.concatenate([a[1:] for a in episodes])


def policy_pairs(policy: TrainedPolicy, tasks: dict, episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(a_{t-1}, a_t) over the policy's deterministic episodes on every task, and their mean length."""
    prev, cur, lengths = [], [], []
    for kwargs in tasks.values():
        env = make_vec_env(policy.env["id"], kwargs, episodes, device="cpu",
                           observation_mask=policy.env.get("observation_mask"), seed=seed)
        try:
            obs = env.reset()
            policy.reset(episodes, seed=seed)
            actions, alive = [], []
            while not env.sim.done.all():
                alive.append(~env.sim.done)
                actions.append(policy.act(obs, deterministic=True))
                obs, *_ = env.step(torch.as_tensor(actions[-1]))
        finally:
            env.close()
        a, live = np.stack(actions), np.stack(alive)
        both = live[1:] & live[:-1]
        prev.append(a[:-1][both])
        cur.append(a[1:][both])
        lengths.append(live.sum(0).mean())
    return np.concatenate(prev), np.concatenate(cur), float(np.mean(lengths))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+", help="trained policies (checkpoint.pt) on the demonstrations' tasks")
    parser.add_argument("--demos", required=True, help="the demonstrations (.npz, with their tasks' metadata)")
    parser.add_argument("--episodes", type=int, default=20, help="deterministic episodes per task (default 20)")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    try:
        demos = Demonstrations.load(args.demos)
        tasks = demos.metadata.get("tasks")
        if not isinstance(tasks, dict) or not tasks:
            raise PomilError(f"{args.demos}: metadata has no tasks (record them with `pomil demos hopper`)")
        print(f"experts ({args.demos}): R2(a_t | a_t-1) = {r_squared(*demo_pairs(demos)):.3f}")
        for path in args.checkpoints:
            prev, cur, length = policy_pairs(TrainedPolicy.load(path), tasks, args.episodes, args.seed)
            print(f"{path}: R2(a_t | a_t-1) = {r_squared(prev, cur):.3f}, mean episode length {length:.0f}")
    except PomilError as err:
        print(f"copycat: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
