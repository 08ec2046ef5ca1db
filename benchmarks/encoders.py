"""InfoGAIL-POMDP with each belief encoder (GRU, LSTM, attention): quality and training speed.

Every run is the library defaults (as ``pomil train infogail-pomdp --demos D``)
with ``belief_encoder`` set, on circles (scored by ``pomil.eval.circles``:
min purity, NMI, modes covered) and on Hopper's paper setting (scored by
``pomil.eval.tasks``: per-task progress and normalised return of the matched
code, deterministic).  Speed is the run's training env-steps per second
(metrics.csv ``time/env_steps_per_s``; periodic evaluation off).  Prints one
table per task, mean ± std over seeds, and writes them as JSON::

    .venv/bin/python benchmarks/encoders.py                       # 3 seeds, both tasks, 30 iterations: hours
    .venv/bin/python benchmarks/encoders.py --tasks circles --seeds 5 --encoders gru,attention
    .venv/bin/python benchmarks/encoders.py --tasks circles --out enc.json --resume   # continue a cut-off one
    .venv/bin/python benchmarks/encoders.py --iterations 1 --seeds 1 --episodes-per-code 2 \\
        --set num_envs=4 --set hidden_size=8 --set bc_init_iterations=2 --set posterior_init_iterations=1 \\
        --set critic_batch=4 --out /tmp/encoders.json            # a smoke run (seconds)
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.api import TrainedPolicy
from pomil.config import from_dict
from pomil.data import Demonstrations
from pomil.eval.circles import evaluate_circles
from pomil.eval.tasks import evaluate_tasks, reference_of
from pomil.training import write_json

ENCODERS = ("gru", "lstm", "attention")
TASKS = {"circles": "data/circles.npz", "hopper": "data/hopper-paper.npz"}
COLUMNS = {  # per task: the figures printed, in order
    "circles": ("min_purity", "nmi", "modes_covered", "env_steps_per_s", "wall_s"),
    "hopper": ("min_progress", "min_normalised_return", "env_steps_per_s", "wall_s"),
}


def train_one(task: str, encoder: str, seed: int, args: argparse.Namespace, episodes: int,
              run_dir: Path) -> dict[str, Any]:
    """One run and its scores (``episodes`` evaluation episodes per code)."""
    values = {**dict(kv.split("=", 1) for kv in args.set), "learner": "infogail-pomdp", "belief_encoder": encoder,
              "demos": args.demos[task], "out": str(run_dir), "seed": seed, "eval_every": 0, "progress": False}
    if args.iterations is not None:
        values["iterations"] = args.iterations
    cfg = from_dict(AdversarialConfig, values, source="benchmarks/encoders.py")
    t0 = time.perf_counter()
    ckpt = train_adversarial(cfg)
    wall = time.perf_counter() - t0
    with open(run_dir / "metrics.csv", newline="") as f:
        last = list(csv.DictReader(f))[-1]
    row: dict[str, Any] = {"seed": seed, "wall_s": wall, "env_steps_per_s": float(last["time/env_steps_per_s"])}
    policy = TrainedPolicy.load(ckpt)
    if task == "circles":
        m, _ = evaluate_circles(policy, episodes, seed=1000 + seed)
        row.update(min_purity=m["min_purity"], nmi=m["nmi"], modes_covered=float(m["modes_covered"]))
    else:
        reference = reference_of(Demonstrations.load(args.demos[task]).metadata, args.demos[task])
        m = evaluate_tasks(policy, reference, episodes, seed=1000 + seed)
        row.update(min_progress=m["min_progress"], min_normalised_return=m["min_normalised_return"],
                   tasks={t: {k: r[k] for k in ("code", "progress", "normalised_return")}
                          for t, r in m["tasks"].items()})
    return row


def table(task: str, results: dict[str, Any]) -> str:
    cols = COLUMNS[task]
    lines = [f"{task}: " + f"{'encoder':10s}" + "".join(f"{c:>24s}" for c in cols)]
    for encoder, r in results.items():
        cells = "".join(f"{r['summary'][c][0]:>15.2f} ± {r['summary'][c][1]:<6.2f}" for c in cols)
        lines.append(" " * (len(task) + 2) + f"{encoder:10s}{cells}  ({len(r['runs'])} seeds)")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--encoders", default=",".join(ENCODERS), help="comma-separated, from " + ", ".join(ENCODERS))
    ap.add_argument("--tasks", default=",".join(TASKS), help="comma-separated, from " + ", ".join(TASKS))
    ap.add_argument("--seeds", type=int, default=3, help="training seeds 0 .. seeds-1")
    ap.add_argument("--iterations", type=int, default=None,
                    help=f"adversarial iterations (default: the library's, {AdversarialConfig.iterations})")
    ap.add_argument("--episodes-per-code", type=int, default=None,
                    help="evaluation episodes per code (default: 100 on circles, 50 per task on hopper)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an AdversarialConfig field for every run (repeatable), e.g. num_envs=64")
    ap.add_argument("--circles-demos", default=TASKS["circles"])
    ap.add_argument("--hopper-demos", default=TASKS["hopper"])
    ap.add_argument("--out", default="results/encoders/metrics.json", help="JSON file")
    ap.add_argument("--resume", action="store_true",
                    help="keep the runs already in --out (a benchmark cut off part way) and train only the others")
    args = ap.parse_args()
    encoders, tasks = args.encoders.split(","), args.tasks.split(",")
    for name, chosen, allowed in (("encoder", encoders, ENCODERS), ("task", tasks, TASKS)):
        if not set(chosen) <= set(allowed):
            ap.error(f"unknown {name} in {chosen}; choose from {', '.join(allowed)}")
    args.demos = {"circles": args.circles_demos, "hopper": args.hopper_demos}
    results: dict[str, Any] = {"command": " ".join(["benchmarks/encoders.py", *sys.argv[1:]]), "seeds": args.seeds,
                               "tasks": {}}
    done: dict[tuple[str, str, int], dict[str, Any]] = {}
    if args.resume and Path(args.out).is_file():  # the runs an earlier (cut-off) benchmark wrote
        earlier = json.loads(Path(args.out).read_text())
        done = {(task, encoder, r["seed"]): r for task, per in earlier.get("tasks", {}).items()
                for encoder, e in per.items() for r in e.get("runs", [])}
        print(f"--resume: {len(done)} run(s) from {args.out} kept", flush=True)
        for task, per in earlier.get("tasks", {}).items():  # encoders and tasks not run now stay in the file
            for encoder, e in per.items():
                results["tasks"].setdefault(task, {})[encoder] = {"runs": e.get("runs", [])}
    with tempfile.TemporaryDirectory() as tmp:
        for task in tasks:
            per_encoder: dict[str, Any] = {}
            episodes = args.episodes_per_code or (100 if task == "circles" else 50)
            for encoder in encoders:
                runs = []
                for seed in range(args.seeds):
                    row = done.get((task, encoder, seed)) or train_one(task, encoder, seed, args, episodes,
                                                                        Path(tmp) / task / encoder / str(seed))
                    runs.append(row)
                    results["tasks"].setdefault(task, {})[encoder] = {"runs": runs}
                    write_json(Path(args.out), {**results, "partial": True})  # a cut-off benchmark keeps its runs
                    print(f"{task} {encoder} seed {seed}: " + ", ".join(f"{c} {row[c]:.2f}" for c in COLUMNS[task]),
                          flush=True)
                per_encoder[encoder] = {"runs": runs}
            results["tasks"][task] = {**results["tasks"].get(task, {}), **per_encoder}
    for task, per_encoder in results["tasks"].items():
        for r in per_encoder.values():
            r["summary"] = {c: [float(np.mean([x[c] for x in r["runs"]])), float(np.std([x[c] for x in r["runs"]]))]
                            for c in COLUMNS[task]}
    print()
    for task, per_encoder in results["tasks"].items():
        print(table(task, per_encoder))
    print("\nmean ± std over each row's seeds; env_steps_per_s: the run's training throughput (metrics.csv)")
    write_json(Path(args.out), results)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
