"""MuJoCo Warp physics behind the batched-simulator interface (opt-in: ``pomil[gpu]``, ``--sim warp``).

:class:`WarpSim` steps N copies of a Gymnasium MuJoCo locomotion task (Hopper-v5,
Walker2d-v5, HalfCheetah-v5) as N worlds of one MuJoCo Warp model, with
observations, rewards, health checks and time limits computed on the Warp device
in torch.  Torch and Warp share the state arrays (``wp.to_torch``): actions go in
and observations come out as tensors on the device, with no copy to the host.
:class:`WarpVecEnv` is its :class:`pomil.envs.vec.TorchVecEnv`: the observation
mask and the seeding of the first reset.

Same environment as ``gymnasium.make(env_id, **kwargs)``, as far as float32
allows: the same model file and frame skip, the reset noise drawn from the same
per-copy NumPy generators (copy i seeded ``seed + i``, as
:class:`pomil.envs.locomotion.HopperSim` and gymnasium's vector envs do), the
same reward terms (control cost on the action as given; MuJoCo Warp clamps the
control to its range, as MuJoCo does), health test and time limit.  MuJoCo Warp
computes in float32 where MuJoCo uses float64, so trajectories agree step by step
within float32 rounding and then drift apart as chaotic contact dynamics amplify
it; ``tests/envs/test_warp.py`` measures both.

One episode per copy between resets, as ``HopperSim``: a copy whose episode
ended keeps its last observation and state and yields reward 0 until the next
``reset`` (``done`` says which copies ended).

Warp runs on the CPU too (``device="cpu"``; slow, for tests) and on CUDA
devices, where the ``frame_skip`` physics steps of one env step are captured
once as a CUDA graph and replayed on Warp's stream, ordered with torch's current
stream by events; the tests run on Warp's CPU device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import torch

from pomil.envs.locomotion import HOPPER_DEFAULTS, HOPPER_ID, LocomotionSim, check_env_kwargs
from pomil.envs.vec import SimState
from pomil.errors import PomilError

INSTALL_HINT = "pip install 'pomil[gpu]' (mujoco-warp==4.0.0)"


@dataclass(frozen=True)
class LocomotionSpec:
    """What a Gymnasium MuJoCo locomotion task computes around the physics (its ``step`` and ``reset_model``)."""

    xml: str
    """model file in gymnasium's ``envs/mujoco/assets``."""
    frame_skip: int
    defaults: dict[str, Any]
    """constructor keywords and their defaults (gymnasium 1.x), plus the registration's ``max_episode_steps``."""
    clip_velocity: bool
    """observation carries ``clip(qvel, -10, 10)`` (Hopper, Walker2d) rather than ``qvel`` (HalfCheetah)."""
    state_range: bool
    """health also asks every entry of ``state_vector()[2:]`` to lie in ``healthy_state_range`` (Hopper)."""
    qvel_noise: str
    """reset noise on qvel: ``uniform`` (+-scale) or ``normal`` (scale * standard normal, HalfCheetah)."""

    @property
    def has_health(self) -> bool:
        return "healthy_reward" in self.defaults


_COMMON = {"forward_reward_weight": 1.0, "exclude_current_positions_from_observation": True, "max_episode_steps": 1000}
SPECS: dict[str, LocomotionSpec] = {
    HOPPER_ID: LocomotionSpec("hopper.xml", 4, dict(HOPPER_DEFAULTS), clip_velocity=True, state_range=True,
                              qvel_noise="uniform"),
    "Walker2d-v5": LocomotionSpec("walker2d_v5.xml", 4, {
        **_COMMON, "ctrl_cost_weight": 1e-3, "healthy_reward": 1.0, "terminate_when_unhealthy": True,
        "healthy_z_range": (0.8, 2.0), "healthy_angle_range": (-1.0, 1.0), "reset_noise_scale": 5e-3,
    }, clip_velocity=True, state_range=False, qvel_noise="uniform"),
    "HalfCheetah-v5": LocomotionSpec("half_cheetah.xml", 5, {
        **_COMMON, "ctrl_cost_weight": 0.1, "reset_noise_scale": 0.1,
    }, clip_velocity=False, state_range=False, qvel_noise="normal"),
}
"""The tasks :class:`WarpSim` runs, by Gymnasium id."""


def warp_available() -> bool:
    """Whether MuJoCo Warp (the ``gpu`` extra) is installed."""
    try:
        _import_warp()
    except PomilError:
        return False
    return True


def _import_warp():
    try:
        import mujoco_warp as mjw
        import warp as wp
    except ImportError as err:
        raise PomilError(f"--sim warp needs MuJoCo Warp, which is not installed ({err}); {INSTALL_HINT}") from None
    return wp, mjw


class WarpSim(LocomotionSim):
    """N copies of a locomotion task as N MuJoCo Warp worlds, torch tensors in and out.

    ``reset(seed) -> obs (N, obs_dim)``; ``step(actions (N, act_dim)) -> (obs,
    reward, terminated, truncated)``: float32 / bool tensors on ``device`` (a
    torch or Warp device name: ``cpu``, ``cuda``, ``cuda:N``).  ``qpos``,
    ``qvel`` (N, nq / nv) are views of the Warp state, ``x_position`` (N,) the
    torso's x, ``done`` (N,) which copies' episodes are over.  ``nconmax`` /
    ``njmax``: MuJoCo Warp's contacts / constraint rows per world (None: its
    defaults; :meth:`check_overflow` says when they were too few).
    """

    def __init__(self, env_id: str, num_envs: int, env_kwargs: dict[str, Any] | None = None, device: Any = "cpu",
                 nconmax: int | None = None, njmax: int | None = None) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if env_id not in SPECS:
            raise ValueError(f"--sim warp runs {sorted(SPECS)}, not {env_id!r} (use --sim cpu)")
        self.kw = check_env_kwargs(env_id, SPECS[env_id].defaults, env_kwargs, "--sim warp: ")
        wp, mjw = _import_warp()
        self._wp, self._mjw = wp, mjw
        self.env_id, self.spec = env_id, SPECS[env_id]
        self.device = torch.device(device)
        if self.device.type == "cuda" and self.device.index is None:
            self.device = torch.device("cuda", torch.cuda.current_device())
        self.wp_device = wp.get_device(str(self.device))
        mjm, mjd = self._load(num_envs, self.spec.xml, self.spec.frame_skip)
        mujoco.mj_forward(mjm, mjd)
        with wp.ScopedDevice(self.wp_device):
            self.model = mjw.put_model(mjm)
            self.data = mjw.put_data(mjm, mjd, nworld=num_envs, nconmax=nconmax, njmax=njmax)
        # Views of the Warp state: writing to them writes the simulation's state.
        self.qpos = wp.to_torch(self.data.qpos)
        self.qvel = wp.to_torch(self.data.qvel)
        self._ctrl = wp.to_torch(self.data.ctrl)
        self._frozen_qpos, self._frozen_qvel = self.qpos.clone(), self.qvel.clone()
        self.done = torch.ones(num_envs, dtype=torch.bool, device=self.device)
        self.t = 0
        self._graph = None
        self._torch_streams: dict[int, Any] = {}  # torch's CUDA streams as Warp streams, by handle

    # -- Warp work: on the CPU in order with torch; on CUDA on Warp's own stream, ordered after
    # torch's current stream and before torch's next work by events (no host synchronisation).
    def _on_device(self, fn) -> None:
        wp = self._wp
        with wp.ScopedDevice(self.wp_device):
            if self.device.type != "cuda":
                fn()
                return
            handle = torch.cuda.current_stream(self.device).cuda_stream
            if handle not in self._torch_streams:
                self._torch_streams[handle] = wp.stream_from_torch(self.device)
            torch_stream = self._torch_streams[handle]
            self.wp_device.stream.wait_stream(torch_stream)
            fn()
            torch_stream.wait_stream(self.wp_device.stream)

    def _physics(self) -> None:
        for _ in range(self.spec.frame_skip):
            self._mjw.step(self.model, self.data)

    def _advance(self) -> None:
        if self.device.type != "cuda":
            self._on_device(self._physics)
            return
        wp = self._wp
        if self._graph is None:  # the frame_skip steps, captured once, replayed every env step
            with wp.ScopedDevice(self.wp_device), wp.ScopedCapture() as capture:
                self._physics()
            self._graph = capture.graph
        self._on_device(lambda: wp.capture_launch(self._graph))

    # -- observations, health
    def _obs(self) -> torch.Tensor:
        pos = self.qpos[:, 1:] if self.kw["exclude_current_positions_from_observation"] else self.qpos
        vel = self.qvel.clamp(-10.0, 10.0) if self.spec.clip_velocity else self.qvel
        return torch.cat([pos, vel], dim=1)

    def healthy(self) -> torch.Tensor:
        if not self.spec.has_health:
            return torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        (zlo, zhi), (alo, ahi) = self.kw["healthy_z_range"], self.kw["healthy_angle_range"]
        z, angle = self.qpos[:, 1], self.qpos[:, 2]
        ok = (zlo < z) & (z < zhi) & (alo < angle) & (angle < ahi)
        if self.spec.state_range:
            lo, hi = self.kw["healthy_state_range"]
            state = torch.cat([self.qpos[:, 2:], self.qvel], dim=1)
            ok &= ((lo < state) & (state < hi)).all(dim=1)
        return ok

    @property
    def x_position(self) -> torch.Tensor:
        return self.qpos[:, 0].clone()

    def check_overflow(self) -> None:
        """RuntimeError if a world ran out of contact or constraint memory since the last reset
        (raise ``nconmax`` / ``njmax``)."""
        overflow = self._wp.to_torch(self.data.overflow)
        if bool((overflow != 0).any()):
            worlds = torch.nonzero(overflow).flatten()[:5].tolist()
            raise RuntimeError(f"MuJoCo Warp overflow in worlds {worlds} (flags {overflow[worlds].tolist()}); "
                               f"raise nconmax / njmax (now {self.data.naconmax // self.num_envs} / {self.data.njmax})")

    # -- the batched-simulator interface
    def reset(self, seed: int | None = None) -> torch.Tensor:
        if self.t > 0:
            self.check_overflow()
        qpos, qvel = self._initial_states(seed, normal_qvel=self.spec.qvel_noise == "normal")
        self._on_device(lambda: self._mjw.reset_data(self.model, self.data))
        self.set_state(torch.as_tensor(qpos), torch.as_tensor(qvel))
        self.done.zero_()
        self.t = 0
        return self._obs()

    def set_state(self, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        """Set every world's joint positions (N, nq) and velocities (N, nv), then run
        MuJoCo's forward pass, as gymnasium's ``MujocoEnv.set_state`` does."""
        self.qpos.copy_(torch.as_tensor(qpos).to(self.device, torch.float32))
        self.qvel.copy_(torch.as_tensor(qvel).to(self.device, torch.float32))
        self._on_device(lambda: self._mjw.forward(self.model, self.data))

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        actions = torch.as_tensor(actions).to(self.device, torch.float32)
        self._check_step(actions)
        was_done = self.done.clone()
        x_before = self.qpos[:, 0].clone()
        self._frozen_qpos.copy_(self.qpos)
        self._frozen_qvel.copy_(self.qvel)
        self._ctrl.copy_(actions)
        self._advance()
        # Ended copies stay where they ended (their worlds were stepped along with the rest).
        frozen = was_done.unsqueeze(1)
        self.qpos.copy_(torch.where(frozen, self._frozen_qpos, self.qpos))
        self.qvel.copy_(torch.where(frozen, self._frozen_qvel, self.qvel))
        self.t += 1
        x_velocity = (self.qpos[:, 0] - x_before) / self.dt
        healthy = self.healthy()
        ctrl_cost = self.kw["ctrl_cost_weight"] * actions.square().sum(dim=1)
        reward = self.kw["forward_reward_weight"] * x_velocity - ctrl_cost
        if self.spec.has_health:
            reward = reward + healthy * float(self.kw["healthy_reward"])
        can_end = self.spec.has_health and self.kw["terminate_when_unhealthy"]
        terminated = ~healthy if can_end else torch.zeros_like(healthy)
        truncated = torch.full_like(healthy, self.t >= int(self.kw["max_episode_steps"]))  # as TimeLimit: may coincide
        reward = reward.masked_fill(was_done, 0.0)
        terminated = terminated & ~was_done
        truncated = truncated & ~was_done
        self.done |= terminated | truncated
        return self._obs(), reward, terminated, truncated

    def close(self) -> None:
        self._graph = None


class WarpVecEnv(SimState):
    """The torch env training steps (the interface of :class:`pomil.envs.vec.TorchVecEnv`) on a :class:`WarpSim`.

    ``reset() -> obs (N, d)``; ``step(actions) -> (obs, reward, terminated,
    truncated)``, tensors on the sim's device; ``observation_mask`` indexes the
    sim's observation (the learner's view), ``full_observation`` is the last
    unmasked one.
    """

    def __init__(self, sim: WarpSim, observation_mask: list[int] | None = None, seed: int | None = None) -> None:
        self.sim = sim
        self.num_envs, self.device, self.act_dim = sim.num_envs, sim.device, sim.act_dim
        self.mask = (None if observation_mask is None
                     else torch.as_tensor(observation_mask, dtype=torch.long, device=sim.device))
        self.obs_dim = sim.obs_dim if self.mask is None else len(self.mask)
        self._seed = seed
        self.full_observation = torch.zeros(sim.num_envs, sim.obs_dim, device=sim.device)

    def _obs(self, full: torch.Tensor) -> torch.Tensor:
        self.full_observation = full
        return full if self.mask is None else full[:, self.mask]

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        obs, reward, terminated, truncated = self.sim.step(actions.detach())
        return self._obs(obs), reward, terminated, truncated


def make_warp_vec_env(env_id: str, env_kwargs: dict[str, Any], num_envs: int, *, device: Any = "cpu",
                      observation_mask: list[int] | None = None, seed: int | None = None) -> WarpVecEnv:
    """``pomil.envs.make_vec_env(..., sim="warp")``: the task's worlds on the torch ``device``."""
    mask = None if observation_mask is None else [int(i) for i in observation_mask]
    sim = WarpSim(env_id, num_envs, env_kwargs, device)
    if mask is not None:
        from pomil.envs.wrappers import check_indices

        check_indices(mask, sim.obs_dim)
    return WarpVecEnv(sim, mask, seed)
