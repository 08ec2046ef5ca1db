"""Hopper throughput, measured in one run on this machine.

Prints env-steps/s of:

1. the raw batched simulator (``pomil.envs.locomotion.HopperSim``: N MjData
   stepped by a thread pool), random actions;
2. gymnasium's ``SyncVectorEnv`` of Hopper-v5, random actions (the peer);
3. one env at a time through ``gymnasium.make`` (the raw simulator as most
   code uses it);
4. expert PPO training (``pomil experts hopper``: rollouts + updates);
5. InfoGAIL-POMDP training on the shipped demonstrations with the Hopper
   defaults of ``pomil reproduce hopper`` (everything included: rollout,
   critic, posterior, PPO with its BC term; warm start and policy warm-up off
   so that only the loop is timed);
6. with ``--rollout-threads 1,0``: item 5 once per setting of the
   ``rollout_threads`` option (1, the default: the rollout's policy steps on one
   torch thread; 0: torch's own thread count), to show what it is worth; with
   ``--precision float32,bfloat16`` once per ``precision`` (bfloat16: the updates'
   network passes under ``torch.autocast``); with ``--belief-encoder gru,lstm,attention``
   once per belief encoder (the same loop, so their throughputs compare); with
   ``--variants '{"NAME": {FIELD: VALUE, ...}, ...}'`` once more per named set of
   ``AdversarialConfig`` values (the recipe's update work cut this way or that);
7. the peers, when the ``bench`` extra is installed (``pip install -e '.[bench]'``):
   Stable-Baselines3's PPO (MLP) and sb3-contrib's RecurrentPPO (LSTM) training on
   the same task (Hopper-v5, paper setting, positions only), ``--peer-envs`` envs in
   SB3's ``DummyVecEnv``, SB3's defaults except ``n_steps`` (so that a rollout is
   ``--peer-envs`` x 256 steps), ``--iterations`` rollouts each.  The last lines
   print each InfoGAIL-POMDP training row / the batched simulator (the target was at least
   50%) and / each peer (at least 3x SB3 PPO), from this one run.

    .venv/bin/python benchmarks/hopper_speed.py [--num-envs 256] [--iterations 3] [--device cpu]
        [--train-envs 256,1024,4096] [--rollout-threads 1,0] [--precision float32,bfloat16]
        [--belief-encoder gru,lstm,attention] [--variants JSON] [--peer-envs 8]

``--train-envs`` times InfoGAIL-POMDP training once per number of parallel
environments (for a GPU: many environments, large batches).
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import torch
from any_task_speed import batched_speed, gym_vector_speed  # benchmarks/ is on sys.path when run as a script

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.algos.expert import ExpertConfig, train_expert
from pomil.config import from_dict
from pomil.data import load_training_demos
from pomil.envs.locomotion import HOPPER_ID, HopperSim, hopper_kwargs, usable_cpus
from pomil.envs.wrappers import ObservationMask
from pomil.errors import PomilError


def gym_single_speed(steps: int) -> float:
    env = gym.make(HOPPER_ID, **hopper_kwargs("forward", "paper"))
    env.reset(seed=0)
    env.action_space.seed(0)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
    return steps / (time.perf_counter() - t0)


def peer_speed(kind: str, demos: str, n_envs: int, rollouts: int, device: str) -> float | None:
    """Env-steps/s of a Stable-Baselines3 learner's ``learn`` (rollouts and updates) on the
    demonstrations' task and observation mask; None without the ``bench`` extra."""
    try:
        from stable_baselines3 import PPO
        from stable_baselines3.common.env_util import make_vec_env
    except ImportError:
        return None
    data, env_id, env_kwargs = load_training_demos(demos)
    env = make_vec_env(env_id, n_envs=n_envs, seed=0, env_kwargs=env_kwargs, wrapper_class=ObservationMask,
                       wrapper_kwargs={"indices": data.metadata["observation_mask"]})
    if kind == "ppo":
        model = PPO("MlpPolicy", env, n_steps=256, seed=0, device=device)
    else:
        from sb3_contrib import RecurrentPPO
        model = RecurrentPPO("MlpLstmPolicy", env, n_steps=256, seed=0, device=device)
    steps = n_envs * 256 * rollouts
    t0 = time.perf_counter()
    model.learn(total_timesteps=steps)
    return steps / (time.perf_counter() - t0)


def last_row(run: Path) -> dict[str, str]:
    return list(csv.DictReader(open(run / "metrics.csv", newline="")))[-1]


def training_configs(args: argparse.Namespace, train_envs: list[int],
                     settings: list[tuple[int, str, str]]) -> list[tuple[str, AdversarialConfig]]:
    """(row label, config) of each timed InfoGAIL-POMDP loop (item 5): one per env count and setting,
    then one per ``--variants`` entry on the first of them; SystemExit with one line on a bad entry."""
    try:
        variants = json.loads(args.variants)
    except ValueError as err:
        raise SystemExit(f"--variants: {VARIANTS_EXPECTED} ({err})") from None
    if not isinstance(variants, dict) or not all(isinstance(v, dict) for v in variants.values()):
        raise SystemExit(f"--variants: {VARIANTS_EXPECTED} (got {args.variants[:60]})")
    runs = [(m, *setting, "", {}) for m in train_envs for setting in settings]
    runs += [(train_envs[0], *settings[0], name, over) for name, over in variants.items()]
    configs = []
    for m, threads, precision, encoder, name, over in runs:
        values = {"learner": "infogail-pomdp", "demos": args.demos, "iterations": args.iterations,
                  "warm_start_iterations": 0, "policy_warmup_iterations": 0, "eval_every": 0, "log_every": 1,
                  "progress": False, "device": args.device, "num_envs": m, "rollout_threads": threads,
                  "precision": precision, "belief_encoder": encoder, **over}
        try:
            cfg = from_dict(AdversarialConfig, values, f"--variants {name}" if name else "benchmark")
        except PomilError as err:
            raise SystemExit(f"--variants: {VARIANTS_EXPECTED} ({str(err).splitlines()[0]})") from None
        note = "".join(f", {label}{value}" for i, (label, value) in
                       enumerate((("rollout_threads ", threads), ("", precision), ("", encoder)))
                       if len({setting[i] for setting in settings}) > 1)  # what the rows differ in
        configs.append((f"InfoGAIL-POMDP training ({m} envs, all updates{note}{', ' + name if name else ''})", cfg))
    return configs


VARIANTS_EXPECTED = ('expected a JSON object of named AdversarialConfig values, e.g. '
                     '\'{"no GP": {"gradient_penalty": 0}}\'')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--num-envs", type=int, default=AdversarialConfig.num_envs,
                    help="environment copies for 1, 2 and 5")
    ap.add_argument("--iterations", type=int, default=3, help="training iterations timed for 4 and 5")
    ap.add_argument("--demos", default="data/hopper-paper.npz")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--train-envs", default="", help="comma-separated env counts for 5 (default: --num-envs)")
    ap.add_argument("--rollout-threads", default="1",
                    help="comma-separated rollout_threads settings for 5 (0: torch's own)")
    ap.add_argument("--precision", default="float32",
                    help="comma-separated precision settings for 5 (float32, bfloat16)")
    ap.add_argument("--belief-encoder", default="gru",
                    help="comma-separated belief encoders for 5 (gru, lstm, attention)")
    ap.add_argument("--variants", default="{}",
                    help='JSON {"name": {"field": value}}: 5 once more per named set of AdversarialConfig values')
    ap.add_argument("--peer-envs", type=int, default=8, help="environments of the SB3 peers (7; 0: skip them)")
    args = ap.parse_args()
    n = args.num_envs
    train_envs = [int(v) for v in args.train_envs.split(",")] if args.train_envs else [n]
    settings = [(int(t), p, e) for t in args.rollout_threads.split(",") for p in args.precision.split(",")
                for e in args.belief_encoder.split(",")]
    configs = training_configs(args, train_envs, settings)  # every one checked before anything is timed
    kw = hopper_kwargs("forward", "paper")
    gpu = torch.cuda.get_device_name() if args.device.startswith("cuda") else "none"
    print(f"torch {torch.__version__}, {usable_cpus()} usable CPU cores, {torch.get_num_threads()} torch threads, "
          f"device {args.device} ({gpu})")
    rows = [("batched simulator (HopperSim)", batched_speed(HopperSim(n, kw), 256)),
            (f"gymnasium SyncVectorEnv x{n}", gym_vector_speed(HOPPER_ID, kw, n, 64)),
            ("gymnasium.make, one env", gym_single_speed(4000))]
    share_lines: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        train_expert(ExpertConfig(out=f"{tmp}/expert", iterations=args.iterations, progress=False, log_every=1,
                                  device=args.device))
        rows.append(("expert PPO training (64 envs, MLP)",
                     float(last_row(Path(tmp) / "expert")["time/env_steps_per_s"])))
        for i, (what, cfg) in enumerate(configs):
            run = Path(tmp) / f"infogail-pomdp-{i}"
            train_adversarial(replace(cfg, out=str(run)))
            row = last_row(run)
            rows.append((what, float(row["time/env_steps_per_s"])))
            shares = {k.split('_', 1)[1]: float(v) for k, v in row.items() if k.startswith("time/share_")}
            share_lines.append(f"time shares, {what}: " + ", ".join(f"{k} {v:.0%}" for k, v in shares.items()))
    ours = [(what, v) for what, v in rows if what.startswith("InfoGAIL-POMDP training")]
    peers = []
    for kind, name in (("ppo", "SB3 PPO (MLP)"), ("recurrent", "sb3-contrib RecurrentPPO (LSTM)")):
        v = peer_speed(kind, args.demos, args.peer_envs, args.iterations, args.device) if args.peer_envs else None
        if v is not None:
            peers.append(name)
            rows.append((f"{name} training ({args.peer_envs} envs)", v))
    base = rows[1][1]
    print(f"{'what':70s} {'env-steps/s':>12s} {'vs SyncVectorEnv':>17s}")
    for name, v in rows:
        print(f"{name:70s} {v:12,.0f} {v / base:16.2f}x")
    print("\n".join(share_lines))
    if not peers and args.peer_envs:
        print("peers: not measured (pip install 'pomil[bench]', in a checkout pip install -e '.[bench]', "
              "for SB3 and sb3-contrib)")
    sim = rows[0][1]
    for what, v in ours:  # the speed targets' ratios, from this one run
        print(f"{what} / batched simulator: {v / sim:.0%}")
        for name in peers:
            peer = next(p for n, p in rows if n.startswith(name))
            print(f"{what} / {name}: {v / peer:.2f}x")


if __name__ == "__main__":
    main()
