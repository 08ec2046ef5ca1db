"""The mixture warm start: behaviour cloning of unlabelled demonstrations, each latent code cloning its own
cluster of episodes.

The cloning steps (``bc_step`` on batches of whole episodes, shared with the BC learner), the codes'
mixture likelihood balanced over the whole demonstration set (:class:`MixtureAssignment`), continuous
codes' episode codes (:class:`EpisodeCodes`), the log std's maximum-likelihood fit, and the warm start's
schedules and loops that the adversarial learners run before their first iteration (and the
``--num-codes auto`` search runs for each K).
"""

from __future__ import annotations

import itertools
import math
import random
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pomil.config import option
from pomil.data import PaddedEpisodes
from pomil.nn.codes import sample_prior, spread_as_prior
from pomil.nn.encoders import fit_input_scale
from pomil.nn.policy import EnsemblePolicy, GaussianPolicy, shift_actions
from pomil.training import DivergenceGuard, precision_context, progress_bar, seed_everything

if TYPE_CHECKING:
    from pomil.algos.adversarial import AdversarialConfig


@dataclass(frozen=True)
class WarmStartOptions:
    """The mixture warm start: behaviour cloning of the demonstrations before the first adversarial iteration."""

    warm_start_iterations: int = option(600, "behaviour-cloning steps on the demonstrations before adversarial "
                                             "training (the warm start; 0: off)", within="[0, inf)")
    warm_start_lr: float = option(1e-2, "Adam learning rate of the behaviour-cloning warm start (its peak; see "
                                     "warm_start_lr_warmup and warm_start_lr_decay)", within="(0, inf)")
    warm_start_lr_decay: bool = option(True, "decay the warm start's learning rate linearly to 0 over its steps")
    warm_start_lr_warmup: float = option(0.2, "the share of the warm start's steps over which its learning rate "
                                              "first rises linearly from 0 to warm_start_lr (with warm_start_lr_decay, "
                                              "the decay follows over the rest)", within="[0, 1)")
    warm_start_log_std_lr_scale: float = option(1.0, "the warm start's learning rate of the policy's log std, as a "
                                                  "multiple of warm_start_lr (Adam moves a parameter by about lr a "
                                                  "step: at 1x the log std needs thousands of steps to fit "
                                                  "deterministic demonstrations)", within="(0, inf)")
    warm_start_fit_log_std: bool = option(False, "end the warm start by setting the log std to its maximum-likelihood "
                                              "value given the means: each action dimension's mean squared error on "
                                              "all demonstrations (weighted by the codes' responsibilities)")
    warm_start_code_lr_scale: float = option(10.0, "continuous codes with warm_start_codes mixture: the warm start's "
                                                "learning rate of the episodes' own codes, as a multiple of "
                                                "warm_start_lr", within="(0, inf)")
    warm_start_batch: int = option(64, "episodes per behaviour-cloning warm-start step and BC-term batch (at most "
                                    "max_batch_steps and warm_start_batch_share's part of the demonstrations)",
                                   within="[1, inf)")
    warm_start_batch_share: int = option(4, "where all the demonstrations' windows or episodes fit in one "
                                            "warm_start_batch, a cloning step (warm start, BC term) draws at most "
                                            "1/N of them, never fewer than 8: a batch of all of them overfits them "
                                            "(standard Hopper: pomil docs hopper, \"How much a cloning step "
                                            "draws\"; 0: no cut)",
                                         within="[0, inf)")
    warm_start_codes: Literal["random", "mixture"] = option("mixture",
                                                         "codes in the warm start: random per episode (InfoGAIL), or "
                                                         "mixture: each code clones its own cluster of episodes "
                                                         "(mixture likelihood; continuous codes: each episode's own "
                                                         "code, fitted with the policy and spread as the prior)")
    mixture_balance: Literal["dataset", "batch"] = option("dataset",
                                                          "with warm_start_codes mixture: every code takes 1/K of "
                                                          "all demonstration episodes (dataset, refreshed every 10 "
                                                          "steps or pass) or of each random batch (batch: noisier, "
                                                          "see MixtureAssignment)")
    warm_start_min_log_std: float = option(-20.0, "raise the warm-started policy's log std to at least this, the "
                                                  "adversarial phase's action noise (-20: fitted)", within="[-20, 2]")
    warm_start_window: int = option(128, "with warm_start_codes mixture and mixture_balance dataset, for a recurrent "
                                           "policy: episodes longer than this are cloned (warm start and BC term) in "
                                           "windows of this many steps, each from the policy's state at its start as "
                                           "the last whole-set pass left it (truncated backpropagation, batches of "
                                           "warm_start_batch windows; 0: whole episodes)", within="[0, inf)")
    warm_start_restarts: int = option(1, "warm starts from this many initialisations (the run's seed, then seeds "
                                         "drawn from it); the one whose deterministic rollouts lie nearest the "
                                         "demonstrations goes on (the hand_over distance, never the environment's "
                                         "reward; 1: the run's own only)", within="[1, inf)")
    posterior_init_iterations: int = option(200, "with warm_start_codes mixture: posterior steps on the "
                                                 "demonstrations, each episode labelled with its most likely code",
                                            within="[0, inf)")
    posterior_init_tolerance: float = option(
        0.01, "with discrete codes: the posterior's warm start stops before posterior_init_iterations once its "
              "cross-entropy (nats per step) has stayed below this for 10 steps in a row: it tells the episodes' "
              "codes apart (0: all the steps)", within="[0, inf)")


FAST_WARM_START: dict[str, Any] = {
    "warm_start_iterations": 600, "warm_start_lr": 3e-3, "warm_start_lr_decay": True, "warm_start_lr_warmup": 0.0,
    "warm_start_log_std_lr_scale": 10.0, "warm_start_fit_log_std": True,
}
"""The fast warm start's settings (preset fast-warm-start; every K's fit of ``--num-codes auto``)."""


TERMINATING_WARM_START: dict[str, Any] = {**FAST_WARM_START, "warm_start_iterations": 2400}
"""Preset terminating's warm start: the fast schedule over 2400 steps.  On standard Hopper's 1000-step episodes 600
steps leave the clone under-trained; 2400 lift it on positions and on velocities alone (docs/hopper.md, "How long the
warm start clones")."""


LONG_WARM_START: dict[str, Any] = {
    "warm_start_iterations": 3000, "warm_start_lr": 1e-3, "warm_start_lr_decay": False, "warm_start_lr_warmup": 0.0,
    "warm_start_log_std_lr_scale": 1.0, "warm_start_fit_log_std": False,
}
"""Preset long-warm-start: 3000 steps at a constant lr 1e-3."""


DEEP_WARM_START: dict[str, Any] = {**FAST_WARM_START, "warm_start_lr": 1e-2, "warm_start_lr_warmup": 0.2}
"""Preset deep-warm-start: the default's schedule with the fast warm start's log std (10x and fitted)."""


def bc_loss(policy: GaussianPolicy, obs: torch.Tensor, actions: torch.Tensor, *, mask: torch.Tensor,
            prev_actions: torch.Tensor | None = None,
            codes: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Masked mean negative log-likelihood over a (T, B) block of whole episodes.

    ``prev_actions`` (a_{t-1} as the environment carried it out) defaults to
    the shifted ``actions``; ``codes`` (B, K) one-hot, for a policy with codes."""
    feats = episode_features(policy, obs, shift_actions(actions) if prev_actions is None else prev_actions, mask)
    return _nll(policy, policy.dist(feats, codes), actions, mask)


def episode_features(policy: GaussianPolicy, obs: torch.Tensor, prev_actions: torch.Tensor,
                     mask: torch.Tensor) -> torch.Tensor:
    """The policy's encoder over a (T, B) block of whole episodes, from a zero state."""
    return policy.features(obs, prev_actions, policy.initial_state(mask.shape[1], mask.device),
                           first_step_starts(mask))[0]


def first_step_starts(mask: torch.Tensor) -> torch.Tensor:
    """Episode starts (T, B) of whole episodes: the first step of each column."""
    starts = torch.zeros_like(mask)
    starts[0] = True
    return starts


def _nll(policy: GaussianPolicy, dist, actions: torch.Tensor,
         mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    m = mask.to(actions.dtype)
    nll = -(dist.log_prob(actions).sum(-1) * m).sum() / m.sum()
    mse = (((dist.mean - actions) ** 2).sum(-1) * m).sum() / m.sum()
    return nll, {"bc/nll": nll.item(), "bc/action_mse": mse.item(), "bc/log_std": policy.log_std.mean().item()}


def demo_batch(data: PaddedEpisodes, prev_actions: torch.Tensor, batch_episodes: int,
               generator: torch.Generator) -> tuple[PaddedEpisodes, torch.Tensor, torch.Tensor]:
    """A random batch of whole demonstration episodes, their previous actions and their indices."""
    n_ep = data.mask.shape[1]
    idx = torch.randint(n_ep, (min(batch_episodes, n_ep),), generator=generator).to(data.mask.device)
    return data.select(idx), prev_actions[:, idx], idx


class MixtureAssignment:
    """Which code clones which demonstration episode: balanced responsibilities (K, E) over the
    *whole* demonstration set, recomputed from the policy every ``refresh`` calls of :meth:`update`.

    Balancing each random batch on its own forces the episodes of whatever mode the batch over-samples
    onto other codes; balancing over all episodes has no such noise (docs/method.md).
    """

    def __init__(self, data: PaddedEpisodes, prev_actions: torch.Tensor, refresh: int = 10, chunk: int = 256,
                 window: int = 0) -> None:
        self.data, self.prev_actions, self.refresh, self.chunk = data, prev_actions, refresh, chunk
        self.window = window if 0 < window < data.mask.shape[0] else 0
        """Steps per cloning window (0: whole episodes): the refresh also keeps the policy's state at each
        window's start, ``states`` (J, E, S), from which :meth:`windows` draws."""
        self.responsibilities: torch.Tensor | None = None
        self.states: torch.Tensor | None = None
        self._calls = 0

    def update(self, policy: GaussianPolicy) -> torch.Tensor:
        """The current responsibilities (K, E), recomputed on every ``refresh``-th call."""
        if (self.responsibilities is None or self._calls % self.refresh == 0
                or (self.window and self.states is None)):
            ll, self.states = demonstration_pass(policy, self.data, self.prev_actions, chunk=self.chunk,
                                                 window=self.window)
            self.responsibilities = balanced_responsibilities(ll)
        self._calls += 1
        return self.responsibilities

    def windows(self, policy: GaussianPolicy, count: int, generator: torch.Generator
                ) -> tuple[PaddedEpisodes, torch.Tensor, torch.Tensor]:
        """``count`` random windows (at most as many as there are) after :meth:`update`: the batch (window,
        n), the policy's features on it from each window's stored state, and the responsibilities of each
        window's episode (K, n)."""
        resp = self.update(policy)
        assert self.states is not None
        batch, prev, h0, starts, episode = demo_windows(self.data, self.prev_actions, self.states, count=count,
                                                        window=self.window, generator=generator)
        return batch, policy.features(batch.observations, prev, h0, starts)[0], resp[:, episode]

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The calls made, the responsibilities and window states of the last refresh (empty before the first):
        what a resumed run needs to refresh at the same steps from the same values (``RunLoop.start``'s
        ``carried``)."""
        resp = self.responsibilities if self.responsibilities is not None else torch.empty(0, 0)
        states = self.states if self.states is not None else torch.empty(0, 0, 0)
        return {"calls": torch.tensor(self._calls), "responsibilities": resp.detach().clone(),
                "states": states.detach().clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        calls, resp = state["calls"], state["responsibilities"]
        states = state.get("states", torch.empty(0, 0, 0))  # older checkpoints: none (the next call refreshes)
        if not (isinstance(calls, torch.Tensor) and calls.numel() == 1 and not calls.is_floating_point()
                and int(calls) >= 0 and isinstance(resp, torch.Tensor) and resp.ndim == 2
                and isinstance(states, torch.Tensor) and states.ndim == 3):
            raise ValueError("the code assignment's state is damaged")
        episodes = self.data.mask.shape[1]
        if resp.numel() and (resp.shape[1] != episodes or not resp.is_floating_point()):
            raise ValueError(f"the code assignment covers {resp.shape[1]} episodes, not the {episodes} demonstrated")
        if states.numel() and states.shape[1] != episodes:
            raise ValueError(f"the code assignment's window states cover {states.shape[1]} episodes, not {episodes}")
        self._calls = int(calls)
        self.responsibilities = resp.to(self.data.mask.device) if resp.numel() else None
        self.states = states.to(self.data.mask.device) if states.numel() and self.window else None


@torch.no_grad()
def demonstration_pass(policy: GaussianPolicy, data: PaddedEpisodes, prev_actions: torch.Tensor, *, chunk: int = 256,
                       window: int = 0) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Each whole episode's log-likelihood under each of the policy's codes, (K, E), and with a ``window``
    the policy's state at the start of each window of that many steps, (J, E, S) (else None)."""
    lls, states = [], []
    for start in range(0, data.mask.shape[1], chunk):
        idx = torch.arange(start, min(start + chunk, data.mask.shape[1]), device=data.mask.device)
        part = data.select(idx)
        if window:
            feats, part_states = window_features(policy, part.observations, prev_actions[:, idx],
                                                 mask=part.mask, window=window)
            states.append(part_states)
        else:
            feats = episode_features(policy, part.observations, prev_actions[:, idx], part.mask)
        lls.append(_code_log_likelihoods(policy.dist_every_code(feats), part))
    return torch.cat(lls, dim=1), torch.cat(states, dim=1) if window else None


def window_features(policy: GaussianPolicy, obs: torch.Tensor, prev_actions: torch.Tensor, *, mask: torch.Tensor,
                    window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The policy's encoder over a (T, B) block of whole episodes unrolled ``window`` steps at a time with
    the state carried (the features of one unroll), and the state at each window's start, (J, B, S)."""
    starts, h = first_step_starts(mask), policy.initial_state(mask.shape[1], mask.device)
    feats, states = [], []
    for a in range(0, mask.shape[0], window):
        states.append(h)
        f, h = policy.features(obs[a:a + window], prev_actions[a:a + window], h, starts[a:a + window])
        feats.append(f)
    return torch.cat(feats), torch.stack(states)


def demo_windows(data: PaddedEpisodes, prev_actions: torch.Tensor, states: torch.Tensor, *, count: int, window: int,
                 generator: torch.Generator) -> tuple[PaddedEpisodes, torch.Tensor, torch.Tensor, torch.Tensor,
                                                      torch.Tensor]:
    """``count`` random windows of ``window`` steps (at most as many as hold a demonstrated step), drawn
    with replacement from those that start at a multiple of ``window`` within an episode: the batch
    (window, n) (steps past the episode's end masked out), previous actions, the stored states
    ``states`` (J, E, S) at their starts (n, S), their episode starts (window, n) and their episodes (n,)."""
    steps, dev = data.mask.shape[0], data.mask.device
    first = torch.arange(states.shape[0], device=dev).unsqueeze(1) * window
    pairs = (first < data.mask.sum(0)).nonzero()  # (window index, episode) with a demonstrated step
    pick = pairs[torch.randint(len(pairs), (min(count, len(pairs)),), generator=generator).to(dev)]
    j, episode = pick[:, 0], pick[:, 1]
    t = j.unsqueeze(0) * window + torch.arange(window, device=dev).unsqueeze(1)  # (window, n)
    inside, e = t < steps, episode.unsqueeze(0).expand_as(t)
    t = t.clamp(max=steps - 1)
    batch = PaddedEpisodes(data.observations[t, e], data.actions[t, e], data.mask[t, e] & inside)
    starts = torch.zeros_like(batch.mask)
    starts[0] = j == 0
    return batch, prev_actions[t, e], states[j, episode], starts, episode


def _code_log_likelihoods(dist_every_code, data: PaddedEpisodes) -> torch.Tensor:
    """(K, B): each whole episode's log-likelihood under each code."""
    m = data.mask.to(data.observations.dtype)
    return (dist_every_code.log_prob(data.actions.unsqueeze(0)).sum(-1) * m).sum(1)


def demo_nll(policy: GaussianPolicy, features: torch.Tensor, batch: PaddedEpisodes, *, generator: torch.Generator,
             num_codes: int = 0, mixture: bool = False, responsibilities: torch.Tensor | None = None,
             codes: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Behaviour-cloning loss of a batch of whole demonstration episodes from the policy's encoder
    features on them (:func:`episode_features`).  A policy with latent codes gets a random code per
    episode (demonstrations carry none), or, with ``mixture``, the codes' mixture likelihood
    (:func:`mixture_bc_loss`), each episode weighted by the given ``responsibilities`` (K, B)
    (:class:`MixtureAssignment`), or by responsibilities balanced within the batch.  ``codes``
    (B, width): each episode's own code vector instead (continuous codes, :class:`EpisodeCodes`)."""
    if codes is not None:
        return _nll(policy, policy.dist(features, codes), batch.actions, batch.mask)
    if mixture:
        loss, _, stats = _mixture_nll(policy, policy.dist_every_code(features), batch, responsibilities)
        return loss, stats
    b = batch.mask.shape[1]
    codes = (F.one_hot(torch.randint(num_codes, (b,), generator=generator), num_codes).float().to(features.device)
             if num_codes else None)
    return _nll(policy, policy.dist(features, codes), batch.actions, batch.mask)


def demo_bc_loss(policy: GaussianPolicy, data: PaddedEpisodes, prev_actions: torch.Tensor, *, batch_episodes: int,
                 generator: torch.Generator, num_codes: int = 0, mixture: bool = False,
                 assignment: MixtureAssignment | None = None,
                 codes_of: Callable[[torch.Tensor], torch.Tensor] | None = None,
                 ) -> tuple[torch.Tensor, dict[str, float]]:
    """Behaviour-cloning loss (:func:`demo_nll`) on a random batch of whole demonstration episodes;
    with ``mixture`` and an ``assignment``, each episode is cloned by the codes it assigns; with
    ``codes_of``, episode ``i`` under the code vector ``codes_of(i)`` (continuous codes: each
    episode's own, :class:`EpisodeCodes`, whose batch rows then learn too; or random ones)."""
    if mixture and assignment is not None and assignment.window:
        batch, feats, resp = assignment.windows(policy, batch_episodes, generator)
        return demo_nll(policy, feats, batch, generator=generator, mixture=True, responsibilities=resp)
    batch, prev, idx = demo_batch(data, prev_actions, batch_episodes, generator)
    resp = assignment.update(policy)[:, idx] if mixture and assignment is not None else None
    return demo_nll(policy, episode_features(policy, batch.observations, prev, batch.mask), batch, generator=generator,
                    num_codes=num_codes, mixture=mixture, responsibilities=resp,
                    codes=codes_of(idx) if codes_of is not None else None)


def bc_step(policy: GaussianPolicy, optimizer: torch.optim.Optimizer, data: PaddedEpisodes, *,
            prev_actions: torch.Tensor,
            batch_episodes: int, generator: torch.Generator, num_codes: int = 0, mixture: bool = False,
            assignment: MixtureAssignment | None = None,
            codes_of: Callable[[torch.Tensor], torch.Tensor] | None = None) -> dict[str, float]:
    """One update of :func:`demo_bc_loss`."""
    loss, stats = demo_bc_loss(policy, data, prev_actions, batch_episodes=batch_episodes, generator=generator,
                               num_codes=num_codes, mixture=mixture, assignment=assignment, codes_of=codes_of)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return stats


def mixture_bc_loss(policy: GaussianPolicy, data: PaddedEpisodes,
                    prev_actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    """Behaviour cloning of unlabelled episodes by a mixture of the policy's K codes (EM).

    Each episode's log-likelihood under each code, L_k = sum_t log pi(a_t | b_t, k), gives
    responsibilities q (K, B); the loss is -sum_k q_k L_k per step, so each code clones the
    episodes it is responsible for.  The responsibilities are balanced so that every code
    is responsible for 1/K of the batch (Sinkhorn iterations on the whole-episode
    log-likelihoods): the code prior is uniform, and without balancing the code that
    starts out slightly better takes every episode and the others never learn.
    Returns (loss per step, responsibilities, stats)."""
    feats = episode_features(policy, data.observations, prev_actions, data.mask)
    return _mixture_nll(policy, policy.dist_every_code(feats), data)


def _mixture_nll(policy: GaussianPolicy, dist_every_code, data: PaddedEpisodes,
                 resp: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    m = data.mask.to(data.observations.dtype)
    ll = _code_log_likelihoods(dist_every_code, data)
    resp = balanced_responsibilities(ll.detach()) if resp is None else resp
    loss = -(resp * ll).sum() / m.sum()
    return loss, resp, {"bc/nll": loss.item(), "bc/responsibility_max": resp.max(0).values.mean().item(),
                        "bc/log_std": policy.log_std.mean().item()}


@torch.no_grad()
def fit_log_std(policy: GaussianPolicy, data: PaddedEpisodes, prev_actions: torch.Tensor,
                *, mixture: bool = False, codes: torch.Tensor | None = None) -> dict[str, float]:
    """Set the policy's state-independent log std to its maximum-likelihood value given its
    means on all demonstration steps: log std_d = 0.5 log mean_t (a_td - mu_td)^2.  With
    ``mixture``, each code's squared errors count with its balanced responsibility for the
    episode (those of :func:`mixture_bc_loss`, under the std before the fit); a policy with
    codes but no mixture counts every code alike (the expectation under a random code).
    ``codes`` (E, width): each episode's own code (continuous codes, :class:`EpisodeCodes`).
    Returns the demonstrations' NLL per step after the fit (with ``mixture``) and the log std."""
    feats = episode_features(policy, data.observations, prev_actions, data.mask)
    m = data.mask.to(data.actions.dtype)
    if codes is not None:
        sq = (policy.dist(feats, codes).mean - data.actions) ** 2
    elif policy.arch.num_codes:
        dist, k = policy.dist_every_code(feats), policy.arch.num_codes
        resp = _mixture_nll(policy, dist, data)[1] if mixture else torch.full((k, m.shape[1]), 1 / k, device=m.device)
        sq = (resp[:, None, :, None] * (dist.mean - data.actions.unsqueeze(0)) ** 2).sum(0)
    else:
        sq = (policy.dist(feats).mean - data.actions) ** 2
    var = (sq * m.unsqueeze(-1)).sum((0, 1)) / m.sum()
    policy.log_std.copy_(0.5 * var.clamp_min(1e-12).log())
    stats = {"bc/log_std": policy.log_std.mean().item()}
    if mixture and policy.arch.num_codes:
        stats["bc/nll"] = _mixture_nll(policy, policy.dist_every_code(feats), data)[0].item()
    return stats


class EpisodeCodes(nn.Module):
    """Each demonstration episode's own continuous code, (E, d): the continuous counterpart of the
    codes' mixture (:class:`MixtureAssignment`).

    The codes start at the episodes' first d principal components (:func:`principal_components`)
    and are then fitted with the policy by the demonstrations' likelihood (each episode's actions
    under its own code); every few steps they are moved onto the prior by their ranks
    (:func:`pomil.nn.codes.spread_as_prior`), so the demonstrations' codes spread exactly as the
    codes that rollouts draw, as the mixture gives every code 1/K of the episodes.  From random codes
    the fit folds the code line, a local optimum it does not leave (docs/method.md).  A module, so that a
    run's checkpoint keeps them."""

    def __init__(self, data: PaddedEpisodes, dim: int, prior: str) -> None:
        super().__init__()
        self.prior = prior
        self.codes = nn.Parameter(spread_as_prior(principal_components(data, dim), prior))

    @torch.no_grad()
    def spread_(self) -> None:
        self.codes.copy_(spread_as_prior(self.codes, self.prior))


@torch.no_grad()
def principal_components(data: PaddedEpisodes, dim: int) -> torch.Tensor:
    """Each whole episode's scores (E, dim) on the first ``dim`` principal components of its
    observations and actions, flattened over time (steps past an episode's end count as zeros),
    each column standardised first."""
    m = data.mask.unsqueeze(-1).to(data.observations.dtype)
    x = (torch.cat([data.observations, data.actions], -1) * m).transpose(0, 1).flatten(1)  # (E, T * (obs + act))
    x = x - x.mean(0)
    x = x / x.std(0, correction=0).clamp_min(1e-8)  # constant columns (one episode, unused steps) stay 0
    u, s, _ = torch.linalg.svd(x.double(), full_matrices=False)
    scores = (u[:, :dim] * s[:dim]).to(x.dtype)
    if scores.shape[1] < dim:  # fewer components than dimensions (tiny sets): zeros, spread by index
        scores = torch.cat([scores, scores.new_zeros(len(scores), dim - scores.shape[1])], 1)
    return scores


def balanced_responsibilities(scores: torch.Tensor, iterations: int = 50) -> torch.Tensor:
    """Soft assignment (K, B) of B items to K codes, each item's column summing to 1 and
    each code's row to B / K, close to softmax(scores) over codes (log-domain Sinkhorn)."""
    k, b = scores.shape
    log_q = scores - scores.max()
    for _ in range(iterations):
        log_q = log_q - torch.logsumexp(log_q, 1, keepdim=True) + math.log(b / k)
        log_q = log_q - torch.logsumexp(log_q, 0, keepdim=True)
    return log_q.exp()


@torch.no_grad()
def most_likely_codes(policy: GaussianPolicy, data: PaddedEpisodes, prev_actions: torch.Tensor) -> torch.Tensor:
    """Each episode's most likely code under the policy, (E,)."""
    return mixture_bc_loss(policy, data, prev_actions)[1].argmax(0)


def episodes_within(max_steps: int, episode_steps: int) -> int:
    """Whole episodes of ``episode_steps`` in ``max_steps`` steps, at least one."""
    return max(1, max_steps // max(int(episode_steps), 1))


def sized_for_episodes(cfg: Any, episode_steps: int, *, window: int = 0) -> Any:
    """``cfg`` with each episode count of its class's ``EPISODE_CAPS`` cut to the whole episodes of
    ``episode_steps`` within its step cap (never below 1), with a note on stderr when one is cut: the paper's
    128-step Hopper and 33-step circles keep the configured counts; Hopper's own 1000 steps get 65 episodes per
    iteration and critic batches of 16.  With a cloning ``window`` (:func:`cloning_window`) the cloning batch
    counts windows of that many steps."""
    caps = type(cfg).EPISODE_CAPS
    counts = {k: episodes_within(getattr(cfg, cap), window if window and k == "warm_start_batch" else episode_steps)
              for k, cap in caps.items()}
    cut = {k: n for k, n in counts.items() if n < getattr(cfg, k)}
    if cut:
        print(f"pomil: note: {episode_steps}-step episodes: " + ", ".join(f"{k} {getattr(cfg, k)} -> {n}" for k, n in
              cut.items()) + " (" + ", ".join(f"{c} {getattr(cfg, c)}" for c in dict.fromkeys(caps.values())) + ")",
              file=sys.stderr)
    return replace(cfg, **cut)


MIN_CLONING_BATCH = 8
"""The fewest windows or episodes a cloning step draws when the demonstrations are few
(:func:`sized_for_demonstrations`)."""


def cloning_units(lengths: Sequence[int], window: int) -> int:
    """What a cloning batch draws from episodes of ``lengths`` steps: their windows of ``window`` steps, or with
    ``window`` 0 the whole episodes."""
    return int(sum(math.ceil(int(n) / window) for n in lengths)) if window else len(lengths)


ENSEMBLE_MEMBERS = 3
"""The ensemble's members where ``policy_members`` is auto and the demonstrations are few
(:func:`members_for_demonstrations`)."""


def members_for_demonstrations(cfg: Any, lengths: Sequence[int], window: int, *, recurrent: bool,
                               mixture: bool) -> Any:
    """``cfg`` with ``policy_members`` auto (0) resolved: an ensemble of :data:`ENSEMBLE_MEMBERS` where all the
    demonstrations' cloning units (:func:`cloning_units`) fit in one ``warm_start_batch`` (the sets whose batch
    ``sized_for_demonstrations`` cuts: four standard-Hopper episodes per mode, up to 64 episodes of circles or of the
    paper's Hopper), for a recurrent policy cloned by the codes' mixture from one initialisation with beliefs of its
    own (``belief`` separate or policy); otherwise one policy.  With few demonstrations one clone's initialisation
    and batches decide much of what it does; three clones acting as one never lost a success there and mended the
    weakest draws (docs/method.md, "Policies acting as one").  With a note on stderr when it is an ensemble.  An
    explicit ``policy_members`` is kept (``--resume`` reads the resolved one)."""
    if cfg.policy_members:
        return cfg
    units = cloning_units(lengths, window)
    few = (units <= cfg.warm_start_batch and recurrent and mixture and cfg.warm_start_restarts == 1
           and cfg.warm_start_iterations > 0 and cfg.belief in ("separate", "policy"))
    if few:
        print(f"pomil: note: {units} {f'{window}-step windows' if window else 'episodes'} of demonstrations: "
              f"policy_members auto -> {ENSEMBLE_MEMBERS} (few demonstrations: {ENSEMBLE_MEMBERS} policies cloned "
              "apart act as one)", file=sys.stderr)
    return replace(cfg, policy_members=ENSEMBLE_MEMBERS if few else 1)


def sized_for_demonstrations(cfg: Any, lengths: Sequence[int], window: int) -> Any:
    """``cfg`` with ``warm_start_batch`` cut to 1/``warm_start_batch_share`` of the units the cloning batch draws from
    episodes of ``lengths`` steps (their windows of ``window`` steps, or with ``window`` 0 the whole episodes), never
    below ``MIN_CLONING_BATCH``, where all the units fit in one batch; with a note on stderr when it is cut.  A batch
    of all the demonstrations (four standard-Hopper episodes per mode: 64 windows, 64 a step) clones every step on the
    same data; a quarter a step clones forward better in half the time.  Eleven per mode (172 windows) clone forward
    worse at a quarter (43) than at 64, so sets larger than one batch keep it (docs/hopper.md, "How much a cloning
    step draws"): the shipped sets, and five or more standard-Hopper episodes per mode."""
    units = cloning_units(lengths, window)
    if not cfg.warm_start_batch_share or units > cfg.warm_start_batch:
        return cfg
    batch = min(cfg.warm_start_batch, max(MIN_CLONING_BATCH, units // cfg.warm_start_batch_share))
    if batch >= cfg.warm_start_batch:
        return cfg
    print(f"pomil: note: {units} {f'{window}-step windows' if window else 'episodes'} of demonstrations: "
          f"warm_start_batch {cfg.warm_start_batch} -> {batch} (at most 1/{cfg.warm_start_batch_share} of them a "
          "cloning step)", file=sys.stderr)
    return replace(cfg, warm_start_batch=batch)


def cloning_window(cfg: AdversarialConfig, episode_steps: int, mixture: bool) -> int:
    """The steps of the warm start's and BC term's cloning windows for episodes of ``episode_steps`` (0: whole
    episodes): ``warm_start_window`` where the dataset-wide assignment keeps the windows' states, the episodes are
    longer and the policy is recurrent (a feed-forward one has no backpropagation through time to cut)."""
    from pomil.learners import LEARNERS  # the learners' table imports this module

    window = cfg.warm_start_window if LEARNERS[cfg.learner].recurrent else 0
    return window if mixture and cfg.mixture_balance == "dataset" and 0 < window < episode_steps else 0


def mixture_assignment(cfg: AdversarialConfig, expert: PaddedEpisodes, expert_prev: torch.Tensor,
                       mixture: bool) -> MixtureAssignment | None:
    """The dataset-wide code assignment of the mixture warm start and BC term (None: balanced per batch),
    refreshed every 10 steps or once per pass over the episodes (or windows), whichever is rarer: the refresh
    (one forward pass over every episode) then costs at most about a third of the training steps between."""
    if not (mixture and cfg.mixture_balance == "dataset"):
        return None
    steps, episodes = expert.mask.shape
    window = cloning_window(cfg, steps, mixture)
    refresh = max(10, math.ceil(episodes * (math.ceil(steps / window) if window else 1) / cfg.warm_start_batch))
    return MixtureAssignment(expert, expert_prev, refresh=refresh, window=window)


CODE_SPREAD_EVERY = 10
"""Warm-start steps between moves of the episodes' continuous codes onto the prior (EpisodeCodes.spread_)."""


def clone_with_continuous_codes(policy: GaussianPolicy, expert: PaddedEpisodes, expert_prev: torch.Tensor,
                                *, cfg: AdversarialConfig, gen: torch.Generator, guard: DivergenceGuard | None = None,
                                episode_codes: EpisodeCodes | None = None) -> dict[str, float]:
    """The warm start's behaviour cloning with continuous codes: each episode under a random code
    from the prior (InfoGAIL), or under its own code in ``episode_codes``, fitted with the policy
    (its own learning rate, warm_start_code_lr_scale x warm_start_lr) and spread as the prior every
    ``CODE_SPREAD_EVERY`` steps and at the end; then the log std's fit (``warm_start_fit_log_std``)."""
    opt, decay = warm_start_optimizer(policy, cfg, episode_codes)
    if episode_codes is not None:
        codes_of = lambda idx: episode_codes.codes[idx]  # noqa: E731
    else:
        codes_of = lambda idx: sample_prior(cfg.code_prior, len(idx), policy.arch.num_codes,  # noqa: E731
                                            gen).to(idx.device)

    def after(i: int) -> None:
        decay.step()
        if episode_codes is not None and (i % CODE_SPREAD_EVERY == 0 or i == cfg.warm_start_iterations):
            episode_codes.spread_()

    stats = cloning_steps(policy, lambda: bc_step(policy, opt, expert, prev_actions=expert_prev, generator=gen,
                                                  batch_episodes=cfg.warm_start_batch, codes_of=codes_of),
                          after=after, cfg=cfg, device=expert.mask.device, guard=guard)
    if cfg.warm_start_fit_log_std:
        codes = (episode_codes.codes.detach() if episode_codes is not None
                 else codes_of(torch.arange(expert.mask.shape[1], device=expert.mask.device)))
        stats.update(fit_log_std(policy, expert, expert_prev, codes=codes))
    return stats


def clone_demonstrations(policy: GaussianPolicy, expert: PaddedEpisodes, expert_prev: torch.Tensor, *, num_codes: int,
                         mixture: bool, cfg: AdversarialConfig, gen: torch.Generator,
                         guard: DivergenceGuard | None = None, where: str = "") -> dict[str, float]:
    """The policy's part of the adversarial learners' ``bc_warm_start``: ``warm_start_iterations`` behaviour-cloning
    steps (the codes' mixture, or random codes), then the log std's fit (``warm_start_fit_log_std``).
    Returns the last step's stats; ``where`` prefixes the step in a divergence's message."""
    opt, decay = warm_start_optimizer(policy, cfg)
    assignment = mixture_assignment(cfg, expert, expert_prev, mixture)

    stats = cloning_steps(policy, lambda: bc_step(policy, opt, expert, prev_actions=expert_prev, generator=gen,
                                                  batch_episodes=cfg.warm_start_batch, num_codes=num_codes,
                                                  mixture=mixture, assignment=assignment),
                          after=lambda i: decay.step(), cfg=cfg, device=expert.mask.device, guard=guard, where=where)
    if cfg.warm_start_fit_log_std:
        stats.update(fit_log_std(policy, expert, expert_prev, mixture=mixture))
    return stats


def clone_members(policy: EnsemblePolicy, expert: PaddedEpisodes, expert_prev: torch.Tensor, *, num_codes: int,
                  mixture: bool, cfg: AdversarialConfig, gen: torch.Generator,
                  guard: DivergenceGuard | None = None) -> dict[str, float]:
    """The warm start of an ensemble (``policy_members``): each member cloned on its own by
    :func:`clone_demonstrations`, the first from the run's random numbers (exactly a one-policy run's warm start),
    every other from its own initialisation and batches (seeds drawn from the run's).  With the codes' mixture,
    each later member's codes are then renamed to agree with the first member's on the demonstrations
    (:func:`code_renaming`: the cloning finds the clusters, in an order of its own).  The ensemble's log std is
    fitted to its mean actions (``warm_start_fit_log_std``), else the members' mean.  Returns the first member's
    stats, the ensemble's NLL and log std after the fit, and ``bc/member_agreement``: the share of demonstration
    episodes on which the least agreeing member's most likely code is the first member's."""
    device, k = expert.mask.device, len(policy.members)
    stats = clone_demonstrations(policy.members[0], expert, expert_prev, num_codes=num_codes, mixture=mixture,
                                 cfg=cfg, gen=gen, guard=guard, where=f"member 1 of {k}: ")
    seeds = np.random.SeedSequence([cfg.seed, 2]).generate_state(k - 1).tolist()
    for i, member in enumerate(policy.members[1:], start=1):
        with own_random_numbers(seeds[i - 1], device) as member_gen:
            member.load_state_dict(GaussianPolicy(member.arch).to(device).state_dict())  # its own initialisation
            fit_input_scale(member.encoder, expert.observations, expert.mask)
            clone_demonstrations(member, expert, expert_prev, num_codes=num_codes, mixture=mixture, cfg=cfg,
                                 gen=member_gen, guard=guard, where=f"member {i + 1} of {k}: ")
    if mixture and num_codes > 1:
        with torch.no_grad():
            first = most_likely_codes(policy.members[0], expert, expert_prev)
            agreement = 1.0
            for member in policy.members[1:]:
                codes = most_likely_codes(member, expert, expert_prev)
                renaming = code_renaming(first, codes, num_codes)
                rename_codes(member, renaming)
                agreement = min(agreement, (renaming.to(codes.device)[codes] == first).float().mean().item())
        stats["bc/member_agreement"] = agreement
    with torch.no_grad():
        if cfg.warm_start_fit_log_std:
            stats.update(fit_log_std(policy, expert, expert_prev, mixture=mixture))
        else:
            policy.log_std.copy_(torch.stack([p.log_std for p in policy.members]).mean(0))
            stats["bc/log_std"] = policy.log_std.mean().item()
    return stats


def code_renaming(reference: torch.Tensor, codes: torch.Tensor, num_codes: int) -> torch.Tensor:
    """The renaming (K,) of ``codes``' names, code j to ``renaming[j]``, under which the most episodes take the
    code ``reference`` gives them (both (E,) code indices of the same episodes): every renaming up to 7 codes (the
    first best in lexicographic order), else greedily by the largest count left."""
    counts = torch.zeros(num_codes, num_codes, dtype=torch.long)
    counts.index_put_((codes.cpu(), reference.cpu()), torch.ones(len(codes), dtype=torch.long), accumulate=True)
    if num_codes <= 7:
        table = counts.tolist()
        best = max(itertools.permutations(range(num_codes)),
                   key=lambda p: sum(table[j][p[j]] for j in range(num_codes)))
        return torch.tensor(best)
    renaming, left = torch.full((num_codes,), -1), counts.clone()
    for _ in range(num_codes):
        j, i = divmod(int(left.argmax()), num_codes)
        renaming[j] = i
        left[j, :], left[:, i] = -1, -1
    return renaming


@torch.no_grad()
def rename_codes(policy: GaussianPolicy, renaming: torch.Tensor) -> None:
    """Rename a one-hot-code policy's codes in place: what code j did, code ``renaming[j]`` does."""
    assert policy.code_embed is not None
    weight = policy.code_embed.weight.clone()  # (features, K): column k is code k's embedding
    policy.code_embed.weight[:, renaming.to(weight.device)] = weight


@contextmanager
def own_random_numbers(seed: int, device: torch.device) -> Iterator[torch.Generator]:
    """A block on its own random numbers (torch's global RNG, CUDA's on a GPU, NumPy's and Python's, seeded with
    ``seed``; yields a generator seeded alike): the run's streams resume after it as they were before."""
    states = random.getstate(), np.random.get_state()
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        try:
            yield seed_everything(seed)
        finally:
            random.setstate(states[0])
            np.random.set_state(states[1])


def cloning_steps(policy: GaussianPolicy, step: Callable[[], dict[str, float]], *, after: Callable[[int], None],
                  cfg: AdversarialConfig, device: torch.device, guard: DivergenceGuard | None,
                  where: str = "") -> dict[str, float]:
    """``warm_start_iterations`` times ``step()`` in the precision's context (one a step, see ``precision_context``),
    then ``after(i)`` (i from 1) and the divergence guard's checks, under a progress bar; the last step's stats."""
    stats: dict[str, float] = {}
    with progress_bar(cfg.warm_start_iterations, f"{where}warm start", cfg.progress) as bar:
        for i in range(1, cfg.warm_start_iterations + 1):
            with precision_context(cfg.precision, device):
                stats = step()
            after(i)
            check_warm_start_step(guard, f"{where}warm-start step {i}", stats, policy)
            bar.set_postfix(nll=f"{stats['bc/nll']:.4g}", refresh=False)
            bar.update()
    return stats


def check_warm_start_step(guard: DivergenceGuard | None, at: str, stats: dict[str, float],
                          policy: GaussianPolicy) -> None:
    """The divergence guard's checks after a warm-start step ``at``: its loss, the policy's gradients and weights."""
    if guard is not None:
        guard.value(at, "warm-start loss (negative log-likelihood)", stats["bc/nll"])
        guard.grads(at, "warm-start policy", policy.parameters())
        guard.params(at, {"warm-start policy": policy})


def warm_start_optimizer(policy: GaussianPolicy, cfg: AdversarialConfig, episode_codes: EpisodeCodes | None = None,
                         ) -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.LambdaLR]:
    """Adam over the policy, its log std at ``warm_start_log_std_lr_scale`` times ``warm_start_lr`` (and
    the episodes' continuous codes at ``warm_start_code_lr_scale`` times), and the schedule to step
    after each update: a linear rise over the first ``warm_start_lr_warmup`` of the steps, then a linear
    decay to 0 over the rest (``warm_start_lr_decay``)."""
    rest = [p for name, p in policy.named_parameters() if name != "log_std"]
    groups = [{"params": rest}, {"params": [policy.log_std], "lr": cfg.warm_start_lr * cfg.warm_start_log_std_lr_scale}]
    if episode_codes is not None:
        groups.append({"params": [episode_codes.codes], "lr": cfg.warm_start_lr * cfg.warm_start_code_lr_scale})
    opt = torch.optim.Adam(groups, lr=cfg.warm_start_lr)
    steps, rise = cfg.warm_start_iterations, int(cfg.warm_start_lr_warmup * cfg.warm_start_iterations)

    def factor(i: int) -> float:  # the learning rate of step i + 1, as a fraction of warm_start_lr
        if i < rise:
            return (i + 1) / rise
        return 1 - (i - rise) / max(steps - rise, 1) if cfg.warm_start_lr_decay else 1.0
    return opt, torch.optim.lr_scheduler.LambdaLR(opt, factor)
