"""Environments: the 2-D circles POMDP (and, later, MuJoCo tasks)."""

from __future__ import annotations

from typing import Any, Callable

import gymnasium as gym
import torch

from pomil.envs.circles import ENV_ID as CIRCLES_ID

if CIRCLES_ID not in gym.registry:
    gym.register(id=CIRCLES_ID, entry_point="pomil.envs.circles:CirclesEnv")


def env_dims(env_id: str, env_kwargs: dict[str, Any]) -> tuple[int, int]:
    """(obs_dim, act_dim) of a registered environment with Box spaces.

    Raises ValueError/TypeError (or gymnasium's errors) for an unknown id or
    bad keyword arguments; callers turn those into user-facing errors.
    """
    if env_id == CIRCLES_ID:
        from pomil.envs.circles import CirclesSpec

        spec = CirclesSpec.from_dict(env_kwargs)
        return spec.obs_dim, spec.act_dim
    env = gym.make(env_id, **env_kwargs)
    try:
        return int(env.observation_space.shape[0]), int(env.action_space.shape[0])
    finally:
        env.close()


def make_vec_env(env_id: str, env_kwargs: dict[str, Any], num_envs: int, device: Any = "cpu"):
    """The batched (torch) environment training uses for ``env_id``."""
    if env_id == CIRCLES_ID:
        from pomil.envs.circles import CirclesSpec, CirclesVecEnv

        return CirclesVecEnv(CirclesSpec.from_dict(env_kwargs), num_envs, device)
    raise ValueError(f"no batched environment for {env_id!r} yet (supported: {CIRCLES_ID})")


def executed_actions_fn(env_id: str, env_kwargs: dict[str, Any]) -> Callable[[torch.Tensor], torch.Tensor]:
    """Maps raw policy actions to the actions the environment carries out.

    Learners feed these to critics and posteriors and as the previous action,
    so that expert and policy actions are compared in the same form.  The
    identity where an environment uses its actions as given.
    """
    if env_id == CIRCLES_ID:
        from pomil.envs.circles import CirclesSpec, executed_actions

        action_type = CirclesSpec.from_dict(env_kwargs).action_type
        return lambda actions: executed_actions(actions, action_type)
    return lambda actions: actions
