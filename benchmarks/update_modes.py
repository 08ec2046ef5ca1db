"""InfoGAIL-POMDP on circles with each recurrent-update mode, over several seeds.

``sequence``: PPO, critic and posterior unroll whole episodes from their
stored initial hidden state.  ``window``: the paper's bootstrapped random
updates (random windows, zero initial state).  Everything else is the
circles recipe of ``pomil reproduce circles``.  Prints the mode metrics and
training throughput per mode and writes them to ``--out`` as JSON.

    .venv/bin/python benchmarks/update_modes.py [--seeds 3] [--iterations 60] [--out results/circles/update_modes.json]
"""

from __future__ import annotations

import argparse
import csv
import tempfile
from dataclasses import replace
import time
from pathlib import Path

import numpy as np

from pomil.algos.adversarial import train_adversarial
from pomil.api import TrainedPolicy
from pomil.eval.rollout import evaluate_circles
from pomil.reproduce import CirclesReproConfig, adversarial_config
from pomil.training import write_json


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--demos", default="data/circles.npz")
    ap.add_argument("--out", default="results/circles/update_modes.json")
    args = ap.parse_args()
    repro = CirclesReproConfig(demos=args.demos, adversarial_iterations=args.iterations, progress=False)
    results: dict = {"command": "benchmarks/update_modes.py " + f"--seeds {args.seeds} --iterations {args.iterations}", "modes": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("sequence", "window"):
            runs = []
            for seed in range(args.seeds):
                cfg = adversarial_config(repro, "infogail-pomdp", seed, Path(tmp) / mode / str(seed))
                cfg = replace(cfg, update_mode=mode, eval_every=0)
                t0 = time.perf_counter()
                ckpt = train_adversarial(cfg)
                wall = time.perf_counter() - t0
                last = list(csv.DictReader(open(Path(cfg.out) / "metrics.csv")))[-1]
                m, _ = evaluate_circles(TrainedPolicy.load(ckpt), 100, seed=1000 + seed)
                runs.append({"seed": seed, "nmi": m["nmi"], "mean_purity": m["mean_purity"], "none_share": m["overall_none_share"],
                             "wall_s": wall, "env_steps_per_s": float(last["time/env_steps_per_s"])})
                print(f"{mode:8s} seed {seed}: NMI {m['nmi']:.2f} purity {m['mean_purity']:.2f} none {m['overall_none_share']:.2f} "
                      f"{wall:.0f} s", flush=True)
            results["modes"][mode] = {"runs": runs, **{k: [float(np.mean([r[k] for r in runs])), float(np.std([r[k] for r in runs]))]
                                                       for k in ("nmi", "mean_purity", "none_share", "wall_s", "env_steps_per_s")}}
    print(f"\n{'mode':10s} {'NMI':>12s} {'purity':>12s} {'none share':>12s} {'env-steps/s':>12s}")
    for mode, r in results["modes"].items():
        f = lambda k: f"{r[k][0]:.2f} ± {r[k][1]:.2f}"  # noqa: E731
        print(f"{mode:10s} {f('nmi'):>12s} {f('mean_purity'):>12s} {f('none_share'):>12s} {r['env_steps_per_s'][0]:12,.0f}")
    write_json(Path(args.out), results)


if __name__ == "__main__":
    main()
