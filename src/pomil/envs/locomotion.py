"""Batched MuJoCo Hopper: N copies of gymnasium's Hopper-v5 stepped with MuJoCo directly.

Gymnasium's vector environments spend most of their time outside the physics.
:class:`HopperSim` keeps one ``MjData`` per copy and steps them from a small
thread pool (MuJoCo releases the GIL while it steps), with observations,
rewards, health checks and resets computed for all copies at once in NumPy.

It is the same environment as ``gymnasium.make("Hopper-v5", **kwargs)``,
number for number: the same model file, frame skip, reset noise drawn from
the same per-copy generators (copy i seeded with ``seed + i``, as gymnasium's
vector envs do), the same reward terms (the control cost on the action as
given; MuJoCo clamps the control to its range), the same health test and the
same time limit.  ``tests/envs/test_locomotion.py`` checks it against
gymnasium step by step.

Tasks (the paper's Hopper experiment) are constructor keywords:
``forward_reward_weight`` +1 (forward) or -1 (backward), ``ctrl_cost_weight``
1e-3.  Settings: ``paper`` = 128-step episodes that never terminate (the
paper's code); ``standard`` = Hopper-v5's own 1000 steps, ending when
unhealthy.

Speed tasks (``pomil/HopperSpeed-v0``, :class:`HopperSpeedEnv`): Hopper-v5's
dynamics with the forward term replaced by ``-forward_reward_weight * |v_x -
target_velocity|``, so an expert is paid for hopping forward at one speed.
The same keywords as Hopper-v5 plus ``target_velocity`` (m/s), a reward term
only: recordings at several target speeds merge into one training set.
"""

from __future__ import annotations

import importlib.resources
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from gymnasium.envs.mujoco.hopper_v5 import HopperEnv
from gymnasium.utils.seeding import np_random

from pomil.envs.vec import SimCopies
from pomil.parallel import usable_cpus

HOPPER_ID = "Hopper-v5"
HOPPER_SPEED_ID = "pomil/HopperSpeed-v0"
REWARD_KEYWORDS = ("target_velocity",)
"""Constructor keywords that change only the reward, beyond gymnasium's ``*_weight`` / ``*_reward``
naming (recordings that differ in them share dynamics and can be merged)."""
TASKS = {"forward": 1.0, "backward": -1.0}
SETTINGS = {
    "paper": {"terminate_when_unhealthy": False, "max_episode_steps": 128},
    "standard": {"terminate_when_unhealthy": True, "max_episode_steps": 1000},
}
SHIPPED_EXPERTS = Path(str(importlib.resources.files("pomil") / "experts"))
"""The experts shipped inside the package (``pomil/experts/NAME.pt``, policy and observation normaliser, with their
training metrics and evaluation), found wherever pomil is installed."""
HOPPER_EXPERTS = {
    setting: {task: str(SHIPPED_EXPERTS / f"hopper{'' if setting == 'paper' else '-' + setting}-{task}.pt")
              for task in ("forward", "backward")}
    for setting in ("paper", "standard")}
"""Per setting, the shipped Hopper experts: the paper setting's never learned to stay healthy past 128 steps, so
the standard setting has experts of its own."""
DEMO_EPISODES = {"paper": 200, "standard": 100}
"""Per setting, the demonstration episodes per task recorded by default (``pomil demos hopper --episodes``,
the hopper and hopper-standard specs' recipes): what the committed results were measured on (the standard
setting's episodes are up to 1000 steps, against the paper's 128)."""
DEMO_ACTION_NOISE = {"paper": 0.0, "standard": 0.1}
"""Per setting, the DART action noise (``pomil demos hopper --action-noise``) its demonstrations are recorded with
by default: the standard setting's episodes end when the hopper falls, and demonstrations that show recoveries
keep its clones up (docs/hopper.md); 0.1 is the largest noise measured that leaves the experts' returns as they
were."""


def demo_recording(setting: str, episodes: int, action_noise: float,
                   names: tuple[str, str] = ("episodes", "action_noise")) -> tuple[int, float]:
    """Episodes per task and DART action noise for recording ``setting``'s demonstrations: -1 (either) is the
    setting's (:data:`DEMO_EPISODES`, :data:`DEMO_ACTION_NOISE`).  ValueError for 0 episodes or another negative
    value, naming the field as ``names`` spell it (the command's flags)."""
    if episodes == 0 or episodes < -1:
        raise ValueError(f"{names[0]} must be -1 (the setting's) or >= 1, got {episodes}")
    if action_noise < 0 and action_noise != -1:
        raise ValueError(f"{names[1]} must be -1 (the setting's) or >= 0, got {action_noise:g}")
    return (DEMO_EPISODES[setting] if episodes == -1 else episodes,
            DEMO_ACTION_NOISE[setting] if action_noise == -1 else action_noise)


FRAME_SKIP = 4
# Hopper-v5's constructor defaults (gymnasium 1.x), plus the time limit of its registration.
HOPPER_DEFAULTS: dict[str, Any] = {
    "forward_reward_weight": 1.0,
    "ctrl_cost_weight": 1e-3,
    "healthy_reward": 1.0,
    "terminate_when_unhealthy": True,
    "healthy_state_range": (-100.0, 100.0),
    "healthy_z_range": (0.7, float("inf")),
    "healthy_angle_range": (-0.2, 0.2),
    "reset_noise_scale": 5e-3,
    "exclude_current_positions_from_observation": True,
    "max_episode_steps": 1000,
}


SPEED_DEFAULTS: dict[str, Any] = {**HOPPER_DEFAULTS, "target_velocity": 1.0}
"""pomil/HopperSpeed-v0's keywords: Hopper-v5's plus the target speed (m/s)."""


class HopperSpeedEnv(HopperEnv):
    """Gymnasium's Hopper-v5 paid for forward speed ``target_velocity``: the forward reward
    ``w * v_x`` becomes ``-w * |v_x - target_velocity|`` (w = ``forward_reward_weight``); the
    healthy reward, control cost, termination and observations are Hopper-v5's."""

    def __init__(self, target_velocity: float = SPEED_DEFAULTS["target_velocity"], **kwargs: Any) -> None:
        self.target_velocity = float(target_velocity)
        if not np.isfinite(self.target_velocity):
            raise ValueError(f"target_velocity must be a finite speed in m/s, got {target_velocity}")
        super().__init__(**kwargs)

    def _get_rew(self, x_velocity: float, action):
        reward, info = super()._get_rew(x_velocity, action)
        speed = -self._forward_reward_weight * abs(x_velocity - self.target_velocity)
        return reward - info["reward_forward"] + speed, {**info, "reward_forward": speed}


def task_name(kwargs: dict[str, Any]) -> str:
    """A recording's task name from its environment keywords: ``speed-V`` (pomil/HopperSpeed-v0),
    ``forward`` / ``backward`` (the sign of forward_reward_weight), else ``task``."""
    if "target_velocity" in kwargs:
        return f"speed-{float(kwargs['target_velocity']):g}"
    w = kwargs.get("forward_reward_weight")
    return "task" if w is None or w == 0 else ("forward" if w > 0 else "backward")


def hopper_kwargs(task: str, setting: str) -> dict[str, Any]:
    """``gymnasium.make("Hopper-v5", **kwargs)`` keywords of a task in a setting."""
    if task not in TASKS:
        raise ValueError(f"unknown Hopper task {task!r}; expected one of {sorted(TASKS)}")
    if setting not in SETTINGS:
        raise ValueError(f"unknown Hopper setting {setting!r}; expected one of {sorted(SETTINGS)}")
    return {"forward_reward_weight": TASKS[task], "ctrl_cost_weight": 1e-3, **SETTINGS[setting]}


def locomotion_kwargs(env_id: str, task: str, setting: str) -> dict[str, Any]:
    """Constructor keywords of a locomotion task in a setting, for any MuJoCo
    locomotion id (Hopper, Walker2d, HalfCheetah, Ant, ...).

    task: ``forward`` / ``backward`` (forward_reward_weight +1 / -1) or ``none``
    (the environment's own reward).  setting: ``paper`` (128-step episodes
    that do not end when unhealthy) or ``standard`` (the environment's own).
    Hopper-v5 gets the paper's exact keywords (:func:`hopper_kwargs`).
    """
    if env_id == HOPPER_ID and task != "none":
        return hopper_kwargs(task, setting)
    if env_id == HOPPER_SPEED_ID and task != "none":
        raise ValueError(f"{env_id} has its own reward (a target speed): use task 'none' and "
                         "--env-kwargs target_velocity=V")
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}; expected one of {sorted(SETTINGS)}")
    if task not in (*TASKS, "none"):
        raise ValueError(f"unknown task {task!r}; expected one of {[*TASKS, 'none']}")
    accepted = constructor_keywords(env_id)
    kw: dict[str, Any] = {}
    if task != "none":
        if "forward_reward_weight" not in accepted:
            raise ValueError(f"task {task!r} needs an environment with a forward_reward_weight keyword; "
                             f"{env_id} has none (use task 'none')")
        kw["forward_reward_weight"] = TASKS[task]
    if setting == "paper":
        kw["max_episode_steps"] = SETTINGS["paper"]["max_episode_steps"]
        if "terminate_when_unhealthy" in accepted:
            kw["terminate_when_unhealthy"] = False
    return kw


def constructor_keywords(env_id: str) -> dict[str, Any]:
    """The keywords a registered environment's constructor takes, with their defaults
    (``inspect.Parameter.empty`` where it has none): its own and, where it passes ``**kwargs``
    on, those of its base classes (:class:`HopperSpeedEnv` -> Hopper-v5's)."""
    import inspect

    import gymnasium as gym

    entry = gym.spec(env_id).entry_point
    if isinstance(entry, str):
        module, _, name = entry.partition(":")
        entry = getattr(__import__(module, fromlist=[name]), name)
    accepted: dict[str, Any] = {}
    for cls in getattr(entry, "__mro__", (entry,)):
        params = inspect.signature(cls).parameters
        for name, p in params.items():
            if p.kind not in (inspect.Parameter.VAR_KEYWORD, inspect.Parameter.VAR_POSITIONAL):
                accepted.setdefault(name, p.default)
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            break
    return accepted


def ends_on_failure(env_id: str, env_kwargs: dict[str, Any]) -> bool:
    """Whether a MuJoCo locomotion environment with keywords ``env_kwargs`` ends an episode when
    the agent fails (Hopper, Walker2d, Ant, Humanoid: ``terminate_when_unhealthy``, default true
    in gymnasium); false for environments without that keyword (HalfCheetah, Swimmer)."""
    default = constructor_keywords(env_id).get("terminate_when_unhealthy", False)
    return bool(env_kwargs.get("terminate_when_unhealthy", default))


def check_env_kwargs(env_id: str, defaults: dict[str, Any], env_kwargs: dict[str, Any] | None,
                     flag: str = "") -> dict[str, Any]:
    """``defaults`` (a simulator's keywords of ``env_id``) with ``env_kwargs`` applied; ValueError, its message
    led by ``flag``, for a keyword the simulator does not take, and for ``max_episode_steps`` below 1."""
    unknown = sorted(set(env_kwargs or {}) - set(defaults))
    if unknown:
        raise ValueError(f"{flag}unsupported {env_id} keyword(s) {unknown}; supported: {sorted(defaults)}")
    kw = {**defaults, **(env_kwargs or {})}
    if int(kw["max_episode_steps"]) < 1:
        raise ValueError(f"max_episode_steps must be >= 1, got {kw['max_episode_steps']}")
    return kw


class LocomotionSim(SimCopies):
    """What the batched MuJoCo locomotion simulators share (:class:`HopperSim`, :class:`pomil.envs.warp.WarpSim`):
    the model's dimensions and initial state, and each copy's reset noise drawn from its own generator."""

    kw: dict[str, Any]

    def _load(self, num_envs: int, xml: str, frame_skip: int) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """The model of gymnasium's asset ``xml`` and a state of it; sets ``num_envs``, ``dt``, ``act_dim``,
        ``obs_dim``, ``init_qpos``, ``init_qvel`` and unseeded generators (``kw`` must be set)."""
        import gymnasium.envs.mujoco as gm

        model = mujoco.MjModel.from_xml_path(os.path.join(os.path.dirname(gm.__file__), "assets", xml))
        data = mujoco.MjData(model)
        self.num_envs, self.dt, self.act_dim = num_envs, model.opt.timestep * frame_skip, model.nu
        self.obs_dim = model.nq + model.nv - (1 if self.kw["exclude_current_positions_from_observation"] else 0)
        self.init_qpos, self.init_qvel = data.qpos.copy(), data.qvel.copy()
        self._rngs = [np_random(None)[0] for _ in range(num_envs)]
        return model, data

    def _initial_states(self, seed: int | None, normal_qvel: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Each copy's initial qpos (N, nq) and qvel (N, nv), drawn in the order of gymnasium's ``reset_model``:
        uniform noise of +-``reset_noise_scale`` (qvel with ``normal_qvel``: the scale times a standard normal).
        ``seed``: copy i's generator is seeded ``seed + i`` first; None: each goes on."""
        if seed is not None:
            self._rngs = [np_random(seed + i)[0] for i in range(self.num_envs)]
        s, nq, nv = self.kw["reset_noise_scale"], len(self.init_qpos), len(self.init_qvel)
        qpos, qvel = np.empty((self.num_envs, nq)), np.empty((self.num_envs, nv))
        for i, rng in enumerate(self._rngs):
            qpos[i] = self.init_qpos + rng.uniform(low=-s, high=s, size=nq)
            qvel[i] = self.init_qvel + (s * rng.standard_normal(nv) if normal_qvel
                                        else rng.uniform(low=-s, high=s, size=nv))
        return qpos, qvel


class HopperSim(LocomotionSim):
    """N Hopper-v5 copies in NumPy (float64), all reset together.

    ``reset(seed) -> obs (N, 11)``; ``step(actions (N, 3)) -> (obs, reward,
    terminated, truncated)``, NumPy arrays.  A copy whose episode ended is
    no longer simulated: it keeps its last observation and yields reward 0
    until the next ``reset`` (``done`` says which copies ended).
    ``x_position`` (N,) is the torso's x coordinate.  ``env_id`` ``pomil/HopperSpeed-v0``:
    the speed task's reward (:class:`HopperSpeedEnv`) and its ``target_velocity`` keyword.
    """

    def __init__(self, num_envs: int, env_kwargs: dict[str, Any] | None = None, threads: int | None = None,
                 env_id: str = HOPPER_ID) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if env_id not in (HOPPER_ID, HOPPER_SPEED_ID):
            raise ValueError(f"HopperSim runs {HOPPER_ID} and {HOPPER_SPEED_ID}, not {env_id!r}")
        self.kw = check_env_kwargs(env_id, SPEED_DEFAULTS if env_id == HOPPER_SPEED_ID else HOPPER_DEFAULTS, env_kwargs)
        self.target_velocity = float(self.kw["target_velocity"]) if env_id == HOPPER_SPEED_ID else None
        self.model, _ = self._load(num_envs, "hopper.xml", FRAME_SKIP)
        self.data = [mujoco.MjData(self.model) for _ in range(num_envs)]
        n_threads = threads if threads is not None else min(usable_cpus(), 16)
        n_threads = max(1, min(n_threads, num_envs // 8 or 1))
        self._chunks = [range(i, num_envs, n_threads) for i in range(n_threads)]
        self._pool = ThreadPoolExecutor(n_threads) if n_threads > 1 else None
        self.qpos = np.zeros((num_envs, self.model.nq))
        self.qvel = np.zeros((num_envs, self.model.nv))
        self.done = np.ones(num_envs, dtype=bool)
        self.t = 0

    # -- physics
    def _run(self, fn) -> None:
        if self._pool is None:
            fn(range(self.num_envs))
        else:
            for f in [self._pool.submit(fn, c) for c in self._chunks]:
                f.result()

    def _gather(self) -> None:
        for i, d in enumerate(self.data):
            self.qpos[i] = d.qpos
            self.qvel[i] = d.qvel

    def _obs(self) -> np.ndarray:
        pos = self.qpos[:, 1:] if self.kw["exclude_current_positions_from_observation"] else self.qpos
        return np.concatenate([pos, np.clip(self.qvel, -10.0, 10.0)], axis=1)

    def healthy(self) -> np.ndarray:
        state = np.concatenate([self.qpos, self.qvel], axis=1)[:, 2:]
        lo, hi = self.kw["healthy_state_range"]
        zlo, zhi = self.kw["healthy_z_range"]
        alo, ahi = self.kw["healthy_angle_range"]
        z, angle = self.qpos[:, 1], self.qpos[:, 2]
        return (np.all((lo < state) & (state < hi), axis=1) & (zlo < z) & (z < zhi) & (alo < angle) & (angle < ahi))

    @property
    def x_position(self) -> np.ndarray:
        return self.qpos[:, 0].copy()

    def reset(self, seed: int | None = None) -> np.ndarray:
        for d, qpos, qvel in zip(self.data, *self._initial_states(seed), strict=True):
            mujoco.mj_resetData(self.model, d)
            d.qpos[:], d.qvel[:] = qpos, qvel
            mujoco.mj_forward(self.model, d)
        self._gather()
        self.done[:] = False
        self.t = 0
        return self._obs()

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        actions = np.asarray(actions, dtype=np.float64)
        self._check_step(actions)
        was_done = self.done.copy()
        x_before = self.qpos[:, 0].copy()

        def advance(chunk):
            for i in chunk:
                if not self.done[i]:
                    d = self.data[i]
                    d.ctrl[:] = actions[i]
                    mujoco.mj_step(self.model, d, nstep=FRAME_SKIP)

        self._run(advance)
        self._gather()
        self.t += 1
        x_velocity = (self.qpos[:, 0] - x_before) / self.dt
        healthy = self.healthy()
        forward = x_velocity if self.target_velocity is None else -np.abs(x_velocity - self.target_velocity)
        reward = (self.kw["forward_reward_weight"] * forward + healthy * self.kw["healthy_reward"]
                  - self.kw["ctrl_cost_weight"] * np.square(actions).sum(axis=1))
        terminated = ~healthy if self.kw["terminate_when_unhealthy"] else np.zeros(self.num_envs, dtype=bool)
        truncated = np.full(self.num_envs,
                            self.t >= int(self.kw["max_episode_steps"]))  # as TimeLimit: may coincide with terminated
        reward[was_done] = 0.0
        terminated[was_done] = False
        truncated[was_done] = False
        self.done |= terminated | truncated
        return self._obs(), reward, terminated, truncated

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None
