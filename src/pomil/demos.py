"""Scripted experts and recording their demonstrations."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch

from pomil.data import Demonstrations
from pomil.envs.circles import DEFAULT_EXPERT_NOISE, ENV_ID, CircleExperts, CirclesSpec, CirclesVecEnv
from pomil.envs.locomotion import HOPPER_ID, REWARD_KEYWORDS, task_name
from pomil.errors import PomilError


def record_circles_demos(spec: CirclesSpec, episodes: int, noise_std: float = DEFAULT_EXPERT_NOISE, *, seed: int = 0,
                         radius_range: tuple[float, float] | None = None) -> Demonstrations:
    """Equal numbers of episodes from every mode's expert, in shuffled order.

    Labels (the mode of each episode) and full states (positions) are kept for evaluation only.
    ``episodes`` must be a positive multiple of the number of modes so that the mix is exactly balanced.

    ``radius_range`` (r1, r2): each episode follows its mode's circle with a radius of its own,
    drawn uniformly in [r1, r2] (same tangent at the origin, same direction): demonstrations
    whose radius varies continuously, for continuous codes.  The radii are kept for evaluation
    only (metadata ``episode_radii``); the environment's circles (its diagnostic reward) stay
    those of ``spec``.
    """
    k = spec.num_modes
    if episodes < 1 or episodes % k:
        raise ValueError(f"episodes must be a positive multiple of the number of modes ({k}), got {episodes}")
    gen = torch.Generator().manual_seed(seed)
    modes = (torch.arange(episodes) % k)[torch.randperm(episodes, generator=gen)]
    env = CirclesVecEnv(spec, episodes)
    experts, expert_modes, radii = CircleExperts(spec, noise_std), modes, None
    if radius_range is not None:
        r1, r2 = radius_range
        if not (0 < r1 <= r2 and np.isfinite(r2)):
            raise ValueError(f"radius_range must be two radii 0 < r1 <= r2, got {radius_range}")
        radii = r1 + (r2 - r1) * torch.rand(episodes, generator=gen, dtype=torch.float64)
        own = tuple(spec.circles[int(m)].with_radius(float(r)) for m, r in zip(modes, radii, strict=True))
        experts, expert_modes = CircleExperts(replace(spec, circles=own), noise_std), torch.arange(episodes)
    obs = env.reset()
    observations, actions, states = [], [], []
    ret = torch.zeros(episodes)
    for _ in range(spec.episode_length):
        act = experts.act(env.positions, expert_modes, gen)
        observations.append(obs)
        states.append(env.positions.clone())
        actions.append(act)
        obs, reward, _, _ = env.step(act)
        ret += reward
    T = spec.episode_length
    # (T, E, d) time-major -> episode-major flat rows
    flat = lambda xs: torch.stack(xs, 1).reshape(episodes * T, -1).numpy()  # noqa: E731
    return Demonstrations(
        observations=flat(observations), actions=flat(actions),
        episode_bounds=torch.arange(0, episodes * T + 1, T).numpy(), labels=modes.numpy(), states=flat(states),
        metadata={
            "env_id": ENV_ID, "env_kwargs": spec.to_dict(), "observation_mask": None,
            "source": f"pomil scripted circle experts, noise_std={noise_std}, seed={seed}",
            "expert_returns": {str(m): float(ret[modes == m].mean()) for m in range(k)},
            "label_names": [f"mode{m}" for m in range(k)],
            **({} if radii is None else {"radius_range": [float(r1), float(r2)],
                                         "episode_radii": [round(float(r), 6) for r in radii]}),
        },
    )


def record_expert_demos(expert_path: str, episodes: int, task: str | None = None,
                        *, observation_mask: str | list[int] | None = "positions-only", seed: int = 0,
                        reset_seed: int | None = None, reference_episodes: int = 100,
                        action_noise: float = 0.0, progress: bool = False) -> Demonstrations:
    """``episodes`` deterministic episodes of one expert checkpoint on its own
    environment (id and keywords from the checkpoint), labelled ``task``.

    Observations are what the learner sees (``observation_mask``: a preset, a
    list of indices, or None for everything); ``states`` keep the full
    observation, for evaluation only.  The metadata carry the task's
    evaluation reference: its environment keywords, the expert's mean return,
    displacement and speed (MuJoCo: m/s over each episode), and the mean return
    of zero actions.  ``reset_seed``
    (default ``seed``) seeds the environments' reset noise, ``seed`` the expert.

    ``action_noise`` > 0 records demonstrations with recoveries (DART, Laskey et al. 2017): the
    environment carries out the expert's action plus N(0, action_noise^2) noise per dimension,
    and the expert's own (noise-free) action is recorded, so the episodes visit states off the
    expert's path and show how the expert acts there.  The expert returns in the metadata are
    those of the noisy episodes.  ``progress``: a bar of the recorded episodes on stderr.
    """
    from pomil.api import TrainedPolicy
    from pomil.training import progress_bar

    expert = TrainedPolicy.load(expert_path)
    if expert.env.get("id") == ENV_ID:
        raise PomilError(f"{expert_path}: circle policies are recorded with `pomil demos circles`")
    with progress_bar(episodes, "record (episodes)", progress) as bar:
        return _record_policy(expert, expert_path, dict(expert.env.get("kwargs") or {}), episodes=episodes,
                              task=task or task_name(expert.env.get("kwargs") or {}),
                              observation_mask=observation_mask, seed=seed,
                              reset_seed=seed if reset_seed is None else reset_seed,
                              reference_episodes=reference_episodes, action_noise=action_noise, bar=bar)


def _record_policy(expert, expert_path: str, kwargs: dict, *, episodes: int, task: str, observation_mask,
                   seed: int, reset_seed: int, reference_episodes: int, action_noise: float = 0.0,
                   bar: Any | None = None) -> Demonstrations:
    from pomil.envs import make_vec_env
    from pomil.envs.wrappers import resolve_observation_mask
    from pomil.training import EpisodeProgress

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not (np.isfinite(action_noise) and action_noise >= 0):
        raise ValueError(f"action_noise must be a standard deviation >= 0, got {action_noise}")
    noise = np.random.default_rng([seed, 1]) if action_noise > 0 else None
    env_id = expert.env["id"]
    mask = resolve_observation_mask(env_id, kwargs, observation_mask)
    expert_mask = expert.env.get("observation_mask")
    sim = make_vec_env(env_id, kwargs, episodes, device="cpu").sim
    full = sim.reset(reset_seed)
    x0 = x_position(sim)
    expert.reset(episodes, seed=seed)
    rec_obs, rec_act, ret, length = [], [], np.zeros(episodes), np.zeros(episodes, dtype=np.int64)
    tick = EpisodeProgress(bar)
    while not sim.done.all():
        alive = ~sim.done
        seen = full if expert_mask is None else full[:, expert_mask]
        act = expert.act(seen.astype(np.float32), deterministic=True)
        rec_obs.append(full.copy())
        rec_act.append(act)
        executed = act.astype(np.float64)
        if noise is not None:  # DART: carry out a perturbed action, record the expert's
            executed = executed + action_noise * noise.standard_normal(executed.shape)
        full, r, _, _ = sim.step(executed)
        ret += r
        length += alive
        tick(sim.done)
    displacement = x_position(sim) - x0
    speed = displacement / (np.maximum(length, 1) * getattr(sim, "dt", np.nan))  # mean x speed per episode, m/s
    sim.close()
    obs_t, act_t = np.stack(rec_obs, 1), np.stack(rec_act, 1)  # (E, T, d)
    full_obs = np.concatenate([obs_t[e, :length[e]] for e in range(episodes)]).astype(np.float32)
    direction = float(np.sign(kwargs.get("forward_reward_weight", 1.0)))
    return Demonstrations(
        observations=full_obs if mask is None else full_obs[:, mask],
        actions=np.concatenate([act_t[e, :length[e]] for e in range(episodes)]).astype(np.float32),
        episode_bounds=np.concatenate([[0], np.cumsum(length)]).astype(np.int64),
        labels=np.zeros(episodes, dtype=np.int64), states=full_obs,
        metadata={
            "env_id": env_id, "env_kwargs": kwargs, "observation_mask": mask,
            "source": f"pomil expert {expert_path}, deterministic, seed={seed}"
                      + (f", executed with N(0, {action_noise:g}^2) action noise (DART)" if action_noise else ""),
            "label_names": [task],
            "tasks": {task: kwargs},
            "expert_returns": {task: float(ret.mean())},
            "expert_displacement": {task: float(direction * displacement.mean())},
            **({} if np.isnan(speed).any() else {"expert_speed": {task: float(speed.mean())}}),
            "still_returns": {task: _zero_action_return(env_id, kwargs, reference_episodes, seed)},
        },
    )


def x_position(sim) -> np.ndarray:
    """The torso x position of every environment of a MuJoCo simulator; NaN elsewhere."""
    try:
        return sim.x_position
    except AttributeError:  # not MuJoCo: no displacement
        return np.full(sim.num_envs, np.nan)


def _is_reward_term(key: str) -> bool:
    """Constructor keywords that change the reward only (gymnasium's MuJoCo naming, and pomil's own)."""
    return key.endswith(("_weight", "_reward")) or key in REWARD_KEYWORDS


def _check_mergeable(sources: list[Demonstrations], names: list[str]) -> None:
    """ValueError unless every source shares the first's environment id, observation mask, sizes, kind of
    states and environment keywords but reward terms."""
    first = sources[0].metadata
    for name, d in zip(names, sources, strict=True):
        md = d.metadata
        for key in ("env_id", "observation_mask"):
            if md.get(key) != first.get(key):
                raise ValueError(f"{name}: metadata.{key} is {md.get(key)!r}, expected {first.get(key)!r} as in "
                                 f"{names[0]}")
        if (d.obs_dim, d.act_dim) != (sources[0].obs_dim, sources[0].act_dim):
            raise ValueError(f"{name}: obs/act dims {(d.obs_dim, d.act_dim)} differ from {names[0]}'s "
                             f"{(sources[0].obs_dim, sources[0].act_dim)}")
        a, b = md.get("env_kwargs") or {}, first.get("env_kwargs") or {}
        differ = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k) and not _is_reward_term(k))
        if differ:
            raise ValueError(f"{name}: metadata.env_kwargs differ from {names[0]}'s in {differ}; only reward terms may "
                             "differ")
        if (d.states is None) != (sources[0].states is None):
            raise ValueError(f"{name}: some files have full states and some not")


def _episodes_to_take(sources: list[Demonstrations], p: np.ndarray, episodes: int | None,
                      names: list[str]) -> np.ndarray:
    """Episodes taken from each source: proportions ``p`` of ``episodes``, or of as many as the sources allow."""
    available = np.array([d.num_episodes for d in sources])
    total = int(np.floor(min(available[p > 0] / p[p > 0]))) if episodes is None else int(episodes)
    take = np.floor(p * total + 1e-9).astype(np.int64)
    if np.any(take > available):
        i = int(np.argmax(take - available))
        raise ValueError(f"{names[i]}: {take[i]} episodes requested, it has {available[i]}")
    if take.sum() < 1:
        raise ValueError("the merge would hold no episodes")
    return take


def _merge_task_metadata(merged: dict[str, dict], weight: dict[str, int], metadata: dict, *, n: int, name: str) -> None:
    """Add one source's per-task metadata (``n`` episodes taken) to ``merged``: its tasks' environment keywords
    (which must agree between files), and each figure as an episode-weighted mean over the files holding the task."""
    for key, table in merged.items():
        for task, value in (metadata.get(key) or {}).items():
            if key == "tasks":
                if task in table and table[task] != value:
                    raise ValueError(f"{name}: task {task!r} has environment keywords {value}, another file "
                                     f"{table[task]}")
                table[task] = value
            else:
                w = weight.get(f"{key}/{task}", 0)
                table[task] = (table.get(task, 0.0) * w + float(value) * n) / (w + n)
                weight[f"{key}/{task}"] = w + n


def merge_demos(sources: list[Demonstrations], proportions: list[float] | None = None, episodes: int | None = None,
                *, seed: int = 0, names: list[str] | None = None) -> Demonstrations:
    """One unlabeled training set from recordings of several experts / tasks.

    Episodes are taken from the sources in ``proportions`` (default: equal) -- as many as the sources allow,
    or ``episodes`` in total -- and shuffled.  Labels (evaluation only) follow the sources' label names, so the
    same task in two files keeps one label.  The sources must share environment id, observation mask and
    sizes, and their environment keywords may differ only in reward terms (``*_weight``, ``*_reward``,
    ``target_velocity``): the learner trains in the first source's environment, whose dynamics they all share.
    """
    if not sources:
        raise ValueError("merge needs at least one demonstrations file")
    names = names or [f"source {i}" for i in range(len(sources))]
    p = np.ones(len(sources)) if proportions is None else np.asarray(proportions, dtype=np.float64)
    if p.shape != (len(sources),) or np.any(~np.isfinite(p)) or np.any(p < 0) or p.sum() <= 0:
        raise ValueError(f"proportions: expected {len(sources)} non-negative numbers (one per file), got {proportions}")
    p = p / p.sum()
    _check_mergeable(sources, names)
    take = _episodes_to_take(sources, p, episodes, names)
    rng = np.random.default_rng(seed)
    label_names: list[str] = []
    merged_md: dict[str, dict] = {k: {} for k in ("tasks", "expert_returns", "expert_displacement", "expert_speed",
                                                  "still_returns")}
    weight: dict[str, int] = {}
    parts, labels = [], []
    for d, n, name in zip(sources, take, names, strict=True):
        if n == 0:
            continue
        # all episodes in order when a source is used whole, else a random subset
        chosen = (np.arange(d.num_episodes) if n == d.num_episodes
                  else np.sort(rng.choice(d.num_episodes, n, replace=False)))
        own = d.metadata.get("label_names") or []
        for lab in (d.labels[chosen] if d.labels is not None else np.zeros(n, dtype=np.int64)).tolist():
            label = own[lab] if lab < len(own) else f"{name} label {lab}"
            if label not in label_names:  # one label per task across files
                label_names.append(label)
            labels.append(label_names.index(label))
        parts.append(d.subset(chosen))
        _merge_task_metadata(merged_md, weight, d.metadata, n=int(n), name=name)
    metadata = {**sources[0].metadata, **{k: v for k, v in merged_md.items() if v}, "label_names": label_names,
                "source": "merge of " + "; ".join(f"{n} episodes of {name}"
                                                  for name, n in zip(names, take, strict=True)),
                "merged_from": [{"file": name, "episodes": int(n), "source": d.metadata.get("source")}
                                for d, n, name in zip(sources, take, names, strict=True)]}
    pooled = Demonstrations(np.concatenate([p.observations for p in parts]),
                            np.concatenate([p.actions for p in parts]),
                            np.concatenate([[0], np.cumsum(np.concatenate([p.episode_lengths for p in parts]))]),
                            np.asarray(labels, dtype=np.int64),
                            None if parts[0].states is None else np.concatenate([p.states for p in parts]), metadata)
    return pooled.subset(rng.permutation(len(labels)))


def record_hopper_demos(experts: dict[str, str], episodes_per_task: int, setting: str = "paper", *, seed: int = 0,
                        observation_mask: str | list[int] = "positions-only",
                        reference_episodes: int = 100, action_noise: float = 0.0,
                        progress: bool = False) -> Demonstrations:
    """Equal numbers of episodes from each Hopper task's expert (checkpoint paths
    by task name), shuffled: :func:`record_expert_demos` in the task's
    ``setting`` for each (``action_noise``: its DART recording), then :func:`merge_demos`
    (``progress``: a bar of the recorded episodes on stderr)."""
    from pomil.api import TrainedPolicy
    from pomil.envs.locomotion import hopper_kwargs
    from pomil.training import progress_bar

    recordings = []
    bar = progress_bar(episodes_per_task * len(experts), "record (episodes)", progress)
    for j, (task, path) in enumerate(experts.items()):
        expert = TrainedPolicy.load(path)
        if expert.obs_dim != 11 or expert.env.get("id") != HOPPER_ID:
            raise PomilError(f"{path}: expected a Hopper expert on the full 11-number observation, got obs_dim "
                             f"{expert.obs_dim}")
        recordings.append(_record_policy(expert, path, hopper_kwargs(task, setting), episodes=episodes_per_task,
                                         task=task, observation_mask=observation_mask, seed=seed,
                                         reset_seed=seed + 1000 * j, reference_episodes=reference_episodes,
                                         action_noise=action_noise, bar=bar))
    bar.close()
    demos = merge_demos(recordings, seed=seed, names=list(experts.values()))
    return replace(demos, metadata={**demos.metadata, "setting": setting})


def _zero_action_return(env_id: str, env_kwargs: dict, episodes: int, seed: int) -> float:
    from pomil.envs import make_vec_env

    sim = make_vec_env(env_id, env_kwargs, episodes, device="cpu").sim
    sim.reset(seed)
    ret = np.zeros(episodes)
    while not sim.done.all():
        ret += sim.step(np.zeros((episodes, sim.act_dim)))[1]
    sim.close()
    return float(ret.mean())
