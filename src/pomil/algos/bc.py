"""Behaviour cloning: maximum likelihood of expert actions.

A Gaussian policy, feed-forward (current observation only) or recurrent
(belief over the whole history), is fitted to the demonstrations by
minimising the negative log-likelihood of the expert's actions.  Recurrent
policies train on whole episodes from a zero initial state, exactly as they
run.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import torch

from pomil.algos.warm_start import bc_step, sized_for_episodes
from pomil.config import RunConfig, option, parse_kwargs, resolved
from pomil.data import Demonstrations, load_training_demos
from pomil.envs import executed_actions_fn
from pomil.envs.wrappers import parse_mask
from pomil.errors import PomilError
from pomil.nn.encoders import OBS_DELTA_HELP, PREV_ACTION_HELP, fit_input_scale
from pomil.nn.policy import GaussianPolicy, PolicyArch, shift_actions
from pomil.training import RunLoop, lr_hint


@dataclass(frozen=True)
class BCConfig(RunConfig):
    preset: Literal["auto", "default", "terminating"] = option(
        "auto", "named settings under the config file and flags: auto (terminating for demonstrations whose "
                "environment ends an episode when the agent fails, such as Hopper's own 1000-step setting; default "
                "otherwise), default, or terminating (the policy sees (z_t, dz_t) without a_{t-1}); config.json "
                "records the one that ran; see PRESETS")
    policy: Literal["mlp", "gru", "lstm", "attention"] = option(
        "gru", "mlp: current observation only; gru, lstm or attention (a one-layer causal transformer over the last "
               "attention_context steps): belief over the history")
    hidden_size: int = option(128, "width of the dense layers and recurrent cells", within="[1, inf)")
    attention_context: int = option(32, "with policy attention: steps it attends to, the current one included",
                                    within="[1, inf)")
    obs_delta: bool = option(False, "the policy: " + OBS_DELTA_HELP)
    prev_action: bool = option(True, "the policy's encoder: " + PREV_ACTION_HELP)
    iterations: int = option(500, "gradient steps", within="[1, inf)")
    batch_episodes: int = option(64, "whole episodes per minibatch (at most max_batch_steps)", within="[1, inf)")
    max_batch_steps: int = option(16384, "long episodes: at most this many steps per minibatch, counted at the "
                                         "demonstrations' longest episode: fewer than batch_episodes (1000-step "
                                         "Hopper: 16)", within="[1, inf)")
    lr: float = option(1e-3, "Adam learning rate", within="(0, inf)")
    log_std_init: float = option(-1.0, "initial log standard deviation of the Gaussian policy", within="(-inf, inf)")

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        # Episodes that end when the agent fails (standard Hopper): with a_{t-1} the clone copies it and falls within
        # 22 steps; (z_t, dz_t) alone stayed up 377-455 steps (docs/hopper.md, "What makes the clone fall").
        "terminating": {"obs_delta": True, "prev_action": False},
    }
    """Named settings (``preset``): applied under a config file's and the flags' values by ``config.from_dict``;
    ``auto`` is replaced by one of them when training starts (``config.resolved``)."""
    EPISODE_CAPS: ClassVar[dict[str, str]] = {"batch_episodes": "max_batch_steps"}
    """Episode counts and the step caps they are cut to for long episodes (``sized_for_episodes``)."""

    def default_out(self) -> str:
        return f"runs/bc-{self.policy}"


def train_bc(config: BCConfig, resume: bool = False) -> Path:
    """Train (or continue) a BC run; returns the checkpoint path."""
    if not config.demos:
        raise PomilError("bc: --demos is required (a demonstrations .npz file)")
    hints = {"bc": lr_hint(config, "lr"), "policy": lr_hint(config, "lr")}
    config = sized_for_episodes(resolved(config), Demonstrations.load(config.demos).episode_lengths.max(initial=0))
    with RunLoop(config, algo="bc", resume=resume, hints=hints) as loop:
        demos, env_id, env_kwargs = load_training_demos(config.demos, parse_kwargs(config.env_kwargs),
                                                        parse_mask(config.observation_mask),
                                                        per_mode_episodes=config.demos_per_mode, seed=config.seed)
        generator = loop.seed()
        arch = PolicyArch(demos.obs_dim, demos.act_dim, config.policy, config.hidden_size, 0, config.log_std_init,
                          context=config.attention_context, obs_delta=config.obs_delta, prev_action=config.prev_action)
        policy = GaussianPolicy(arch).to(loop.device)
        data = demos.padded(loop.device)
        fit_input_scale(policy.encoder, data.observations, data.mask)
        optimizer = torch.optim.Adam(policy.parameters(), lr=config.lr)
        if config.batch_episodes > demos.num_episodes:
            print(f"pomil: note: batch_episodes {config.batch_episodes} is more than the {demos.num_episodes} "
                  f"demonstration episodes; each batch draws {demos.num_episodes}", file=sys.stderr)
        env = {"id": env_id, "kwargs": env_kwargs, "observation_mask": demos.metadata.get("observation_mask")}
        if not loop.start(env=env, nets={"policy": policy}, optimizers={"policy": optimizer}, env_steps=False):
            return loop.ckpt_path
        prev_all = shift_actions(executed_actions_fn(env_id, env_kwargs)(data.actions))

        def update(iteration: int) -> dict[str, float]:
            stats = bc_step(policy, optimizer, data, prev_actions=prev_all, batch_episodes=config.batch_episodes,
                            generator=generator)
            loop.guard.value(iteration, "bc loss (negative log-likelihood)", stats["bc/nll"])
            loop.guard.grads(iteration, "policy", policy.parameters())  # the step's gradients are still on them
            return stats

        return loop.run(update, desc="bc", key_stats=("bc/nll", "bc/action_mse"))
