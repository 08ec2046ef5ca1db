"""The public policy API: load a trained policy and run it.

>>> from pomil import TrainedPolicy
>>> policy = TrainedPolicy.load("runs/bc/checkpoint.pt")      # doctest: +SKIP
>>> policy.reset(num_envs=8, codes=[0, 1] * 4, seed=0)        # doctest: +SKIP
>>> actions = policy.act(observations)                        # doctest: +SKIP

The policy keeps its own recurrent state and previous action between
``act`` calls; ``reset`` starts new episodes.  Codes are ignored by learners
that have none (behaviour cloning, GAIL).  A policy with continuous codes
(``--code-kind continuous``) takes an (N, d) float array instead:

>>> policy.reset(num_envs=3, codes=[[-1.0], [0.0], [1.0]])   # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pomil.envs import executed_actions_fn
from pomil.errors import InvalidArgument, PomilError
from pomil.nn.codes import code_vectors, prior_grid
from pomil.nn.normalize import RunningNorm
from pomil.nn.policy import GaussianPolicy, PolicyArch, make_policy
from pomil.training import load_checkpoint, resolve_device, save_checkpoint


def _policy_of(arch: Any) -> Any:
    """The network of a checkpoint's architecture: a Gaussian policy, or a diffusion policy."""
    if isinstance(arch, PolicyArch):
        return make_policy(arch)
    from pomil.nn.diffusion import DiffusionPolicy

    return DiffusionPolicy(arch)


class TrainedPolicy:
    """A policy with what it needs to act: its environment (``env``: id, kwargs,
    observation_mask) and, for PPO experts, its observation normaliser.

    A diffusion policy (learners ``diffusion``, ``diffusion-codes``) samples its plans with the
    generator that :meth:`reset` seeds: its actions are one seed's draw whether or not ``act`` is
    asked for deterministic ones (it has no mean action to return)."""

    def __init__(self, policy: Any, algo: str, env: dict[str, Any], device: torch.device | str = "cpu",
                 obs_norm: RunningNorm | None = None) -> None:
        self.policy = policy.to(device).eval()
        self.obs_norm = obs_norm.to(device) if obs_norm is not None else None
        self.algo = algo
        self.env = env
        self.device = torch.device(device)
        self._h: Any = None
        self._executed = executed_actions_fn(env.get("id", ""), env.get("kwargs") or {})

    @classmethod
    def load(cls, path: str | Path, device: torch.device | str = "cpu") -> TrainedPolicy:
        device = resolve_device(device)  # a bad device is reported as one, before the file is read
        ckpt = load_checkpoint(path, map_location=device)
        try:
            diffusion = isinstance(ckpt["policy_arch"], dict) and ckpt["policy_arch"].get("kind") == "diffusion"
            if diffusion:
                from pomil.nn.diffusion import DiffusionArch

            arch = DiffusionArch(**ckpt["policy_arch"]) if diffusion else PolicyArch(**ckpt["policy_arch"])
            for f in dataclasses.fields(arch):  # the file's values, with the declared types (no tensors, no None)
                value, tp = getattr(arch, f.name), {"int": int, "float": (int, float), "bool": bool, "str": str}[f.type]
                if not isinstance(value, tp) or (f.type != "bool" and isinstance(value, bool)):
                    raise TypeError(f"policy_arch.{f.name} is {value!r:.40}")
            policy = _policy_of(arch)
            policy.load_state_dict(ckpt["policy"])
            obs_norm = None
            if ckpt.get("obs_norm") is not None:
                obs_norm = RunningNorm(policy.arch.obs_dim)
                obs_norm.load_state_dict(ckpt["obs_norm"])
        except Exception as err:  # a damaged file: torch and the architecture raise many types
            first = (str(err).strip().splitlines() or [""])[0][:160]
            raise PomilError(f"{path}: checkpoint has no usable policy ({type(err).__name__}: {first})") from None
        env = ckpt.get("env", {})
        if (not isinstance(env, dict) or not isinstance(env.get("id", ""), str)
                or not isinstance(env.get("kwargs") or {}, dict)):
            raise PomilError(f"{path}: checkpoint's 'env' is not an environment description (got {env!r:.160})")
        try:
            return cls(policy, str(ckpt.get("algo", "?")), dict(env), device, obs_norm)
        except Exception as err:  # its environment cannot be built (unknown id, bad keywords)
            first = (str(err).strip().splitlines() or [""])[0][:160]
            raise PomilError(f"{path}: checkpoint's environment {env.get('id')!r} cannot be built "
                             f"({type(err).__name__}: {first})") from None

    def save(self, path: str | Path) -> None:
        """Write the policy alone (no critic, optimiser or RNG state): a small
        checkpoint that :meth:`load` and ``pomil evaluate`` read."""
        save_checkpoint(path, {"algo": self.algo, "env": self.env, "policy_arch": self.policy.arch.to_dict(),
                               "policy": {k: v.detach().cpu() for k, v in self.policy.state_dict().items()},
                               "obs_norm": None if self.obs_norm is None
                               else {k: v.cpu() for k, v in self.obs_norm.state_dict().items()}})

    @property
    def num_codes(self) -> int:
        """Number of discrete latent codes (0 for learners without codes and for continuous codes)."""
        return 0 if self.policy.arch.continuous_codes else self.policy.arch.num_codes

    @property
    def code_dim(self) -> int:
        """Dimension d of a continuous code (0 for discrete codes and learners without codes)."""
        return self.policy.arch.num_codes if self.policy.arch.continuous_codes else 0

    @property
    def code_prior(self) -> str | None:
        """The prior of a continuous code (``uniform`` on [-1, 1]^d or ``gaussian``), None otherwise."""
        return self.policy.arch.code_prior if self.code_dim else None

    @property
    def obs_dim(self) -> int:
        return self.policy.arch.obs_dim

    @property
    def act_dim(self) -> int:
        return self.policy.arch.act_dim

    def reset(self, num_envs: int, codes: Sequence[int] | np.ndarray | torch.Tensor | None = None,
              seed: int | None = None) -> None:
        """Start ``num_envs`` episodes.  ``codes``: one code per episode
        (default: 0, 1, ..., K-1, 0, 1, ...); for continuous codes an (num_envs, d) array of
        finite numbers (default: the prior's quantiles at (i + 0.5) / num_envs in every
        dimension, low to high); ignored without codes.  Bad arguments raise
        :class:`pomil.errors.InvalidArgument` (a ValueError) naming the argument."""
        # integers (numpy's too), not bools, floats or strings
        if isinstance(num_envs, (bool, np.bool_)) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise InvalidArgument(f"num_envs must be a positive integer, got {num_envs!r}")
        num_envs = int(num_envs)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise InvalidArgument(f"seed must be a non-negative integer or None, got {seed!r}")
        c = None
        if self.num_codes > 0:
            c = torch.arange(num_envs) % self.num_codes if codes is None else self._codes_arg(codes, num_envs)
        elif self.code_dim > 0:
            c = (prior_grid(self.policy.arch.code_prior, num_envs).unsqueeze(1).expand(-1, self.code_dim)
                 if codes is None else self._continuous_codes_arg(codes, num_envs))
        self._n = num_envs
        self._h = self.policy.initial_state(num_envs, self.device)
        self._prev = torch.zeros(num_envs, self.act_dim, device=self.device)
        self._start = torch.ones(num_envs, dtype=torch.bool, device=self.device)
        self._gen = torch.Generator(device=self.device)
        if seed is not None:
            self._gen.manual_seed(seed)
        else:
            self._gen.seed()
        self._codes = (None if c is None else
                       code_vectors(c, self.policy.arch.code_kind, self.policy.arch.num_codes).to(self.device))

    def _codes_arg(self, codes: Any, num_envs: int) -> torch.Tensor:
        """``codes`` as a (num_envs,) long tensor: integers only (no truncated floats, strings or bools)."""
        try:
            arr = codes.detach().cpu().numpy() if isinstance(codes, torch.Tensor) else np.asarray(codes)
        except ValueError:  # ragged lists
            raise InvalidArgument(f"codes must be {num_envs} integers in [0, {self.num_codes}), "
                                  f"got {codes!r}") from None
        want = f"codes must be {num_envs} integers in [0, {self.num_codes})"
        if arr.ndim == 2:
            raise InvalidArgument(f"{want} (this policy has {self.num_codes} discrete codes), got an array of shape "
                                  f"{arr.shape}")
        if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
            raise InvalidArgument(f"{want}, got {np.asarray(arr).tolist()!r} (dtype {arr.dtype})")
        if arr.shape != (num_envs,) or arr.min() < 0 or arr.max() >= self.num_codes:
            raise InvalidArgument(f"{want}, got {arr.tolist()}")
        return torch.as_tensor(arr, dtype=torch.long)

    def _continuous_codes_arg(self, codes: Any, num_envs: int) -> torch.Tensor:
        """``codes`` as a (num_envs, d) float tensor of finite numbers (no bools or strings)."""
        d = self.code_dim
        want = f"codes must be a ({num_envs}, {d}) array of finite numbers (this policy has a continuous code)"
        try:
            arr = codes.detach().cpu().numpy() if isinstance(codes, torch.Tensor) else np.asarray(codes)
        except ValueError:  # ragged lists
            raise InvalidArgument(f"{want}, got {codes!r:.80}") from None
        if arr.dtype == np.bool_ or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise InvalidArgument(f"{want}, got dtype {arr.dtype}")
        if arr.shape != (num_envs, d):
            raise InvalidArgument(f"{want}, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise InvalidArgument(f"{want}, got NaN/inf")
        return torch.as_tensor(arr, dtype=torch.float32)

    @torch.no_grad()
    def act(self, observations: np.ndarray | torch.Tensor, deterministic: bool = False) -> np.ndarray | torch.Tensor:
        """Actions for one step of every episode; numpy in, numpy out."""
        if self._h is None:
            raise RuntimeError("call reset(num_envs, codes) before act()")
        as_numpy = not isinstance(observations, torch.Tensor)
        try:
            obs = torch.as_tensor(np.asarray(observations) if as_numpy else observations, dtype=torch.float32,
                                  device=self.device)
        except (TypeError, ValueError):
            raise InvalidArgument(f"observations must be a ({self._n}, {self.obs_dim}) array of numbers") from None
        if obs.shape != (self._n, self.obs_dim):
            raise InvalidArgument(f"observations must have shape ({self._n}, {self.obs_dim}), got {tuple(obs.shape)}")
        finite = torch.isfinite(obs).all(-1)
        if not bool(finite.all()):  # refused before it reaches (and poisons) the recurrent state
            rows = (~finite).nonzero().flatten().tolist()
            raise InvalidArgument(f"observations must be finite; rows {rows[:10]} hold NaN/inf (state unchanged)")
        if self.obs_norm is not None:
            obs = self.obs_norm(obs)
        if isinstance(self.policy, GaussianPolicy):
            dist, self._h = self.policy.step(obs, self._prev, self._h, self._start, self._codes)
            action = dist.mean
            if not deterministic:
                action = action + dist.stddev * torch.randn(dist.mean.shape, generator=self._gen, device=self.device)
        else:  # a diffusion policy: its receding-horizon plans, drawn with this generator
            action, self._h = self.policy.act(obs, self._h, self._start, self._codes, self._gen)
        self._prev = self._executed(action)  # a_{t-1} as the environment carried it out, as in training
        self._start = torch.zeros_like(self._start)
        return action.cpu().numpy() if as_numpy else action
