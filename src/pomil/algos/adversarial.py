"""Adversarial imitation, one loop for GAIL, InfoGAIL and InfoGAIL-POMDP.

Per iteration:

1. **Rollout**: N episodes, each with a latent code c ~ Uniform{0..K-1}
   fixed for the episode (one-hot into the policy); continuous codes
   (``code_kind``): c in R^d from ``code_prior``, into the policy as it is.
2. **Critic**: ``critic_steps`` updates on expert vs. policy sequences.
   Wasserstein (the paper): maximise E_expert[f] - E_policy[f], weights
   clipped to +-``weight_clip`` (RMSProp, as in the text), or a gradient
   penalty (Adam).  GAN (Ho & Ermon's GAIL): logistic loss, expert = 1.
   pomil's critic score f is "higher = more expert-like"; the paper's
   D_omega is -f, so its policy reward -D is our f.
3. **Posterior**: cross-entropy of the episode's code under P(c | b(tau; psi), a_t)
   (continuous codes: -log N(c; mu, sigma) of a diagonal Gaussian, ``pomil.nn.codes``).
4. **Reward** r_t = norm(f_t) + lambda1 * log P(c | b_t, a_t), where norm
   standardises the critic term over the batch, so that lambda1 weighs the MI
   bound against one standard deviation of critic score (docs/method.md;
   ``normalize_reward``).  GAN critic: the adversarial term is softplus(f).
5. **PPO + GAE** on policy and value (the entropy bonus lambda2 is
   ``ent_coef``), in one of two recurrent-update modes: ``sequence`` (whole
   episodes from their stored initial hidden state) or ``window`` (the
   paper's bootstrapped random updates: random windows, zero initial state).
   The critic and posterior train with the same mode.

Learners: ``gail`` (MLP, no codes, GAN critic), ``infogail`` (MLP, codes,
Wasserstein), ``infogail-pomdp`` (separate belief encoders for policy,
value, critic and posterior: GRU, or LSTM or attention by ``belief_encoder``;
codes; Wasserstein).
"""

from __future__ import annotations

import copy
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
import torch.nn.functional as F

from pomil.algos.num_codes import NumCodesChoice, search_num_codes
from pomil.algos.selection import PolicySelection
from pomil.algos.warm_start import (
    DEEP_WARM_START,
    FAST_WARM_START,
    LONG_WARM_START,
    TERMINATING_WARM_START,
    EpisodeCodes,
    MixtureAssignment,
    WarmStartOptions,
    clone_demonstrations,
    clone_members,
    clone_with_continuous_codes,
    cloning_window,
    demo_batch,
    demo_nll,
    episodes_within,
    first_step_starts,
    members_for_demonstrations,
    mixture_assignment,
    most_likely_codes,
    own_random_numbers,
    sized_for_demonstrations,
    sized_for_episodes,
)
from pomil.api import TrainedPolicy
from pomil.config import RunConfig, option, parse_kwargs, resolved
from pomil.data import Demonstrations, PaddedEpisodes, load_training_demos
from pomil.envs import SIM_HELP, default_num_codes, evaluation_kind, executed_actions_fn, make_vec_env
from pomil.envs.wrappers import parse_mask
from pomil.errors import ConfigError, PomilError
from pomil.learners import LEARNERS
from pomil.nn import heads
from pomil.nn.codes import code_log_likelihood, gaussian_params, sample_prior
from pomil.nn.encoders import OBS_DELTA_HELP, PREV_ACTION_HELP, fit_input_scale
from pomil.nn.heads import BeliefHead
from pomil.nn.policy import EnsemblePolicy, GaussianPolicy, PolicyArch, make_policy, shift_actions
from pomil.rl.collect import collect
from pomil.rl.gae import gae
from pomil.rl.ppo import PPOOptions, masked_mean, normalize, ppo_loss
from pomil.rl.storage import Rollout, window_index
from pomil.training import (
    DivergenceGuard,
    RunLoop,
    load_checkpoint,
    lr_hint,
    native_bfloat16,
    precision_context,
    progress_bar,
)

# The defaults are the recipe measured best, each choice with its measurement in docs/method.md ("Defaults and
# presets"); the paper's text is the ``paper-text`` preset.


def _value_on_policy(shared: bool, values: dict[str, Any]) -> dict[str, Any]:
    """An old config's ``shared_value_encoder`` as a ``belief`` (shared beliefs had the value on the policy's
    encoder anyway)."""
    belief = values.get("belief", "separate")
    if not shared or belief == "shared":
        return {}
    if belief != "separate":
        raise ConfigError(f"config key 'shared_value_encoder': retired; true with belief {belief!r} has no "
                          "equivalent (belief value-on-policy is the value head on the policy's encoder)")
    return {"belief": "value-on-policy"}


@dataclass(frozen=True)
class CodeOptions:
    """The latent codes: how many (or chosen how), discrete or continuous."""

    num_codes: int = option(-1,
                            "latent codes K >= 2; -1 = number of modes the demonstrations' metadata or labels name, "
                            "at least 2; auto = chosen by the mixture warm start's held-out classification likelihood "
                            "for K = 1..num_codes_max (pomil docs method; 0 in Python) (ignored by gail)",
                            within="[-1, inf)", named={"auto": 0})
    num_codes_max: int = option(6, "with num_codes auto: the largest K tried (one warm start each)", within="[2, inf)")
    num_codes_search_iterations: int = option(500, "with num_codes auto: mixture warm-start steps of each K's fit "
                                                   "on the training split, on the fast warm start's schedule "
                                                   "(FAST_WARM_START: lr 3e-3 decaying to 0, the log std at 10x, "
                                                   "its maximum-likelihood fit at the end) whatever the run's own",
                                              within="[1, inf)")
    num_codes_tolerance: float = option(0.25, "with num_codes auto: a larger K is taken only when its held-out "
                                              "score exceeds the current K's by more than this fraction of the "
                                              "current K's average gain per code, (score_K - score_1) / (K - 1)",
                                        within="[0, inf)")
    num_codes_min_gain: float = option(0.01, "with num_codes auto: K 1 (then trained with 2 codes) when the best K's "
                                             "held-out score is at most this many nats per step above K 1's",
                                       within="[0, inf)")
    code_kind: Literal["discrete", "continuous"] = option(
        "discrete", "latent codes: discrete (one of num_codes, one-hot) or continuous (c in R^code_dim from "
                    "code_prior, a Gaussian posterior: InfoGAIL's continuous c; pomil docs method); ignored by gail")
    code_dim: int = option(1, "with code_kind continuous: the code's dimension d", within="[1, inf)")
    code_prior: Literal["uniform", "gaussian"] = option(
        "uniform", "with code_kind continuous: the prior codes are drawn from, uniform on [-1, 1]^d or a standard "
                   "gaussian")

@dataclass(frozen=True)
class NetworkOptions:
    """The networks: width, belief encoders and what each sees, the policy's output."""

    hidden_size: int = option(128, "dense width and recurrent cells (attention: model width) of every network",
                              within="[1, inf)")
    belief_encoder: Literal["gru", "lstm", "attention"] = option(
        "gru", "infogail-pomdp's belief encoder over (z_t, a_{t-1}) in policy, value, critic and posterior: gru (the "
               "paper), lstm, or attention (a one-layer causal transformer over the last attention_context steps); "
               "ignored by gail and infogail (feed-forward)")
    attention_context: int = option(32, "with belief_encoder attention: steps it attends to, the current one included",
                                    within="[1, inf)")
    belief: Literal["separate", "value-on-policy", "shared", "policy"] = option(
        "separate", "belief encoders: separate = policy, value, critic and posterior each have their own (the paper); "
                    "value-on-policy = the value head on the policy's encoder, critic and posterior their own "
                    "(measured: pomil docs method); shared = one encoder for all four, trained by every loss; policy = "
                    "the policy's only, value, critic and posterior feed-forward (the last two are ablations)")
    policy_obs_delta: bool = option(False, "the policy (not critic, value or posterior): " + OBS_DELTA_HELP)
    policy_prev_action: bool = option(True, "the policy's encoder: " + PREV_ACTION_HELP)
    log_std_init: float = option(-1.0, "initial log std of the policy", within="(-inf, inf)")
    policy_members: int = option(0, "policies acting as one (an ensemble): each member has its own encoder and is "
                                    "cloned in the warm start from its own initialisation and batches, its codes "
                                    "renamed to agree with the first member's on the demonstrations; the ensemble "
                                    "acts with the mean of the members' mean actions and one log std, and the "
                                    "adversarial phase trains it as one policy (1: one policy; 0: auto, 3 where the "
                                    "demonstrations fit in one warm_start_batch and the policy is recurrent with the "
                                    "mixture warm start, else 1: pomil docs method, \"Policies acting as one\")",
                                 within="[0, inf)")
    tanh_mean: bool = option(False, "squash the policy mean with tanh (the paper's Hopper code)")

@dataclass(frozen=True)
class CriticOptions:
    """The critic f (Wasserstein or GAN) and the reward's critic term."""

    lr_critic: float = option(5e-4, "critic learning rate", within="(0, inf)")
    critic_optimizer: Literal["rmsprop", "adam"] = option("adam", "adam (the paper's code) or rmsprop (its text)")
    critic_steps: int = option(3, "critic updates per iteration", within="[1, inf)")
    critic_batch: int = option(64, "expert and policy episodes per critic update (at most max_batch_steps)",
                               within="[1, inf)")
    expert_action_noise: bool = option(False,
                                       "add the policy's current action noise to the demonstrations' actions the "
                                       "critic sees, so that it cannot tell deterministic experts from the policy by "
                                       "action jitter")
    weight_clip: float = option(0.0, "clip Wasserstein critic weights to +-this after each update (0: off; the "
                                     "paper's text: 0.01; never for GAIL's GAN critic)", within="[0, inf)")
    gradient_penalty: float = option(10.0, "WGAN-GP weight (0: off); use with weight_clip 0 and adam",
                                     within="[0, inf)")
    normalize_reward: bool = option(True, "standardise the critic term of the reward per batch")

@dataclass(frozen=True)
class PosteriorOptions:
    """The posterior P(c | b) and the reward's mutual-information term."""

    lr_posterior: float = option(2e-4, "posterior learning rate (Adam)", within="(0, inf)")
    posterior_steps: int = option(1, "posterior updates per iteration", within="[1, inf)")
    mi_weight: float = option(5.0, "lambda1: weight of log P(c | b) in the reward (the paper's code: 10)",
                              within="[0, inf)")


@dataclass(frozen=True)
class AdversarialConfig(PosteriorOptions, CriticOptions, PPOOptions, NetworkOptions, WarmStartOptions, CodeOptions,
                        RunConfig):  # fields in the reverse order: the run's, codes, warm start, ...
    """GAIL, InfoGAIL and InfoGAIL-POMDP: the run and its loop here, each part's options in its group."""

    ppo_epochs: int = option(2, "PPO epochs per iteration", within="[1, inf)")
    minibatches: int = option(4, "PPO minibatches per epoch", within="[1, inf)")
    learner: Literal["gail", "infogail", "infogail-pomdp"] = option("infogail-pomdp",
                                                                    "which learner (set by the subcommand)")
    preset: Literal["auto", "default", "paper-text", "long-warm-start", "fast-warm-start", "deep-warm-start",
                    "terminating"] = option(
        "auto", "named settings under the config file and flags: auto (terminating for demonstrations whose "
                "environment ends an episode when the agent fails, such as Hopper's own 1000-step setting; default "
                "otherwise), default (pomil's measured recipe), paper-text (the paper's text), long-warm-start (3000 "
                "steps at lr 1e-3), fast-warm-start (600 steps at lr 3e-3, the log std at 10x and fitted), "
                "deep-warm-start (the default's schedule, the log std at 10x and fitted) or terminating (the policy "
                "sees (z_t, dz_t) without a_{t-1}; the fast warm start over 2400 steps); config.json records the one "
                "that ran")
    # 15: 30 scored the same on circles (10 seeds), the paper's Hopper and standard Hopper (5 seeds each) at up to
    # twice the wall time (docs/method.md, "How many adversarial iterations").
    iterations: int = option(15, "training iterations (rollout + critic + posterior + PPO); 0: the warm start only",
                             within="[0, inf)")
    num_envs: int = option(256, "episodes collected per iteration (at most max_iteration_steps of them)",
                           within="[1, inf)")
    max_iteration_steps: int = option(65536, "long episodes: at most this many env steps per iteration, counted at the "
                                             "demonstrations' longest episode: fewer than num_envs episodes (1000-step "
                                             "Hopper: 65)", within="[1, inf)")
    max_batch_steps: int = option(16384, "long episodes: at most this many steps in a batch of whole episodes "
                                         "(warm-start, BC-term and critic batches): fewer than warm_start_batch and "
                                         "critic_batch episodes (1000-step Hopper: 16)", within="[1, inf)")
    sim: Literal["cpu", "warp"] = option("cpu", SIM_HELP)
    precision: Literal["float32", "bfloat16"] = option(
        "float32", "the updates' and the warm start's network passes (critic, posterior, policy and value; not the "
                   "rollout's): float32, or bfloat16 through torch.autocast, with outputs, losses and weights in "
                   "float32; faster on a CPU with bfloat16 instructions (AVX512-BF16), slower without; other numerics "
                   "(pomil docs speed)")
    rollout_threads: int = option(1, "torch threads while collecting rollouts (0: torch's own setting); one keeps "
                                     "torch's idle OpenMP workers off the cores that a batched simulator steps on",
                                     within="[0, inf)")
    lr: float = option(5e-5, "policy learning rate (Adam; the paper's text: 2e-4)", within="(0, inf)")
    lr_value: float = option(5e-4, "value-function learning rate (Adam)", within="(0, inf)")
    termination: Literal["end", "absorbing"] = option(
        "end", "a policy episode that terminates (e.g. Hopper falls): end = its return ends there; absorbing = it "
               "goes on in an absorbing state paid the batch's lowest step reward, so ending early never pays (DAC; "
               "measured on standard Hopper: no better, see pomil docs hopper)")
    value_clip: float = option(0.0, "PPO value clip (0: off)", within="[0, inf)")
    update_mode: Literal["sequence", "window"] = option("sequence",
                                                        "recurrent updates: whole sequences or random windows from a "
                                                        "zero state")
    window_length: int = option(8, "steps per window in window mode", within="[1, inf)")
    bc_weight: float = option(10.0,
                              "weight of the warm start's behaviour-cloning loss on the demonstrations, added to the "
                                    "policy's PPO loss (keeps the policy near the demonstrations; 0: off)",
                                    within="[0, inf)")
    policy_warmup_iterations: int = option(5, "first iterations in which only the critic, posterior and value learn "
                                              "(the warm-started policy waits for a trained value and critic)",
                                              within="[0, inf)")
    eval_every: int = option(
        5, "iterations between evaluations: mode metrics on circles, per-task scores on Hopper demos, the distance to "
           "the demonstrations that hand_over nearest compares (0: off, and the last policy handed over)",
        within="[0, inf)")
    eval_episodes: int = option(10, "evaluation rollouts per code", within="[1, inf)")
    hand_over: Literal["nearest", "last"] = option(
        "nearest", "the policy the run hands over (the checkpoint's policy, what pomil evaluate loads): nearest = of "
                   "the policies at the warm start and every eval_every iterations, the one whose deterministic "
                   "rollouts lie nearest the demonstrations on what the learner observes (no environment reward; the "
                   "run trains on unchanged, --resume goes on from its last policy); last = the last iteration's "
                   "(pomil docs method)")
    log_every: int = option(5, "iterations between log rows", within="[1, inf)")
    checkpoint_every: int = option(100, "iterations between checkpoints (one is always written at the end)",
                                   within="[1, inf)")

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        # The paper's text: weight clipping, RMSProp, lr 2e-4, random windows; InfoGAIL's warm start (random codes).
        "paper-text": {
            "critic_optimizer": "rmsprop", "weight_clip": 0.01, "gradient_penalty": 0.0, "lr": 2e-4, "lr_critic": 2e-4,
            "lr_posterior": 2e-4, "update_mode": "window", "warm_start_codes": "random", "warm_start_iterations": 300,
            "warm_start_lr": 1e-3, "warm_start_lr_decay": False, "warm_start_lr_warmup": 0.0, "bc_weight": 0.0,
            "policy_warmup_iterations": 0, "hand_over": "last",
        },
        # The warm starts compared in docs/method.md, "The warm start's schedule".
        "long-warm-start": LONG_WARM_START,
        "fast-warm-start": FAST_WARM_START,
        "deep-warm-start": DEEP_WARM_START,
        # Episodes that end when the agent fails (standard Hopper): a clone that sees a_{t-1} copies it and falls;
        # the velocity dz_t and the fast warm start keep it up (docs/hopper.md, "Standard setting"), over 2400 steps
        # (docs/hopper.md, "How long the warm start clones").
        "terminating": {"policy_obs_delta": True, "policy_prev_action": False, **TERMINATING_WARM_START},
    }
    """Named settings (``preset``): applied under a config file's and the flags' values by ``config.from_dict``;
    ``auto`` is replaced by one of them when training starts (``config.resolved``)."""

    RENAMED: ClassVar[dict[str, str]] = {f"bc_init_{k}": f"warm_start_{k}" for k in (
        "iterations", "lr", "lr_decay", "lr_warmup", "log_std_lr_scale", "fit_log_std", "code_lr_scale", "batch",
        "codes")}
    """Old config keys, still read from config files and checkpoints (old -> new name)."""
    EPISODE_CAPS: ClassVar[dict[str, str]] = {"num_envs": "max_iteration_steps", "warm_start_batch": "max_batch_steps",
                                               "critic_batch": "max_batch_steps"}
    """Episode counts and the step caps they are cut to for long episodes (``sized_for_episodes``)."""
    FOLDED: ClassVar[dict[str, tuple[type, Any]]] = {"shared_value_encoder": (bool, _value_on_policy)}
    """Retired config keys, still read: ``shared_value_encoder`` true is ``belief`` value-on-policy."""

    def default_out(self) -> str:
        return f"runs/{self.learner}"

    def __post_init__(self) -> None:
        super().__post_init__()  # every field in its interval (see the option declarations)
        if self.num_codes == 1:
            raise ConfigError("config key 'num_codes': expected -1 (from the demonstrations), auto or >= 2, got "
                              f"{self.num_codes}")
        if self.code_kind == "continuous" and self.num_codes != -1:
            given = "auto" if self.num_codes == NUM_CODES_AUTO else self.num_codes
            raise ConfigError(f"config key 'num_codes': discrete codes only, got {given} with code_kind continuous "
                              "(its size is code_dim)")
        if self.policy_members > 1:
            clash = {"code_kind": self.code_kind != "discrete", "belief": self.belief not in ("separate", "policy"),
                     "warm_start_restarts": self.warm_start_restarts > 1}
            for key, bad in clash.items():
                if bad:
                    raise ConfigError(f"config key 'policy_members': an ensemble of {self.policy_members} needs "
                                      "code_kind discrete, belief separate or policy and warm_start_restarts 1, got "
                                      f"{key} {getattr(self, key)!r}")
        if self.code_kind == "discrete" and (self.code_dim != 1 or self.code_prior != "uniform"):
            key = "code_dim" if self.code_dim != 1 else "code_prior"
            raise ConfigError(f"config key {key!r}: continuous codes only (set code_kind continuous), got "
                              f"{getattr(self, key)!r} with code_kind discrete")


@dataclass
class Modules:
    policy: GaussianPolicy
    value: BeliefHead
    critic: BeliefHead
    posterior: BeliefHead | None


def side_by_side(unroll: Callable[..., torch.Tensor], first: tuple[torch.Tensor, ...],
                 second: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """``unroll(*inputs)`` on two blocks of time-major (T, N, ...) inputs: once over both
    blocks' columns side by side when their lengths agree, else once each.  Same numbers
    up to rounding; one pass with twice the columns is cheaper on a CPU than two."""
    if first[0].shape[0] != second[0].shape[0]:
        return unroll(*first), unroll(*second)
    out = unroll(*(torch.cat(pair, dim=1) for pair in zip(first, second, strict=True)))
    return out[:, :first[0].shape[1]], out[:, first[0].shape[1]:]


# ------------------------------------------------------------------ batches
class BatchSampler:
    """Where every update's batches come from: the one place that knows ``update_mode``.

    ``sequence``: whole episodes from their stored initial hidden state, exactly the
    computation of the rollout.  ``window``: the paper's bootstrapped random updates,
    random windows of ``window_length`` steps from a zero state.  The critic, the
    posterior and PPO all draw their batches here, with the run's generator.
    """

    def __init__(self, mode: Literal["sequence", "window"], window_length: int) -> None:
        self.windows = mode == "window"
        self.window_length = window_length

    def expert(self, expert: PaddedEpisodes, actions: torch.Tensor, prev: torch.Tensor, count: int,
               gen: torch.Generator) -> tuple[torch.Tensor, ...]:
        """(obs, prev_actions, actions, starts, mask) of ``count`` expert episodes or windows.

        ``actions`` (T, E, act_dim) are the demonstrations' actions as the critic
        sees them (noised or not) and ``prev`` = shift_actions(actions)."""
        T, E = expert.mask.shape
        if self.windows:
            t_idx, e = window_index(T, E, self.window_length, count=count, generator=gen)
        else:
            e = torch.randint(E, (count,), generator=gen)
            t_idx = torch.arange(T).unsqueeze(1).expand(-1, len(e))
        dev = expert.mask.device
        t_idx, e = t_idx.to(dev), e.to(dev)
        ei = e.unsqueeze(0).expand_as(t_idx)
        mask = expert.mask[t_idx, ei]
        return expert.observations[t_idx, ei], prev[t_idx, ei], actions[t_idx, ei], first_step_starts(mask), mask

    def policy(self, roll: Rollout, count: int, gen: torch.Generator) -> Rollout:
        """``count`` random episodes or windows of the rollout (the critic's policy side)."""
        if self.windows:
            return roll.windows(self.window_length, count, gen)
        return roll.columns(torch.randint(roll.num_envs, (count,), generator=gen).to(roll.starts.device))

    def posterior(self, roll: Rollout, code_steps: torch.Tensor,
                  gen: torch.Generator) -> Iterator[tuple[torch.Tensor, Rollout]]:
        """(code per step, batch): the whole rollout, or as many random windows as it has windows' worth of steps."""
        if not self.windows:
            yield code_steps, roll
            return
        count = max(1, roll.num_steps * roll.num_envs // self.window_length)
        t_idx, env = window_index(roll.num_steps, roll.num_envs, self.window_length, count=count, generator=gen)
        dev = roll.starts.device
        t_idx, env = t_idx.to(dev), env.to(dev)
        batch = roll._gather(t_idx, env, roll.h0_policy[env] * 0, roll.h0_value[env] * 0, zero_first=True)
        yield code_steps[t_idx, env.unsqueeze(0).expand_as(t_idx)], batch

    def minibatches(self, roll: Rollout, count: int, gen: torch.Generator) -> Iterator[Rollout]:
        """One PPO epoch's minibatches."""
        if self.windows:
            return roll.window_batches(count, self.window_length, gen)
        return roll.sequence_batches(count, gen)

    def behaviour(self, policy: GaussianPolicy, value: BeliefHead) -> Callable[[Rollout], Rollout]:
        """What makes a minibatch's "old" log-probs and values.  Windows start from a zero
        state, unlike the rollout: their old log-probs and values are recomputed under the
        same conditioning by a frozen copy of the networks, so that the PPO ratio starts at
        exactly 1.  Whole sequences keep the rollout's."""
        if not self.windows:
            return lambda b: b
        frozen = (copy.deepcopy(policy), copy.deepcopy(value))
        return lambda b: _window_behaviour(b, *frozen)


@torch.no_grad()
def _window_behaviour(b: Rollout, policy: GaussianPolicy, value: BeliefHead) -> Rollout:
    dist, _ = policy.unroll(b.observations, b.prev_actions, b.h0_policy, b.starts, codes=b.codes)
    v, _ = value.unroll(b.observations, b.prev_actions, b.h0_value, b.starts, extra=b.codes)
    return b.with_(log_probs=dist.log_prob(b.actions).sum(-1), values=v)


# -------------------------------------------------------------- critic, posterior
def noisy_expert_actions(expert: PaddedEpisodes, policy: GaussianPolicy,
                         execute: Callable[[torch.Tensor], torch.Tensor],
                         gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(actions, prev_actions) of the demonstrations with the policy's current action noise added.

    Deterministic experts never show the jitter of a sampled Gaussian action;
    a critic fed raw demonstrations can tell them from the policy by that
    jitter alone, whatever the gait.  Each demonstration action gets
    N(0, std^2) noise (std = the policy's current std) and is then mapped to
    an executed action as the policy's samples are.
    """
    with torch.no_grad():
        noise = torch.randn(expert.actions.shape, generator=gen).to(expert.actions.device)
        actions = execute(expert.actions + policy.log_std.exp() * noise)
    return actions, shift_actions(actions)


def critic_loss(
    critic: BeliefHead, expert: tuple, policy: Rollout, *, objective: str, gp_weight: float, generator: torch.Generator,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The critic's loss on an expert batch (obs, prev, actions, starts, mask) against a policy batch: the
    Wasserstein estimate's negative, or the discriminator's cross-entropy; plus the gradient penalty on
    interpolates (weights drawn from ``generator``) when ``gp_weight`` > 0."""
    e_obs, e_prev, e_act, e_starts, e_mask = expert

    def score(obs, prev, act, starts):
        return critic.unroll(obs, prev, critic.initial_state(obs.shape[1], obs.device), starts, extra=act)[0]

    f_exp, f_pol = side_by_side(score, (e_obs, e_prev, e_act, e_starts),
                                (policy.observations, policy.prev_actions, policy.executed_actions, policy.starts))
    if objective == "wasserstein":
        w = masked_mean(f_exp, e_mask) - masked_mean(f_pol, policy.mask)
        loss = -w
        stats = {"critic/wasserstein": w.item()}
    else:
        loss = (masked_mean(F.binary_cross_entropy_with_logits(f_exp, torch.ones_like(f_exp), reduction="none"), e_mask)
                + masked_mean(F.binary_cross_entropy_with_logits(f_pol, torch.zeros_like(f_pol), reduction="none"),
                              policy.mask))
        stats = {"critic/expert_prob": masked_mean(torch.sigmoid(f_exp), e_mask).item(),
                 "critic/policy_prob": masked_mean(torch.sigmoid(f_pol), policy.mask).item()}
    if gp_weight > 0:
        b = min(e_obs.shape[1], policy.num_envs)
        t = min(e_obs.shape[0], policy.num_steps)
        alpha = torch.rand(1, b, 1, generator=generator).to(e_obs.device)
        mix = lambda x, y: (alpha * x[:t, :b] + (1 - alpha) * y[:t, :b]).detach().requires_grad_(True)  # noqa: E731
        obs_i, prev_i = mix(e_obs, policy.observations), mix(e_prev, policy.prev_actions)
        act_i = mix(e_act, policy.executed_actions)
        with torch.backends.cudnn.flags(enabled=False):  # cuDNN's GRU has no double backward; the penalty needs one
            f_i = score(obs_i, prev_i, act_i, e_starts[:t, :b])
        inputs = (obs_i, prev_i, act_i)
        grads = torch.autograd.grad(f_i.sum(), inputs, create_graph=True, allow_unused=True)  # MLPs ignore prev
        norm = torch.cat([g if g is not None else torch.zeros_like(x) for g, x in zip(grads, inputs, strict=True)],
                         dim=-1).norm(dim=-1)
        gp = ((norm - 1) ** 2).mean()
        loss = loss + gp_weight * gp
        stats["critic/gradient_penalty"] = gp.item()
    stats["critic/loss"] = loss.item()
    return loss, stats


def posterior_loss(post: BeliefHead, batch: Rollout, code_idx_steps: torch.Tensor,
                   code_kind: str = "discrete") -> tuple[torch.Tensor, dict[str, float]]:
    """Masked negative log-likelihood of each step's code: code_idx_steps (T, B) code indices
    (cross-entropy), or continuous codes (T, B, d) (Gaussian, :func:`_code_gaussian_nll`)."""
    code_nll = _code_cross_entropy if code_kind == "discrete" else _code_gaussian_nll
    return code_nll(post, batch.observations, batch.prev_actions, actions=batch.executed_actions,
                    starts=batch.starts, mask=batch.mask, targets=code_idx_steps)


def _code_cross_entropy(post: BeliefHead, obs, prev_actions, *, actions, starts, mask,
                        targets) -> tuple[torch.Tensor, dict[str, float]]:
    """Masked mean cross-entropy of each step's code index; targets (T, B)."""
    logits, _ = post.unroll(obs, prev_actions, post.initial_state(obs.shape[1], obs.device), starts, extra=actions)
    ce = F.cross_entropy(logits.flatten(0, 1), targets.flatten(), reduction="none").view_as(targets)
    loss = masked_mean(ce, mask)
    acc = masked_mean((logits.argmax(-1) == targets).float(), mask)
    return loss, {"posterior/loss": loss.item(), "posterior/accuracy": acc.item()}


def _code_gaussian_nll(post: BeliefHead, obs, prev_actions, *, actions, starts, mask,
                       targets) -> tuple[torch.Tensor, dict[str, float]]:
    """Masked mean of -log N(c; mu(b_t), sigma(b_t)) over the steps; targets (T, B, d) continuous codes."""
    out, _ = post.unroll(obs, prev_actions, post.initial_state(obs.shape[1], obs.device), starts, extra=actions)
    loss = masked_mean(-code_log_likelihood(out, targets, "continuous"), mask)
    mean, log_std = gaussian_params(out)
    err = masked_mean((mean - targets).abs().mean(-1), mask)
    return loss, {"posterior/loss": loss.item(), "posterior/code_error": err.item(),
                  "posterior/log_std": masked_mean(log_std.mean(-1), mask).item()}


@torch.no_grad()
def rewards(m: Modules, roll: Rollout, code_idx: torch.Tensor, *, cfg: AdversarialConfig,
            objective: str) -> tuple[torch.Tensor, dict[str, float]]:
    """r_t = norm(f_t) + lambda1 log P(c | b_t, a_t); ``code_idx`` (N,) code indices, or (N, d)
    continuous codes (log N(c; mu, sigma), see :func:`pomil.nn.codes.code_log_likelihood`)."""
    dev = roll.starts.device
    f, _ = m.critic.unroll(roll.observations, roll.prev_actions, m.critic.initial_state(roll.num_envs, dev),
                           roll.starts, extra=roll.executed_actions)
    adv = f if objective == "wasserstein" else F.softplus(f)
    stats = {"reward/critic_raw_mean": adv.mean().item(), "reward/critic_raw_std": adv.std().item()}
    if cfg.normalize_reward:
        adv = normalize(adv, roll.mask)
    r = adv
    if m.posterior is not None:
        logits, _ = m.posterior.unroll(roll.observations, roll.prev_actions,
                                       m.posterior.initial_state(roll.num_envs, dev),
                                       roll.starts, extra=roll.executed_actions)
        logq = code_log_likelihood(logits, code_idx.unsqueeze(0).expand(logits.shape[0], *code_idx.shape),
                                   cfg.code_kind)
        r = r + cfg.mi_weight * logq
        stats["reward/log_posterior"] = logq.mean().item()
    stats["reward/total"] = r.mean().item()
    return r, stats


# ---------------------------------------------------------------------- train
def policy_arch(cfg: AdversarialConfig, obs_dim: int, act_dim: int, num_codes: int) -> PolicyArch:
    """The policy of a run with ``num_codes`` codes."""
    enc = cfg.belief_encoder if LEARNERS[cfg.learner].recurrent else "mlp"
    return PolicyArch(obs_dim, act_dim, enc, cfg.hidden_size, num_codes, cfg.log_std_init, cfg.tanh_mean,
                      cfg.attention_context, cfg.policy_obs_delta, cfg.policy_prev_action, cfg.code_kind,
                      cfg.code_prior, max(cfg.policy_members, 1))  # auto unresolved (0): one policy


def build_modules(cfg: AdversarialConfig, obs_dim: int, act_dim: int, *, num_codes: int,
                  device: torch.device | str) -> tuple[Modules, PolicyArch]:
    enc = cfg.belief_encoder if LEARNERS[cfg.learner].recurrent else "mlp"
    ctx = cfg.attention_context
    arch = policy_arch(cfg, obs_dim, act_dim, num_codes)
    policy = make_policy(arch).to(device)
    heads_enc = "mlp" if cfg.belief == "policy" else enc
    value = heads.value(obs_dim, act_dim, num_codes, encoder=heads_enc, hidden_size=cfg.hidden_size,
                        context=ctx).to(device)
    if cfg.belief in ("value-on-policy", "shared"):
        value.encoder = policy.encoder  # one module: the value loss also trains the policy's encoder
    m = Modules(
        policy=policy, value=value,
        critic=heads.critic(obs_dim, act_dim, heads_enc, hidden_size=cfg.hidden_size, context=ctx).to(device),
        posterior=(heads.posterior(obs_dim, act_dim, num_codes, encoder=heads_enc, hidden_size=cfg.hidden_size,
                                   context=ctx, code_kind=cfg.code_kind).to(device) if num_codes else None),
    )
    if cfg.belief == "shared":  # one belief b_t for all four; each loss's own optimiser steps it
        m.critic.encoder = policy.encoder
        if m.posterior is not None:
            m.posterior.encoder = policy.encoder
    return m, arch


NUM_CODES_AUTO = 0
"""``num_codes`` of ``--num-codes auto`` (config.json records the word): K chosen by :func:`auto_num_codes`."""


def resolve_num_codes(cfg: AdversarialConfig, demos: Demonstrations) -> int:
    """The run's number of codes: 0 without codes, the configured K, or (-1) the demonstrations'
    modes; ``num_codes auto`` is chosen by :func:`auto_num_codes` instead.  Continuous codes: their
    dimension d (the width of the code input, as K is for one-hot codes)."""
    if not LEARNERS[cfg.learner].codes:
        return 0
    if cfg.code_kind == "continuous":
        return cfg.code_dim
    if cfg.num_codes == NUM_CODES_AUTO:
        raise ValueError("num_codes auto is chosen from the demonstrations by auto_num_codes")
    if cfg.num_codes > 0:
        return cfg.num_codes
    suggested = default_num_codes(demos.metadata)  # circles: one per circle
    if suggested:
        return suggested
    if demos.labels is not None:  # at least 2: a single code carries no information
        return max(2, int(len(set(demos.labels.tolist()))))
    return 2


def uses_mixture(cfg: AdversarialConfig, num_codes: int) -> bool:
    """Whether the warm start's and the BC term's likelihood is the discrete codes' mixture (else random
    codes, or continuous codes: each episode's own, ``EpisodeCodes``)."""
    return cfg.warm_start_codes == "mixture" and num_codes > 0 and cfg.code_kind == "discrete"


@dataclass(frozen=True)
class AdversarialRun:
    """What every phase of an iteration reads, fixed for the run: the networks, their optimisers, the
    demonstrations (with executed actions), the batch sampler and the run's generators (``gen`` for
    batches and codes, ``penalty_gen`` for the gradient penalty, :meth:`pomil.training.RunLoop.start`).
    A phase takes the iteration's own inputs (rollout, codes) as arguments and returns its stats."""

    cfg: AdversarialConfig
    m: Modules
    opt: dict[str, torch.optim.Optimizer]
    gen: torch.Generator
    penalty_gen: torch.Generator
    sampler: BatchSampler
    expert: PaddedEpisodes
    expert_prev: torch.Tensor
    execute: Callable[[torch.Tensor], torch.Tensor]
    num_codes: int
    guard: DivergenceGuard | None = None
    assignment: MixtureAssignment | None = None  # the BC term's code per demonstration episode (whole-set balance)
    episode_codes: EpisodeCodes | None = None  # continuous codes, mixture warm start: each demo episode's own code

    @property
    def objective(self) -> str:
        return LEARNERS[self.cfg.learner].critic_objective

    @property
    def mixture(self) -> bool:
        return uses_mixture(self.cfg, self.num_codes)

    def demo_codes(self, idx: torch.Tensor) -> torch.Tensor | None:
        """The BC term's continuous codes for demonstration episodes ``idx``: each episode's own
        (``episode_codes``), or random ones from the prior; None for discrete codes."""
        if self.cfg.code_kind != "continuous" or not self.num_codes:
            return None
        if self.episode_codes is not None:
            return self.episode_codes.codes[idx].detach()
        return sample_prior(self.cfg.code_prior, len(idx), self.num_codes, self.gen).to(idx.device)

    def precision(self) -> AbstractContextManager[None]:
        """The context of the updates' network passes (``precision``, :func:`pomil.training.precision_context`)."""
        return precision_context(self.cfg.precision, self.expert.mask.device)

    def check(self, it: int, quantity: str, x: float | torch.Tensor) -> None:
        if self.guard is not None:
            self.guard.value(it, quantity, x)

    def step(self, it: int, name: str, loss: torch.Tensor, params: Callable[[], Any]) -> None:
        """One optimiser step of ``opt[name]`` on ``loss``, its gradients checked first."""
        self.opt[name].zero_grad(set_to_none=True)
        loss.backward()
        if self.guard is not None:
            self.guard.grads(it, name, params())
        self.opt[name].step()


def build_optimizers(cfg: AdversarialConfig, m: Modules) -> dict[str, torch.optim.Optimizer]:
    opt = {
        "policy": torch.optim.Adam(m.policy.parameters(), lr=cfg.lr),
        "value": torch.optim.Adam(m.value.mlp.parameters() if m.value.encoder is m.policy.encoder
                                  else m.value.parameters(), lr=cfg.lr_value),
        "critic": (torch.optim.RMSprop(m.critic.parameters(), lr=cfg.lr_critic) if cfg.critic_optimizer == "rmsprop"
                   else torch.optim.Adam(m.critic.parameters(), lr=cfg.lr_critic, betas=(0.5, 0.9))),
    }
    if m.posterior is not None:
        opt["posterior"] = torch.optim.Adam(m.posterior.parameters(), lr=cfg.lr_posterior)
    return opt


def bc_warm_start(m: Modules, expert: PaddedEpisodes, expert_prev: torch.Tensor, *, num_codes: int, mixture: bool,
                  cfg: AdversarialConfig, gen: torch.Generator, guard: DivergenceGuard | None = None,
                  episode_codes: EpisodeCodes | None = None) -> dict[str, float]:
    """Behaviour cloning of the whole (unlabelled) demonstration set before adversarial training.

    Without ``mixture`` (``warm_start_codes = "random"``, InfoGAIL's initialisation) each
    episode gets a random code, so the policy starts out ignoring it and the
    mutual-information reward later makes the codes choose between modes.  With
    ``mixture`` (``warm_start_codes = "mixture"`` and a policy with codes) the policy maximises the
    demonstrations' likelihood under a uniform mixture of its codes, so each code clones
    its own cluster of episodes; the posterior then learns, on the demonstrations, to
    tell each episode's most likely code from its steps (``posterior_init_iterations``).
    Continuous codes (``code_kind``): random codes from the prior, or with ``episode_codes``
    each episode's own code, fitted with the policy (:func:`clone_with_continuous_codes`); the
    posterior then learns those codes."""
    codes, posterior = None, m.posterior is not None and cfg.posterior_init_iterations > 0
    if cfg.code_kind == "continuous" and num_codes:
        stats = clone_with_continuous_codes(m.policy, expert, expert_prev, cfg=cfg, gen=gen, guard=guard,
                                            episode_codes=episode_codes)
        if episode_codes is not None and posterior:
            codes = episode_codes.codes.detach()
            stats["bc/code_spread"] = codes.std(0).mean().item()
    else:
        clone = clone_members if isinstance(m.policy, EnsemblePolicy) else clone_demonstrations
        stats = clone(m.policy, expert, expert_prev, num_codes=num_codes, mixture=mixture, cfg=cfg, gen=gen,
                      guard=guard)
        if mixture and posterior:
            codes = most_likely_codes(m.policy, expert, expert_prev)
            stats["bc/code_share_min"] = torch.bincount(codes, minlength=num_codes).min().item() / len(codes)
    if codes is not None:
        stats.update(warm_start_posterior(m.posterior, expert, expert_prev, codes=codes, cfg=cfg, gen=gen, guard=guard))
    with torch.no_grad():  # the adversarial phase's action noise; a floor below every value leaves them as they are
        m.policy.log_std.clamp_(min=cfg.warm_start_min_log_std)
    return {f"init/{k.replace('/', '_')}": v for k, v in stats.items()}


def restarted_warm_start(m: Modules, run: AdversarialRun, *, num_codes: int, env_info: dict[str, Any],
                         episode_codes: EpisodeCodes | None, device: torch.device) -> dict[str, float]:
    """The warm start (:func:`bc_warm_start`) from ``warm_start_restarts`` initialisations, the run's own first
    (its random numbers, so that one restart is the plain warm start), then fresh modules on seeds drawn from the
    run's; each restart's deterministic rollouts are measured against the demonstrations as ``hand_over nearest``
    measures them (:class:`PolicySelection`), and the nearest restart's policy, posterior and episode codes go on
    in ``m``.  Critic and value stay the run's.  The measures and the choice are logged (``init/restart*``)."""
    cfg, expert, expert_prev = run.cfg, run.expert, run.expert_prev

    def warm_start(mods: Modules, codes: EpisodeCodes | None, gen: torch.Generator) -> dict[str, float]:
        return bc_warm_start(mods, expert, expert_prev, num_codes=num_codes, mixture=run.mixture, cfg=cfg, gen=gen,
                             guard=run.guard, episode_codes=codes)

    stats = warm_start(m, episode_codes, run.gen)
    if cfg.warm_start_restarts == 1:
        return stats
    nearest = PolicySelection(expert, expert_prev, env_info=env_info, learner=cfg.learner)
    seeds = np.random.SeedSequence([cfg.seed, 1]).generate_state(cfg.warm_start_restarts - 1).tolist()
    kept, distances = {}, []
    for r in range(cfg.warm_start_restarts):
        with own_random_numbers(seeds[r - 1] if r else cfg.seed, device) as gen:
            mods, codes = m, episode_codes
            if r:
                obs_dim, act_dim = expert.observations.shape[-1], expert.actions.shape[-1]
                mods, _ = build_modules(cfg, obs_dim, act_dim, num_codes=num_codes, device=device)
                fit_input_scale(mods.policy.encoder, expert.observations, expert.mask)
                codes = (EpisodeCodes(expert, num_codes, cfg.code_prior).to(device) if episode_codes is not None
                         else None)
                restart_stats = warm_start(mods, codes, gen)
            distances.append(nearest(mods.policy, r)["select/distance"])
        print(f"pomil: warm start {r + 1} of {cfg.warm_start_restarts}: distance to the demonstrations "
              f"{distances[-1]:.4f}", file=sys.stderr)
        if nearest.best is not None and nearest.best["iteration"] == r and r:
            kept = {"stats": restart_stats, "posterior": None if mods.posterior is None else
                    copy.deepcopy(mods.posterior.state_dict()),
                    "codes": None if codes is None else copy.deepcopy(codes.state_dict())}
    chosen = int(nearest.best["iteration"]) if nearest.best is not None else 0
    if chosen:
        m.policy.load_state_dict(nearest.best["policy"])
        if m.posterior is not None:
            m.posterior.load_state_dict(kept["posterior"])
        if episode_codes is not None:
            episode_codes.load_state_dict(kept["codes"])
        stats = kept["stats"]
    return {**stats, "init/restart": float(chosen),
            **{f"init/restart_{r}_distance": d for r, d in enumerate(distances)}}


POSTERIOR_INIT_PATIENCE = 10
"""Steps in a row under ``posterior_init_tolerance`` that end the posterior's warm start early."""


def warm_start_posterior(post: BeliefHead, expert: PaddedEpisodes, expert_prev: torch.Tensor, *, codes: torch.Tensor,
                         cfg: AdversarialConfig, gen: torch.Generator,
                         guard: DivergenceGuard | None = None) -> dict[str, float]:
    """``posterior_init_iterations`` steps of the posterior on the demonstrations, each episode
    under its code in ``codes``: indices (E,) (cross-entropy) or continuous codes (E, d)
    (:func:`_code_gaussian_nll`).  With discrete codes it stops early once it tells the codes apart
    (``posterior_init_tolerance``).  Returns the last step's stats."""
    code_nll = _code_cross_entropy if codes.ndim == 1 else _code_gaussian_nll
    post_opt = torch.optim.Adam(post.parameters(), lr=cfg.warm_start_lr)
    starts = first_step_starts(expert.mask)
    batch = min(cfg.warm_start_batch, episodes_within(cfg.max_batch_steps, expert.mask.shape[0]), len(codes))
    s: dict[str, float] = {}
    below = 0  # steps in a row under posterior_init_tolerance (discrete codes)
    with progress_bar(cfg.posterior_init_iterations, "posterior warm start", cfg.progress) as bar:
        for step in range(cfg.posterior_init_iterations):
            idx = torch.randint(len(codes), (batch,), generator=gen).to(codes.device)  # whole episodes
            targets = codes[idx].expand(expert.mask.shape[0], *codes[idx].shape)  # every step of each episode
            with precision_context(cfg.precision, starts.device):
                loss, s = code_nll(post, expert.observations[:, idx], expert_prev[:, idx],
                                   actions=expert.actions[:, idx], starts=starts[:, idx], mask=expert.mask[:, idx],
                                   targets=targets)
            if guard is not None:
                guard.value("warm start of the posterior", "warm-start posterior loss", s["posterior/loss"])
            post_opt.zero_grad(set_to_none=True)
            loss.backward()
            post_opt.step()
            below = below + 1 if codes.ndim == 1 and s["posterior/loss"] < cfg.posterior_init_tolerance else 0
            bar.set_postfix(loss=f"{s['posterior/loss']:.4g}", refresh=False)
            bar.update()
            if below == POSTERIOR_INIT_PATIENCE and step + 1 < cfg.posterior_init_iterations:
                s["posterior/stopped_after"] = float(step + 1)  # row 0's init/posterior_stopped_after
                break
    return s


def update_critic(run: AdversarialRun, roll: Rollout, it: int = 0) -> dict[str, float]:
    """``critic_steps`` updates on expert vs. policy batches; weights clipped after each (Wasserstein, weight_clip)."""
    cfg, m = run.cfg, run.m
    for _ in range(cfg.critic_steps):
        e_act, e_prev = (noisy_expert_actions(run.expert, m.policy, run.execute, run.gen) if cfg.expert_action_noise
                         else (run.expert.actions, run.expert_prev))
        expert = run.sampler.expert(run.expert, e_act, e_prev, cfg.critic_batch, run.gen)
        with run.precision():
            loss, s = critic_loss(m.critic, expert, run.sampler.policy(roll, cfg.critic_batch, run.gen),
                                  objective=run.objective, gp_weight=cfg.gradient_penalty, generator=run.penalty_gen)
        run.check(it, "critic loss", s["critic/loss"])
        run.step(it, "critic", loss, m.critic.parameters)
        if cfg.weight_clip > 0 and run.objective == "wasserstein":
            with torch.no_grad():
                for p in m.critic.parameters():
                    p.clamp_(-cfg.weight_clip, cfg.weight_clip)
    return s


def update_posterior(run: AdversarialRun, roll: Rollout, code_idx: torch.Tensor, it: int = 0) -> dict[str, float]:
    """``posterior_steps`` passes of the code's cross-entropy over the rollout ({} without codes)."""
    if run.m.posterior is None:
        return {}
    code_steps = code_idx.unsqueeze(0).expand(roll.num_steps, *code_idx.shape)
    for _ in range(run.cfg.posterior_steps):
        for batch_idx, batch in run.sampler.posterior(roll, code_steps, run.gen):
            with run.precision():
                loss, s = posterior_loss(run.m.posterior, batch, batch_idx, run.cfg.code_kind)
            run.check(it, "posterior loss", s["posterior/loss"])
            run.step(it, "posterior", loss, run.m.posterior.parameters)
    return s


def with_rewards(run: AdversarialRun, roll: Rollout, code_idx: torch.Tensor, *, next_values: torch.Tensor,
                 it: int = 0) -> tuple[Rollout, dict[str, float]]:
    """The rollout with the imitation rewards (:func:`rewards`), GAE advantages and returns."""
    with run.precision():
        r, s = rewards(run.m, roll, code_idx, cfg=run.cfg, objective=run.objective)
    run.check(it, "reward", r)
    cfg, terminated = run.cfg, roll.terminated
    if cfg.termination == "absorbing" and bool(terminated.any()):
        next_values, s["reward/absorbing_value"] = absorbing_bootstrap(r, roll.mask, terminated,
                                                                       next_values=next_values, gamma=cfg.gamma)
        terminated = torch.zeros_like(terminated)  # bootstrapped from the absorbing state's value, like a truncation
    ended = roll.terminated | roll.truncated
    adv, ret = gae(r, roll.values, next_values, terminated=terminated, truncated=ended, gamma=cfg.gamma,
                   lam=cfg.gae_lambda)
    return roll.with_(rewards=r, advantages=adv, returns=ret), s


def absorbing_bootstrap(r: torch.Tensor, mask: torch.Tensor, terminated: torch.Tensor, *, next_values: torch.Tensor,
                        gamma: float) -> tuple[torch.Tensor, float]:
    """``next_values`` with each terminated step's replaced by the value of an absorbing state.

    Imitation rewards have no fixed sign (the critic term is standardised to zero mean, and
    lambda1 log P(c | b) <= 0), so a return that simply ends at termination pays the policy to
    fall whenever its rewards run negative.  As in DAC (Kostrikov et al., 2019), the episode
    goes on in an absorbing state instead; demonstrations that never terminate never show it,
    so it is paid the lowest step reward of the batch, r_min, forever: V = r_min / (1 - gamma)
    (with gamma = 1, for as many steps as the rollout has, T r_min).  Staying in the episode
    then never pays less than leaving it.  Returns the values and V."""
    if not bool(terminated.any()):
        return next_values, 0.0
    r_min = float(r[mask].min())
    v_abs = r_min * (r.shape[0] if gamma == 1.0 else 1.0 / (1.0 - gamma))
    return torch.where(terminated, torch.full_like(next_values, v_abs), next_values), v_abs


def update_policy(run: AdversarialRun, roll: Rollout, it: int = 0) -> dict[str, float]:
    """``ppo_epochs`` epochs of PPO minibatches on policy and value (the policy waits out
    ``policy_warmup_iterations``)."""
    behaviour = run.sampler.behaviour(run.m.policy, run.m.value)
    for _ in range(run.cfg.ppo_epochs):
        for b in run.sampler.minibatches(roll, run.cfg.minibatches, run.gen):
            with run.precision():  # one context a step: autocast's weight copies last as long as it does
                s = ppo_step(run, behaviour(b), it)
    return s


def ppo_step(run: AdversarialRun, b: Rollout, it: int = 0) -> dict[str, float]:
    """One PPO update of policy and value on minibatch ``b``, with the BC term on demonstrations (bc_weight)."""
    cfg, m = run.cfg, run.m
    windows = run.assignment is not None and run.assignment.window
    if cfg.bc_weight > 0 and not windows:  # the BC term's demonstrations go through the encoder with the minibatch
        demo, demo_prev, demo_idx = demo_batch(run.expert, run.expert_prev, cfg.warm_start_batch, run.gen)
        feats, demo_feats = policy_and_demo_features(m.policy, b, demo, demo_prev)
    else:
        feats, _ = m.policy.features(b.observations, b.prev_actions, b.h0_policy, b.starts)
    dist = m.policy.dist(feats, b.codes)
    new_v, _ = m.value.unroll(b.observations, b.prev_actions, b.h0_value, b.starts, extra=b.codes)
    loss, s = ppo_loss(
        new_logp=dist.log_prob(b.actions).sum(-1), old_logp=b.log_probs,
        advantages=normalize(b.advantages, b.mask), new_values=new_v, old_values=b.values, returns=b.returns,
        entropy=dist.entropy().sum(-1), mask=b.mask, clip=cfg.clip, value_clip=cfg.value_clip or None,
        vf_coef=cfg.vf_coef, ent_coef=cfg.ent_coef,
    )
    if cfg.bc_weight > 0:
        if windows:  # windows come with the discrete codes' mixture: no code per episode
            demo, demo_feats, resp = run.assignment.windows(m.policy, cfg.warm_start_batch, run.gen)
            codes = None
        else:
            resp = run.assignment.update(m.policy)[:, demo_idx] if run.assignment is not None else None
            codes = run.demo_codes(demo_idx)
        bc, bc_stats = demo_nll(m.policy, demo_feats, demo, generator=run.gen, num_codes=run.num_codes,
                                mixture=run.mixture, responsibilities=resp, codes=codes)
        loss = loss + cfg.bc_weight * bc
        s["ppo/bc_nll"] = bc_stats["bc/nll"]
    run.check(it, "policy loss (PPO)", s["ppo/policy_loss"])
    run.check(it, "value loss", s["ppo/value_loss"])
    run.opt["policy"].zero_grad(set_to_none=True)
    run.opt["value"].zero_grad(set_to_none=True)
    loss.backward()
    run.check(it, "policy gradient norm", torch.nn.utils.clip_grad_norm_(m.policy.parameters(), cfg.max_grad_norm))
    run.check(it, "value gradient norm",  # without a shared encoder
              torch.nn.utils.clip_grad_norm_(run.opt["value"].param_groups[0]["params"], cfg.max_grad_norm))
    if it > cfg.policy_warmup_iterations:
        run.opt["policy"].step()
    run.opt["value"].step()
    return s


class PhaseClock:
    """Wall time spent in each phase of the loop, summed over iterations (``with clock("critic"): ...``); on a
    CUDA ``device`` each phase ends by waiting for the GPU, so that a phase's share is its GPU work."""

    def __init__(self, *phases: str, device: torch.device | None = None) -> None:
        self.spent = dict.fromkeys(phases, 0.0)
        self.cuda = device is not None and device.type == "cuda"

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.cuda:
                torch.cuda.synchronize()
            self.spent[phase] += time.perf_counter() - t0

    def shares(self) -> dict[str, float]:
        total = max(sum(self.spent.values()), 1e-9)
        return {f"time/share_{k}": v / total for k, v in self.spent.items()}


KEY_STATS = ("eval/nmi", "eval/spearman", "eval/mean_purity", "env/true_return", "posterior/accuracy",
             "critic/wasserstein")


def iteration(run: AdversarialRun, loop: RunLoop, env: Any, *, clock: PhaseClock, it: int) -> dict[str, float]:
    """One iteration's phases: collect, critic, posterior, rewards and policy (the run loop evaluates,
    logs and checkpoints)."""
    cfg, m = run.cfg, run.m
    with clock("rollout"):
        roll, next_values, code_idx, env_rewards = collect(env, m.policy, m.value, num_codes=run.num_codes,
                                                           execute=run.execute, generator=run.gen, device=loop.device,
                                                           threads=cfg.rollout_threads, code_kind=cfg.code_kind,
                                                           code_prior=cfg.code_prior)
        stats = {"env/true_return": env_rewards.sum(0).mean().item()}
        run.check(it, "environment reward", stats["env/true_return"])
        loop.env_steps += roll.num_steps * roll.num_envs  # eval/env_steps counts the whole run, across resumes
    with clock("critic"):
        stats.update(update_critic(run, roll, it))
    with clock("posterior"):
        stats.update(update_posterior(run, roll, code_idx, it))
    with clock("ppo"):
        roll, s = with_rewards(run, roll, code_idx, next_values=next_values, it=it)
        stats.update(s)
        stats.update(update_policy(run, roll, it))
    return stats


def policy_and_demo_features(policy: GaussianPolicy, b: Rollout, demo: PaddedEpisodes,
                              demo_prev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The policy encoder's features on a PPO minibatch (from its stored initial state) and on
    whole demonstration episodes (from a zero state), side by side when their lengths agree."""
    def features(obs, prev, starts, h0):  # h0 as (1, N, H), so that every input has its columns on dim 1
        return policy.features(obs, prev, h0[0], starts)[0]

    demo_h0 = policy.initial_state(demo.mask.shape[1], demo.mask.device).unsqueeze(0)
    return side_by_side(features, (b.observations, b.prev_actions, b.starts, b.h0_policy.unsqueeze(0)),
                        (demo.observations, demo_prev, first_step_starts(demo.mask), demo_h0))


def make_evaluator(cfg: AdversarialConfig, env_info: dict[str, Any],
                   demos: Demonstrations) -> Callable[[GaussianPolicy], dict[str, float]] | None:
    """The periodic evaluation of a run: mode metrics on circles (continuous codes: code against
    fitted radius, ``evaluate_code_radius``), per-task figures
    on multi-task demonstrations (``pomil demos hopper``); None otherwise (see ``pomil.envs.evaluation_kind``)."""
    kind = evaluation_kind(env_info["id"], demos.metadata) if cfg.eval_every else None
    if kind is None:
        return None
    if kind == "circles" and cfg.code_kind == "continuous" and LEARNERS[cfg.learner].codes:
        from pomil.eval.circles import evaluate_code_radius

        def measure(tp: TrainedPolicy) -> dict[str, float]:
            metrics, _ = evaluate_code_radius(tp, episodes_per_value=cfg.eval_episodes, seed=12345)
            return {"eval/spearman": metrics["spearman"], "eval/radius_low": metrics["radius_covered"][0],
                    "eval/radius_high": metrics["radius_covered"][1]}
    elif kind == "circles":
        from pomil.eval.circles import evaluate_circles

        def measure(tp: TrainedPolicy) -> dict[str, float]:
            metrics, _ = evaluate_circles(tp, cfg.eval_episodes, seed=12345)
            return {"eval/nmi": metrics["nmi"], "eval/mean_purity": metrics["mean_purity"],
                    "eval/modes_covered": float(metrics["modes_covered"]),
                    "eval/none_share": metrics["overall_none_share"]}
    else:
        from pomil.eval.tasks import evaluate_tasks, reference_of

        reference = reference_of(demos.metadata, cfg.demos)

        def measure(tp: TrainedPolicy) -> dict[str, float]:
            res = evaluate_tasks(tp, reference, cfg.eval_episodes, seed=12345)
            return {f"eval/{task}/{k}": float(v) for task, r in res["tasks"].items() for k, v in r.items()}

    last: dict[str, Any] = {}

    def evaluate(policy: GaussianPolicy) -> dict[str, float]:
        # The evaluation is deterministic in the policy's weights: a policy that has not moved since the last one
        # (the policy warm-up's iterations) gets its figures again without the rollouts.
        weights = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        if last and all(torch.equal(v, last["weights"][k]) for k, v in weights.items()):
            return dict(last["stats"])
        stats = measure(TrainedPolicy(policy, cfg.learner, env_info, policy.log_std.device))
        policy.train()
        last.update(weights=weights, stats=stats)
        return stats

    return evaluate


def with_selection(evaluate: Callable[[GaussianPolicy], dict[str, float]] | None, selection: PolicySelection,
                   loop: RunLoop) -> Callable[[GaussianPolicy], dict[str, float]]:
    """The run's evaluation (if any) followed by the selection's measure of the same policy."""
    def evaluate_and_select(policy: GaussianPolicy) -> dict[str, float]:
        return {**(evaluate(policy) if evaluate is not None else {}), **selection(policy, loop.iteration)}

    return evaluate_and_select


# ------------------------------------------------------------------------- train
def divergence_hints(cfg: AdversarialConfig) -> dict[str, str]:
    """The option to lower when a quantity (named by its first word) turns NaN or inf."""
    rewards = ("lr_critic", "lr_posterior") if LEARNERS[cfg.learner].codes else ("lr_critic",)
    return {"policy": lr_hint(cfg, "lr"), "value": lr_hint(cfg, "lr_value", *rewards),  # value targets are rewards
            "critic": lr_hint(cfg, "lr_critic"), "posterior": lr_hint(cfg, "lr_posterior"),
            "reward": lr_hint(cfg, *rewards), "warm-start": lr_hint(cfg, "warm_start_lr")}


def _training_demos(cfg: AdversarialConfig) -> tuple[Demonstrations, str, dict[str, Any]]:
    """The run's demonstrations (its mask and draw of episodes per mode applied), env id and keywords."""
    return load_training_demos(cfg.demos, parse_kwargs(cfg.env_kwargs), parse_mask(cfg.observation_mask),
                               per_mode_episodes=cfg.demos_per_mode, seed=cfg.seed)


def _environment(cfg: AdversarialConfig, demos: Demonstrations, *, env_id: str, env_kwargs: dict[str, Any],
                 device: torch.device):
    """(env info, evaluator, batched env, executed-actions function) of a run on ``demos``."""
    env_info = {"id": env_id, "kwargs": env_kwargs, "observation_mask": demos.metadata.get("observation_mask")}
    evaluate = make_evaluator(cfg, env_info, demos)
    try:
        env = make_vec_env(env_id, env_kwargs, cfg.num_envs, device=device,
                           observation_mask=env_info["observation_mask"], seed=cfg.seed, sim=cfg.sim)
    except ValueError as err:
        raise PomilError(f"{cfg.demos}: {err}") from None
    return env_info, evaluate, env, executed_actions_fn(env_id, env_kwargs)


def train_adversarial(cfg: AdversarialConfig, resume: bool = False) -> Path:
    """Train (or continue) an adversarial run; returns the checkpoint path."""
    if not cfg.demos:
        raise PomilError(f"{cfg.learner}: --demos is required (a demonstrations .npz file)")
    cfg = resolved(cfg)
    longest = Demonstrations.load(cfg.demos).episode_lengths.max(initial=0)
    window = cloning_window(cfg, longest, uses_mixture(cfg, int(LEARNERS[cfg.learner].codes)))
    cfg = sized_for_episodes(cfg, longest, window=window)
    demos, env_id, env_kwargs = _training_demos(cfg)
    cfg = members_for_demonstrations(cfg, demos.episode_lengths, window, recurrent=LEARNERS[cfg.learner].recurrent,
                                     mixture=uses_mixture(cfg, int(LEARNERS[cfg.learner].codes)))
    cfg = sized_for_demonstrations(cfg, demos.episode_lengths, window)
    with RunLoop(cfg, algo=cfg.learner, resume=resume, hints=divergence_hints(cfg)) as loop:
        env_info, evaluate, env, execute = _environment(cfg, demos, env_id=env_id, env_kwargs=env_kwargs,
                                                           device=loop.device)
        choice = None
        if cfg.num_codes == NUM_CODES_AUTO and LEARNERS[cfg.learner].codes:
            choice = (recorded_choice(loop.ckpt_path) if resume else
                      auto_num_codes(cfg, demos.padded(loop.device), execute, loop.guard))
        num_codes = choice.trained if choice is not None else resolve_num_codes(cfg, demos)
        gen = loop.seed()  # after the search, which seeds its own fits: the run is that of --num-codes K
        m, _ = build_modules(cfg, demos.obs_dim, demos.act_dim, num_codes=num_codes, device=loop.device)
        expert = demos.padded(loop.device)
        fit_input_scale(m.policy.encoder, expert.observations, expert.mask)
        opt = build_optimizers(cfg, m)
        if cfg.precision == "bfloat16" and not native_bfloat16(loop.device):
            print(f"pomil: note: precision bfloat16 on {loop.device}, which has no bfloat16 instructions (AVX512-BF16 "
                  "or AMX): emulated, slower than float32", file=sys.stderr)
        if cfg.update_mode == "sequence" and cfg.minibatches > cfg.num_envs:
            print(f"pomil: note: minibatches {cfg.minibatches} is more than num_envs {cfg.num_envs}: each PPO epoch "
                  f"has {cfg.num_envs} minibatches of one episode", file=sys.stderr)
        nets = {"policy": m.policy, "value": m.value, "critic": m.critic, "posterior": m.posterior}
        episode_codes = None
        if cfg.code_kind == "continuous" and num_codes and cfg.warm_start_codes == "mixture":
            episode_codes = EpisodeCodes(expert, num_codes, cfg.code_prior).to(loop.device)
            nets["episode_codes"] = episode_codes  # the BC term's codes, kept for --resume
        expert = replace(expert, actions=execute(expert.actions))  # same form as the policy's, see collect
        expert_prev = shift_actions(expert.actions)
        run = AdversarialRun(cfg, m, opt, gen, loop.penalty_generator, BatchSampler(cfg.update_mode, cfg.window_length),
                             expert, expert_prev, execute, num_codes, loop.guard, episode_codes=episode_codes,
                             assignment=mixture_assignment(cfg, expert, expert_prev, uses_mixture(cfg, num_codes)))
        selection = (PolicySelection(expert, expert_prev, env_info=env_info, learner=cfg.learner)
                     if cfg.hand_over == "nearest" and cfg.eval_every > 0 else None)
        if not loop.start(env=env_info, nets=nets, optimizers=opt, record=choice.record() if choice else None,
                          carried={"env": env, "assignment": run.assignment, "selection": selection},
                          hand_over=selection.policy_state if selection is not None else None):
            return loop.ckpt_path
        # A checkpoint at iteration 0 is that of a warm start alone (--iterations 0): resuming it goes on from there.
        init_stats = (restarted_warm_start(m, run, num_codes=num_codes, env_info=env_info,
                                           episode_codes=episode_codes, device=loop.device)
                      if loop.iteration == 0 and not resume and cfg.warm_start_iterations > 0 else {})
        clock = PhaseClock("rollout", "critic", "posterior", "ppo", device=loop.device)
        if selection is not None:
            evaluate = with_selection(evaluate, selection, loop)
        return loop.run(lambda it: iteration(run, loop, env, clock=clock, it=it), desc=cfg.learner, key_stats=KEY_STATS,
                        first_row={**(choice.stats() if choice else {}), **init_stats}, evaluate=evaluate,
                        eval_every=cfg.eval_every,
                        log_extras=lambda: {"policy/log_std": m.policy.log_std.mean().item(), **clock.shares()})


def auto_num_codes(cfg: AdversarialConfig, expert: PaddedEpisodes, execute: Callable[[torch.Tensor], torch.Tensor],
                   guard: DivergenceGuard | None = None) -> NumCodesChoice:
    """``--num-codes auto``: K from the demonstrations ``expert`` by the held-out classification
    likelihood of the mixture warm start (:mod:`pomil.algos.num_codes`).  Each K's policy is the run's, seeded by the
    run's seed and fitted by the run's warm start (:func:`clone_demonstrations`, always the codes' mixture) for
    ``num_codes_search_iterations`` steps on the training split, on the fast warm start's schedule
    (:data:`FAST_WARM_START`, whatever the run's own): the scores compare fits, so each K's fit must be near its end,
    with its log std at its maximum-likelihood value (docs/method.md, "How many codes")."""
    expert = replace(expert, actions=execute(expert.actions))  # as the warm start sees them
    search_cfg = replace(cfg, **{**FAST_WARM_START, "warm_start_iterations": cfg.num_codes_search_iterations,
                                 "precision": "float32"})  # scores a few hundredths of a nat apart: no rounding

    def fit(k: int, train: PaddedEpisodes, train_prev: torch.Tensor) -> GaussianPolicy:
        torch.manual_seed(cfg.seed)  # every K from the same random numbers: fewer differences by chance
        gen = torch.Generator().manual_seed(cfg.seed)
        arch = policy_arch(cfg, expert.observations.shape[-1], expert.actions.shape[-1], k)
        policy = GaussianPolicy(replace(arch, members=1))  # K is chosen on one policy's fit
        policy = policy.to(expert.mask.device)
        fit_input_scale(policy.encoder, train.observations, train.mask)
        clone_demonstrations(policy, train, train_prev, num_codes=k, mixture=True, cfg=search_cfg, gen=gen,
                             guard=guard, where=f"num_codes auto, K {k}: ")
        return policy

    try:
        return search_num_codes(fit, expert, shift_actions(expert.actions), max_codes=cfg.num_codes_max, seed=cfg.seed,
                                tolerance=cfg.num_codes_tolerance, min_gain=cfg.num_codes_min_gain)
    except ValueError as err:
        raise PomilError(f"{cfg.demos}: num_codes auto: {err}") from None


def recorded_choice(ckpt_path: Path) -> NumCodesChoice:
    """The K that a ``--num-codes auto`` run chose, from its checkpoint (``--resume`` searches no more)."""
    if not ckpt_path.exists():
        raise PomilError(f"{ckpt_path}: nothing to resume (no checkpoint in {ckpt_path.parent})")
    try:
        return NumCodesChoice.from_record(load_checkpoint(ckpt_path).get("record"))
    except (TypeError, ValueError):
        raise PomilError(f"{ckpt_path}: cannot resume a num_codes auto run from this checkpoint: it records no chosen "
                         "number of codes") from None
