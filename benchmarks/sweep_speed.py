"""Wall time of N seeds as one Ray sweep vs one after another, measured in one run on this machine.

Runs ``pomil sweep`` twice on the same config (InfoGAIL-POMDP on circles with
the library defaults): once on a local Ray (each run 1 CPU, as many at a
time as there are cores) and once with ``--no-ray`` (one run at a time, torch
using every core).  Prints both wall times, the ratio, and whether the two
sweeps' tables agree.

    .venv/bin/python benchmarks/sweep_speed.py [--seeds 4] [--iterations 30]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pomil.algos.adversarial import AdversarialConfig
from pomil.demos import record_circles_demos
from pomil.envs.circles import make_spec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=AdversarialConfig.iterations)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        demos = Path(tmp) / "circles.npz"
        record_circles_demos(make_spec(), 400, seed=0).save(demos)
        config = Path(tmp) / "sweep.json"
        config.write_text(json.dumps({"learner": "infogail-pomdp", "demos": str(demos), "iterations": args.iterations,
                                      "eval_every": 0}))
        walls, summaries = {}, {}
        for mode in ("--ray", "--no-ray"):
            out = Path(tmp) / mode.strip("-")
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "pomil.cli", "sweep", str(config), "--seeds", str(args.seeds), mode,
                            "--out", str(out)], check=True, stdout=subprocess.DEVNULL)
            walls[mode] = time.perf_counter() - t0
            summaries[mode] = json.loads((out / "metrics.json").read_text())["rows"]["base"]["summary"]
    print(f"{args.seeds} seeds x InfoGAIL-POMDP on circles, {args.iterations} iterations each")
    print(f"Ray sweep (local, 1 CPU per run):  {walls['--ray']:7.1f} s")
    print(f"one after another (--no-ray):       {walls['--no-ray']:7.1f} s")
    print(f"speed-up: {walls['--no-ray'] / walls['--ray']:.2f}x")
    for key in ("nmi", "mean_purity"):
        print(f"{key}: ray {summaries['--ray'][key][0]:.3f} ± {summaries['--ray'][key][1]:.3f}, "
              f"sequential {summaries['--no-ray'][key][0]:.3f} ± {summaries['--no-ray'][key][1]:.3f}")


if __name__ == "__main__":
    main()
