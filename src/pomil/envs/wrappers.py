"""Partial observability as a wrapper: keep some entries of a Box observation.

:class:`ObservationMask` works on any Gymnasium environment with a 1-D Box
observation.  :func:`resolve_observation_mask` turns a mask given by the user
(a list of indices, or a named preset) into indices for one environment.

Presets:

* ``positions-only`` -- MuJoCo locomotion tasks (Hopper, Walker2d,
  HalfCheetah, Ant, ...): keep the joint positions and angles (the qpos part
  of the observation, as its ``observation_structure`` says), drop the
  velocities and everything after them.  On Hopper-v5 that is qpos[1:]:
  height and 4 angles, 5 numbers (the paper's observation).
* ``velocities`` -- the same tasks: keep the velocities alone (the qvel part),
  drop the positions and angles.  On Hopper-v5 that is qvel: 6 numbers,
  from which posture must be integrated over time (pomdp-baselines'
  Hopper-V, where memory decides).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

PRESETS = ("positions-only", "velocities")


class ObservationMask(gym.ObservationWrapper):
    """Observe ``obs[indices]`` of the wrapped environment.

    >>> env = ObservationMask(gym.make("Pendulum-v1"), [0, 1])   # cos, sin; no angular velocity
    >>> env.observation_space.shape
    (2,)
    """

    def __init__(self, env: gym.Env, indices: Sequence[int]) -> None:
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise ValueError(f"ObservationMask needs a 1-D Box observation space, got {space}")
        self.indices = check_indices(indices, space.shape[0])
        self.observation_space = gym.spaces.Box(space.low[self.indices], space.high[self.indices], dtype=space.dtype)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return observation[self.indices]


def parse_mask(text: str) -> str | list[int] | None:
    """A mask as the user writes it: '' (observe everything), a preset name, or '0,1,2'."""
    text = text.strip()
    if not text:
        return None
    if text in PRESETS:
        return text
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"observation mask: expected one of {list(PRESETS)} or comma-separated integers, "
                         f"got {text!r}") from None


def check_indices(indices: Sequence[int], obs_dim: int) -> np.ndarray:
    idx = np.asarray(list(indices))
    if idx.ndim != 1 or len(idx) == 0 or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"observation mask must be a non-empty list of integer indices, got {list(indices)!r}")
    if idx.min() < 0 or idx.max() >= obs_dim:
        raise ValueError(f"observation mask indices must lie in [0, {obs_dim}), got {idx.tolist()}")
    if len(set(idx.tolist())) != len(idx):
        raise ValueError(f"observation mask indices must be distinct, got {idx.tolist()}")
    return idx.astype(np.int64)


def resolve_observation_mask(env_id: str, env_kwargs: dict[str, Any],
                             mask: str | Sequence[int] | None) -> list[int] | None:
    """Indices into ``env_id``'s observation for a preset name or an index list (None: no mask)."""
    if mask is None:
        return None
    env = gym.make(env_id, **env_kwargs)
    try:
        obs_dim = int(env.observation_space.shape[0])
        if isinstance(mask, str):
            if mask not in PRESETS:
                raise ValueError(f"unknown observation mask preset {mask!r}; expected a list of indices or one of "
                                 f"{list(PRESETS)}")
            structure = getattr(env.unwrapped, "observation_structure", None)
            if not isinstance(structure, dict) or "qpos" not in structure or "qvel" not in structure:
                raise ValueError(f"observation mask {mask!r} needs a MuJoCo locomotion environment "
                                 f"(with an observation_structure), {env_id!r} has none")
            # MuJoCo locomotion observations begin with the kept qpos entries, then the qvel ones.
            n_pos, n_vel = int(structure["qpos"]), int(structure["qvel"])
            return list(range(n_pos)) if mask == "positions-only" else list(range(n_pos, n_pos + n_vel))
        return check_indices(mask, obs_dim).tolist()
    finally:
        env.close()
