"""What each seed's draw of demonstrations scores itself: the ceiling an imitation learner trained on it is held to.

``--demos-per-mode N`` trains on N episodes of each labelled mode drawn with the run's seed (pomil.data.per_mode).
Where the experts were recorded with action noise (DART), some of their episodes end early (standard Hopper's
forward expert falls in about a quarter of them), and a small draw can hold several of those. This script prints,
per seed and task, the drawn episodes' lengths, how many ended before the task's step limit, and their mean
normalised return (return / the file's mean expert return, as ``pomil evaluate`` scores a policy).

The demonstration files keep no per-episode return, so it is rebuilt from the recorded full observations
(``states``): Hopper pays healthy_reward (where episodes do not end on a fall: while healthy) +
forward_reward_weight * x velocity - ctrl_cost_weight * |a|^2 a step, read from the next step's observation (the
last step: its own).  Over the whole file the rebuilt mean is printed beside the recorded ``expert_returns`` as a
check.  The environment's reward is read here only; no learner sees it.

    .venv/bin/python benchmarks/demo_draws.py D --demos-per-mode 4 --seeds 0 1 2 3 4
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from pomil.data import Demonstrations, per_mode
from pomil.errors import PomilError

ENV_ID = "Hopper-v5"
X_VELOCITY = 5
"""The column of qvel[0] (the torso's x velocity) in Hopper's full observation (qpos[1:], qvel)."""


def healthy(obs: np.ndarray) -> np.ndarray:
    """Gymnasium Hopper-v5's health test on full observations (T, 11) with its default ranges: z above 0.7, the
    torso's angle within 0.2, every other value within 100."""
    return (obs[:, 0] > 0.7) & (np.abs(obs[:, 1]) < 0.2) & (np.abs(obs[:, 1:]) < 100).all(1)


def episode_returns(demos: Demonstrations) -> np.ndarray:
    """Each episode's return under its own task's reward, rebuilt from the recorded full observations."""
    md = demos.metadata
    if demos.states is None or md.get("env_id") != ENV_ID or "tasks" not in md:
        raise PomilError(f"expected {ENV_ID} demonstrations with full observations and tasks (pomil demos hopper), "
                         f"got env_id {md.get('env_id')!r}")
    names, bounds = md["label_names"], demos.episode_bounds
    out = np.zeros(demos.num_episodes)
    for e in range(demos.num_episodes):
        task = md["tasks"][names[int(demos.labels[e])]]
        s, a = demos.states[bounds[e]:bounds[e + 1]], demos.actions[bounds[e]:bounds[e + 1]].astype(np.float64)
        after = np.concatenate([s[1:], s[-1:]]).astype(np.float64)  # each step's next observation
        alive = np.ones(len(s)) if task.get("terminate_when_unhealthy", True) else healthy(after)
        out[e] = np.sum(task.get("healthy_reward", 1.0) * alive
                        + task.get("forward_reward_weight", 1.0) * after[:, X_VELOCITY]
                        - task.get("ctrl_cost_weight", 1e-3) * (a ** 2).sum(-1))
    return out


def draw_rows(demos: Demonstrations, rebuilt: np.ndarray, n: int, seeds: list[int], source: str) -> list[str]:
    """The table's row of each seed: per task the drawn episodes' lengths, how many ended early, their mean
    normalised return."""
    md, names = demos.metadata, demos.metadata["label_names"]
    limits = {t: int(md["tasks"][t].get("max_episode_steps", 1000)) for t in names}
    bounds = demos.episode_bounds
    # a drawn episode is found by its length and first observation (Hopper's starts are drawn at random)
    index = {(int(bounds[e + 1] - bounds[e]), demos.observations[bounds[e]].tobytes()): e
             for e in range(demos.num_episodes)}
    if len(index) != demos.num_episodes:
        raise PomilError(f"{source}: two episodes share their length and first observation")
    rows = []
    for seed in seeds:
        draw, cells = per_mode(demos, n, seed, source), []
        for m, t in enumerate(names):
            eps = [index[(int(draw.episode_bounds[j + 1] - draw.episode_bounds[j]),
                          draw.observations[draw.episode_bounds[j]].tobytes())]
                   for j in range(draw.num_episodes) if int(draw.labels[j]) == m]
            lengths = [int(bounds[e + 1] - bounds[e]) for e in eps]
            early = sum(k < limits[t] for k in lengths)
            cells.append(f"{', '.join(map(str, lengths))}; {early}; "
                         f"{rebuilt[eps].mean() / float(md['expert_returns'][t]):.2f}")
        rows.append(f"| {seed} | " + " | ".join(cells) + " |")
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("demos")
    p.add_argument("--demos-per-mode", type=int, default=4)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    args = p.parse_args(argv)
    if args.demos_per_mode < 1:
        p.error(f"--demos-per-mode: expected a positive number of episodes, got {args.demos_per_mode}")
    try:
        demos = Demonstrations.load(args.demos)
        rebuilt, names, labels = episode_returns(demos), demos.metadata["label_names"], np.asarray(demos.labels)
        rows = draw_rows(demos, rebuilt, args.demos_per_mode, args.seeds, args.demos)
    except PomilError as err:
        print(f"demo_draws: error: {err}", file=sys.stderr)
        return 2
    expert = demos.metadata["expert_returns"]
    print("whole file, rebuilt / recorded mean return: " + ", ".join(
        f"{t} {rebuilt[labels == m].mean():.1f} / {float(expert[t]):.1f}" for m, t in enumerate(names)))
    print("| seed | " + " | ".join(f"{t}: lengths, ended early, normalised return" for t in names) + " |")
    print("|---|" + "---|" * len(names))
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
