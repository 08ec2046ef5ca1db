"""How far a policy's behaviour is from the demonstrations, measured on what the learner sees.

A signal that needs no environment reward: each code's deterministic rollouts against the
demonstration episodes the policy itself assigns to that code, compared as distributions of
steps.  A step is the observation and its change to the next step, standardised by the
demonstrations; an episode that ends before the demonstrations' horizon fills its remaining
steps with one absorbing point far from every live step, so that falling early counts as
being elsewhere.  The distance is the maximum mean discrepancy (MMD, Gaussian kernel, its
width the demonstrations' median pairwise distance) between equal-size samples of steps,
averaged over codes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pomil.api import TrainedPolicy
from pomil.envs import make_vec_env

ABSORBING_WIDTHS = 3.0
"""The absorbing point's distance from the origin of the standardised live steps, in kernel widths."""


def step_features(obs: torch.Tensor, mask: torch.Tensor, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per step of (T, B, D) observations with a (T, B) live mask: ``[o_t, o_{t+1} - o_t]`` (steps with a
    next live step), (horizon - 1, B, 2D), and whether each is a live pair (horizon - 1, B)."""
    t, b, d = obs.shape
    if t < horizon:
        obs = torch.cat([obs, obs.new_zeros(horizon - t, b, d)])
        mask = torch.cat([mask, mask.new_zeros(horizon - t, b)])
    obs, mask = obs[:horizon], mask[:horizon].bool()
    live = mask[:-1] & mask[1:]
    return torch.cat([obs[:-1], obs[1:] - obs[:-1]], dim=-1), live


@dataclass(frozen=True)
class DemoReference:
    """The demonstrations as the distance sees them: standardised step features, the live mask, the
    kernel width and the absorbing point."""

    features: torch.Tensor  # (H - 1, E, F) standardised
    live: torch.Tensor  # (H - 1, E)
    mean: torch.Tensor  # (F,)
    std: torch.Tensor  # (F,)
    width: float
    horizon: int

    def __post_init__(self) -> None:
        if self.features.shape[:2] != self.live.shape or self.features.shape[0] != self.horizon - 1:
            raise ValueError(f"features {tuple(self.features.shape)} do not fit live {tuple(self.live.shape)} "
                             f"and horizon {self.horizon}")

    @classmethod
    def of(cls, obs: torch.Tensor, mask: torch.Tensor, *, samples: int = 1024, seed: int = 0) -> DemoReference:
        horizon = int(mask.sum(0).max())
        feats, live = step_features(obs.float(), mask, horizon)
        pts = feats[live]
        mean, std = pts.mean(0), pts.std(0).clamp_min(1e-6)
        z = (feats - mean) / std
        gen = torch.Generator().manual_seed(seed)
        sub = z[live][torch.randint(0, int(live.sum()), (samples,), generator=gen)]
        width = float(torch.cdist(sub, sub).median().clamp_min(1e-6))
        return cls(z, live, mean, std, width, horizon)

    def sample(self, feats: torch.Tensor, live: torch.Tensor, samples: int, gen: torch.Generator) -> torch.Tensor:
        """``samples`` steps drawn uniformly over (step, episode) cells, absorbing where not live."""
        cells = feats.shape[0] * feats.shape[1]
        idx = torch.randint(0, cells, (samples,), generator=gen)
        x = feats.reshape(cells, -1)[idx]
        dead = ~live.reshape(cells)[idx]
        out = torch.cat([x, torch.zeros(samples, 1)], dim=1)
        out[dead] = 0.0
        out[dead, -1] = ABSORBING_WIDTHS * self.width
        return out


def mmd(x: torch.Tensor, y: torch.Tensor, width: float) -> float:
    """The (biased, V-statistic) maximum mean discrepancy between samples ``x`` and ``y``, Gaussian kernel."""
    k = lambda a, b: torch.exp(-torch.cdist(a, b).pow(2) / (2 * width ** 2))  # noqa: E731
    return float((k(x, x).mean() + k(y, y).mean() - 2 * k(x, y).mean()).clamp_min(0).sqrt())


@torch.no_grad()
def rollout_observations(policy: TrainedPolicy, codes: np.ndarray, horizon: int, *, seed: int = 12345
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Deterministic episodes of the policy in its training environment, one per entry of ``codes``:
    observations (horizon, n, D) and the live mask (horizon, n)."""
    n = len(codes)
    env = make_vec_env(policy.env["id"], policy.env.get("kwargs", {}), n, device="cpu",
                       observation_mask=policy.env.get("observation_mask"), seed=seed)
    try:
        obs = env.reset()
        policy.reset(n, codes if policy.num_codes else None, seed=seed)
        ended = torch.zeros(n, dtype=torch.bool)
        observations, live = [], []
        for _ in range(horizon):
            observations.append(obs.float().cpu())
            live.append(~ended)
            if bool(ended.all()):
                continue
            obs, _, term, trunc = env.step(torch.as_tensor(policy.act(obs, True)))
            ended = ended | term.cpu() | trunc.cpu()
        return torch.stack(observations), torch.stack(live)
    finally:
        env.close()


def demo_distance(policy: TrainedPolicy, reference: DemoReference, assignment: torch.Tensor, *,
                  episodes_per_code: int = 16, samples: int = 2048, seed: int = 12345) -> dict[str, Any]:
    """The distance of each code's rollouts from the demonstration episodes assigned to it (``assignment``:
    each demonstration episode's code, (E,)), and their mean over codes (``distance``)."""
    k = max(policy.num_codes, 1)
    codes = np.repeat(np.arange(k), episodes_per_code)
    obs, mask = rollout_observations(policy, codes, reference.horizon, seed=seed)
    feats, live = step_features(obs, mask, reference.horizon)
    feats = (feats - reference.mean) / reference.std
    gen = torch.Generator().manual_seed(seed)
    per_code = []
    for c in range(k):
        mine = torch.as_tensor(codes == c)
        theirs = assignment == c if policy.num_codes else torch.ones_like(assignment, dtype=torch.bool)
        if not bool(theirs.any()):
            per_code.append(float("nan"))
            continue
        x = reference.sample(feats[:, mine], live[:, mine], samples, gen)
        y = reference.sample(reference.features[:, theirs], reference.live[:, theirs], samples, gen)
        per_code.append(mmd(x, y, reference.width))
    return {"distance": float(np.nanmean(per_code)), "per_code": per_code,
            "live_share": float(live.float().mean())}
