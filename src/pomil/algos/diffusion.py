"""Diffusion Policy as a peer learner: ``diffusion`` (unconditional) and ``diffusion-codes``
(conditioned on the code pomil's mixture warm start assigns to each demonstration episode).

A denoiser (``pomil.nn.diffusion``) learns to predict the noise that ``diffusers``' DDPM
schedule added to a horizon of demonstrated actions, given the observations before it; at run
time DDIM samples a plan from the last observations and the policy carries out its first
actions (receding horizon).  A diffusion policy samples one of the demonstrated behaviours: it
covers several modes without collapsing them, but a user cannot choose which.

``diffusion-codes`` is the same model with a code input.  The codes come without labels: an
InfoGAIL-POMDP mixture warm start (``pomil train infogail-pomdp --iterations 0``, run into the
run directory's ``warm-start/``, or an existing run's checkpoint given as ``--codes-from``)
assigns each demonstration episode its most likely code, and the denoiser learns each episode's
actions under its code.  At run time the user picks the code, as with InfoGAIL-POMDP.

One update: draw a batch of (episode, step) places, cut each one's observation window and action
horizon (the first observation repeated before an episode's start, the last action after its
end, as Diffusion Policy pads), noise the scaled actions at random diffusion steps, regress the
noise.  The weights handed over (the checkpoint's ``policy``) are an exponential moving average
of the trained ones (Diffusion Policy's EMA); ``nets`` keeps both for ``--resume``.
"""

from __future__ import annotations

import copy
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

from pomil.config import RunConfig, option, parse_kwargs
from pomil.data import Demonstrations, PaddedEpisodes, load_training_demos
from pomil.envs import executed_actions_fn
from pomil.envs.wrappers import parse_mask
from pomil.errors import PomilError
from pomil.nn.diffusion import DiffusionArch, DiffusionPolicy, noise_schedulers
from pomil.training import RunLoop, lr_hint


@dataclass(frozen=True)
class DiffusionConfig(RunConfig):
    conditioning: Literal["none", "codes"] = option(
        "none", "none: an unconditional policy (learner diffusion); codes: conditioned on the codes the mixture "
                "warm start assigns to the demonstration episodes (learner diffusion-codes)")
    codes_from: str = option("", "with codes: a checkpoint of an InfoGAIL-POMDP run (its warm start or more) whose "
                                 "policy assigns the codes ('': run the warm start into OUT/warm-start)")
    obs_horizon: int = option(2, "observations the denoiser sees: the current one and those before it",
                              within="[1, inf)")
    action_horizon: int = option(16, "actions in each sampled plan", within="[1, inf)")
    execute_horizon: int = option(8, "actions of a plan carried out before the next plan (at most action_horizon)",
                                  within="[1, inf)")
    hidden_size: int = option(256, "width of the denoiser's residual MLP", within="[1, inf)")
    layers: int = option(3, "residual blocks of the denoiser", within="[1, inf)")
    train_timesteps: int = option(100, "DDPM diffusion steps in training", within="[1, inf)")
    inference_steps: int = option(10, "DDIM steps per sampled plan", within="[1, inf)")
    beta_schedule: Literal["squaredcos_cap_v2", "linear", "scaled_linear"] = option(
        "squaredcos_cap_v2", "the noise schedule (diffusers' names; squaredcos_cap_v2: the cosine schedule)")
    iterations: int = option(0, "gradient steps (auto: epochs passes over the demonstrations' steps, at least "
                                "min_iterations)", within="[0, inf)", named={"auto": 0})
    epochs: float = option(75.0, "with iterations auto: passes over the demonstrations' steps", within="(0, inf)")
    min_iterations: int = option(4000, "with iterations auto: at least this many gradient steps", within="[1, inf)")
    batch_size: int = option(256, "(episode, step) places per gradient step", within="[1, inf)")
    lr: float = option(1e-3, "AdamW learning rate at its peak (linear warm-up, then cosine decay to 0)",
                       within="(0, inf)")
    lr_warmup: int = option(200, "gradient steps of the learning rate's linear warm-up", within="[0, inf)")
    weight_decay: float = option(1e-6, "AdamW weight decay", within="[0, inf)")
    ema_power: float = option(0.75, "the EMA's decay at step s: 1 - (1 + s)^-ema_power, at most 0.9999 (Diffusion "
                                    "Policy's schedule)", within="(0, inf)")
    log_every: int = option(250, "iterations between log rows", within="[1, inf)")
    checkpoint_every: int = option(1000, "iterations between checkpoints (one is always written at the end)",
                                   within="[1, inf)")

    def default_out(self) -> str:
        return "runs/diffusion" + ("-codes" if self.conditioning == "codes" else "")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.execute_horizon > self.action_horizon:
            raise PomilError(f"config key 'execute_horizon': expected at most action_horizon "
                             f"({self.action_horizon}), got {self.execute_horizon}")
        if self.inference_steps > self.train_timesteps:
            raise PomilError(f"config key 'inference_steps': expected at most train_timesteps "
                             f"({self.train_timesteps}), got {self.inference_steps}")
        if self.codes_from and self.conditioning != "codes":
            raise PomilError("config key 'codes_from': only with conditioning codes (learner diffusion-codes)")


def sized_for_steps(cfg: DiffusionConfig, steps: int) -> DiffusionConfig:
    """``cfg`` with ``iterations`` auto made a count: ``epochs`` passes over ``steps`` demonstration steps in batches
    of ``batch_size``, at least ``min_iterations`` (two circles' 13,200 steps: 4000; the paper's Hopper, 51,200:
    15,000)."""
    if cfg.iterations:
        return cfg
    return replace(cfg, iterations=max(cfg.min_iterations, math.ceil(cfg.epochs * steps / cfg.batch_size)))


def lr_factor(cfg: DiffusionConfig, step: int) -> float:
    """The learning rate of gradient step ``step`` (1-based) as a fraction of ``cfg.lr``."""
    if step <= cfg.lr_warmup:
        return step / cfg.lr_warmup
    done = (step - cfg.lr_warmup) / max(cfg.iterations - cfg.lr_warmup, 1)
    return 0.5 * (1 + math.cos(math.pi * min(done, 1.0)))


def ema_decay(power: float, step: int) -> float:
    """Diffusion Policy's EMA decay after ``step`` updates: 1 - (1 + step)^-power, in [0, 0.9999]."""
    return min(max(1 - (1 + step) ** -power, 0.0), 0.9999)


@dataclass(frozen=True)
class Places:
    """Every valid (step, episode) place of the demonstrations and the indices of its windows:
    ``obs_steps`` (S, obs_horizon) and ``act_steps`` (S, action_horizon) time indices, clamped to the
    episode's first and last step; ``episodes`` (S,)."""

    episodes: torch.Tensor
    obs_steps: torch.Tensor
    act_steps: torch.Tensor

    @classmethod
    def of(cls, mask: torch.Tensor, obs_horizon: int, action_horizon: int) -> Places:
        t_idx, e_idx = mask.bool().nonzero(as_tuple=True)  # (S,) each
        lengths = mask.bool().sum(0)
        last = (lengths[e_idx] - 1)[:, None]
        obs_steps = (t_idx[:, None] + torch.arange(1 - obs_horizon, 1)[None]).clamp(min=0)
        act_steps = torch.minimum(t_idx[:, None] + torch.arange(action_horizon)[None], last)
        return cls(e_idx, obs_steps, act_steps)

    def batch(self, data: PaddedEpisodes, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(observation windows (B, obs_horizon, obs_dim), action horizons (B, action_horizon, act_dim),
        episodes (B,)) of the places ``idx``."""
        e = self.episodes[idx]
        return (data.observations[self.obs_steps[idx], e[:, None]], data.actions[self.act_steps[idx], e[:, None]], e)


def denoising_loss(policy: DiffusionPolicy, scheduler, windows: torch.Tensor, *, actions: torch.Tensor,
                   codes: torch.Tensor | None, generator: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
    """DDPM's simplified loss: the mean squared error of the predicted noise, at diffusion steps drawn
    uniformly from [0, train_timesteps); returns (loss, stats)."""
    clean = policy.scale(actions, "act")
    noise = torch.randn(clean.shape, generator=generator).to(clean.device)
    steps = torch.randint(0, policy.arch.train_timesteps, (len(clean),), generator=generator).to(clean.device)
    noisy = scheduler.add_noise(clean, noise, steps)
    loss = F.mse_loss(policy(noisy, steps, policy.condition(windows, codes)), noise)
    return loss, {"diffusion/loss": loss.item()}


def warm_start_codes(cfg: DiffusionConfig, run_dir: Path, resume: bool) -> Path:
    """The checkpoint whose policy assigns the codes: ``codes_from``, or InfoGAIL-POMDP's warm start run into
    ``run_dir/warm-start`` (kept; a resumed run reuses it)."""
    if cfg.codes_from:
        return Path(cfg.codes_from)
    from pomil.algos.adversarial import AdversarialConfig, train_adversarial

    out = run_dir / "warm-start"
    if resume and (out / "checkpoint.pt").exists():
        return out / "checkpoint.pt"
    print(f"pomil: diffusion-codes: the codes come from InfoGAIL-POMDP's mixture warm start, run into {out}",
          file=sys.stderr)
    return train_adversarial(AdversarialConfig(  # its preset auto is resolved from the demonstrations there
        learner="infogail-pomdp", demos=cfg.demos, env_kwargs=cfg.env_kwargs, observation_mask=cfg.observation_mask,
        demos_per_mode=cfg.demos_per_mode, seed=cfg.seed, iterations=0, eval_every=0, out=str(out), overwrite=True,
        device=cfg.device, progress=cfg.progress))


def episode_codes(ckpt: Path, demos: Demonstrations, *, env_id: str, env_kwargs: dict, device: torch.device
                  ) -> tuple[torch.Tensor, int]:
    """Each demonstration episode's most likely code under the policy of ``ckpt`` (E,), and K."""
    from pomil.algos.warm_start import most_likely_codes
    from pomil.api import TrainedPolicy
    from pomil.nn.policy import GaussianPolicy, shift_actions

    policy = TrainedPolicy.load(ckpt, device).policy
    k = policy.arch.num_codes
    if not isinstance(policy, GaussianPolicy) or policy.arch.continuous_codes or k < 2:
        raise PomilError(f"{ckpt}: codes_from must be a run with discrete latent codes (InfoGAIL-POMDP), got one with "
                         f"{k} {'continuous' if policy.arch.continuous_codes else 'discrete'} code(s)")
    if (policy.arch.obs_dim, policy.arch.act_dim) != (demos.obs_dim, demos.act_dim):
        raise PomilError(f"{ckpt}: codes_from's policy sees {policy.arch.obs_dim} observations and acts in "
                         f"{policy.arch.act_dim} dimensions; the demonstrations have {demos.obs_dim} and "
                         f"{demos.act_dim}")
    data = demos.padded(device)
    data = replace(data, actions=executed_actions_fn(env_id, env_kwargs)(data.actions))  # as the warm start saw them
    return most_likely_codes(policy, data, shift_actions(data.actions)).cpu(), k


def train_diffusion(config: DiffusionConfig, resume: bool = False) -> Path:
    """Train (or continue) a diffusion run; returns the checkpoint path."""
    if not config.demos:
        raise PomilError("diffusion: --demos is required (a demonstrations .npz file)")
    hints = {"diffusion": lr_hint(config, "lr"), "policy": lr_hint(config, "lr")}
    demos, env_id, env_kwargs = load_training_demos(config.demos, parse_kwargs(config.env_kwargs),
                                                    parse_mask(config.observation_mask),
                                                    per_mode_episodes=config.demos_per_mode, seed=config.seed)
    config = sized_for_steps(config, int(demos.episode_lengths.sum()))
    with RunLoop(config, algo="diffusion" + ("-codes" if config.conditioning == "codes" else ""), resume=resume,
                 hints=hints) as loop:
        codes, num_codes, record = None, 0, {}
        if config.conditioning == "codes":
            source = warm_start_codes(config, loop.dir, resume)
            codes, num_codes = episode_codes(source, demos, env_id=env_id, env_kwargs=env_kwargs, device=loop.device)
            shares = np.bincount(codes.numpy(), minlength=num_codes) / len(codes)
            record = {"codes_from": str(source), "code_shares": shares.round(4).tolist()}
            if demos.labels is not None:
                from pomil.eval.metrics import normalized_mutual_info

                record["codes_nmi_with_labels"] = round(normalized_mutual_info(codes.numpy(), demos.labels), 4)
        generator = loop.seed()
        arch = DiffusionArch(demos.obs_dim, demos.act_dim, num_codes, config.obs_horizon, config.action_horizon,
                             config.execute_horizon, config.hidden_size, config.layers, config.train_timesteps,
                             config.inference_steps, config.beta_schedule)
        policy = DiffusionPolicy(arch).to(loop.device)
        data = demos.padded(loop.device)
        valid = data.mask.bool()
        policy.fit_ranges(data.observations[valid], data.actions[valid])
        ema = copy.deepcopy(policy).requires_grad_(False)
        optimizer = torch.optim.AdamW(policy.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        places = Places.of(data.mask.cpu(), config.obs_horizon, config.action_horizon)
        one_hot = None if codes is None else F.one_hot(codes, num_codes).float().to(loop.device)
        scheduler = noise_schedulers(arch)[0]
        env = {"id": env_id, "kwargs": env_kwargs, "observation_mask": demos.metadata.get("observation_mask")}
        if not loop.start(env=env, nets={"policy": policy, "ema": ema}, optimizers={"policy": optimizer},
                          env_steps=False, record=record, hand_over=ema.state_dict):
            return loop.ckpt_path

        def update(iteration: int) -> dict[str, float]:
            for group in optimizer.param_groups:
                group["lr"] = config.lr * lr_factor(config, iteration)
            idx = torch.randint(0, len(places.episodes), (config.batch_size,), generator=generator)
            windows, actions, episodes = places.batch(data, idx.to(data.mask.device))
            loss, stats = denoising_loss(policy, scheduler, windows, actions=actions,
                                         codes=None if one_hot is None else one_hot[episodes], generator=generator)
            loop.guard.value(iteration, "diffusion loss (noise MSE)", stats["diffusion/loss"])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            loop.guard.grads(iteration, "policy", policy.parameters())
            optimizer.step()
            decay = ema_decay(config.ema_power, iteration - 1)
            with torch.no_grad():
                for e, p in zip(ema.parameters(), policy.parameters(), strict=True):
                    e.lerp_(p, 1 - decay)
            return {**stats, "diffusion/lr": optimizer.param_groups[0]["lr"]}

        return loop.run(update, desc=loop.algo, key_stats=("diffusion/loss",))
