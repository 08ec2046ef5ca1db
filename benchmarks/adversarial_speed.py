"""Training throughput of each adversarial learner on circles, measured in one run.

Runs every learner for a few iterations with the library defaults, as in
``pomil reproduce circles`` (BC warm start off: only the loop is timed) and prints
env-steps/s (everything included: rollout, critic, posterior, PPO) and the
share of time spent in each phase, read from the run's own timers.

    .venv/bin/python benchmarks/adversarial_speed.py [--iterations 10] [--demos data/circles.npz]
"""

from __future__ import annotations

import argparse
import csv
import tempfile
from dataclasses import replace
from pathlib import Path

from pomil.algos.adversarial import train_adversarial
from pomil.demos import record_circles_demos
from pomil.envs.circles import make_spec
from pomil.learners import ADVERSARIAL, LEARNERS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--demos", default=None, help="demonstrations (default: record 400 circles episodes)")
    ap.add_argument("--update-mode", default="sequence", choices=["sequence", "window"])
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        demos = args.demos
        if demos is None:
            demos = str(Path(tmp) / "circles.npz")
            record_circles_demos(make_spec(), 400, seed=0).save(demos)
        print(f"{'learner':16s} {'env-steps/s':>12s} {'rollout':>8s} {'critic':>8s} {'posterior':>9s} {'ppo':>6s}")
        for learner in ADVERSARIAL:
            out = Path(tmp) / learner
            cfg = LEARNERS[learner].make_config({"demos": demos, "iterations": args.iterations, "out": str(out),
                                                 "progress": False})
            train_adversarial(replace(cfg, eval_every=0, warm_start_iterations=0, update_mode=args.update_mode))
            with open(out / "metrics.csv", newline="") as f:
                last = list(csv.DictReader(f))[-1]
            share = lambda k, last=last: float(last[f"time/share_{k}"])  # noqa: E731
            print(f"{learner:16s} {float(last['time/env_steps_per_s']):12,.0f} {share('rollout'):8.0%} "
                  f"{share('critic'):8.0%} "
                  f"{share('posterior'):9.0%} {share('ppo'):6.0%}")


if __name__ == "__main__":
    main()
