"""Environments, and the registry that says how pomil runs each family of them.

Three families, each declared once in :data:`FAMILIES` (Gymnasium's registry is
the model: an id maps to how to make it):

* ``circles``: the 2-D multi-modal POMDP (``pomil/Circles-v0``), its own batched simulator;
* ``hopper``: Hopper-v5 and its speed task ``pomil/HopperSpeed-v0`` on their fast batched MuJoCo
  simulator (:class:`pomil.envs.locomotion.HopperSim`);
* ``gymnasium``: any other Gymnasium id with 1-D Box spaces, N copies stepped in turn
  (:class:`pomil.envs.batch.GymSim`).

A family says how to build its batched simulator, its dimensions, the actions its
environment carries out, how a policy on it is evaluated (``circles``: mode metrics,
``tasks``: per-task scores, for demonstrations that name their tasks) and its
default number of latent codes.  Nothing outside ``envs/`` tests an environment id:
it asks :func:`env_family` (or the functions below, which do).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import gymnasium as gym
import torch

from pomil.envs import circles
from pomil.envs.batch import GymSim, check_box_spaces
from pomil.envs.circles import ENV_ID as CIRCLES_ID
from pomil.envs.locomotion import HOPPER_ID, HOPPER_SPEED_ID, HopperSim
from pomil.envs.locomotion import ends_on_failure as _gym_ends_on_failure
from pomil.envs.vec import BatchedEnv, TorchVecEnv
from pomil.envs.wrappers import check_indices

if CIRCLES_ID not in gym.registry:
    gym.register(id=CIRCLES_ID, entry_point="pomil.envs.circles:CirclesEnv")
if HOPPER_SPEED_ID not in gym.registry:
    gym.register(id=HOPPER_SPEED_ID, entry_point="pomil.envs.locomotion:HopperSpeedEnv", max_episode_steps=1000)

Executor = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class EnvFamily:
    """How pomil runs the environments of one family (see the module docstring).

    ``make(env_id, kwargs, num_envs, device, observation_mask, seed)`` -> the batched env;
    ``dims(env_id, kwargs)`` -> (obs_dim, act_dim) unmasked; ``state_dim(env_id, kwargs)``
    -> columns of the demonstrations' ``states``; ``executed_actions(env_id, kwargs)`` ->
    raw policy actions to the actions carried out; ``default_num_codes(metadata)`` ->
    the number of codes the demonstrations (their metadata) suggest, or None;
    ``ends_on_failure(env_id, kwargs)`` -> whether an episode ends when the agent fails."""

    name: str
    claims: Callable[[str], bool]
    make: Callable[..., Any]
    dims: Callable[[str, dict[str, Any]], tuple[int, int]]
    state_dim: Callable[[str, dict[str, Any]], int]
    executed_actions: Callable[[str, dict[str, Any]], Executor]
    evaluation: Literal["circles", "tasks"]
    default_num_codes: Callable[[dict[str, Any]], int | None] = lambda metadata: None
    ends_on_failure: Callable[[str, dict[str, Any]], bool] = lambda env_id, kwargs: False


# ------------------------------------------------------------------- circles
def _circles_make(env_id, env_kwargs, num_envs, *, device="cpu", observation_mask=None, seed=None):
    if observation_mask is not None:
        raise ValueError("the circles environment takes no observation mask (it observes positions only)")
    return circles.CirclesVecEnv(circles.CirclesSpec.from_dict(env_kwargs), num_envs, device)


def _circles_dims(env_id: str, env_kwargs: dict[str, Any]) -> tuple[int, int]:
    spec = circles.CirclesSpec.from_dict(env_kwargs)
    return spec.obs_dim, spec.act_dim


def _circles_executed(env_id: str, env_kwargs: dict[str, Any]) -> Executor:
    action_type = circles.CirclesSpec.from_dict(env_kwargs).action_type
    return lambda actions: circles.executed_actions(actions, action_type)


def _circles_codes(metadata: dict[str, Any]) -> int | None:
    modes = (metadata.get("env_kwargs") or {}).get("circles")
    return len(modes) if modes else None  # one code per circle (mode)


# ------------------------------------------------------- Gymnasium and Hopper
def _gym_dims(env_id: str, env_kwargs: dict[str, Any]) -> tuple[int, int]:
    env = gym.make(env_id, **env_kwargs)
    try:
        return check_box_spaces(env, env_id)
    finally:
        env.close()


def _hopper_make(env_id, env_kwargs, num_envs, *, device="cpu", observation_mask=None, seed=None):
    return TorchVecEnv(HopperSim(num_envs, env_kwargs, env_id=env_id), observation_mask, device, seed)


def _gym_make(env_id, env_kwargs, num_envs, *, device="cpu", observation_mask=None, seed=None):
    return TorchVecEnv(GymSim(env_id, num_envs, env_kwargs), observation_mask, device, seed)


def _gym_executed(env_id: str, env_kwargs: dict[str, Any]) -> Executor:
    """MuJoCo: controls clamped to the actuators' range (what MuJoCo applies); the identity elsewhere."""
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


def _full_observation(env_id: str, env_kwargs: dict[str, Any]) -> int:
    return _gym_dims(env_id, env_kwargs)[0]


FAMILIES: tuple[EnvFamily, ...] = (
    EnvFamily("circles", lambda env_id: env_id == CIRCLES_ID, _circles_make, _circles_dims,
              state_dim=lambda env_id, kwargs: 2,  # the positions
              executed_actions=_circles_executed, evaluation="circles", default_num_codes=_circles_codes),
    EnvFamily("hopper", lambda env_id: env_id in (HOPPER_ID, HOPPER_SPEED_ID), _hopper_make, _gym_dims,
              _full_observation, _gym_executed, evaluation="tasks", ends_on_failure=_gym_ends_on_failure),
    EnvFamily("gymnasium", lambda env_id: True, _gym_make, _gym_dims, _full_observation, _gym_executed,
              evaluation="tasks", ends_on_failure=_gym_ends_on_failure),
)
"""Every family; the first that claims an id runs it (the last claims every id)."""


def env_family(env_id: str) -> EnvFamily:
    """The family that runs ``env_id``."""
    return next(family for family in FAMILIES if family.claims(env_id))


def env_dims(env_id: str, env_kwargs: dict[str, Any], observation_mask: Sequence[int] | None = None) -> tuple[int, int]:
    """(obs_dim, act_dim) of a registered environment with Box spaces, as the
    learner sees it (``observation_mask``: indices of the observed entries).

    Raises ValueError/TypeError (or gymnasium's errors) for an unknown id or
    bad keyword arguments; callers turn those into user-facing errors.
    """
    obs_dim, act_dim = env_family(env_id).dims(env_id, env_kwargs)
    if observation_mask is not None:
        obs_dim = len(check_indices(observation_mask, obs_dim))
    return obs_dim, act_dim


def state_dim(env_id: str, env_kwargs: dict[str, Any]) -> int:
    """Columns of the demonstrations' ``states`` for an environment: the circles'
    positions (2), otherwise the full (unmasked) observation."""
    return env_family(env_id).state_dim(env_id, env_kwargs)


SIMS = ("cpu", "warp")
"""Physics a batched environment can run on: ``cpu`` (each family's own simulator, the default)
or ``warp`` (MuJoCo Warp on the torch device, :mod:`pomil.envs.warp`; the optional ``gpu`` extra)."""
SIM_HELP = ("physics of the training rollouts: cpu (MuJoCo on the CPU cores) or warp (MuJoCo Warp on --device, for "
            "Hopper, Walker2d and HalfCheetah; needs the gpu extra: pip install 'pomil[gpu]')")
"""The ``sim`` option's help, shared by every config that collects rollouts."""


def make_vec_env(env_id: str, env_kwargs: dict[str, Any], num_envs: int, *, device: Any = "cpu",
                 observation_mask: Sequence[int] | None = None, seed: int | None = None,
                 sim: str = "cpu") -> BatchedEnv:
    """The batched (torch) environment training uses for ``env_id``.

    ``reset() -> obs (N, d)``; ``step(actions) -> (obs, reward, terminated,
    truncated)``; one episode per copy between resets.  Circles and Hopper-v5
    have their own batched simulators; every other id runs N gymnasium copies
    (:class:`pomil.envs.batch.GymSim`).  ``sim="warp"`` runs the MuJoCo
    locomotion tasks that :data:`pomil.envs.warp.SPECS` lists as MuJoCo Warp
    worlds on ``device`` instead (ValueError for another id; PomilError when
    MuJoCo Warp is not installed).
    """
    if sim == "warp":
        from pomil.envs.warp import make_warp_vec_env

        return make_warp_vec_env(env_id, env_kwargs, num_envs, device=device, observation_mask=observation_mask,
                                 seed=seed)
    if sim != "cpu":
        raise ValueError(f"unknown sim {sim!r}; expected one of {list(SIMS)}")
    return env_family(env_id).make(env_id, env_kwargs, num_envs, device=device, observation_mask=observation_mask,
                                   seed=seed)


def executed_actions_fn(env_id: str, env_kwargs: dict[str, Any]) -> Executor:
    """Maps raw policy actions to the actions the environment carries out.

    Learners feed these to critics and posteriors and as the previous action,
    so that expert and policy actions are compared in the same form.  Circles:
    unit moving directions; MuJoCo: controls clamped to the actuators' range
    (what MuJoCo applies); the identity elsewhere.
    """
    return env_family(env_id).executed_actions(env_id, env_kwargs)


def evaluation_kind(env_id: str, metadata: dict[str, Any]) -> Literal["circles", "tasks"] | None:
    """How a policy on ``env_id`` trained on demonstrations with ``metadata`` is evaluated:
    ``circles`` (mode metrics), ``tasks`` (per-task scores: the demonstrations name their
    tasks, as ``pomil demos hopper`` and ``pomil demos merge`` record them) or None."""
    kind = env_family(env_id).evaluation
    return kind if kind != "tasks" or "tasks" in metadata else None


def default_num_codes(metadata: dict[str, Any]) -> int | None:
    """The number of latent codes the demonstrations' environment suggests (circles: one per circle)."""
    return env_family(str(metadata.get("env_id", ""))).default_num_codes(metadata)


def ends_on_failure(env_id: str, env_kwargs: dict[str, Any]) -> bool:
    """Whether ``env_id`` with keywords ``env_kwargs`` ends an episode when the agent fails
    (standard Hopper falls); the circles and the paper's Hopper setting never do."""
    return env_family(env_id).ends_on_failure(env_id, env_kwargs)
