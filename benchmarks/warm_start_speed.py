"""The warm start's time and fit under each recipe, from the same initial networks, in one run.

For each demonstrations file, learner and seed, runs ``bc_warm_start`` (the adversarial
learners' behaviour-cloning warm start, with its posterior steps) once per recipe:

* ``default``: ``AdversarialConfig``'s warm start (600 Adam steps, lr rising to 1e-2 over the
  first 20%, then decaying to 0; the log std at the network's rate, not fitted);
* ``long``: the ``long-warm-start`` preset (3000 steps at a constant lr 1e-3, the former
  default);
* ``fast``: the ``fast-warm-start`` preset (600 steps, lr 3e-3 decaying to 0, the log std
  at 10x and fitted in closed form at the end);
* ``deep``: the ``deep-warm-start`` preset (600 steps, lr rising to 1e-2 over the first 20%,
  then decaying to 0; the log std as in ``fast``);
* ``bf16``: the default's steps with ``precision`` bfloat16 (``torch.autocast``);
* ``long-bf16``: the ``long`` steps in bfloat16;
* ``fast-bf16``: the ``fast`` steps in bfloat16.

and prints its wall time, the policy part's time, and the demonstrations' negative
log-likelihood per step on *all* episodes at the end (in float32: the mixture likelihood of
``mixture_bc_loss`` for learners with codes, the plain one for GAIL), with each recipe's
time ratio and NLL change against the first one::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/warm_start_speed.py \
        [--demos data/circles.npz,data/hopper-paper.npz] [--learners infogail-pomdp] [--seeds 0] \
        [--recipes long,default,fast,deep,bf16,long-bf16,fast-bf16]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import torch

from pomil.algos.adversarial import AdversarialConfig, bc_warm_start, build_modules, resolve_num_codes
from pomil.algos.warm_start import (
    DEEP_WARM_START,
    FAST_WARM_START,
    LONG_WARM_START,
    _nll,
    episode_features,
    mixture_bc_loss,
)
from pomil.data import load_training_demos
from pomil.envs import executed_actions_fn
from pomil.nn.policy import shift_actions
from pomil.training import precision_context

RECIPES = {"default": {}, "long": LONG_WARM_START, "fast": FAST_WARM_START, "deep": DEEP_WARM_START,
           "bf16": {"precision": "bfloat16"}, "long-bf16": {**LONG_WARM_START, "precision": "bfloat16"},
           "fast-bf16": {**FAST_WARM_START, "precision": "bfloat16"}}


@torch.no_grad()
def demo_nll(policy, expert, prev, mixture: bool) -> float:
    if mixture:
        return mixture_bc_loss(policy, expert, prev)[0].item()
    feats = episode_features(policy, expert.observations, prev, expert.mask)
    return _nll(policy, policy.dist(feats), expert.actions, expert.mask)[0].item()


def measure(demos_path: str, learner: str, seed: int, settings: dict) -> dict[str, float]:
    cfg = replace(AdversarialConfig(demos=demos_path, learner=learner, seed=seed), **settings)
    demos, env_id, env_kwargs = load_training_demos(demos_path)
    num_codes = resolve_num_codes(cfg, demos)
    torch.manual_seed(seed)
    m, _ = build_modules(cfg, demos.obs_dim, demos.act_dim, num_codes=num_codes, device="cpu")
    expert = demos.padded("cpu")
    expert = replace(expert, actions=executed_actions_fn(env_id, env_kwargs)(expert.actions))
    prev = shift_actions(expert.actions)
    mixture = cfg.warm_start_codes == "mixture" and num_codes > 0
    gen = torch.Generator().manual_seed(seed)
    precision = precision_context(cfg.precision, torch.device("cpu"))  # as train_adversarial runs it
    t0 = time.perf_counter()
    with precision:
        bc_warm_start(m, expert, prev, num_codes=num_codes, mixture=mixture, cfg=replace(cfg,
                                                                                         posterior_init_iterations=0),
                      gen=gen)
    policy_s = time.perf_counter() - t0
    nll = demo_nll(m.policy, expert, prev, generator=mixture)
    t1 = time.perf_counter()
    if mixture:  # the posterior's steps (the same number in every recipe), timed on their own
        with precision_context(cfg.precision, torch.device("cpu")):
            bc_warm_start(m, expert, prev, num_codes=num_codes, mixture=mixture, cfg=replace(cfg,
                                                                                             warm_start_iterations=0),
                          gen=gen)
    return {"seconds": policy_s + time.perf_counter() - t1, "policy_s": policy_s, "nll": nll,
            "log_std": m.policy.log_std.mean().item()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demos", default="data/circles.npz,data/hopper-paper.npz")
    ap.add_argument("--learners", default="infogail-pomdp")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--recipes", default=",".join(RECIPES), help=f"comma-separated, some of {list(RECIPES)}")
    args = ap.parse_args()
    recipes = args.recipes.split(",")
    if not recipes or any(r not in RECIPES for r in recipes):
        ap.error(f"--recipes: expected some of {list(RECIPES)}, got {args.recipes!r}")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} torch threads")
    print(f"{'demonstrations':24s} {'learner':15s} {'seed':>4s} {'recipe':10s} {'s':>7s} {'policy s':>9s} "
          f"{'NLL':>8s} {'log std':>8s} {'time ratio':>11s} {'NLL change':>11s}")
    for demos in args.demos.split(","):
        for learner in args.learners.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                rows = {name: measure(demos, learner, seed, RECIPES[name]) for name in recipes}
                first = rows[recipes[0]]
                for name, r in rows.items():
                    print(f"{demos:24s} {learner:15s} {seed:4d} {name:10s} {r['seconds']:7.1f} {r['policy_s']:9.1f} "
                          f"{r['nll']:8.3f} {r['log_std']:8.2f} {first['seconds'] / r['seconds']:10.1f}x "
                          f"{r['nll'] - first['nll']:+11.3f}", flush=True)


if __name__ == "__main__":
    main()
