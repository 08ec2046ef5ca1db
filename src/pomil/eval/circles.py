"""Roll a trained policy out in the batched circles environment."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from pomil.api import TrainedPolicy
from pomil.envs.circles import ENV_ID, CirclesSpec, CirclesVecEnv, DEFAULT_NONE_THRESHOLD, classify_modes
from pomil.errors import PomilError
from pomil.eval.metrics import mode_metrics


def circles_spec_of(policy: TrainedPolicy) -> CirclesSpec:
    if policy.env.get("id") != ENV_ID:
        raise PomilError(f"this checkpoint was trained on {policy.env.get('id')!r}; only {ENV_ID} is supported here")
    return CirclesSpec.from_dict(policy.env.get("kwargs", {}))


@torch.no_grad()
def rollout_circles(policy: TrainedPolicy, episodes_per_code: int = 100, seed: int = 0,
                    deterministic: bool = False) -> dict[str, np.ndarray]:
    """positions (E, T, 2) visited after each step, codes (E,), returns (E,)."""
    spec = circles_spec_of(policy)
    if (policy.obs_dim, policy.act_dim) != (spec.obs_dim, spec.act_dim):
        raise PomilError(f"policy sizes {(policy.obs_dim, policy.act_dim)} do not match the environment "
                         f"{(spec.obs_dim, spec.act_dim)}")
    k = max(policy.num_codes, 1)
    n = episodes_per_code * k
    codes = np.repeat(np.arange(k), episodes_per_code)
    env = CirclesVecEnv(spec, n)
    obs = env.reset()
    policy.reset(n, codes if policy.num_codes else None, seed=seed)
    positions, ret = [], torch.zeros(n)
    for _ in range(spec.episode_length):
        obs, reward, _, _ = env.step(torch.as_tensor(policy.act(obs, deterministic)))
        positions.append(env.positions.clone())
        ret += reward
    return {"positions": torch.stack(positions, 1).numpy(), "codes": codes, "returns": ret.numpy()}


def evaluate_circles(
    policy: TrainedPolicy, episodes_per_code: int = 100, seed: int = 0, deterministic: bool = False,
    threshold: float = DEFAULT_NONE_THRESHOLD,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Mode metrics of the policy's rollouts (and the rollouts themselves)."""
    spec = circles_spec_of(policy)
    roll = rollout_circles(policy, episodes_per_code, seed, deterministic)
    modes = classify_modes(roll["positions"], spec, threshold)
    roll["modes"] = modes
    metrics = mode_metrics(roll["codes"], modes, max(policy.num_codes, 1), spec.num_modes)
    metrics.update({
        "algo": policy.algo, "num_codes": policy.num_codes, "episodes_per_code": episodes_per_code,
        "deterministic": deterministic, "none_threshold": threshold, "seed": seed,
        "mean_return": float(roll["returns"].mean()),
    })
    return metrics, roll
