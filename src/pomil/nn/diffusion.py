"""A state-based diffusion policy (Diffusion Policy, Chi et al. 2023): a denoiser over a short
horizon of actions, conditioned on a window of recent observations (and, optionally, a latent
code), trained as a DDPM and sampled with DDIM; executed with a receding horizon.

The noise schedules are ``diffusers``' (an optional extra, ``pomil[diffusion]``); the denoiser is
ours: a residual MLP over the flattened noisy action horizon, the flattened observation window,
the one-hot code and a sinusoidal embedding of the diffusion step.

Observations and actions are scaled to [-1, 1] per dimension by the demonstrations' range
(``fit_ranges``), as Diffusion Policy does; DDIM clips its estimate of the clean sample to that
interval.

Running it is explicit about its state (:class:`DiffusionState`): the last ``obs_horizon``
observations (the first one repeated at an episode's start), the plan (``execute_horizon``
actions) and the next action's place in it.  An episode that starts, or whose plan is used up,
samples a new plan from its window; the others go on with theirs.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
from torch import nn

from pomil.errors import PomilError

BETA_SCHEDULES = ("squaredcos_cap_v2", "linear", "scaled_linear")


def noise_schedulers(arch: DiffusionArch) -> tuple[Any, Any]:
    """(DDPM scheduler for training, DDIM scheduler set to ``arch.inference_steps``) from ``diffusers``."""
    try:
        from diffusers import DDIMScheduler, DDPMScheduler
    except ImportError:
        raise PomilError("the diffusion learners need the optional extra diffusers: pip install 'pomil[diffusion]'") \
            from None
    common = {"num_train_timesteps": arch.train_timesteps, "beta_schedule": arch.beta_schedule, "clip_sample": True,
              "prediction_type": "epsilon"}
    ddpm = DDPMScheduler(**common)
    ddim = DDIMScheduler(**common, set_alpha_to_one=True, steps_offset=0)
    ddim.set_timesteps(arch.inference_steps)
    return ddpm, ddim


@dataclass(frozen=True)
class DiffusionArch:
    """What it takes to rebuild a diffusion policy from its state dict (``kind`` marks it in a checkpoint).

    ``obs_horizon`` observations condition a plan of ``action_horizon`` actions, of which the first
    ``execute_horizon`` are carried out before the next plan; ``num_codes``: K one-hot codes (0: none)."""

    obs_dim: int
    act_dim: int
    num_codes: int = 0
    obs_horizon: int = 2
    action_horizon: int = 16
    execute_horizon: int = 8
    hidden_size: int = 256
    layers: int = 3
    train_timesteps: int = 100
    inference_steps: int = 10
    beta_schedule: str = "squaredcos_cap_v2"
    kind: str = "diffusion"

    def __post_init__(self) -> None:
        for f in fields(self):  # a checkpoint's values: the declared types (no bools for numbers)
            value = getattr(self, f.name)
            if not isinstance(value, {"int": int, "str": str}[f.type]) or isinstance(value, bool):
                raise TypeError(f"{f.name} is {value!r:.40}")
        if self.kind != "diffusion":
            raise ValueError(f"kind must be 'diffusion', got {self.kind!r}")
        if not 1 <= self.execute_horizon <= self.action_horizon:
            raise ValueError(f"execute_horizon must be in [1, action_horizon = {self.action_horizon}], got "
                             f"{self.execute_horizon}")
        if min(self.obs_dim, self.act_dim, self.obs_horizon, self.hidden_size, self.layers) < 1 or self.num_codes < 0:
            raise ValueError(f"sizes must be positive (num_codes >= 0), got {self}")
        if not 1 <= self.inference_steps <= self.train_timesteps:
            raise ValueError(f"inference_steps must be in [1, train_timesteps = {self.train_timesteps}], got "
                             f"{self.inference_steps}")
        if self.beta_schedule not in BETA_SCHEDULES:
            raise ValueError(f"beta_schedule must be one of {list(BETA_SCHEDULES)}, got {self.beta_schedule!r}")

    # what pomil.TrainedPolicy asks of a policy's architecture
    code_kind = "discrete"
    code_prior = "uniform"
    continuous_codes = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class DiffusionState:
    """A batch of N running episodes: ``window`` (N, obs_horizon, obs_dim) raw observations, oldest
    first; ``plan`` (N, execute_horizon, act_dim) actions; ``index`` (N,) the next action's place in
    the plan (``execute_horizon``: used up)."""

    window: torch.Tensor
    plan: torch.Tensor
    index: torch.Tensor

    def __post_init__(self) -> None:
        n = self.index.shape[0]
        if self.index.shape != (n,) or self.window.shape[0] != n or self.plan.shape[0] != n:
            raise ValueError(f"state shapes disagree: window {tuple(self.window.shape)}, plan "
                             f"{tuple(self.plan.shape)}, index {tuple(self.index.shape)}")


def step_embedding(steps: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding (B, dim) of diffusion steps (B,), as in DDPM's U-Net."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=steps.device) / half)
    args = steps.float()[:, None] * freqs[None]
    return torch.cat([args.sin(), args.cos()], dim=-1)


class _Residual(nn.Module):
    def __init__(self, width: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, width), nn.Mish(), nn.Linear(width, width))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return h + self.net(h)


class DiffusionPolicy(nn.Module):
    """The denoiser eps(x_k, k | observation window, code) and its sampler (see the module's text)."""

    STEP_EMBED = 64

    def __init__(self, arch: DiffusionArch) -> None:
        super().__init__()
        self.arch = arch
        self.cond_dim = arch.obs_horizon * arch.obs_dim + arch.num_codes
        self.plan_dim = arch.action_horizon * arch.act_dim
        width = arch.hidden_size
        self.step_mlp = nn.Sequential(nn.Linear(self.STEP_EMBED, width), nn.Mish(), nn.Linear(width, width))
        self.inp = nn.Linear(self.plan_dim + self.cond_dim + width, width)
        self.blocks = nn.Sequential(*(_Residual(width) for _ in range(arch.layers)))
        self.out = nn.Sequential(nn.LayerNorm(width), nn.Mish(), nn.Linear(width, self.plan_dim))
        for name, dim in (("obs", arch.obs_dim), ("act", arch.act_dim)):
            self.register_buffer(f"{name}_low", -torch.ones(dim))
            self.register_buffer(f"{name}_high", torch.ones(dim))
        self._ddim: Any = None

    # ------------------------------------------------------------------ scaling
    def fit_ranges(self, observations: torch.Tensor, actions: torch.Tensor) -> None:
        """Set the [-1, 1] scaling from the demonstrations' valid steps, (S, obs_dim) and (S, act_dim);
        a dimension that never changes keeps a range of width 2 around its value."""
        for name, x in (("obs", observations), ("act", actions)):
            low, high = x.min(0).values, x.max(0).values
            flat = (high - low) < 1e-6
            getattr(self, f"{name}_low").copy_(torch.where(flat, low - 1, low))
            getattr(self, f"{name}_high").copy_(torch.where(flat, high + 1, high))

    def scale(self, x: torch.Tensor, name: str) -> torch.Tensor:
        low, high = getattr(self, f"{name}_low"), getattr(self, f"{name}_high")
        return 2 * (x - low) / (high - low) - 1

    def unscale(self, x: torch.Tensor, name: str) -> torch.Tensor:
        low, high = getattr(self, f"{name}_low"), getattr(self, f"{name}_high")
        return (x + 1) / 2 * (high - low) + low

    # ------------------------------------------------------------------ denoiser
    def condition(self, window: torch.Tensor, codes: torch.Tensor | None) -> torch.Tensor:
        """The conditioning vector (B, cond_dim) from raw observation windows (B, obs_horizon, obs_dim) and
        one-hot codes (B, K)."""
        cond = self.scale(window, "obs").flatten(1)
        if self.arch.num_codes:
            if codes is None:
                raise ValueError("this diffusion policy is conditioned on codes: pass them (one-hot)")
            cond = torch.cat([cond, codes.to(cond.dtype)], dim=-1)
        return cond

    def forward(self, noisy: torch.Tensor, steps: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """The predicted noise (B, action_horizon, act_dim) of scaled plans ``noisy`` at diffusion ``steps`` (B,)."""
        t = self.step_mlp(step_embedding(steps, self.STEP_EMBED))
        h = self.inp(torch.cat([noisy.flatten(1), cond, t], dim=-1))
        return self.out(self.blocks(h)).view_as(noisy)

    # ------------------------------------------------------------------ sampling
    @torch.no_grad()
    def sample(self, cond: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """Plans (B, action_horizon, act_dim) in the environment's units: DDIM (eta 0) from noise drawn
        with ``generator``."""
        if self._ddim is None:
            self._ddim = noise_schedulers(self.arch)[1]
        x = torch.randn(cond.shape[0], self.arch.action_horizon, self.arch.act_dim, generator=generator,
                        device=cond.device)
        for k in self._ddim.timesteps:
            eps = self(x, torch.full((cond.shape[0],), int(k), device=cond.device), cond)
            x = self._ddim.step(eps, int(k), x, eta=0.0).prev_sample
        return self.unscale(x, "act")

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> DiffusionState:
        a = self.arch
        return DiffusionState(torch.zeros(batch, a.obs_horizon, a.obs_dim, device=device),
                              torch.zeros(batch, a.execute_horizon, a.act_dim, device=device),
                              torch.full((batch,), a.execute_horizon, dtype=torch.long, device=device))

    @torch.no_grad()
    def act(self, obs: torch.Tensor, state: DiffusionState, start: torch.Tensor, codes: torch.Tensor | None,
            generator: torch.Generator | None) -> tuple[torch.Tensor, DiffusionState]:
        """One step of N episodes: obs (N, obs_dim), ``start`` (N,) where an episode begins -> (actions
        (N, act_dim), the next state).  Episodes that begin or have used up their plan sample a new one."""
        start = start.bool()
        shifted = torch.cat([state.window[:, 1:], obs[:, None]], dim=1)
        window = torch.where(start[:, None, None], obs[:, None].expand_as(state.window), shifted)
        plan, index = state.plan.clone(), state.index.clone()
        replan = start | (index >= self.arch.execute_horizon)
        if bool(replan.any()):
            rows = replan.nonzero().flatten()
            picked = None if codes is None else codes[rows]
            plan[rows] = self.sample(self.condition(window[rows], picked), generator)[:, :self.arch.execute_horizon]
            index[rows] = 0
        action = plan[torch.arange(len(index), device=index.device), index]
        return action, DiffusionState(window, plan, index + 1)
