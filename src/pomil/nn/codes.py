"""Latent codes: discrete (one of K, one-hot) or continuous (c in R^d, InfoGAIL's continuous c).

A code enters the policy and the value network as a vector: one-hot (K wide) or the
continuous c itself (d wide), embedded linearly in both cases.  The posterior's output
gives log P(c | b): K logits (categorical) or, for continuous codes, a mean and a log
std per dimension (a diagonal Gaussian, log std clamped to ``LOG_STD_RANGE``).

The continuous prior is ``uniform`` on [-1, 1]^d or a standard ``gaussian``.  Its
quantiles place codes evenly over the prior (evaluation grids, default codes) and
:func:`spread_as_prior` moves a set of codes onto the prior by their ranks.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

CODE_PRIORS = ("uniform", "gaussian")
LOG_STD_RANGE = (-5.0, 2.0)
"""The continuous posterior's log std is clamped here: std in [0.0067, 7.4].  Without a floor
log N(c; mu, sigma) grows without bound as sigma shrinks, and with it the reward term."""


def _check_prior(prior: str) -> None:
    if prior not in CODE_PRIORS:
        raise ValueError(f"unknown code prior {prior!r}; expected one of {list(CODE_PRIORS)}")


def sample_prior(prior: str, n: int, dim: int, generator: torch.Generator) -> torch.Tensor:
    """n codes (n, dim) from the prior: uniform on [-1, 1]^dim or a standard Gaussian."""
    _check_prior(prior)
    if prior == "uniform":
        return 2 * torch.rand(n, dim, generator=generator) - 1
    return torch.randn(n, dim, generator=generator)


def prior_quantile(prior: str, p: torch.Tensor) -> torch.Tensor:
    """The prior's quantile function per dimension at probabilities ``p`` in (0, 1)."""
    _check_prior(prior)
    return 2 * p - 1 if prior == "uniform" else math.sqrt(2) * torch.erfinv(2 * p - 1)


def prior_grid(prior: str, n: int) -> torch.Tensor:
    """n values evenly spread over the prior: its quantiles at (i + 0.5) / n, i = 0 .. n-1.

    >>> prior_grid("uniform", 4).tolist()
    [-0.75, -0.25, 0.25, 0.75]"""
    return prior_quantile(prior, (torch.arange(n, dtype=torch.float32) + 0.5) / n)


def spread_as_prior(codes: torch.Tensor, prior: str) -> torch.Tensor:
    """Codes (E, d) moved onto the prior, dimension by dimension, keeping their order: the
    i-th smallest of E values becomes the prior's quantile at (i + 0.5) / E.  The continuous
    counterpart of balancing a mixture's codes (every code 1/K of the episodes): the codes
    of the demonstrations are then spread exactly as the prior that rollouts draw from."""
    e = codes.shape[0]
    ranks = codes.argsort(0).argsort(0).to(codes.dtype)
    return prior_quantile(prior, (ranks + 0.5) / e)


def draw_codes(kind: str, prior: str, n: int, *, width: int,
               generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """n episodes' codes from the prior, as (codes, vectors): discrete, the indices (n,) uniform
    over the K = ``width`` codes and their one-hot vectors (n, K) (no codes when ``width`` is 0:
    indices 0 and (n, 0) vectors); continuous, the codes (n, d) twice."""
    if kind == "discrete":
        idx = torch.randint(max(width, 1), (n,), generator=generator)
        return idx, (F.one_hot(idx, width).float() if width else torch.zeros(n, 0))
    codes = sample_prior(prior, n, width, generator)
    return codes, codes


def code_log_likelihood(out: torch.Tensor, codes: torch.Tensor, kind: str) -> torch.Tensor:
    """log P(c | b) per step from the posterior's output ``out`` (..., K) or (..., 2d).

    ``codes``: discrete, the code indices (...) (long); continuous, the codes (..., d).
    Continuous: out = [mean (d), log std (d)], log std clamped to ``LOG_STD_RANGE``,
    log N(c; mean, std) summed over the d dimensions."""
    if kind == "discrete":
        return torch.log_softmax(out, -1).gather(-1, codes.unsqueeze(-1)).squeeze(-1)
    mean, log_std = gaussian_params(out)
    z = (codes - mean) / log_std.exp()
    return (-0.5 * z ** 2 - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)


def gaussian_params(out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean, clamped log std) of a continuous posterior's output (..., 2d)."""
    d = out.shape[-1] // 2
    return out[..., :d], out[..., d:].clamp(*LOG_STD_RANGE)


def code_vectors(codes: torch.Tensor, kind: str, width: int) -> torch.Tensor:
    """What the networks take: one-hot (..., K) of discrete indices; continuous codes as they are."""
    return F.one_hot(codes, width).float() if kind == "discrete" else codes.float()
