"""Scripted experts and recording their demonstrations."""

from __future__ import annotations

import torch

from pomil.data import Demonstrations
from pomil.envs.circles import CircleExperts, CirclesSpec, CirclesVecEnv, ENV_ID, DEFAULT_EXPERT_NOISE


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
