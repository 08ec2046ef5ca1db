"""Multi-task locomotion evaluation: every latent code on every task, codes matched to tasks.

Three figures per task, for the code assigned to it:

* normalised return = R / R_expert (the paper's measure);
* progress score = (R - R_still) / (R_expert - R_still), R_still the return of
  zero actions: 0 for standing still, 1 for the expert (the paper's measure
  alone cannot tell hopping from standing: in the 128-step setting zero
  actions already score about 0.5 forward and 0.9 backward);
* displacement ratio = distance moved in the task's direction / the expert's.

Codes are assigned to tasks by the one-to-one matching with the highest total
progress score (all permutations; K and the number of tasks are small).  A
policy with fewer codes than tasks (BC, GAIL: one) gets, for each task, its
best code.

Behaviour by speed, when the demonstrations record the experts' mean speeds
(``expert_speed``, m/s; MuJoCo tasks): each of a code's episodes (all tasks'
rollouts pooled: the tasks share dynamics) is assigned to the task whose
expert speed is nearest its own mean speed.  Per code: the shares and the
purity (the largest share); per task, for its matched code: the share of
that code's episodes nearest this task (``on_task_share``) and the speed
error |mean speed - expert speed|.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import torch

from pomil.api import TrainedPolicy
from pomil.demos import x_position
from pomil.envs import make_vec_env
from pomil.errors import PomilError
from pomil.eval.metrics import EPISODE_SEGMENTS, coverage, episode_purity
from pomil.training import EpisodeProgress, progress_bar


@torch.no_grad()
def rollout_locomotion(policy: TrainedPolicy, env_kwargs: dict[str, Any], episodes: int, *, seed: int = 0,
                       deterministic: bool = True, codes: np.ndarray | None = None,
                       observation_mask: list[int] | None = None, env_id: str | None = None,
                       bar: Any | None = None) -> dict[str, np.ndarray]:
    """One episode in each of ``episodes`` copies of the policy's environment
    (or ``env_id``) built with ``env_kwargs``; per episode: ``returns``,
    ``displacement`` (final minus initial torso x; NaN off MuJoCo), ``length``
    (steps) and ``speed`` (displacement / duration, m/s; NaN off MuJoCo).  ``bar``
    (a progress bar) counts the episodes as they end."""
    env = make_vec_env(env_id or policy.env["id"], env_kwargs, episodes, device="cpu",
                       observation_mask=observation_mask, seed=seed)
    try:
        obs = env.reset()
        x0 = x_position(env.sim)
        policy.reset(episodes, codes if policy.num_codes else None, seed=seed)
        ret, length, tick = np.zeros(episodes), np.zeros(episodes, dtype=np.int64), EpisodeProgress(bar)
        path = [x0]
        while not env.sim.done.all():
            alive = ~env.sim.done
            obs, r, _, _ = env.step(torch.as_tensor(policy.act(obs, deterministic)))
            ret += r.numpy()
            length += alive
            path.append(np.where(alive, x_position(env.sim), path[-1]))  # an ended episode stays where it ended
            tick(env.sim.done)
        displacement = x_position(env.sim) - x0
        speed = displacement / (np.maximum(length, 1) * getattr(env.sim, "dt", np.nan))
        ends = np.round(np.arange(EPISODE_SEGMENTS + 1)[:, None] * length[None] / EPISODE_SEGMENTS).astype(np.int64)
        x_at = np.stack(path)[ends, np.arange(episodes)[None]]  # (segments + 1, episodes)
        segment_rates = (np.diff(x_at, axis=0) / np.maximum(np.diff(ends, axis=0), 1)).T
        return {"returns": ret, "displacement": displacement, "length": length, "speed": speed,
                "segment_rates": segment_rates}
    finally:
        env.close()


def task_of_rates(rates: np.ndarray, reference: dict[str, Any], *, standing: bool = True) -> np.ndarray:
    """The task each rate (displacement per step, any shape) looks like: the index of the task whose expert's
    signed rate (its displacement in the task's direction over its episode's ``max_episode_steps``, 1000 when
    unset) is nearest; with ``standing``, -1 where standing still (rate 0) is nearer than every task."""
    tasks = list(reference["tasks"])
    targets = np.array([0.0] * standing + [np.sign(reference["tasks"][t].get("forward_reward_weight", 1.0))
                                           * float(reference["expert_displacement"][t])
                                           / float(reference["tasks"][t].get("max_episode_steps", 1000))
                                           for t in tasks])
    nearest = np.abs(np.asarray(rates)[..., None] - targets).argmin(-1)
    return nearest - int(standing)


def free_sampling(roll: dict[str, np.ndarray], reference: dict[str, Any]) -> dict[str, Any]:
    """What a user who samples freely (the codes drawn evenly) sees on one task's rollouts, which share the
    dynamics of every task: each episode's task by its mean rate, or standing (:func:`task_of_rates`), their
    shares and ``coverage`` (entropy over log J), and whether a moving episode keeps to one task
    (``episode_purity``, ``switch_share``: each third of it assigned alone to the nearest task; a third may start
    slowly from rest, so only the whole episode is ever called standing, and a standing episode is never pure)."""
    tasks = list(reference["tasks"])
    modes = task_of_rates(roll["displacement"] / np.maximum(roll["length"], 1), reference)
    thirds = np.where(modes[:, None] >= 0, task_of_rates(roll["segment_rates"], reference, standing=False), -1)
    return {"mode_share": {t: float((modes == j).mean()) for j, t in enumerate(tasks)},
            "still_share": float((modes == -1).mean()), "coverage": coverage(modes, len(tasks)),
            **episode_purity(thirds)}


def task_scores(returns: np.ndarray, displacement: np.ndarray, reference: dict[str, Any],
                task: str) -> dict[str, float]:
    """The three figures for mean return and mean displacement on ``task``."""
    r_exp, r_still = float(reference["expert_returns"][task]), float(reference["still_returns"][task])
    direction = float(np.sign(reference["tasks"][task].get("forward_reward_weight", 1.0)))
    return {"return": float(returns), "normalised_return": float(returns) / r_exp,
            "progress": (float(returns) - r_still) / (r_exp - r_still),
            "displacement_ratio": direction * float(displacement) / float(reference["expert_displacement"][task])}


def match_codes(score: np.ndarray) -> list[int]:
    """Code assigned to each task (columns) maximising the summed score (K, J).
    One-to-one when K >= J; otherwise each task takes its best code."""
    k, j = score.shape
    if k < j:
        return [int(c) for c in score.argmax(axis=0)]
    best = max(itertools.permutations(range(k), j), key=lambda perm: sum(score[c, t] for t, c in enumerate(perm)))
    return [int(c) for c in best]


def speed_behaviour(speeds: np.ndarray, codes: np.ndarray, expert_speed: dict[str, float], k: int) -> dict[str, Any]:
    """Per code: its episodes' mean speed, the share nearest each task's expert speed, and the purity.

    ``speeds`` (n,) m/s per episode, ``codes`` (n,) the code of each episode."""
    tasks = list(expert_speed)
    targets = np.array([expert_speed[t] for t in tasks])
    nearest = np.abs(speeds[:, None] - targets[None, :]).argmin(axis=1)
    out = {}
    for c in range(k):
        sel = codes == c
        shares = {t: float((nearest[sel] == j).mean()) for j, t in enumerate(tasks)}
        out[f"code{c}"] = {"mean_speed": float(speeds[sel].mean()), "speed_std": float(speeds[sel].std()),
                           "shares": shares, "purity": max(shares.values())}
    return out


def reference_of(metadata: dict[str, Any], source: str = "demonstrations") -> dict[str, Any]:
    """The task reference (tasks, expert and zero-action returns, expert displacement, and the
    expert speeds where recorded) in demo metadata."""
    keys = ("tasks", "expert_returns", "still_returns", "expert_displacement")
    missing = [k for k in keys if k not in metadata]
    if missing:
        raise PomilError(f"{source}: metadata lacks {missing}; record them with `pomil demos hopper`")
    speeds = metadata.get("expert_speed") or {}
    return {**{k: metadata[k] for k in keys},
            **({"expert_speed": speeds} if set(speeds) == set(metadata["tasks"]) else {})}


def evaluate_tasks(policy: TrainedPolicy, reference: dict[str, Any], episodes_per_code: int = 20, *, seed: int = 0,
                   deterministic: bool = True, progress: bool = False) -> dict[str, Any]:
    """Roll every code out on every task; per-task figures of the matched code (``progress``: a bar of the
    episodes on stderr)."""
    tasks = list(reference["tasks"])
    k = max(policy.num_codes, 1)
    bar = progress_bar(len(tasks) * k * episodes_per_code, "evaluate (episodes)", progress)
    codes = np.repeat(np.arange(k), episodes_per_code)
    mask = policy.env.get("observation_mask")
    per_pair: dict[str, dict[str, dict[str, float]]] = {}
    progress = np.zeros((k, len(tasks)))
    speeds = []
    free = None
    for j, task in enumerate(tasks):
        roll = rollout_locomotion(policy, reference["tasks"][task], k * episodes_per_code, seed=seed,
                                  deterministic=deterministic, codes=codes, observation_mask=mask, bar=bar)
        speeds.append(roll["speed"])
        if free is None and not np.isnan(roll["displacement"]).any():
            free = free_sampling(roll, reference)
        for c in range(k):
            sel = codes == c
            s = task_scores(roll["returns"][sel].mean(), roll["displacement"][sel].mean(), reference, task)
            s["return_std"] = float(roll["returns"][sel].std())
            per_pair.setdefault(f"code{c}", {})[task] = s
            progress[c, j] = s["progress"]
    bar.close()
    assigned = match_codes(progress)
    per_task = {task: {"code": c, **per_pair[f"code{c}"][task]} for task, c in zip(tasks, assigned, strict=True)}
    summary = {f"min_{m}": min(per_task[t][m] for t in tasks) for m in ("normalised_return", "progress",
                                                                        "displacement_ratio")}
    behaviour = None
    if "expert_speed" in reference and not np.isnan(np.concatenate(speeds)).any():
        behaviour = speed_behaviour(np.concatenate(speeds), np.tile(codes, len(tasks)), reference["expert_speed"], k)
        for task, c in zip(tasks, assigned, strict=True):
            per_task[task]["on_task_share"] = behaviour[f"code{c}"]["shares"][task]
            per_task[task]["speed_error"] = abs(behaviour[f"code{c}"]["mean_speed"] - reference["expert_speed"][task])
        summary.update(min_on_task_share=min(per_task[t]["on_task_share"] for t in tasks),
                       max_speed_error=max(per_task[t]["speed_error"] for t in tasks))
    return {"tasks": per_task, "codes": per_pair, "num_codes": policy.num_codes, "episodes_per_code": episodes_per_code,
            "deterministic": deterministic, "seed": seed, **summary,
            **({} if behaviour is None else {"behaviour": behaviour}), **({} if free is None else {"free": free})}
