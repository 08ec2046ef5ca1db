"""The clipped PPO objective as a pure function returning (loss, stats), and PPO's options."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pomil.config import option


@dataclass(frozen=True)
class PPOOptions:
    """PPO's options (the experts' and the adversarial learners'): GAE, the clipped loss, its epochs and batches."""

    gamma: float = option(0.99, "discount", within="(0, 1]")
    gae_lambda: float = option(0.95, "GAE lambda", within="(0, 1]")
    clip: float = option(0.2, "PPO ratio clip", within="(0, inf)")
    ppo_epochs: int = option(10, "PPO epochs per iteration", within="[1, inf)")
    minibatches: int = option(16, "PPO minibatches per epoch", within="[1, inf)")
    ent_coef: float = option(0.0, "lambda2: entropy bonus in the PPO loss", within="[0, inf)")
    vf_coef: float = option(0.5, "weight of the value loss in the PPO loss", within="[0, inf)")
    max_grad_norm: float = option(0.5, "gradient-norm clip of the policy's and of the value's update",
                                  within="(0, inf)")


def masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def normalize(x: torch.Tensor, mask: torch.Tensor | None = None, eps: float = 1e-8) -> torch.Tensor:
    mean = masked_mean(x, mask)
    std = masked_mean((x - mean) ** 2, mask).sqrt()
    return (x - mean) / (std + eps)


def ppo_loss(*, new_logp: torch.Tensor, old_logp: torch.Tensor, advantages: torch.Tensor, new_values: torch.Tensor,
             old_values: torch.Tensor, returns: torch.Tensor, entropy: torch.Tensor, mask: torch.Tensor | None = None,
             clip: float = 0.2, value_clip: float | None = None, vf_coef: float = 0.5,
             ent_coef: float = 0.0) -> tuple[torch.Tensor, dict[str, float]]:
    """Clipped surrogate + (optionally clipped) value loss - entropy bonus.

    All tensors share one shape; ``mask`` selects the valid entries.
    Advantages are used as given (normalise them beforehand if wanted).
    Keyword arguments only: twelve positional numbers cannot be read at a call site.
    """
    log_ratio = new_logp - old_logp
    ratio = log_ratio.exp()
    surrogate = torch.min(ratio * advantages, ratio.clamp(1 - clip, 1 + clip) * advantages)
    policy_loss = -masked_mean(surrogate, mask)
    v_err = (new_values - returns) ** 2
    if value_clip is not None:
        v_clipped = old_values + (new_values - old_values).clamp(-value_clip, value_clip)
        v_err = torch.max(v_err, (v_clipped - returns) ** 2)
    value_loss = 0.5 * masked_mean(v_err, mask)
    ent = masked_mean(entropy, mask)
    loss = policy_loss + vf_coef * value_loss - ent_coef * ent
    with torch.no_grad():
        stats = {
            "ppo/policy_loss": policy_loss.item(),
            "ppo/value_loss": value_loss.item(),
            "ppo/entropy": ent.item(),
            "ppo/approx_kl": masked_mean((ratio - 1) - log_ratio, mask).item(),
            "ppo/clip_fraction": masked_mean(((ratio - 1).abs() > clip).to(ratio.dtype), mask).item(),
        }
    return loss, stats
