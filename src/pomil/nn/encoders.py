"""Observation encoders with a common interface.

* :class:`MLPEncoder` sees the current observation only (feed-forward).
* :class:`BeliefEncoder` keeps a belief b_t = GRU(b_{t-1}, [z_t, a_{t-1}])
  over the history of observations and previous actions (the paper's eq. 4):
  a dense ELU layer, then the GRU core.
* :class:`LSTMEncoder`: the same with an LSTM core; its state is [h, c].
* :class:`AttentionEncoder`: a one-layer causal transformer over the last
  ``context`` embedded inputs [z_t, a_{t-1}] of the episode; its state is the
  window of earlier inputs.

All offer ``out_size``, ``initial_state(n)`` (one (n, S) tensor, all zeros),
``step(obs, prev_action, h, start) -> (features, h)`` and
``unroll(obs, prev_actions, h0, starts) -> (features (T, N, F), h_T)`` over
time-major (T, N, ...) blocks.  ``start`` marks an episode's first step: the
state is reset there and a_{t-1} is taken as zero.  The feed-forward encoder
carries an empty (n, 0) state so that callers need no special case.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from pomil.nn.recurrent import GRUCore, LSTMCore

ENCODERS = ("mlp", "gru", "lstm", "attention")
"""The encoder kinds :func:`make_encoder` builds."""


def history_inputs(obs: torch.Tensor, prev_action: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """[z_t, a_{t-1}] with a_{t-1} zero at an episode's first step, whatever the caller passed."""
    prev_action = prev_action * (~start).unsqueeze(-1).to(prev_action.dtype)
    return torch.cat([obs, prev_action], dim=-1)


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
    """A dense ELU layer, then the recurrent core (``core_class``: the GRU); features = the core's h_t."""

    core_class: type[nn.Module] = GRUCore

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int = 128) -> None:
        super().__init__()
        self.out_size = hidden_size
        self.embed = nn.Sequential(nn.Linear(obs_dim + act_dim, hidden_size), nn.ELU())
        self.core = self.core_class(hidden_size, hidden_size)

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return self.core.initial_state(batch, device)

    def step(self, obs, prev_action, h, start):
        return self.core.step(self.embed(history_inputs(obs, prev_action, start)), h, start)

    def unroll(self, obs, prev_actions, h0, starts):
        return self.core.unroll(self.embed(history_inputs(obs, prev_actions, starts)), h0, starts)


class LSTMEncoder(BeliefEncoder):
    """The same with an LSTM core; features h_t, state [h_t, c_t] (n, 2 * hidden_size)."""

    core_class = LSTMCore


class AttentionEncoder(nn.Module):
    """Causal self-attention over the last ``context`` steps of the episode.

    Each step's input [z_t, a_{t-1}] is embedded (dense ELU layer, width d =
    ``hidden_size``); the features at step t come from one pre-norm transformer
    layer whose query is step t and whose keys are steps t - context + 1 .. t,
    those before the episode's start left out.  Positions are relative: a
    learned key and value vector per age 0 .. context - 1 (Shaw et al., 2018),
    so a step is treated alike wherever the window stands.  Then a residual MLP
    and a final LayerNorm.

    The state is the window of the ``context - 1`` earlier steps, oldest first:
    each step's attention key and value (the projections of its embedded input,
    kept so that acting does not recompute the window's every step) and a
    validity flag (1: of this episode), packed into one
    (n, (context - 1) * (2d + 1)) tensor; invalid slots are zero, so the zero
    tensor is the initial state.  ``unroll`` computes every step's attention at
    once (in chunks of ``query_chunk`` queries); ``step`` attends from one step,
    for acting.  They agree to float tolerance (tested).
    """

    query_chunk = 64  # queries per attention block in unroll: bounds memory at (chunk, chunk + context) scores

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int = 128, context: int = 32,
                 heads: int = 4) -> None:
        super().__init__()
        if context < 1:
            raise ValueError(f"attention context must be at least 1, got {context}")
        d = hidden_size
        self.out_size = d
        self.context = context
        self._slots = context - 1  # the state's window: the earlier steps a query sees
        self.heads = math.gcd(heads, d)  # as many as divide the width (4 by default; fewer for odd widths)
        self.embed = nn.Sequential(nn.Linear(obs_dim + act_dim, d), nn.ELU())
        self.norm1 = nn.LayerNorm(d)
        self.qkv = nn.Linear(d, 3 * d)
        self.rel_key = nn.Parameter(torch.empty(context, d))
        self.rel_value = nn.Parameter(torch.empty(context, d))
        nn.init.normal_(self.rel_key, std=0.02)
        nn.init.normal_(self.rel_value, std=0.02)
        self.proj = nn.Linear(d, d)
        self.norm2 = nn.LayerNorm(d)
        self.mlp = nn.Sequential(nn.Linear(d, d), nn.ELU(), nn.Linear(d, d))
        self.norm_out = nn.LayerNorm(d)

    # ------------------------------------------------------------------ state
    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return torch.zeros(batch, self._slots * (2 * self.out_size + 1), device=device)

    def _unpack(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(keys, values (n, heads, P, dh), valid (n, P) bool) of a packed state."""
        d = self.out_size
        s = h.view(h.shape[0], self._slots, 2 * d + 1)
        return self._heads(s[..., :d]), self._heads(s[..., d:2 * d]), s[..., -1] > 0.5

    def _pack(self, k: torch.Tensor, v: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """The packed state (n, P * (2d + 1)) of the window's keys and values (n, heads, P, dh); invalid slots zero."""
        n, _, slots, _ = k.shape
        flag = valid.to(k.dtype).unsqueeze(-1)
        k, v = (x.transpose(1, 2).reshape(n, slots, self.out_size) * flag for x in (k, v))
        return torch.cat([k, v, flag], dim=-1).flatten(1)

    # -------------------------------------------------------------- attention
    def _heads(self, x: torch.Tensor) -> torch.Tensor:
        """(n, L, d) -> (n, heads, L, d / heads)."""
        return x.reshape(x.shape[0], x.shape[1], self.heads, self.out_size // self.heads).transpose(1, 2)

    def _project(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Queries, keys and values (n, heads, L, dh) of embedded inputs (n, L, d)."""
        return tuple(self._heads(p) for p in self.qkv(self.norm1(x)).chunk(3, dim=-1))

    def _attend(self, x_q: torch.Tensor, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
                allowed: torch.Tensor) -> torch.Tensor:
        """Features (n, nq, d) of nq queries whose keys are the nq + P steps ending at them.

        x_q (n, nq, d) the queries' embedded inputs (the residual stream); q (n, H, nq, dh); k, v (n, H, nq + P,
        dh), key s of query i at age P + i - s; allowed (n, nq, nq + P) bool, false outside the window."""
        n, heads, nq, dh = q.shape
        P, C = self._slots, self.context
        i = torch.arange(nq, device=q.device)
        age = (P + i).unsqueeze(1) - torch.arange(nq + P, device=q.device)  # (nq, L)
        rel_k = self.rel_key.view(C, heads, dh).permute(1, 2, 0)  # (H, dh, C)
        rel_v = self.rel_value.view(C, heads, dh).transpose(0, 1)  # (H, C, dh)
        scores = q @ k.transpose(-1, -2) + (q @ rel_k).gather(-1, age.clamp(0, C - 1).expand(n, heads, nq, -1))
        scores = scores.masked_fill(~allowed.unsqueeze(1), float("-inf")) / math.sqrt(dh)
        attn = torch.softmax(scores, dim=-1)  # each query sees itself, so no row is all -inf
        key_of_age = (P + i).unsqueeze(1) - torch.arange(C, device=q.device)  # (nq, C): the key at each age
        out = attn @ v + attn.gather(-1, key_of_age.expand(n, heads, nq, -1)) @ rel_v
        y = x_q + self.proj(out.transpose(1, 2).reshape(n, nq, -1))
        y = y + self.mlp(self.norm2(y))
        return self.norm_out(y)

    # ------------------------------------------------------------ interface
    def step(self, obs, prev_action, h, start):
        x = self.embed(history_inputs(obs, prev_action, start)).unsqueeze(1)  # (n, 1, d)
        k0, v0, valid = self._unpack(h)
        n = x.shape[0]
        valid = torch.cat([valid & ~start.unsqueeze(1), torch.ones(n, 1, dtype=torch.bool, device=x.device)], dim=1)
        q, k, v = self._project(x)
        k, v = torch.cat([k0, k], dim=2), torch.cat([v0, v], dim=2)  # (n, H, C, dh): oldest first, this step last
        feats = self._attend(x, q, k, v, valid.unsqueeze(1))[:, 0]
        return feats, self._pack(k[:, :, 1:], v[:, :, 1:], valid[:, 1:])

    def unroll(self, obs, prev_actions, h0, starts):
        T, n = starts.shape
        P = self._slots
        dev = starts.device
        x = self.embed(history_inputs(obs, prev_actions, starts)).transpose(0, 1)  # (n, T, d)
        k0, v0, valid0 = self._unpack(h0)
        q, k, v = self._project(x)
        k, v = torch.cat([k0, k], dim=2), torch.cat([v0, v], dim=2)  # (n, H, P + T, dh): the window, then the block
        valid = torch.cat([valid0, torch.ones(n, T, dtype=torch.bool, device=dev)], dim=1)
        key_time = torch.arange(-P, T, device=dev)  # block time of each key (the carried-in window's are negative)
        t = torch.arange(T, device=dev).unsqueeze(1).expand(T, n)
        # Each step's episode start in this block (-P: none, the carried-in window stays visible).
        last_start = torch.cummax(torch.where(starts, t, torch.full_like(t, -P)), dim=0).values.T  # (n, T)
        feats = []
        for a in range(0, T, self.query_chunk):
            b = min(a + self.query_chunk, T)
            age = (P + torch.arange(b - a, device=dev)).unsqueeze(1) - torch.arange(b - a + P, device=dev)
            allowed = ((age >= 0) & (age <= P)).unsqueeze(0) & valid[:, a:b + P].unsqueeze(1) & (
                key_time[a:b + P].view(1, 1, -1) >= last_start[:, a:b].unsqueeze(2))
            feats.append(self._attend(x[:, a:b], q[:, :, a:b], k[:, :, a:b + P], v[:, :, a:b + P], allowed))
        # The next block's window: the last P keys and values, those of the last step's episode.
        valid_end = valid[:, T:] & (key_time[T:].unsqueeze(0) >= last_start[:, -1:])
        return torch.cat(feats, dim=1).transpose(0, 1), self._pack(k[:, :, T:], v[:, :, T:], valid_end)


OBS_DELTA_HELP = ("also see each observation's change since the previous step, scaled by the demonstrations' std "
                  "of it (a finite-difference velocity for positions-only observations)")
PREV_ACTION_HELP = ("see the previous action a_{t-1} (the paper's belief); false: zeros in its place, against the "
                    "copycat problem of cloning deterministic demonstrations (pomil docs hopper)")
"""The policy input options' help (:class:`InputView`), shared by every config that builds a policy."""


class InputView(nn.Module):
    """Another encoder (``inner``) fed a chosen view of each step.

    * ``obs_delta``: the observation gains its change since the previous step,
      (z_t - z_{t-1}) * ``delta_scale`` (zero at an episode's first step), so that a
      positions-only observation carries its finite-difference velocity.  The previous
      observation is part of the state: [inner state, z_{t-1}].  ``delta_scale`` is a
      buffer (saved with the policy), 1 until a trainer sets it from the
      demonstrations (:func:`fit_input_scale`).
    * ``prev_action = False``: a_{t-1} is replaced by zeros.  Behaviour cloning from
      deterministic demonstrations with a_{t-1} in the input learns to repeat the
      previous action (the "copycat" problem), which then compounds its own errors.
    """

    def __init__(self, inner: nn.Module, obs_dim: int, obs_delta: bool, prev_action: bool) -> None:
        super().__init__()
        self.inner, self.obs_dim, self.obs_delta, self.prev_action = inner, obs_dim, obs_delta, prev_action
        self.out_size = inner.out_size
        self.register_buffer("delta_scale", torch.ones(obs_dim))

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        h = self.inner.initial_state(batch, device)
        return torch.cat([h, torch.zeros(batch, self.obs_dim if self.obs_delta else 0, device=device)], dim=-1)

    def _split(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n = h.shape[-1] - (self.obs_dim if self.obs_delta else 0)
        return h[..., :n], h[..., n:]

    def _view(self, obs, prev_actions, last_obs, starts):
        """(observations as the inner encoder sees them, previous actions); obs (..., N, D) with
        ``last_obs`` the observation before the first of them."""
        if self.obs_delta:
            before = torch.cat([last_obs.unsqueeze(0), obs[:-1]], dim=0) if obs.ndim == 3 else last_obs
            delta = (obs - before) * (~starts).unsqueeze(-1).to(obs.dtype) * self.delta_scale
            obs = torch.cat([obs, delta], dim=-1)
        return obs, prev_actions if self.prev_action else torch.zeros_like(prev_actions)

    def step(self, obs, prev_action, h, start):
        inner_h, last = self._split(h)
        x, a = self._view(obs, prev_action, last, start)
        feats, inner_h = self.inner.step(x, a, inner_h, start)
        return feats, torch.cat([inner_h, obs if self.obs_delta else last], dim=-1)

    def unroll(self, obs, prev_actions, h0, starts):
        inner_h, last = self._split(h0)
        x, a = self._view(obs, prev_actions, last, starts)
        feats, inner_h = self.inner.unroll(x, a, inner_h, starts)
        return feats, torch.cat([inner_h, obs[-1] if self.obs_delta else last], dim=-1)


class EnsembleEncoder(nn.Module):
    """Several encoders side by side over the same inputs: their features and states concatenated on the last
    dimension, each encoder carrying its own part of the state (:class:`pomil.nn.policy.EnsemblePolicy`).

    It holds the encoders without registering them: they are registered where they belong (each member policy
    of the ensemble), so that a state dict names each weight once."""

    def __init__(self, encoders: list[nn.Module]) -> None:
        super().__init__()
        self.parts = tuple(encoders)  # a tuple: not a submodule
        self.out_size = sum(e.out_size for e in encoders)
        self.feature_sizes = [e.out_size for e in encoders]
        self.state_sizes = [e.initial_state(1).shape[-1] for e in encoders]

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> torch.Tensor:
        return torch.cat([e.initial_state(batch, device) for e in self.parts], dim=-1)

    def _each(self, method: str, obs, prev, h, start) -> tuple[torch.Tensor, torch.Tensor]:
        outs = [getattr(e, method)(obs, prev, part, start)
                for e, part in zip(self.parts, h.split(self.state_sizes, dim=-1), strict=True)]
        return torch.cat([f for f, _ in outs], dim=-1), torch.cat([s for _, s in outs], dim=-1)

    def step(self, obs, prev_action, h, start):
        return self._each("step", obs, prev_action, h, start)

    def unroll(self, obs, prev_actions, h0, starts):
        return self._each("unroll", obs, prev_actions, h0, starts)


@torch.no_grad()
def fit_input_scale(encoder: nn.Module, observations: torch.Tensor, mask: torch.Tensor) -> None:
    """With an ``obs_delta`` :class:`InputView`, set ``delta_scale`` to 1 / the std of the
    demonstrations' step-to-step observation changes (time-major (T, E, D) episodes from their
    first step, ``mask`` (T, E)), so that the change is about as large as the observation;
    an :class:`EnsembleEncoder`'s encoders each; any other encoder is left as it is."""
    if isinstance(encoder, EnsembleEncoder):
        for part in encoder.parts:
            fit_input_scale(part, observations, mask)
        return
    if not (isinstance(encoder, InputView) and encoder.obs_delta):
        return
    both = mask[1:] & mask[:-1]
    delta = (observations[1:] - observations[:-1])[both]
    std = delta.std(0) if len(delta) > 1 else torch.ones_like(encoder.delta_scale)
    encoder.delta_scale.copy_(1.0 / std.clamp_min(1e-6))


def make_encoder(kind: str, obs_dim: int, act_dim: int, *, hidden_size: int, context: int = 32,
                 obs_delta: bool = False, prev_action: bool = True) -> nn.Module:
    """The encoder called ``kind`` (one of :data:`ENCODERS`); ``context`` is the attention encoder's window;
    ``obs_delta`` / ``prev_action = False``: seen through an :class:`InputView` (else the encoder itself)."""
    if obs_delta or not prev_action:
        inner = make_encoder(kind, obs_dim * (2 if obs_delta else 1), act_dim, hidden_size=hidden_size, context=context)
        return InputView(inner, obs_dim, obs_delta, prev_action)
    if kind not in ENCODERS:
        raise ValueError(f"unknown encoder {kind!r}; expected one of {', '.join(map(repr, ENCODERS))}")
    if kind == "attention":
        return AttentionEncoder(obs_dim, act_dim, hidden_size, context)
    return {"mlp": MLPEncoder, "gru": BeliefEncoder, "lstm": LSTMEncoder}[kind](obs_dim, act_dim, hidden_size)
