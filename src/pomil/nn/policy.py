"""Gaussian policy pi(a | encoder(history), c) with an optional latent code.

The code c (one-hot, K codes; or a continuous c in R^d, see ``pomil.nn.codes``)
is embedded linearly and added to the encoder's features, as in the paper's
code.  The log standard deviation is a learned state-independent vector.
``tanh_mean`` squashes the mean into (-1, 1) (the paper's Hopper code).
:class:`EnsemblePolicy` is several such policies acting as one (``PolicyArch.members``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import torch
from torch import nn
from torch.distributions import Normal

from pomil.nn.codes import CODE_PRIORS
from pomil.nn.encoders import EnsembleEncoder, make_encoder


@dataclass(frozen=True)
class PolicyArch:
    """What it takes to rebuild a policy from its state dict.

    ``encoder``: one of ``pomil.nn.encoders.ENCODERS``; ``context``: the attention
    encoder's window in steps (ignored by the others); ``obs_delta`` and
    ``prev_action``: what the encoder sees of each step (``pomil.nn.encoders.InputView``).
    ``num_codes``: width of the code input, K one-hot codes or the dimension d of a continuous
    code (``code_kind``), drawn from ``code_prior`` (``pomil.nn.codes``; continuous codes only).
    ``members``: policies of this architecture acting as one (:class:`EnsemblePolicy`; 1: one policy)."""

    obs_dim: int
    act_dim: int
    encoder: str = "gru"
    hidden_size: int = 128
    num_codes: int = 0
    log_std_init: float = -1.0
    tanh_mean: bool = False
    context: int = 32
    obs_delta: bool = False
    prev_action: bool = True
    code_kind: str = "discrete"
    code_prior: str = "uniform"
    members: int = 1

    def __post_init__(self) -> None:
        if self.members < 1:
            raise ValueError(f"members must be at least 1, got {self.members}")
        if self.code_kind not in ("discrete", "continuous"):
            raise ValueError(f"code_kind must be 'discrete' or 'continuous', got {self.code_kind!r}")
        if self.code_prior not in CODE_PRIORS:
            raise ValueError(f"code_prior must be one of {list(CODE_PRIORS)}, got {self.code_prior!r}")

    @property
    def continuous_codes(self) -> bool:
        return self.code_kind == "continuous" and self.num_codes > 0

    def to_dict(self) -> dict[str, Any]:
        """The fields; ``context`` only for the attention encoder, ``obs_delta`` and ``prev_action``
        only when not their defaults, ``code_kind`` and ``code_prior`` only for continuous codes,
        ``members`` only for an ensemble (so that other policies' checkpoints are as before these existed;
        a checkpoint without them loads with the defaults: discrete codes, one policy)."""
        d = asdict(self)
        if self.encoder != "attention":
            del d["context"]
        if not self.continuous_codes:
            del d["code_kind"], d["code_prior"]
        for key, default in (("obs_delta", False), ("prev_action", True), ("members", 1)):
            if d[key] == default:
                del d[key]
        return d


class GaussianPolicy(nn.Module):
    def __init__(self, arch: PolicyArch) -> None:
        super().__init__()
        self.arch = arch
        self.encoder = make_encoder(arch.encoder, arch.obs_dim, arch.act_dim, hidden_size=arch.hidden_size,
                                    context=arch.context, obs_delta=arch.obs_delta, prev_action=arch.prev_action)
        feat = self.encoder.out_size
        self.code_embed = nn.Linear(arch.num_codes, feat, bias=False) if arch.num_codes > 0 else None
        self.mean = nn.Sequential(nn.Linear(feat, arch.hidden_size), nn.ELU(),
                                  nn.Linear(arch.hidden_size, arch.act_dim))
        self.log_std = nn.Parameter(torch.full((arch.act_dim,), float(arch.log_std_init)))

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return self.encoder.initial_state(batch, device)

    def dist(self, features: torch.Tensor, codes: torch.Tensor | None = None) -> Normal:
        """The action distribution from encoder features (..., feat) and codes (..., K) (one-hot,
        or continuous (..., d)) that broadcast against them (e.g. (N, K) codes for (T, N, feat) features)."""
        if self.code_embed is not None:  # codes are ignored by a policy without them
            if codes is None:
                raise ValueError("this policy has latent codes: pass them (one-hot, or continuous)")
            features = features + self.code_embed(codes)
        mean = self.mean(features).float()  # float32 under an autocast too (precision bfloat16), as the log std
        if self.arch.tanh_mean:
            mean = torch.tanh(mean)
        # No argument validation: the NaN of a diverging policy must reach the loss, where the
        # divergence guard names it (pomil.training), not end deep inside torch.distributions.
        return Normal(mean, self.log_std.exp().expand_as(mean), validate_args=False)

    def step(self, obs, prev_action, h, start, codes=None) -> tuple[Normal, torch.Tensor]:
        """One step for N environments: obs (N, obs_dim) ... -> (dist, new h)."""
        feats, h = self.encoder.step(obs, prev_action, h, start)
        return self.dist(feats, codes), h

    def features(self, obs, prev_actions, h0, starts) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoder over a (T, N) block: (features (T, N, feat), final state)."""
        return self.encoder.unroll(obs, prev_actions, h0, starts)

    def unroll(self, obs, prev_actions, h0, starts, codes=None) -> tuple[Normal, torch.Tensor]:
        """A (T, N) block of steps; codes (N, K) or (T, N, K)."""
        feats, h = self.features(obs, prev_actions, h0, starts)
        if codes is not None and codes.ndim == 2:
            codes = codes.unsqueeze(0).expand(feats.shape[0], -1, -1)
        return self.dist(feats, codes), h

    def dist_every_code(self, features: torch.Tensor) -> Normal:
        """The action distribution under each of the K codes: batch shape (K, *features.shape[:-1], act_dim)."""
        if not self.arch.num_codes or self.arch.continuous_codes:
            raise ValueError("this policy has no discrete latent codes")
        k = self.arch.num_codes
        lead = features.shape[:-1]
        codes = torch.eye(k, device=features.device).view(k, *(1,) * len(lead), k).expand(k, *lead, k)
        return self.dist(features.unsqueeze(0).expand(k, *features.shape), codes)

    def unroll_every_code(self, obs, prev_actions, h0, starts) -> Normal:
        """The action distribution under each of the K codes for a (T, N) block:
        batch shape (K, T, N, act_dim).  The encoder runs once (the code enters after it)."""
        return self.dist_every_code(self.features(obs, prev_actions, h0, starts)[0])


class EnsemblePolicy(GaussianPolicy):
    """``arch.members`` Gaussian policies acting as one: each member keeps its own encoder state and reads
    the same observations and previous actions (those carried out: the ensemble's), and the ensemble's mean
    action is the average of the members' means (after ``tanh_mean``), under the ensemble's own state-independent
    log std.  Its features and state are the members' side by side (:class:`pomil.nn.encoders.EnsembleEncoder`),
    so it runs wherever a :class:`GaussianPolicy` does.  ``members[i]`` is member i as a policy of its own: the
    warm start clones each on its own (``pomil.algos.warm_start.clone_members``)."""

    def __init__(self, arch: PolicyArch) -> None:
        nn.Module.__init__(self)
        self.arch = arch
        one = replace(arch, members=1)
        first = GaussianPolicy(one)
        with torch.random.fork_rng(devices=[]):  # the run's random numbers go on as after one policy
            rest = [GaussianPolicy(one) for _ in range(arch.members - 1)]
        self.members = nn.ModuleList([first, *rest])
        self.encoder = EnsembleEncoder([p.encoder for p in self.members])
        self.log_std = nn.Parameter(torch.full((arch.act_dim,), float(arch.log_std_init)))

    def dist(self, features: torch.Tensor, codes: torch.Tensor | None = None) -> Normal:
        parts = features.split(self.encoder.feature_sizes, dim=-1)
        mean = torch.stack([p.dist(f, codes).mean for p, f in zip(self.members, parts, strict=True)]).mean(0)
        return Normal(mean, self.log_std.exp().expand_as(mean), validate_args=False)


def make_policy(arch: PolicyArch) -> GaussianPolicy:
    """The policy of an architecture: one :class:`GaussianPolicy`, or an :class:`EnsemblePolicy` of ``members``."""
    return EnsemblePolicy(arch) if arch.members > 1 else GaussianPolicy(arch)


def shift_actions(actions: torch.Tensor) -> torch.Tensor:
    """Previous actions a_{t-1} for a time-major (T, N, act_dim) block, zero at t = 0."""
    return torch.cat([torch.zeros_like(actions[:1]), actions[:-1]], dim=0)
