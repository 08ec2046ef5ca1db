"""Environments: the 2-D circles POMDP, batched MuJoCo Hopper, and any Gymnasium
environment with 1-D Box spaces (:class:`pomil.envs.batch.GymSim`)."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import gymnasium as gym
import torch

from pomil.envs.circles import ENV_ID as CIRCLES_ID
from pomil.envs.locomotion import HOPPER_ID

if CIRCLES_ID not in gym.registry:
    gym.register(id=CIRCLES_ID, entry_point="pomil.envs.circles:CirclesEnv")


def env_dims(env_id: str, env_kwargs: dict[str, Any], observation_mask: Sequence[int] | None = None) -> tuple[int, int]:
    """(obs_dim, act_dim) of a registered environment with Box spaces, as the
    learner sees it (``observation_mask``: indices of the observed entries).

    Raises ValueError/TypeError (or gymnasium's errors) for an unknown id or
    bad keyword arguments; callers turn those into user-facing errors.
    """
    if env_id == CIRCLES_ID:
        from pomil.envs.circles import CirclesSpec

        spec = CirclesSpec.from_dict(env_kwargs)
        obs_dim, act_dim = spec.obs_dim, spec.act_dim
    else:
        from pomil.envs.batch import check_box_spaces

        env = gym.make(env_id, **env_kwargs)
        try:
            obs_dim, act_dim = check_box_spaces(env, env_id)
        finally:
            env.close()
    if observation_mask is not None:
        from pomil.envs.wrappers import check_indices

        obs_dim = len(check_indices(observation_mask, obs_dim))
    return obs_dim, act_dim


def state_dim(env_id: str, env_kwargs: dict[str, Any]) -> int:
    """Columns of the demonstrations' ``states`` for an environment: the circles'
    positions (2), otherwise the full (unmasked) observation."""
    return 2 if env_id == CIRCLES_ID else env_dims(env_id, env_kwargs)[0]


def make_vec_env(env_id: str, env_kwargs: dict[str, Any], num_envs: int, device: Any = "cpu",
                 observation_mask: Sequence[int] | None = None, seed: int | None = None):
    """The batched (torch) environment training uses for ``env_id``.

    ``reset() -> obs (N, d)``; ``step(actions) -> (obs, reward, terminated,
    truncated)``; one episode per copy between resets.  Circles and Hopper-v5
    have their own batched simulators; every other id runs N gymnasium copies
    (:class:`pomil.envs.batch.GymSim`).
    """
    if env_id == CIRCLES_ID:
        from pomil.envs.circles import CirclesSpec, CirclesVecEnv

        if observation_mask is not None:
            raise ValueError("the circles environment takes no observation mask (it observes positions only)")
        return CirclesVecEnv(CirclesSpec.from_dict(env_kwargs), num_envs, device)
    from pomil.envs.locomotion import HopperSim
    from pomil.envs.vec import TorchVecEnv

    if env_id == HOPPER_ID:
        return TorchVecEnv(HopperSim(num_envs, env_kwargs), observation_mask, device, seed)
    from pomil.envs.batch import GymSim

    return TorchVecEnv(GymSim(env_id, num_envs, env_kwargs), observation_mask, device, seed)


def executed_actions_fn(env_id: str, env_kwargs: dict[str, Any]) -> Callable[[torch.Tensor], torch.Tensor]:
    """Maps raw policy actions to the actions the environment carries out.

    Learners feed these to critics and posteriors and as the previous action,
    so that expert and policy actions are compared in the same form.  Circles:
    unit moving directions; MuJoCo: controls clamped to the actuators' range
    (what MuJoCo applies); the identity elsewhere.
    """
    if env_id == CIRCLES_ID:
        from pomil.envs.circles import CirclesSpec, executed_actions

        action_type = CirclesSpec.from_dict(env_kwargs).action_type
        return lambda actions: executed_actions(actions, action_type)
    env = gym.make(env_id, **env_kwargs)
    try:
        model = getattr(env.unwrapped, "model", None)
        if model is None or not hasattr(model, "actuator_ctrlrange"):
            return lambda actions: actions
        limited = torch.as_tensor(model.actuator_ctrllimited, dtype=torch.bool)
        inf = torch.full((model.nu,), float("inf"))
        lo = torch.where(limited, torch.as_tensor(model.actuator_ctrlrange[:, 0], dtype=torch.float32), -inf)
        hi = torch.where(limited, torch.as_tensor(model.actuator_ctrlrange[:, 1], dtype=torch.float32), inf)
    finally:
        env.close()
    return lambda actions: torch.maximum(torch.minimum(actions, hi.to(actions.device)), lo.to(actions.device))
