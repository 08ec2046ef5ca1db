"""``--num-codes auto`` over seeds: how often the search picks the true number of modes.

Runs only the search of ``pomil train infogail-pomdp --num-codes auto --demos D --seed S``
(:func:`pomil.algos.adversarial.auto_num_codes`, the library defaults otherwise) for each
dataset and seed, and prints per dataset the chosen K per seed, the share of seeds that
chose the true K, each K's mean held-out score and the search's wall time.  The datasets
are recorded into ``--data`` when missing: the ``two`` and ``four`` circle presets
(``pomil demos circles``, 400 episodes) and Hopper Forward/Backward in the paper's setting
(``data/hopper-paper.npz``, the committed demonstrations); ``hopper-speed`` (three target
speeds, true K 3) reads ``runs/demos/hopper-speed.npz``, which ``bash scripts/hopper_speed.sh`` records::

    .venv/bin/python benchmarks/num_codes_seeds.py --out benchmarks/results/num_codes_seeds.json   # 10 seeds: ~2.5 h
    .venv/bin/python benchmarks/num_codes_seeds.py --datasets two --seeds 1 --set num_codes_max=2 \\
        --set num_codes_search_iterations=2 --out /tmp/nc.json                                       # a smoke run
    .venv/bin/python benchmarks/num_codes_seeds.py --rechoose benchmarks/results/num_codes_seeds.json  # seconds
    .venv/bin/python benchmarks/num_codes_seeds.py --datasets hopper-speed,three-radii,five --seeds 5 \\
        --out /tmp/heldout.json                               # sets the criterion was not tuned on: ~2.5 h

``--rechoose`` runs no search: it takes the held-out scores recorded in JSONs this script
wrote (one dataset's runs from several joined in seed order) and chooses K again by today's
criterion (``choose_num_codes`` with the config's ``num_codes_tolerance`` and
``num_codes_min_gain``, or those given with ``--set``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from pomil.algos.adversarial import AdversarialConfig, auto_num_codes
from pomil.algos.num_codes import choose_num_codes
from pomil.config import from_dict, parse_kwargs
from pomil.data import load_training_demos
from pomil.envs import executed_actions_fn
from pomil.envs.circles import Circle, CirclesSpec, circles_preset
from pomil.envs.wrappers import parse_mask
from pomil.training import write_json

TRUE_K = {"two": 2, "four": 4, "hopper": 2, "hopper-speed": 3, "three-radii": 3, "five": 5}
SPEED_DEMOS = Path("runs/demos/hopper-speed.npz")


def circle_set(name: str) -> tuple[Circle, ...]:
    """The circles of ``name``: a preset (``two``, ``four``) or one of two sets that the criterion was
    not tuned on: ``three-radii`` (one tangent and direction, radii 3, 5 and 8: modes told apart by
    curvature only) and ``five`` (radius 5, tangents 72 degrees apart, directions alternating)."""
    if name == "three-radii":
        return tuple(Circle.through_origin(90.0, r, 1) for r in (3.0, 5.0, 8.0))
    if name == "five":
        return tuple(Circle.through_origin(90.0 + 72.0 * i, 5.0, 1 if i % 2 == 0 else -1) for i in range(5))
    return circles_preset(name)


def dataset(name: str, data_dir: Path) -> Path:
    """The demonstrations of ``name``, recorded when missing (circles: 100 episodes per mode for the
    sets beyond the presets, 400 in all for the presets)."""
    if name == "hopper":
        return Path("data/hopper-paper.npz")
    if name == "hopper-speed":
        if not SPEED_DEMOS.exists():
            sys.exit(f"{SPEED_DEMOS}: missing; scripts/hopper_speed.sh records it (its demos record and merge steps)")
        return SPEED_DEMOS
    path = data_dir / f"circles-{name}.npz"
    if not path.exists():
        from pomil.demos import record_circles_demos

        circles = circle_set(name)
        data_dir.mkdir(parents=True, exist_ok=True)
        episodes = 400 if name in ("two", "four") else 100 * len(circles)
        record_circles_demos(CirclesSpec(circles), episodes=episodes, seed=0).save(path)
    return path


def search(path: Path, seed: int, overrides: dict[str, str]) -> dict[str, Any]:
    """One search's choice, scores and wall time."""
    cfg = from_dict(AdversarialConfig, {**overrides, "demos": str(path), "seed": seed, "num_codes": "auto"},
                    source="benchmarks/num_codes_seeds.py")
    demos, env_id, env_kwargs = load_training_demos(cfg.demos, parse_kwargs(cfg.env_kwargs),
                                                    parse_mask(cfg.observation_mask))
    t0 = time.perf_counter()
    choice = auto_num_codes(cfg, demos.padded("cpu"), executed_actions_fn(env_id, env_kwargs))
    return {"seed": seed, "chosen": choice.chosen, "scores": {str(k): v for k, v in choice.scores.items()},
            "wall_s": time.perf_counter() - t0, "heldout_episodes": choice.record().get("num_codes_heldout_episodes")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", default="two,four,hopper", help="comma-separated: " + ", ".join(TRUE_K))
    ap.add_argument("--seeds", type=int, default=10, help="seeds per dataset: first-seed .. first-seed+seeds-1")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--data", default="runs/num_codes_seeds", help="where the circle demonstrations are recorded")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an AdversarialConfig setting (repeatable)")
    ap.add_argument("--out", default="", help="JSON of every search")
    ap.add_argument("--rechoose", nargs="+", default=[], metavar="JSON",
                    help="no search: choose K again from the scores recorded in these JSONs (written by this script; "
                         "the runs of one dataset joined in seed order)")
    args = ap.parse_args()
    overrides = dict(kv.split("=", 1) for kv in args.set)
    if args.rechoose:
        results = rechoose(joined([json.loads(Path(p).read_text())["datasets"] for p in args.rechoose]), overrides)
    else:
        results = run_searches(args, overrides)
    print("| demonstrations | true K | chosen K per seed | true K chosen | search wall s (mean) |")
    print("|---|---|---|---|---|")
    for name, r in results.items():
        chosen = [x["chosen"] for x in r["runs"]]
        hits = sum(k == r["true_k"] for k in chosen)
        print(f"| {name} | {r['true_k']} | {', '.join(map(str, chosen))} | {hits} / {len(chosen)} | "
              f"{np.mean([x['wall_s'] for x in r['runs']]):.0f} |")
    if args.out:
        write_json(Path(args.out), {"settings": overrides, "datasets": results})


def run_searches(args: argparse.Namespace, overrides: dict[str, str]) -> dict[str, Any]:
    names = [n for n in args.datasets.split(",") if n]
    unknown = [n for n in names if n not in TRUE_K]
    if unknown:
        sys.exit(f"--datasets: unknown {unknown}; expected some of {list(TRUE_K)}")
    results: dict[str, Any] = {}
    for name in names:
        path = dataset(name, Path(args.data))
        rows = []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            rows.append(search(path, seed, overrides))
            print(f"{name} seed {seed}: K {rows[-1]['chosen']} ({rows[-1]['wall_s']:.0f} s)", file=sys.stderr)
        results[name] = {"true_k": TRUE_K[name], "demos": str(path), "runs": rows}
    return results


def joined(recorded: list[dict[str, Any]]) -> dict[str, Any]:
    """The datasets of several recorded JSONs as one: each dataset's runs in seed order; a seed recorded
    twice, or a dataset recorded with two different demonstrations, exits with a message."""
    out: dict[str, Any] = {}
    for datasets in recorded:
        for name, r in datasets.items():
            if name in out and out[name]["demos"] != r["demos"]:
                sys.exit(f"--rechoose: dataset {name} was recorded from {out[name]['demos']} and {r['demos']}")
            out.setdefault(name, {**r, "runs": []})["runs"].extend(r["runs"])
    for name, r in out.items():
        seeds = [run["seed"] for run in r["runs"]]
        if len(set(seeds)) != len(seeds):
            sys.exit(f"--rechoose: dataset {name} has seed(s) recorded twice: {sorted(seeds)}")
        r["runs"].sort(key=lambda run: run["seed"])
    return out


def rechoose(datasets: dict[str, Any], overrides: dict[str, str]) -> dict[str, Any]:
    """``datasets`` with each run's K chosen again from its recorded scores by today's criterion."""
    cfg = from_dict(AdversarialConfig, {**overrides, "demos": "x.npz"}, source="--set")
    return {name: {**r, "runs": [{**run, "chosen": choose_num_codes({int(k): v for k, v in run["scores"].items()},
                                                                    cfg.num_codes_tolerance, cfg.num_codes_min_gain)}
                                 for run in r["runs"]]}
            for name, r in datasets.items()}


if __name__ == "__main__":
    main()
