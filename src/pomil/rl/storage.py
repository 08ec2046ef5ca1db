"""Rollout storage (T, N, ...) with the initial hidden states, and its minibatches.

Three ways to cut a rollout into minibatches:

* ``sequence_batches``: whole columns (T steps of a few environments) from
  their stored initial hidden states — exactly the computation of the rollout.
* ``window_batches``: the paper's "bootstrapped random updates" (Hausknecht &
  Stone): random windows of L steps from random environments, the hidden
  state zeroed at each window's start.
* ``step_batches``: single steps in random order, for feed-forward networks
  (each batch a (1, B) rollout).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, fields, replace

import torch


def window_index(num_steps: int, num_seqs: int, length: int, *, count: int,
                 generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices of ``count`` random windows: time (length, count) and sequence (count,)."""
    length = min(length, num_steps)
    seq = torch.randint(num_seqs, (count,), generator=generator)
    t0 = torch.randint(num_steps - length + 1, (count,), generator=generator)
    return t0.unsqueeze(0) + torch.arange(length).unsqueeze(1), seq


@dataclass(frozen=True)
class Rollout:
    """One rollout of T steps in N environments.

    observations (T, N, obs_dim); actions (T, N, act_dim); prev_actions
    (T, N, act_dim) = a_{t-1}, zero at episode starts; starts (T, N) bool,
    True where an episode begins; codes (T, N, K) one-hot (K may be 0);
    log_probs, values, rewards, advantages, returns (T, N) float;
    terminated, truncated (T, N) bool; mask (T, N) bool, valid steps;
    h0_policy (N, H), h0_value (N, H): hidden states before step 0;
    env_actions (T, N, act_dim): the actions as the environment carried them
    out (see ``pomil.envs.executed_actions_fn``), what critics and posteriors
    see; ``None`` means the same as ``actions``.
    """

    observations: torch.Tensor
    actions: torch.Tensor
    prev_actions: torch.Tensor
    starts: torch.Tensor
    codes: torch.Tensor
    log_probs: torch.Tensor
    values: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    mask: torch.Tensor
    h0_policy: torch.Tensor
    h0_value: torch.Tensor
    env_actions: torch.Tensor | None = None
    rewards: torch.Tensor | None = None
    advantages: torch.Tensor | None = None
    returns: torch.Tensor | None = None

    def __post_init__(self) -> None:
        t, n = self.starts.shape
        for name, x in self._per_step().items():
            if tuple(x.shape[:2]) != (t, n):
                raise ValueError(f"Rollout.{name}: expected leading shape ({t}, {n}), got {tuple(x.shape)}")
        for name in ("h0_policy", "h0_value"):
            if getattr(self, name).shape[0] != n:
                raise ValueError(f"Rollout.{name}: expected {n} rows, got {tuple(getattr(self, name).shape)}")

    def _per_step(self) -> dict[str, torch.Tensor]:
        """The (T, N, ...) fields that are set: all but the initial states and the optional ones left None."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) is not None and not f.name.startswith("h0_")}

    @property
    def executed_actions(self) -> torch.Tensor:
        return self.actions if self.env_actions is None else self.env_actions

    @property
    def num_steps(self) -> int:
        return int(self.starts.shape[0])

    @property
    def num_envs(self) -> int:
        return int(self.starts.shape[1])

    def with_(self, **changes: torch.Tensor) -> Rollout:
        return replace(self, **changes)

    def columns(self, idx: torch.Tensor) -> Rollout:
        """Whole sequences of the environments in ``idx``, with their initial states."""
        return self._gather(torch.arange(self.num_steps, device=idx.device).unsqueeze(1).expand(-1, len(idx)), idx,
                            self.h0_policy[idx], self.h0_value[idx], zero_first=False)

    def windows(self, length: int, count: int, generator: torch.Generator) -> Rollout:
        """``count`` random windows of ``length`` steps, hidden state zeroed at their start."""
        t_idx, env = window_index(self.num_steps, self.num_envs, length, count=count, generator=generator)
        dev = self.starts.device
        return self._gather(t_idx.to(dev), env.to(dev), self.h0_policy[env.to(dev)] * 0, self.h0_value[env.to(dev)] * 0,
                            zero_first=True)

    def _gather(self, t_idx: torch.Tensor, env: torch.Tensor, h0p: torch.Tensor, h0v: torch.Tensor,
                zero_first: bool) -> Rollout:
        e_idx = env.unsqueeze(0).expand_as(t_idx)
        out = {name: x[t_idx, e_idx] for name, x in self._per_step().items()}  # indexing copies
        if zero_first:
            # A window starts from a zero state, as if an episode began there (the
            # encoders then also ignore a_{t-1} at its first step).
            out["starts"][0] = True
        return Rollout(**out, h0_policy=h0p, h0_value=h0v)

    def sequence_batches(self, num_batches: int, generator: torch.Generator) -> Iterator[Rollout]:
        perm = torch.randperm(self.num_envs, generator=generator).to(self.starts.device)
        for chunk in perm.chunk(min(num_batches, self.num_envs)):
            yield self.columns(chunk)

    def window_batches(self, num_batches: int, length: int, generator: torch.Generator) -> Iterator[Rollout]:
        # As many windows in total as there are steps / length, so one epoch sees
        # about as many steps as a pass over whole sequences.
        per_batch = max(1, (self.num_steps * self.num_envs) // (length * num_batches))
        for _ in range(num_batches):
            yield self.windows(length, per_batch, generator)

    def step_batches(self, num_batches: int, generator: torch.Generator) -> Iterator[Rollout]:
        """Every step once, shuffled, in ``num_batches`` (1, B) batches (feed-forward networks only)."""
        dev = self.starts.device
        perm = torch.randperm(self.num_steps * self.num_envs, generator=generator).to(dev)
        for chunk in perm.chunk(num_batches):
            t, env = chunk // self.num_envs, chunk % self.num_envs
            yield self._gather(t.unsqueeze(0), env, self.h0_policy[env], self.h0_value[env], zero_first=True)
