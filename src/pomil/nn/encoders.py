"""Observation encoders with a common interface.

* :class:`MLPEncoder` sees the current observation only (feed-forward).
* :class:`BeliefEncoder` keeps a belief b_t = GRU(b_{t-1}, [z_t, a_{t-1}])
  over the history of observations and previous actions (the paper's eq. 4):
  a dense ELU layer, then the GRU core.

Both offer ``initial_state(n)``, ``step(obs, prev_action, h, start)`` and
``unroll(obs, prev_actions, h0, starts)``; the feed-forward encoder carries an
empty (n, 0) state so that callers need no special case.
"""

from __future__ import annotations

import torch
from torch import nn

from pomil.nn.recurrent import GRUCore


class MLPEncoder(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int = 128) -> None:
        super().__init__()
        self.out_size = hidden_size
        self.net = nn.Sequential(
            nn.Linear(obs_dim, hidden_size), nn.ELU(), nn.Linear(hidden_size, hidden_size), nn.ELU()
        )

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return torch.zeros(batch, 0, device=device)

    def step(self, obs, prev_action, h, start):
        return self.net(obs), h

    def unroll(self, obs, prev_actions, h0, starts):
        return self.net(obs), h0


class BeliefEncoder(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int = 128) -> None:
        super().__init__()
        self.out_size = hidden_size
        self.embed = nn.Sequential(nn.Linear(obs_dim + act_dim, hidden_size), nn.ELU())
        self.core = GRUCore(hidden_size, hidden_size)

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return self.core.initial_state(batch, device)

    @staticmethod
    def _inputs(obs: torch.Tensor, prev_action: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        # a_{t-1} is zero at an episode's first step, whatever the caller passed.
        prev_action = prev_action * (~start).unsqueeze(-1).to(prev_action.dtype)
        return torch.cat([obs, prev_action], dim=-1)

    def step(self, obs, prev_action, h, start):
        h = self.core.step(self.embed(self._inputs(obs, prev_action, start)), h, start)
        return h, h

    def unroll(self, obs, prev_actions, h0, starts):
        return self.core.unroll(self.embed(self._inputs(obs, prev_actions, starts)), h0, starts)


def make_encoder(kind: str, obs_dim: int, act_dim: int, hidden_size: int) -> nn.Module:
    if kind == "mlp":
        return MLPEncoder(obs_dim, act_dim, hidden_size)
    if kind == "gru":
        return BeliefEncoder(obs_dim, act_dim, hidden_size)
    raise ValueError(f"unknown encoder {kind!r}; expected 'mlp' or 'gru'")
