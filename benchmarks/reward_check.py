"""The reward check: does an adversarial run's learned reward rank its own episodes as the task's reward does?

For each task of the demonstrations (without tasks in their metadata, or without --demos: the run's own environment
and its reward), the run's last (running) policy collects a batch of stochastic episodes, as in training, with the
codes drawn at random; the run's own critic and posterior pay them the training reward (the critic term standardised
over the batch plus lambda1 log P(c | b_t), pomil.algos.adversarial.rewards). Per code, over its episodes: the mean
environment return; Spearman's rank correlation of the imitation return (the undiscounted sum of that reward) with
the task's return and with the episode's length; the mean step reward's two terms. A reward that ranks the episodes
the task's way (correlation near 1) gives PPO the direction; one near 0 gives it none, whatever the optimiser. Where
an episode can end early, a code whose mean step reward is negative is paid to end it.

The environment's reward is read here only; no learner sees it.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/reward_check.py --demos D runs/infogail-pomdp/checkpoint.pt ...

Hopper's Forward/Backward demonstrations train with the forward task's reward in the environment; --demos D scores
each code on both tasks' rewards (a code's own task: where its return is highest).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import torch

from pomil.algos.adversarial import AdversarialConfig, build_modules, rewards
from pomil.config import from_dict, saved_config
from pomil.data import Demonstrations
from pomil.envs import executed_actions_fn, make_vec_env
from pomil.errors import PomilError
from pomil.eval.metrics import spearman
from pomil.rl.collect import collect
from pomil.training import load_checkpoint


def episode_table(path: str, tasks: dict | None, episodes: int, seed: int) -> list[dict]:
    """Per task and code: episodes, mean env return and length, Spearman(imitation return, env return / length).
    ``tasks``: environment keywords by task name (None: the run's own environment, as task ``own``)."""
    ckpt = load_checkpoint(path)
    if ckpt.get("algo") not in ("gail", "infogail", "infogail-pomdp"):
        raise PomilError(f"{path}: not an adversarial run's checkpoint (its learner: {ckpt.get('algo')!r:.40})")
    try:
        cfg = from_dict(AdversarialConfig, saved_config(AdversarialConfig, ckpt["config"]), source=path)
        arch, nets = ckpt["policy_arch"], ckpt["nets"]
        m, _ = build_modules(cfg, arch["obs_dim"], arch["act_dim"], num_codes=arch["num_codes"], device="cpu")
        for name in ("policy", "value", "critic", "posterior"):
            if getattr(m, name) is not None:
                getattr(m, name).load_state_dict(nets[name])
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise PomilError(f"{path}: not an adversarial run's checkpoint ({type(err).__name__}: {err})") from None
    env_info = ckpt["env"]
    tasks = tasks or {"own": env_info.get("kwargs") or {}}
    objective = "wasserstein" if cfg.learner != "gail" else "gan"
    gen = torch.Generator().manual_seed(seed)
    rows = []
    for task, kwargs in tasks.items():
        env = make_vec_env(env_info["id"], kwargs, episodes, device="cpu",
                           observation_mask=env_info.get("observation_mask"), seed=seed)
        try:
            with torch.no_grad():
                roll, _, code_idx, env_rewards = collect(
                    env, m.policy, m.value, num_codes=arch["num_codes"],
                    execute=executed_actions_fn(env_info["id"], kwargs), generator=gen, device="cpu", threads=1,
                    code_kind=cfg.code_kind, code_prior=cfg.code_prior)
                r, _ = rewards(m, roll, code_idx, cfg=cfg, objective=objective)
                critic_term, _ = rewards(m, roll, code_idx, cfg=replace(cfg, mi_weight=0.0), objective=objective)
        finally:
            env.close()
        mask = roll.mask.float()
        imitation = (r * mask).sum(0).numpy()
        returns, lengths = env_rewards.sum(0).numpy(), mask.sum(0).numpy()
        for code in range(arch["num_codes"]):
            pick = (code_idx == code).numpy()
            if pick.sum() < 3:
                continue
            steps = mask[:, pick].sum()
            rows.append({"task": task, "code": code, "episodes": int(pick.sum()),
                         "return": float(returns[pick].mean()), "length": float(lengths[pick].mean()),
                         "rho_return": spearman(imitation[pick], returns[pick]),
                         "rho_length": spearman(imitation[pick], lengths[pick]),
                         "critic_step": float((critic_term * mask)[:, pick].sum() / steps),
                         "mi_step": float(((r - critic_term) * mask)[:, pick].sum() / steps)})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+", help="adversarial runs' checkpoint.pt on the demonstrations' tasks")
    parser.add_argument("--demos", default="", help="the demonstrations (.npz) whose tasks' metadata name the tasks "
                                                    "(default: each run's own environment)")
    parser.add_argument("--episodes", type=int, default=64, help="stochastic episodes per task, codes at random "
                                                                 "(default 64)")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    try:
        if args.episodes < 1:
            raise PomilError(f"--episodes: expected a positive number of episodes, got {args.episodes}")
        tasks = Demonstrations.load(args.demos).metadata.get("tasks") if args.demos else None
        if tasks is not None and (not isinstance(tasks, dict) or not all(isinstance(v, dict) for v in tasks.values())):
            raise PomilError(f"{args.demos}: metadata 'tasks' is not a table of environment keywords")
        print("| checkpoint | task | code | episodes | env return | length | rho(imitation, env return) | "
              "rho(imitation, length) | critic term / step | MI term / step |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for path in args.checkpoints:
            for row in episode_table(path, tasks, args.episodes, args.seed):
                print(f"| {path} | {row['task']} | {row['code']} | {row['episodes']} | {row['return']:.0f} | "
                      f"{row['length']:.0f} | {row['rho_return']:.2f} | {row['rho_length']:.2f} | "
                      f"{row['critic_step']:.2f} | {row['mi_step']:.2f} |")
    except PomilError as err:
        print(f"reward_check: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
