"""Any Gymnasium environment as a batched NumPy simulator.

:class:`GymSim` steps N copies of ``gymnasium.make(env_id, **kwargs)`` one
after another, behind the interface of :class:`pomil.envs.locomotion.HopperSim`
(one episode per copy between resets, ended copies frozen with reward 0), so
that every training loop runs on any environment with 1-D Box observation and
action spaces.  It is the general path: Hopper has a faster dedicated
simulator, this one costs gymnasium's per-step overhead (see
``benchmarks/hopper_speed.py`` for the ratio).
"""

from __future__ import annotations

import sys
from typing import Any

import gymnasium as gym
import numpy as np

from pomil.envs.vec import SimCopies


def mujoco_warnings_once() -> None:
    """Show each distinct MuJoCo warning once per process (MuJoCo prints one per model load: gymnasium's
    HalfCheetah gives one for each of N copies, every run).  Installed only where no hook is set yet
    (``mujoco.set_mju_user_warning``); nothing happens without MuJoCo."""
    try:
        import mujoco
    except ImportError:
        return
    if mujoco.get_mju_user_warning() is not None:
        return
    seen: set[str] = set()

    def warn(message: str) -> None:
        if message not in seen:
            seen.add(message)
            print(f"WARNING (MuJoCo; repeats of it are not shown): {message}", file=sys.stderr, flush=True)

    mujoco.set_mju_user_warning(warn)


def check_box_spaces(env: gym.Env, env_id: str) -> tuple[int, int]:
    """(obs_dim, act_dim) of an environment with 1-D Box spaces; ValueError otherwise."""
    for name, space in (("observation", env.observation_space), ("action", env.action_space)):
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise ValueError(f"{env_id} has a {name} space {space}; pomil needs 1-D Box observation and action spaces")
    return int(env.observation_space.shape[0]), int(env.action_space.shape[0])


class GymSim(SimCopies):
    """N copies of a Gymnasium environment, NumPy in and out.

    ``reset(seed) -> obs (N, obs_dim)`` (copy i seeded ``seed + i``, as
    gymnasium's vector envs do; ``None`` continues each copy's generator);
    ``step(actions (N, act_dim)) -> (obs, reward, terminated, truncated)``.
    A copy whose episode ended keeps its last observation and yields reward 0
    until the next ``reset``; ``done`` says which copies ended.
    """

    def __init__(self, env_id: str, num_envs: int, env_kwargs: dict[str, Any] | None = None) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.env_id = env_id
        mujoco_warnings_once()
        self.envs = [gym.make(env_id, **(env_kwargs or {})) for _ in range(num_envs)]
        self.obs_dim, self.act_dim = check_box_spaces(self.envs[0], env_id)
        self.num_envs = num_envs
        self._act_dtype = self.envs[0].action_space.dtype
        self.obs = np.zeros((num_envs, self.obs_dim))
        self.done = np.ones(num_envs, dtype=bool)

    @property
    def _rngs(self) -> list[np.random.Generator]:
        return [env.unwrapped.np_random for env in self.envs]

    def reset(self, seed: int | None = None) -> np.ndarray:
        for i, env in enumerate(self.envs):
            self.obs[i], _ = env.reset(seed=None if seed is None else seed + i)
        self.done[:] = False
        return self.obs.copy()

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        actions = np.asarray(actions)
        self._check_step(actions)
        reward = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        for i in np.flatnonzero(~self.done):
            step = self.envs[i].step(actions[i].astype(self._act_dtype))
            self.obs[i], reward[i], terminated[i], truncated[i], _ = step
        self.done |= terminated | truncated
        return self.obs.copy(), reward, terminated, truncated

    @property
    def dt(self) -> float:
        """Seconds per step (MuJoCo environments; AttributeError elsewhere)."""
        dt = getattr(self.envs[0].unwrapped, "dt", None)
        if dt is None:
            raise AttributeError(f"{self.env_id} has no time step (dt)")
        return float(dt)

    @property
    def x_position(self) -> np.ndarray:
        """qpos[0] of every copy (the torso's x on MuJoCo locomotion tasks)."""
        data = getattr(self.envs[0].unwrapped, "data", None)
        if data is None or not hasattr(data, "qpos"):
            raise AttributeError(f"{self.env_id} is not a MuJoCo environment: it has no x position")
        return np.array([float(env.unwrapped.data.qpos[0]) for env in self.envs])

    def close(self) -> None:
        for env in self.envs:
            env.close()
