"""Rollouts: one episode in each copy of a batched environment.

Shared by every on-policy loop (adversarial learners, PPO experts).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NamedTuple

import torch

from pomil.nn.codes import draw_codes
from pomil.nn.heads import BeliefHead
from pomil.nn.policy import GaussianPolicy
from pomil.rl.storage import Rollout


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run a block with ``n`` torch intra-op threads (0: leave the setting alone)."""
    before = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class Collected(NamedTuple):
    """What :func:`collect` returns."""

    rollout: Rollout
    next_values: torch.Tensor
    """(T, N): V(s_{t+1}), the final observation's value at the last step."""
    codes: torch.Tensor
    """(N,): the latent code index of each copy's episode; continuous codes: (N, d), the codes."""
    env_rewards: torch.Tensor
    """(T, N): the environment's own rewards, zero outside episodes (never learned from by imitation learners)."""


@torch.no_grad()
def collect(env, policy: GaussianPolicy, value: BeliefHead, *, num_codes: int,
            execute: Callable[[torch.Tensor], torch.Tensor],
            generator: torch.Generator, device: torch.device, threads: int = 1, code_kind: str = "discrete",
            code_prior: str = "uniform") -> Collected:
    """One episode in each of the env's N copies, a latent code per episode (none when ``num_codes`` is 0): one
    of ``num_codes`` codes, or with ``code_kind`` continuous a ``num_codes``-dimensional code from ``code_prior``
    (``pomil.nn.codes``).  ``execute`` maps raw actions to executed ones (``pomil.envs.executed_actions_fn``).
    Episodes may end at different steps; ``mask`` marks the steps that belong to an episode.  Returns a
    :class:`Collected`: the rollout, the next states' values, each episode's code and the environment's rewards.

    The policy steps with ``threads`` torch threads (0: as set): its per-step tensors are small, and with one
    thread torch's OpenMP workers do not spin on the cores that a batched simulator's own threads step the
    physics on (``benchmarks/hopper_speed.py``).  The values come after the episodes, in one unroll of the
    value network over the whole rollout."""
    n = env.num_envs
    obs = env.reset()
    code_idx, codes = draw_codes(code_kind, code_prior, n, width=num_codes, generator=generator)
    code_idx, codes = code_idx.to(device), codes.to(device)
    h_pi, h0_v = policy.initial_state(n, device), value.initial_state(n, device)
    h0_pi = h_pi.clone()
    prev = torch.zeros(n, policy.arch.act_dim, device=device)
    start = torch.ones(n, dtype=torch.bool, device=device)
    alive = torch.ones(n, dtype=torch.bool, device=device)
    steps: list[dict[str, torch.Tensor]] = []
    with torch_threads(threads):
        while True:
            dist, h_pi = policy.step(obs, prev, h_pi, start, codes)
            action = dist.mean + dist.stddev * torch.randn(dist.mean.shape, generator=generator).to(device)
            executed = execute(action)
            rec = {"obs": obs, "act": action, "exec": executed, "prev": prev * (~start).unsqueeze(-1), "start": start,
                   "logp": dist.log_prob(action).sum(-1), "mask": alive}
            obs, env_reward, term, trunc = env.step(action)
            steps.append({**rec, "env_reward": env_reward * alive, "term": term & alive, "trunc": trunc & alive})
            alive = alive & ~(term | trunc)
            prev, start = executed, torch.zeros_like(start)
            if not bool(alive.any()):
                break
    st = {k: torch.stack([step[k] for step in steps]) for k in steps[0]}
    T = st["obs"].shape[0]
    # V(s_0) ... V(s_T): the steps' observations, then the final one (its a_{t-1} the last executed action).
    values, _ = value.unroll(torch.cat([st["obs"], obs.unsqueeze(0)]), torch.cat([st["prev"], prev.unsqueeze(0)]), h0_v,
                             torch.cat([st["start"], start.unsqueeze(0)]),
                             extra=codes.unsqueeze(0).expand(T + 1, -1, -1))
    roll = Rollout(
        observations=st["obs"], actions=st["act"], env_actions=st["exec"], prev_actions=st["prev"], starts=st["start"],
        codes=codes.unsqueeze(0).expand(T, -1, -1), log_probs=st["logp"], values=values[:-1],
        terminated=st["term"], truncated=st["trunc"], mask=st["mask"], h0_policy=h0_pi, h0_value=h0_v,
    )
    return Collected(roll, values[1:], code_idx, st["env_reward"])
