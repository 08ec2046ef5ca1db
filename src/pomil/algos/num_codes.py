"""``--num-codes auto``: the number of latent codes K chosen from unlabelled demonstrations.

For each K = 1..K_max the mixture warm start (each of K codes clones its own balanced
share of the episodes, :func:`pomil.algos.warm_start.clone_demonstrations`) is fitted to
a training split of the episodes (80%, split by the run's seed), and the held-out
episodes are scored per step by their *classification* log-likelihood under the uniform
mixture of the K codes (:func:`classification_log_likelihood`, the held-out form of
Biernacki et al.'s ICL): sum_k q_k (log p(episode | k) - log K), q the episode's
posterior over the codes.  That is the mixture log-likelihood log (1/K) sum_k p(episode | k)
less the entropy of q.  The criterion (:func:`choose_num_codes`) goes forward from the first
K that gains more than ``min_gain`` nats per step over K = 1 (K = 1 when none does): a larger K
is taken only when it scores more than ``tolerance`` x the current K's average gain per code
above it (the criterion's evidence: docs/method.md, "How many codes").

The entropy term tells duplicates apart: the balanced warm start gives every code 1/K of the episodes, so
with more codes than modes some codes clone the *same* mode, which leaves the mixture log-likelihood
unchanged (two codes at p each: log(2p / 4) = log(p / 2)); a duplicated mode splits its episodes' q between
the duplicates, and the entropy charges log 2 nats per such episode.
Held-out scores need no parameter count (a BIC's would mean little for networks that
share all but a code embedding); log-likelihood differences do not depend on the
actions' units, so ``min_gain`` is in nats and ``tolerance`` a fraction of a gain.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch

from pomil.algos.warm_start import demonstration_pass
from pomil.data import PaddedEpisodes
from pomil.nn.policy import GaussianPolicy

HELDOUT_SHARE = 0.2
"""Share of the demonstration episodes held out to score each K."""


def mixture_log_likelihood(code_log_likelihoods: torch.Tensor) -> torch.Tensor:
    """Each episode's log-likelihood under the uniform mixture of K codes, (E,), from its
    log-likelihood under each code, (K, E): log (1/K) sum_k exp(L_k)."""
    return torch.logsumexp(code_log_likelihoods, 0) - math.log(code_log_likelihoods.shape[0])


def code_posterior_entropy(code_log_likelihoods: torch.Tensor) -> torch.Tensor:
    """Each episode's entropy (nats) of its posterior over the K codes under a uniform prior, (E,),
    from its log-likelihood under each code, (K, E): 0 when one code explains it, log 2 when two alike."""
    log_q = torch.log_softmax(code_log_likelihoods, 0)
    return -(log_q.exp() * log_q).sum(0)


def classification_log_likelihood(code_log_likelihoods: torch.Tensor) -> torch.Tensor:
    """Each episode's classification log-likelihood, (E,): sum_k q_k (L_k - log K) with q =
    softmax(L), the mixture log-likelihood less the entropy of the posterior over the codes."""
    return mixture_log_likelihood(code_log_likelihoods) - code_posterior_entropy(code_log_likelihoods)


class HeldoutScore(NamedTuple):
    score: float
    """Classification log-likelihood per step (:func:`classification_log_likelihood`)."""
    log_likelihood: float
    """Mixture log-likelihood per step (:func:`mixture_log_likelihood`)."""
    entropy: float
    """Mean entropy of an episode's posterior over the codes, nats per episode."""
    episodes: tuple[float, ...]
    """Each episode's classification log-likelihood (nats, summed over its steps): ``score`` is their
    sum over all the episodes' steps."""


def heldout_score(policy: GaussianPolicy, data: PaddedEpisodes, prev_actions: torch.Tensor) -> HeldoutScore:
    """The score of (held-out) whole episodes under the policy's codes, per step: their summed
    classification log-likelihood / their steps."""
    ll = demonstration_pass(policy, data, prev_actions)[0]
    steps = data.mask.sum().item()
    per_episode = classification_log_likelihood(ll)
    return HeldoutScore(per_episode.sum().item() / steps, mixture_log_likelihood(ll).sum().item() / steps,
                        code_posterior_entropy(ll).mean().item(), tuple(per_episode.tolist()))


def paired_standard_error(a: Sequence[float], b: Sequence[float], steps: Sequence[int]) -> float:
    """The standard error (nats per step) of the difference of two per-step scores over the same
    held-out episodes, sum(a) / sum(steps) - sum(b) / sum(steps), from the episodes' paired
    differences a_e - b_e (a ratio estimator's: episodes of unequal length weigh by their steps);
    0 for fewer than two episodes."""
    if not len(a) == len(b) == len(steps):
        raise ValueError(f"needs a score per episode on both sides and steps per episode, got {len(a)}, {len(b)}, "
                         f"{len(steps)}")
    d = torch.tensor(a, dtype=torch.float64) - torch.tensor(b, dtype=torch.float64)
    n = torch.tensor(steps, dtype=torch.float64)
    if d.numel() < 2:
        return 0.0
    residual = d - n * d.sum() / n.sum()
    return (residual.std() * math.sqrt(d.numel()) / n.sum()).item()


def choose_num_codes(scores: Mapping[int, float], tolerance: float, min_gain: float) -> int:
    """The number of codes that ``scores`` (held-out scores per step, by K = 1..K_max) call for,
    chosen forward: 1 when no K scores more than ``min_gain`` (nats per step) above K 1; else start
    at the smallest K that does, and move on to the smallest larger K whose score exceeds the
    current K's by more than ``tolerance`` x the current K's average gain per code,
    (score_K - score_1) / (K - 1), until no larger K does.

    Each further code must add a share of what an average code added so far: a code for another
    expert adds about as much as the ones before it, a code that splits one expert's episodes (a
    branch of its start, a variant of its gait) much less.  The yardstick grows with the codes'
    own gains, not with the whole gain up to the best K, so a fifth mode is judged as a second was."""
    ks = sorted(scores)
    if ks[:1] != [1] or ks != list(range(1, len(ks) + 1)):
        raise ValueError(f"scores must be given for K = 1, 2, ..., K_max; got K = {ks}")
    if not all(math.isfinite(scores[k]) for k in ks):
        raise ValueError(f"scores must be finite, got {dict(scores)}")
    k = next((j for j in ks if scores[j] - scores[1] > min_gain), 1)
    while k > 1 and (further := [j for j in ks if j > k
                                 and scores[j] - scores[k] > tolerance * average_gain_per_code(scores, k)]):
        k = further[0]
    return k


def average_gain_per_code(scores: Mapping[int, float], k: int) -> float:
    """(score_K - score_1) / (K - 1): what each code beyond the first added on average up to K (K >= 2)."""
    return (scores[k] - scores[1]) / (k - 1)


def heldout_split(num_episodes: int, seed: int, share: float = HELDOUT_SHARE) -> tuple[torch.Tensor, torch.Tensor]:
    """(training, held-out) episode indices, each sorted: ``share`` of the episodes (at least one)
    held out at random by ``seed``, at least one kept for training."""
    if num_episodes < 2:
        raise ValueError(f"needs at least 2 demonstration episodes to hold some out, got {num_episodes}")
    perm = torch.randperm(num_episodes, generator=torch.Generator().manual_seed(seed))
    held = min(max(1, round(share * num_episodes)), num_episodes - 1)
    return perm[held:].sort().values, perm[:held].sort().values


@dataclass(frozen=True)
class NumCodesChoice:
    """What ``--num-codes auto`` chose and its evidence (config.json, the checkpoint, row 0 of the log)."""

    chosen: int
    """The criterion's K (:func:`choose_num_codes`); 1: no evidence of more than one mode."""
    scores: dict[int, float]
    """Held-out classification log-likelihood per step (:func:`heldout_score`), by K."""
    entropies: dict[int, float]
    """Mean entropy of a held-out episode's posterior over the codes (nats), by K."""
    episode_scores: dict[int, tuple[float, ...]] = field(default_factory=dict)
    """Each held-out episode's classification log-likelihood (nats), by K: the evidence for the
    scores' noise over episodes (:func:`paired_standard_error`); empty in records written before it."""
    episode_steps: tuple[int, ...] = ()
    """Each held-out episode's steps, in the order of ``episode_scores``."""

    @property
    def trained(self) -> int:
        """The codes the run trains: the chosen K, but at least 2 (a single code carries no information)."""
        return max(2, self.chosen)

    def record(self) -> dict[str, Any]:
        return {"num_codes_chosen": self.chosen, "num_codes_trained": self.trained,
                "num_codes_evidence": {str(k): v for k, v in self.scores.items()},
                "num_codes_code_entropy": {str(k): v for k, v in self.entropies.items()},
                **({"num_codes_heldout_episodes": {"steps": list(self.episode_steps),
                                                   **{str(k): list(v) for k, v in self.episode_scores.items()}}}
                   if self.episode_scores else {})}

    @classmethod
    def from_record(cls, record: Any) -> NumCodesChoice:
        """The choice that :meth:`record` wrote; ValueError when it is missing or damaged."""
        if not isinstance(record, dict):
            raise ValueError("no record")
        chosen, evidence = record.get("num_codes_chosen"), record.get("num_codes_evidence")
        entropy = record.get("num_codes_code_entropy")
        if type(chosen) is not int or chosen < 1 or not isinstance(evidence, dict) or not isinstance(entropy, dict):
            raise ValueError("no chosen number of codes")
        scores = {int(k): float(v) for k, v in evidence.items()}
        if chosen not in scores:
            raise ValueError("the chosen number of codes has no score")
        episodes = record.get("num_codes_heldout_episodes") or {}
        if not isinstance(episodes, dict) or not isinstance(episodes.get("steps", []), list):
            raise ValueError("damaged held-out episode scores")
        return cls(chosen, scores, {int(k): float(v) for k, v in entropy.items()},
                   {int(k): tuple(float(x) for x in v) for k, v in episodes.items() if k != "steps"},
                   tuple(int(n) for n in episodes.get("steps", [])))

    def stats(self) -> dict[str, float]:
        """Row 0 of the run's log."""
        return {"init/num_codes": float(self.trained), "init/num_codes_chosen": float(self.chosen),
                **{f"init/num_codes_score_k{k}": v for k, v in self.scores.items()},
                **{f"init/num_codes_entropy_k{k}": v for k, v in self.entropies.items()}}


def search_num_codes(fit: Callable[[int, PaddedEpisodes, torch.Tensor], GaussianPolicy], data: PaddedEpisodes,
                     prev_actions: torch.Tensor, *, max_codes: int, seed: int, tolerance: float,
                     min_gain: float) -> NumCodesChoice:
    """Fit ``fit(K, training episodes, their previous actions) -> policy`` for K = 1..``max_codes``
    (fewer when the training split has fewer episodes), score each on the held-out episodes
    (:func:`heldout_score`) and choose K (:func:`choose_num_codes`); one line per K and one for
    the choice on stderr."""
    train, held = heldout_split(data.mask.shape[1], seed)
    train_data, held_data = data.select(train.to(data.mask.device)), data.select(held.to(data.mask.device))
    train_prev, held_prev = prev_actions[:, train.to(data.mask.device)], prev_actions[:, held.to(data.mask.device)]
    scores: dict[int, float] = {}
    entropies: dict[int, float] = {}
    per_episode: dict[int, tuple[float, ...]] = {}
    for k in range(1, min(max_codes, len(train)) + 1):
        s = heldout_score(fit(k, train_data, train_prev), held_data, held_prev)
        scores[k], entropies[k], per_episode[k] = s.score, s.entropy, s.episodes
        print(f"pomil: num_codes auto: K {k}: held-out score {s.score:.4f} per step (gain over K 1: "
              f"{s.score - scores[1]:+.4f}): mixture log-likelihood {s.log_likelihood:.4f} per step less the codes' "
              f"posterior entropy, {s.entropy:.3f} nats per episode ({len(train)} training, {len(held)} held-out "
              "episodes)", file=sys.stderr)
    steps = tuple(int(n) for n in held_data.mask.sum(0).tolist())
    choice = NumCodesChoice(choose_num_codes(scores, tolerance, min_gain), scores, entropies, per_episode, steps)
    best = max(scores, key=lambda k: (scores[k], -k))
    if best != 1:  # how far each smaller K sits below the best, against the held-out episodes' noise
        se = {k: paired_standard_error(per_episode[best], per_episode[k], steps) for k in range(1, best)}
        print(f"pomil: num_codes auto: below the best K {best}: "
              + ", ".join(f"K {k} {scores[best] - scores[k]:.4f} ± {se[k]:.4f}" for k in se)
              + " nats per step (± the standard error over the held-out episodes, paired)", file=sys.stderr)
    k = choice.chosen
    why = (f"no K scores more than num_codes_min_gain {min_gain:g} nats per step above K 1" if k == 1 else
           f"no larger K scores above K {k} by more than num_codes_tolerance {tolerance:g} x K {k}'s average gain "
           f"per code ({average_gain_per_code(scores, k):.4f} nats per step)")
    print(f"pomil: num_codes auto: chose K {choice.chosen} ({why})"
          + (f"; training with {choice.trained} codes, since a single code carries no information"
             if choice.trained != choice.chosen else ""), file=sys.stderr)
    return choice
