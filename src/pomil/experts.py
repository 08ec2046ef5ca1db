"""Scripted experts and recording their demonstrations."""

from __future__ import annotations

import numpy as np
import torch

from pomil.data import Demonstrations
from pomil.envs.circles import CircleExperts, CirclesSpec, CirclesVecEnv, ENV_ID, DEFAULT_EXPERT_NOISE
from pomil.envs.locomotion import TASKS, HopperSim
from pomil.errors import PomilError


def record_circles_demos(
    spec: CirclesSpec, episodes: int, noise_std: float = DEFAULT_EXPERT_NOISE, seed: int = 0
) -> Demonstrations:
    """Equal numbers of episodes from every mode's expert, in shuffled order.

    Labels (the mode of each episode) and full states (positions) are kept for
    evaluation only.  ``episodes`` must be a positive multiple of the number
    of modes so that the mix is exactly balanced.
    """
    k = spec.num_modes
    if episodes < 1 or episodes % k:
        raise ValueError(f"episodes must be a positive multiple of the number of modes ({k}), got {episodes}")
    gen = torch.Generator().manual_seed(seed)
    modes = (torch.arange(episodes) % k)[torch.randperm(episodes, generator=gen)]
    env = CirclesVecEnv(spec, episodes)
    experts = CircleExperts(spec, noise_std)
    obs = env.reset()
    observations, actions, states = [], [], []
    ret = torch.zeros(episodes)
    for _ in range(spec.episode_length):
        act = experts.act(env.positions, modes, gen)
        observations.append(obs)
        states.append(env.positions.clone())
        actions.append(act)
        obs, reward, _, _ = env.step(act)
        ret += reward
    T = spec.episode_length
    # (T, E, d) time-major -> episode-major flat rows
    flat = lambda xs: torch.stack(xs, 1).reshape(episodes * T, -1).numpy()  # noqa: E731
    expert_returns = {str(m): float(ret[modes == m].mean()) for m in range(k)}
    return Demonstrations(
        observations=flat(observations),
        actions=flat(actions),
        episode_bounds=torch.arange(0, episodes * T + 1, T).numpy(),
        labels=modes.numpy(),
        states=flat(states),
        metadata={
            "env_id": ENV_ID,
            "env_kwargs": spec.to_dict(),
            "observation_mask": None,
            "source": f"pomil scripted circle experts, noise_std={noise_std}, seed={seed}",
            "expert_returns": expert_returns,
            "label_names": [f"mode{m}" for m in range(k)],
        },
    )


def record_hopper_demos(experts: dict[str, str], episodes_per_task: int, setting: str = "paper", seed: int = 0,
                        observation_mask: str | list[int] = "positions-only", reference_episodes: int = 100) -> Demonstrations:
    """Equal numbers of episodes from each task's expert (checkpoint paths by task
    name), shuffled; the experts act deterministically on the full observation.

    Observations are what the learner sees (``observation_mask``); ``states``
    keep the full observation and ``labels`` the task, for evaluation only.  The
    metadata carry each task's environment keywords and the evaluation
    reference: expert return and displacement (over the recorded episodes) and
    the return of zero actions (over ``reference_episodes`` episodes).
    """
    from pomil.api import TrainedPolicy
    from pomil.envs.locomotion import HOPPER_ID, hopper_kwargs
    from pomil.envs.wrappers import resolve_observation_mask

    if episodes_per_task < 1:
        raise ValueError(f"episodes_per_task must be >= 1, got {episodes_per_task}")
    tasks = list(experts)
    kwargs = {t: hopper_kwargs(t, setting) for t in tasks}
    mask = resolve_observation_mask(HOPPER_ID, kwargs[tasks[0]], observation_mask)
    states_all, acts_all, labels, lengths = [], [], [], []
    ref: dict[str, dict[str, float]] = {"expert_returns": {}, "expert_displacement": {}, "still_returns": {}}
    for j, task in enumerate(tasks):
        expert = TrainedPolicy.load(experts[task])
        if expert.obs_dim != 11:
            raise PomilError(f"{experts[task]}: expected a Hopper expert on the full 11-number observation, got obs_dim {expert.obs_dim}")
        sim = HopperSim(episodes_per_task, kwargs[task])
        full = sim.reset(seed + 1000 * j)
        x0 = sim.x_position
        expert.reset(episodes_per_task, seed=seed)
        rec_obs, rec_act, ret, length = [], [], np.zeros(episodes_per_task), np.zeros(episodes_per_task, dtype=np.int64)
        while not sim.done.all():
            alive = ~sim.done
            act = expert.act(full.astype(np.float32), deterministic=True)
            rec_obs.append(full.copy())
            rec_act.append(act)
            full, r, _, _ = sim.step(act.astype(np.float64))
            ret += r
            length += alive
        sim.close()
        ref["expert_returns"][task] = float(ret.mean())
        ref["expert_displacement"][task] = float(np.sign(TASKS[task]) * (sim.x_position - x0).mean())
        ref["still_returns"][task] = _zero_action_return(kwargs[task], reference_episodes, seed)
        obs_t, act_t = np.stack(rec_obs, 1), np.stack(rec_act, 1)  # (E, T, d)
        for e in range(episodes_per_task):
            states_all.append(obs_t[e, :length[e]])
            acts_all.append(act_t[e, :length[e]])
            labels.append(j)
            lengths.append(int(length[e]))
    order = np.random.default_rng(seed).permutation(len(labels))
    states = [states_all[i] for i in order]
    bounds = np.concatenate([[0], np.cumsum([lengths[i] for i in order])])
    full_obs = np.concatenate(states).astype(np.float32)
    return Demonstrations(
        observations=full_obs[:, mask],
        actions=np.concatenate([acts_all[i] for i in order]).astype(np.float32),
        episode_bounds=bounds.astype(np.int64),
        labels=np.asarray(labels, dtype=np.int64)[order],
        states=full_obs,
        metadata={
            "env_id": HOPPER_ID,
            "env_kwargs": kwargs[tasks[0]],
            "observation_mask": mask,
            "setting": setting,
            "source": f"pomil PPO experts {experts}, deterministic, seed={seed}",
            "label_names": tasks,
            "tasks": kwargs,
            **ref,
        },
    )


def _zero_action_return(env_kwargs: dict, episodes: int, seed: int) -> float:
    sim = HopperSim(episodes, env_kwargs)
    sim.reset(seed)
    ret = np.zeros(episodes)
    while not sim.done.all():
        ret += sim.step(np.zeros((episodes, sim.act_dim)))[1]
    sim.close()
    return float(ret.mean())
