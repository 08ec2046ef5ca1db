"""Roll a trained policy out in the batched circles environment."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from pomil.api import TrainedPolicy
from pomil.envs.circles import DEFAULT_NONE_THRESHOLD, ENV_ID, CirclesSpec, CirclesVecEnv, classify_modes, fit_circles
from pomil.errors import PomilError
from pomil.eval.metrics import EPISODE_SEGMENTS, coverage, episode_purity, mode_metrics, spearman
from pomil.nn.codes import prior_grid


def circles_spec_of(policy: TrainedPolicy) -> CirclesSpec:
    if policy.env.get("id") != ENV_ID:
        raise PomilError(f"this checkpoint was trained on {policy.env.get('id')!r}; only {ENV_ID} is supported here")
    return CirclesSpec.from_dict(policy.env.get("kwargs", {}))


@torch.no_grad()
def rollout_circles(policy: TrainedPolicy, episodes_per_code: int = 100, seed: int = 0,
                    *, deterministic: bool = False, codes: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """positions (E, T, 2) visited after each step, codes (E,), returns (E,).  ``codes``: the
    episodes' codes (E,) or continuous (E, d) (default: each discrete code ``episodes_per_code`` times)."""
    spec = circles_spec_of(policy)
    if (policy.obs_dim, policy.act_dim) != (spec.obs_dim, spec.act_dim):
        raise PomilError(f"policy sizes {(policy.obs_dim, policy.act_dim)} do not match the environment "
                         f"{(spec.obs_dim, spec.act_dim)}")
    if codes is None and policy.code_dim:
        raise PomilError("this policy has continuous codes: pass the codes to roll out (see evaluate_code_radius)")
    if codes is None:
        codes = np.repeat(np.arange(max(policy.num_codes, 1)), episodes_per_code)
    n = len(codes)
    env = CirclesVecEnv(spec, n)
    obs = env.reset()
    policy.reset(n, codes if policy.num_codes or policy.code_dim else None, seed=seed)
    positions, ret = [], torch.zeros(n)
    for _ in range(spec.episode_length):
        obs, reward, _, _ = env.step(torch.as_tensor(policy.act(obs, deterministic)))
        positions.append(env.positions.clone())
        ret += reward
    return {"positions": torch.stack(positions, 1).numpy(), "codes": codes, "returns": ret.numpy()}


def evaluate_circles(policy: TrainedPolicy, episodes_per_code: int = 100, seed: int = 0, *, deterministic: bool = False,
                     threshold: float = DEFAULT_NONE_THRESHOLD) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Mode metrics of the policy's rollouts (and the rollouts themselves): per code (``mode_metrics``), and
    over all its episodes, with the codes drawn evenly as a user sampling freely would: ``coverage`` (the
    modes' entropy over log M) and whether an episode stays in one mode (``episode_purity``, ``switch_share``:
    each of its :data:`EPISODE_SEGMENTS` parts classified alone)."""
    spec = circles_spec_of(policy)
    roll = rollout_circles(policy, episodes_per_code, seed, deterministic=deterministic)
    roll["modes"] = classify_modes(roll["positions"], spec, threshold)
    metrics = mode_metrics(roll["codes"], roll["modes"], max(policy.num_codes, 1), spec.num_modes)
    thirds = np.array_split(np.arange(roll["positions"].shape[1]), EPISODE_SEGMENTS)
    segments = np.stack([classify_modes(roll["positions"][:, part], spec, threshold) for part in thirds], 1)
    metrics.update(coverage=coverage(roll["modes"], spec.num_modes), **episode_purity(segments))
    metrics.update(algo=policy.algo, num_codes=policy.num_codes, episodes_per_code=episodes_per_code,
                   deterministic=deterministic, none_threshold=threshold, seed=seed,
                   mean_return=float(roll["returns"].mean()))
    return metrics, roll


def evaluate_code_radius(policy: TrainedPolicy, values: int = 9, episodes_per_value: int = 20, *, seed: int = 0,
                         deterministic: bool = False) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """How a continuous code maps to the radius of the circle the policy draws.

    For each code dimension j: ``values`` codes evenly over the prior (its quantiles at
    (i + 0.5) / values; the other dimensions at the prior's median, 0), ``episodes_per_value``
    rollouts each, a least-squares circle fitted to every trajectory (``fit_circles``), and
    Spearman's rho between code value and fitted radius over all trajectories (its largest
    possible value with the code values' ties, ``spearman_max``, is reached when the radii of
    different code values never overlap: 0.994 for 9 values of 20).  Also each code value's
    median radius and the range they cover.  ``spearman`` is the rho of the dimension
    with the largest |rho|.  Returns (metrics, rollouts of dimension 0 with codes and radii)."""
    if not policy.code_dim:
        raise PomilError("evaluate_code_radius: this policy has no continuous code")
    grid = prior_grid(policy.code_prior, values).numpy()
    dims, first = [], None
    for j in range(policy.code_dim):
        codes = np.zeros((values * episodes_per_value, policy.code_dim), dtype=np.float32)
        codes[:, j] = np.repeat(grid, episodes_per_value)
        roll = rollout_circles(policy, seed=seed + j, deterministic=deterministic, codes=codes)
        _, radii = fit_circles(roll["positions"])
        medians = [float(np.median(radii[codes[:, j] == v])) for v in grid]
        dims.append({"dim": j, "spearman": spearman(codes[:, j], radii),
                     "spearman_max": spearman(codes[:, j], np.arange(len(codes))), "code_values": grid.tolist(),
                     "median_radius": medians, "radius_covered": [min(medians), max(medians)],
                     "mean_return": float(roll["returns"].mean())})
        if first is None:
            first = {**roll, "code_values": codes[:, 0], "radii": radii}
    best = max(dims, key=lambda d: abs(d["spearman"]))
    metrics = {"algo": policy.algo, "code_dim": policy.code_dim, "code_prior": policy.code_prior,
               "values": values, "episodes_per_value": episodes_per_value, "deterministic": deterministic,
               "seed": seed, "spearman": best["spearman"], "spearman_max": best["spearman_max"],
               "spearman_dim": best["dim"], "radius_covered": best["radius_covered"], "dims": dims}
    return metrics, first
