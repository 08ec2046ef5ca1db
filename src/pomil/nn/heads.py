"""Critic, posterior and value networks, each with its own encoder.

Each is a :class:`BeliefHead`: an encoder (feed-forward, or a GRU, LSTM or
attention belief over (z_t, a_{t-1}), see ``pomil.nn.encoders``) followed by
an MLP over [features, extra], where ``extra`` is the current action a_t
(critic, posterior) or the code (value: one-hot, or a continuous code).
Separate encoders per module are the paper's design: b(tau; omega) for the
critic, b(tau; psi) for the posterior.
"""

from __future__ import annotations

import torch
from torch import nn

from pomil.nn.encoders import make_encoder


class BeliefHead(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, extra_dim: int, out_dim: int, encoder: str = "gru",
                 hidden_size: int = 128, context: int = 32) -> None:
        super().__init__()
        self.encoder = make_encoder(encoder, obs_dim, act_dim, hidden_size=hidden_size, context=context)
        self.out_dim = out_dim
        self.mlp = nn.Sequential(nn.Linear(self.encoder.out_size + extra_dim, hidden_size), nn.ELU(),
                                 nn.Linear(hidden_size, out_dim))

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return self.encoder.initial_state(batch, device)

    def _out(self, feats: torch.Tensor, extra: torch.Tensor | None) -> torch.Tensor:
        x = feats if extra is None else torch.cat([feats, extra], dim=-1)
        y = self.mlp(x).float()  # float32 outputs whatever the autocast (precision bfloat16): the losses' own
        return y.squeeze(-1) if self.out_dim == 1 else y

    def step(self, obs, prev_action, h, start, extra=None) -> tuple[torch.Tensor, torch.Tensor]:
        feats, h = self.encoder.step(obs, prev_action, h, start)
        return self._out(feats, extra), h

    def unroll(self, obs, prev_actions, h0, starts, extra=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(T, N) block -> outputs (T, N) for out_dim 1, else (T, N, out_dim)."""
        feats, h = self.encoder.unroll(obs, prev_actions, h0, starts)
        return self._out(feats, extra), h


def critic(obs_dim: int, act_dim: int, encoder: str = "gru", *, hidden_size: int = 128,
           context: int = 32) -> BeliefHead:
    """Scores f(b(tau; omega), a_t): higher = more expert-like."""
    return BeliefHead(obs_dim, act_dim, act_dim, 1, encoder, hidden_size, context)


def posterior(obs_dim: int, act_dim: int, num_codes: int, *, encoder: str = "gru", hidden_size: int = 128,
              context: int = 32, code_kind: str = "discrete") -> BeliefHead:
    """P(c | b(tau; psi), a_t): K logits, or for a continuous code of ``num_codes`` = d dimensions
    a diagonal Gaussian's mean and log std (2d outputs; ``pomil.nn.codes.code_log_likelihood``)."""
    out = num_codes if code_kind == "discrete" else 2 * num_codes
    return BeliefHead(obs_dim, act_dim, act_dim, out, encoder, hidden_size, context)


def value(obs_dim: int, act_dim: int, num_codes: int, *, encoder: str = "gru", hidden_size: int = 128,
          context: int = 32) -> BeliefHead:
    """V(b(tau), c)."""
    return BeliefHead(obs_dim, act_dim, num_codes, 1, encoder, hidden_size, context)
