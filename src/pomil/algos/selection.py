"""The policy a run hands over: of those its evaluations measured, the one nearest the demonstrations.

An adversarial phase can drift away from what its warm start had right (docs: "Which policy a run hands
over").  At each evaluation (the warm start's first) the run measures how far its policy's deterministic
rollouts lie from the demonstrations (:func:`pomil.eval.demo_distance.demo_distance`, on what the learner
observes, never the environment's reward) and keeps the nearest policy so far.  The checkpoint's ``policy``,
what :class:`pomil.TrainedPolicy` and ``pomil evaluate`` load, is that one; the run's own policy goes on
training and stays in ``nets.policy``, which ``--resume`` restores.
"""

from __future__ import annotations

from typing import Any

import torch

from pomil.api import TrainedPolicy
from pomil.data import PaddedEpisodes
from pomil.eval.demo_distance import DemoReference, demo_distance
from pomil.nn.policy import GaussianPolicy


class PolicySelection:
    """The nearest policy so far of a run (``best``: its iteration, distance and weights; None before the
    first measure).  ``expert``: the demonstrations with actions in the policy's executed form and
    ``expert_prev`` their previous actions (the codes' assignment of each episode); ``env_info`` and
    ``learner``: what a :class:`TrainedPolicy` of the run needs to roll out."""

    def __init__(self, expert: PaddedEpisodes, expert_prev: torch.Tensor, *, env_info: dict[str, Any], learner: str,
                 episodes_per_code: int = 16) -> None:
        self.expert, self.expert_prev = expert, expert_prev
        self.env_info, self.learner, self.episodes_per_code = env_info, learner, episodes_per_code
        self.reference = DemoReference.of(expert.observations.cpu(), expert.mask.cpu())
        self.best: dict[str, Any] | None = None
        self._last: dict[str, Any] = {}

    @torch.no_grad()
    def assignment(self, policy: GaussianPolicy) -> torch.Tensor:
        """Each demonstration episode's code under the policy (balanced over codes), (E,); zeros without discrete
        codes (continuous codes: every code value's rollouts against all the demonstrations)."""
        from pomil.algos.warm_start import balanced_responsibilities, demonstration_pass

        if policy.arch.continuous_codes or policy.arch.num_codes < 2:
            return torch.zeros(self.expert.mask.shape[1], dtype=torch.long)
        ll, _ = demonstration_pass(policy, self.expert, self.expert_prev)
        return balanced_responsibilities(ll).argmax(0).cpu()

    def __call__(self, policy: GaussianPolicy, iteration: int) -> dict[str, float]:
        """Measure the policy of ``iteration``; keep it when it is nearer than every one before (a policy that
        has not moved since the last measure keeps that measure, without rollouts)."""
        weights = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        if self._last and all(torch.equal(v, self._last["weights"][k]) for k, v in weights.items()):
            distance = self._last["distance"]
        else:
            assignment = self.assignment(policy)
            distance = demo_distance(TrainedPolicy(policy, self.learner, self.env_info, policy.log_std.device),
                                     self.reference, assignment, episodes_per_code=self.episodes_per_code)["distance"]
            policy.train()
            self._last = {"weights": weights, "distance": distance}
        if self.best is None or distance < self.best["distance"]:
            self.best = {"iteration": iteration, "distance": distance, "policy": weights}
        return {"select/distance": distance, "select/iteration": float(self.best["iteration"]),
                "select/best_distance": self.best["distance"]}

    def policy_state(self) -> dict[str, torch.Tensor] | None:
        """The nearest policy's weights (None before the first measure)."""
        return None if self.best is None else self.best["policy"]

    def state_dict(self) -> dict[str, Any]:
        """The nearest policy so far (empty before the first measure): what ``--resume`` needs to hand over the
        same policy as the run uninterrupted."""
        if self.best is None:
            return {}
        return {"iteration": torch.tensor(self.best["iteration"]), "distance": torch.tensor(self.best["distance"],
                                                                                          dtype=torch.float64),
                "policy": self.best["policy"]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not isinstance(state, dict) or (state and set(state) != {"iteration", "distance", "policy"}):
            raise ValueError("the policy selection's state is not {iteration, distance, policy}")
        if not state:
            self.best = None
            return
        it, dist, weights = state["iteration"], state["distance"], state["policy"]
        if not (isinstance(it, torch.Tensor) and it.numel() == 1 and isinstance(dist, torch.Tensor)
                and dist.numel() == 1 and isinstance(weights, dict)
                and all(isinstance(v, torch.Tensor) for v in weights.values())):
            raise ValueError("the policy selection's state is damaged")
        self.best = {"iteration": int(it), "distance": float(dist), "policy": dict(weights)}
