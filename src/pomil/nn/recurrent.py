"""Recurrent cores: one step function for rollouts, one unroll for training.

Recurrent state is explicit.  ``start[i]`` marks that environment i begins a
new episode at this step, so its incoming hidden state is zeroed before the
step.  ``unroll`` runs the torch RNN once per stretch of time in which no
episode starts (exact, and far faster than a Python loop over steps); it
agrees with repeated ``step`` calls to float tolerance (tested).

:class:`GRUCore` keeps h (N, H); :class:`LSTMCore` keeps [h, c] concatenated
into one (N, 2H) tensor, so that every core's state is one 2-D tensor that a
rollout can store per episode.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn


def _reset(h: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """The state with the rows of episodes that start here zeroed."""
    return h * (~start).unsqueeze(-1).to(h.dtype)


def unroll_by_chunks(run: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                     xs: torch.Tensor, h0: torch.Tensor, starts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``run(x_chunk, h) -> (outputs, h_n)`` once per stretch of time without episode starts.

    xs (T, N, D), h0 (N, S), starts (T, N) bool -> (outputs (T, N, F), final state (N, S)).
    The state of the episodes that start at a chunk's first step is zeroed before it."""
    steps = xs.shape[0]
    # Time indices (beyond 0) at which some episode starts: chunk borders.
    cut = torch.nonzero(starts[1:].any(dim=1)).flatten().add(1).tolist()
    borders = [0, *cut, steps]
    h = h0
    outs = []
    for a, b in zip(borders[:-1], borders[1:], strict=True):
        out, h = run(xs[a:b], _reset(h, starts[a]))
        outs.append(out)
    return torch.cat(outs, dim=0), h


class _Core(nn.Module):
    """A torch RNN with its state explicit: (x, state, start) -> (h, new state), resets by mask.  Subclasses
    give ``_run(xs, state) -> (outputs, final state)``, one call of the RNN over a stretch of time."""

    hidden_size: int
    state_width = 1
    """The state's columns per hidden unit."""

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return torch.zeros(batch, self.state_width * self.hidden_size, device=device)

    def step(self, x: torch.Tensor, state: torch.Tensor, start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x (N, D), state (N, S), start (N,) bool -> (h (N, H), new state (N, S))."""
        out, state = self._run(x.unsqueeze(0), _reset(state, start))
        return out[0], state

    def unroll(self, xs: torch.Tensor, h0: torch.Tensor, starts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """xs (T, N, D), h0 (N, S), starts (T, N) bool -> (hs (T, N, H), final state (N, S)).

        ``hs[t]`` is h after consuming ``xs[t]``.
        """
        return unroll_by_chunks(self._run, xs, h0, starts)


class GRUCore(_Core):
    """The GRU core; the state is h (N, H)."""

    def __init__(self, input_size: int, hidden_size: int = 128) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        self.gru = nn.GRU(input_size, hidden_size)

    def _run(self, xs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out, h_n = self.gru(xs, h.unsqueeze(0).contiguous())
        return out, h_n[0]


class LSTMCore(_Core):
    """The LSTM core; the state is h and c side by side, (N, 2H)."""

    state_width = 2

    def __init__(self, input_size: int, hidden_size: int = 128) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        self.lstm = nn.LSTM(input_size, hidden_size)

    def _run(self, xs: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h, c = state.chunk(2, dim=-1)
        out, (h_n, c_n) = self.lstm(xs, (h.unsqueeze(0).contiguous(), c.unsqueeze(0).contiguous()))
        return out, torch.cat([h_n[0], c_n[0]], dim=-1)
