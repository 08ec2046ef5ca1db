"""Generalised advantage estimation, termination kept apart from truncation.

A terminated step has no future: nothing is bootstrapped.  A truncated step
(time limit) does have one: its value is bootstrapped from V(s_{t+1}), the
value of the observation the environment returned before the reset, and only
the recursion of advantages is cut there.
"""

from __future__ import annotations

import torch


def gae(rewards: torch.Tensor, values: torch.Tensor, next_values: torch.Tensor, *, terminated: torch.Tensor,
        truncated: torch.Tensor, gamma: float = 0.99, lam: float = 0.95) -> tuple[torch.Tensor, torch.Tensor]:
    """All inputs (T, N); ``next_values[t]`` = V(s_{t+1}) (the final observation's value
    where step t ended an episode).  Returns (advantages, returns), both (T, N)."""
    if not (rewards.shape == values.shape == next_values.shape == terminated.shape == truncated.shape):
        raise ValueError(f"gae inputs must share one (T, N) shape, got rewards {tuple(rewards.shape)}, values "
                         f"{tuple(values.shape)}, next_values {tuple(next_values.shape)}, terminated "
                         f"{tuple(terminated.shape)}, truncated {tuple(truncated.shape)}")
    not_term = (~terminated).to(rewards.dtype)
    not_done = (~(terminated | truncated)).to(rewards.dtype)
    deltas = rewards + gamma * next_values * not_term - values
    adv = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[0])
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = deltas[t] + gamma * lam * not_done[t] * running
        adv[t] = running
    return adv, adv + values
