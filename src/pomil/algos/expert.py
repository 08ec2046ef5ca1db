"""PPO experts: an MLP policy trained on a task's reward, for any Gymnasium
environment with 1-D Box spaces (Hopper on its fast batched simulator).

The experts whose demonstrations the imitation learners see; by default they
observe everything (``observation_mask`` restricts that).  One readable
loop: collect one episode in each of ``num_envs`` batched copies, GAE,
``ppo_epochs`` passes of shuffled single-step minibatches through the clipped
PPO loss.  Observations are normalised by running statistics (kept in the
checkpoint and applied by :class:`pomil.TrainedPolicy`); rewards are divided
by the running standard deviation of the discounted return; the learning rate
decays linearly to zero.  These are the usual PPO settings for MuJoCo
locomotion.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

import torch

from pomil.config import RunConfig, option, parse_kwargs
from pomil.envs import SIM_HELP, executed_actions_fn, make_vec_env
from pomil.envs.locomotion import HOPPER_ID, locomotion_kwargs
from pomil.envs.wrappers import parse_mask, resolve_observation_mask
from pomil.errors import PomilError
from pomil.nn import heads
from pomil.nn.normalize import RunningNorm
from pomil.nn.policy import GaussianPolicy, PolicyArch
from pomil.rl.collect import collect
from pomil.rl.gae import gae
from pomil.rl.ppo import PPOOptions, normalize, ppo_loss
from pomil.rl.storage import Rollout
from pomil.training import DivergenceGuard, RunLoop, lr_hint


@dataclass(frozen=True)
class ExpertConfig(PPOOptions, RunConfig):
    env_id: str = option(HOPPER_ID, "Gymnasium environment id (1-D Box observation and action spaces)")
    task: Literal["forward", "backward", "none"] = option(
        "forward", "locomotion task: forward_reward_weight +1 or -1; none: the environment's own reward")
    setting: Literal["paper", "standard"] = option(
        "paper", "paper: 128-step episodes that do not end when unhealthy; standard: the environment's own episodes")
    env_kwargs: tuple[str, ...] = option((), "more constructor keywords as key=value (JSON values), applied after task "
                                             "and setting, e.g. ctrl_cost_weight=0.05,max_episode_steps=200")
    observation_mask: str = option("",
                                   "what the expert observes: '' (everything), positions-only, velocities, or "
                                   "comma-separated indices")
    iterations: int = option(200,
                             "iterations; each is one episode in every copy (paper setting: num_envs * 128 env steps)",
                             within="[1, inf)")
    num_envs: int = option(64, "environment copies stepped together", within="[1, inf)")
    sim: Literal["cpu", "warp"] = option("cpu", SIM_HELP)
    rollout_threads: int = option(1, "torch threads while collecting rollouts (0: torch's own setting); one keeps "
                                     "torch's idle OpenMP workers off the cores that a batched simulator steps on",
                                     within="[0, inf)")
    hidden_size: int = option(64, "width of the policy's and value's hidden layers", within="[1, inf)")
    lr: float = option(3e-4, "Adam learning rate (decays linearly to 0)", within="(0, inf)")
    log_std_init: float = option(0.0, "initial log std of the policy", within="(-inf, inf)")
    log_every: int = option(5, "iterations between log rows", within="[1, inf)")
    checkpoint_every: int = option(50, "iterations between checkpoints (one is always written at the end)",
                                   within="[1, inf)")

    RENAMED: ClassVar[dict[str, str]] = {"epochs": "ppo_epochs"}
    """Old config keys, still read from config files and checkpoints (old -> new name)."""

    def default_out(self) -> str:
        return f"runs/expert-{self.env_id.split('-')[0].lower()}-{self.task}-{self.setting}"

    def env_settings(self) -> tuple[dict, list[int] | None]:
        """(constructor keywords, observation indices or None); ValueError when the env rejects them."""
        kwargs = {**locomotion_kwargs(self.env_id, self.task, self.setting), **parse_kwargs(self.env_kwargs)}
        return kwargs, resolve_observation_mask(self.env_id, kwargs, parse_mask(self.observation_mask))


class _NormalizedObs:
    """Observations through a RunningNorm whose statistics every observation updates."""

    def __init__(self, env, norm: RunningNorm) -> None:
        self.env, self.norm = env, norm
        self.num_envs = env.num_envs

    def _obs(self, obs: torch.Tensor) -> torch.Tensor:
        self.norm.update(obs)
        return self.norm(obs)

    def reset(self) -> torch.Tensor:
        return self._obs(self.env.reset())

    def step(self, actions: torch.Tensor):
        obs, *rest = self.env.step(actions)
        return (self._obs(obs), *rest)


def discounted_returns(rewards: torch.Tensor, mask: torch.Tensor, gamma: float) -> torch.Tensor:
    """Return-to-go of each valid step of (T, N) episodes that start at t = 0."""
    out = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[0])
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = (rewards[t] + gamma * running) * mask[t]
        out[t] = running
    return out


def _environment(cfg: ExpertConfig, device: torch.device):
    """(batched env, constructor keywords, observation indices or None) of a run."""
    try:
        env_kwargs, mask = cfg.env_settings()
        env = make_vec_env(cfg.env_id, env_kwargs, cfg.num_envs, device=device, observation_mask=mask, seed=cfg.seed,
                           sim=cfg.sim)
        return env, env_kwargs, mask
    except PomilError:
        raise
    except Exception as err:  # unknown id, rejected keywords: gymnasium raises several types
        raise PomilError(f"experts: cannot build {cfg.env_id!r} ({str(err).splitlines()[0][:200]})") from None


def ppo_update(cfg: ExpertConfig, policy: GaussianPolicy, value: torch.nn.Module, *, opt: torch.optim.Optimizer,
               roll: Rollout, gen: torch.Generator, guard: DivergenceGuard, it: int) -> dict[str, float]:
    """``ppo_epochs`` passes of shuffled single-step minibatches through the clipped PPO loss."""
    stats: dict[str, float] = {}
    params = [p for group in opt.param_groups for p in group["params"]]
    for _ in range(cfg.ppo_epochs):
        for b in roll.step_batches(cfg.minibatches, gen):
            dist, _ = policy.unroll(b.observations, b.prev_actions, b.h0_policy, b.starts)
            new_v, _ = value.unroll(b.observations, b.prev_actions, b.h0_value, b.starts)
            loss, stats = ppo_loss(
                new_logp=dist.log_prob(b.actions).sum(-1), old_logp=b.log_probs,
                advantages=normalize(b.advantages, b.mask), new_values=new_v, old_values=b.values, returns=b.returns,
                entropy=dist.entropy().sum(-1), mask=b.mask, clip=cfg.clip, value_clip=None, vf_coef=cfg.vf_coef,
                ent_coef=cfg.ent_coef)
            guard.value(it, "policy loss (PPO)", stats["ppo/policy_loss"])
            guard.value(it, "value loss", stats["ppo/value_loss"])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            guard.value(it, "policy and value gradient norm", torch.nn.utils.clip_grad_norm_(params, cfg.max_grad_norm))
            opt.step()
    return stats


def train_expert(cfg: ExpertConfig, resume: bool = False) -> Path:
    """Train (or continue) a PPO expert; returns the checkpoint path."""
    hints = {"policy": lr_hint(cfg, "lr"), "value": lr_hint(cfg, "lr")}
    with RunLoop(cfg, algo="expert", resume=resume, hints=hints) as loop:
        raw_env, env_kwargs, mask = _environment(cfg, loop.device)
        obs_norm = RunningNorm(raw_env.obs_dim).to(loop.device)
        env = _NormalizedObs(raw_env, obs_norm)
        reward_norm = RunningNorm(1).to(loop.device)
        execute = executed_actions_fn(cfg.env_id, env_kwargs)
        gen = loop.seed()
        arch = PolicyArch(raw_env.obs_dim, raw_env.act_dim, "mlp", cfg.hidden_size, 0, cfg.log_std_init)
        policy = GaussianPolicy(arch).to(loop.device)
        value = heads.value(raw_env.obs_dim, raw_env.act_dim, 0, encoder="mlp",
                            hidden_size=cfg.hidden_size).to(loop.device)
        opt = torch.optim.Adam(list(policy.parameters()) + list(value.parameters()), lr=cfg.lr, eps=1e-5)
        nets = {"policy": policy, "value": value, "obs_norm": obs_norm, "reward_norm": reward_norm}
        if not loop.start(env={"id": cfg.env_id, "kwargs": env_kwargs, "observation_mask": mask}, nets=nets,
                          optimizers={"ppo": opt}, carried={"env": raw_env}):
            raw_env.close()
            return loop.ckpt_path

        def update(it: int) -> dict[str, float]:
            for group in opt.param_groups:
                group["lr"] = cfg.lr * (1.0 - (it - 1) / cfg.iterations)
            roll, next_values, _, raw_rewards = collect(env, policy, value, num_codes=0, execute=execute,
                                                        generator=gen, device=loop.device, threads=cfg.rollout_threads)
            loop.env_steps += int(roll.mask.sum())
            reward_norm.update(discounted_returns(raw_rewards, roll.mask, cfg.gamma)[roll.mask].unsqueeze(-1))
            loop.guard.value(it, "environment reward", raw_rewards)
            r = raw_rewards / torch.sqrt(reward_norm.var.float() + 1e-8)  # divided by the running std of the return
            adv, ret = gae(r, roll.values, next_values, terminated=roll.terminated, truncated=roll.truncated,
                           gamma=cfg.gamma, lam=cfg.gae_lambda)
            stats = ppo_update(cfg, policy, value, opt=opt, roll=roll.with_(rewards=r, advantages=adv, returns=ret),
                               gen=gen, guard=loop.guard, it=it)
            return {**stats, "env/return": raw_rewards.sum(0).mean().item(), "env/steps": float(loop.env_steps)}

        loop.run(update, desc=f"expert {cfg.env_id} {cfg.task}", key_stats=("env/return", "ppo/approx_kl"),
                 log_extras=lambda: {"policy/log_std": policy.log_std.mean().item()})
        raw_env.close()
        return loop.ckpt_path
