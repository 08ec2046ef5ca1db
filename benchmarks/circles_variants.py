"""InfoGAIL-POMDP on circles with one setting varied, over several seeds.

Everything else is the library defaults, as in ``pomil reproduce circles``.
Prints the mode metrics and training throughput per value and writes them
as JSON.  Used to choose defaults:

    .venv/bin/python benchmarks/circles_variants.py --vary update_mode=sequence,window
    .venv/bin/python benchmarks/circles_variants.py --vary shared_value_encoder=false,true

(``--seeds 3 --iterations 30`` by default; output
``results/circles/variants-KEY.json``.)
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.api import TrainedPolicy
from pomil.config import from_dict
from pomil.eval.circles import evaluate_circles
from pomil.reproduce import CirclesReproConfig, adversarial_config
from pomil.training import write_json

KEYS = ("nmi", "min_purity", "none_share", "wall_s", "env_steps_per_s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vary", required=True, help="KEY=V1,V2,...: an AdversarialConfig field and its values")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=AdversarialConfig.iterations)
    ap.add_argument("--demos", default="data/circles.npz")
    ap.add_argument("--out", default=None, help="JSON file (default results/circles/variants-KEY.json)")
    args = ap.parse_args()
    key, _, values = args.vary.partition("=")
    repro = CirclesReproConfig(demos=args.demos, adversarial_iterations=args.iterations, progress=False)
    results: dict = {"command": " ".join(["benchmarks/circles_variants.py", *sys.argv[1:]]), "vary": key, "values": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for value in values.split(","):
            runs = []
            for seed in range(args.seeds):
                base = adversarial_config(repro, "infogail-pomdp", seed, Path(tmp) / value / str(seed))
                cfg = replace(from_dict(AdversarialConfig, {**base.__dict__, key: value}, source="--vary"),
                              eval_every=0)
                t0 = time.perf_counter()
                ckpt = train_adversarial(cfg)
                wall = time.perf_counter() - t0
                with open(Path(cfg.out) / "metrics.csv", newline="") as f:
                    last = list(csv.DictReader(f))[-1]
                m, _ = evaluate_circles(TrainedPolicy.load(ckpt), 100, seed=1000 + seed)
                runs.append({"seed": seed, "nmi": m["nmi"], "min_purity": m["min_purity"],
                             "none_share": m["overall_none_share"],
                             "wall_s": wall, "env_steps_per_s": float(last["time/env_steps_per_s"])})
                print(f"{key}={value} seed {seed}: NMI {m['nmi']:.2f} min purity {m['min_purity']:.2f} "
                      f"none {m['overall_none_share']:.2f} {wall:.0f} s", flush=True)
            results["values"][value] = {"runs": runs,
                                        **{k: [float(np.mean([r[k] for r in runs])),
                                               float(np.std([r[k] for r in runs]))]
                                                         for k in KEYS}}
    print(f"\n{key:22s} {'NMI':>12s} {'min purity':>12s} {'none share':>12s} {'env-steps/s':>12s}")
    for value, r in results["values"].items():
        f = lambda k, r=r: f"{r[k][0]:.2f} ± {r[k][1]:.2f}"  # noqa: E731
        print(f"{value:22s} {f('nmi'):>12s} {f('min_purity'):>12s} {f('none_share'):>12s} "
              f"{r['env_steps_per_s'][0]:12,.0f}")
    write_json(Path(args.out or f"results/circles/variants-{key}.json"), results)


if __name__ == "__main__":
    main()
