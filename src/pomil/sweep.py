"""``pomil sweep``: one training config over seeds and a grid of settings, in parallel on Ray.

The sweep config is a JSON object: ``"learner"`` (bc, gail, infogail or
infogail-pomdp) and that learner's config keys (``demos`` at least).  Each
grid point is a *setting*; each (setting, seed) a run in
``OUT/<setting>/seed<k>/`` with its checkpoint, logs and ``result.json``
(the final evaluation: mode metrics on circles, per-task figures on
multi-task demonstrations).  A run whose ``result.json`` exists is finished
and is not run again; one with a checkpoint but no ``result.json`` (its
worker died, and Ray retries it, or the sweep was stopped) resumes from
its checkpoint.  The sweep writes ``OUT/sweep.json`` (every run, failed
ones with their error), ``OUT/table.md`` (mean +- std over seeds per setting)
and ``OUT/figure.png`` (the matching reproduction's figure: trajectories
coloured by code on circles, normalised-return curves on tasks).
"""

from __future__ import annotations

import itertools
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pomil.config import check_fields, load_config_file, option, parse_kwargs
from pomil.data import atomic_write
from pomil.errors import PomilError
from pomil.learners import LEARNERS
from pomil.learners import learner as learner_named
from pomil.training import write_json


@dataclass(frozen=True)
class SweepConfig:
    out: str = option("runs/sweep",
                      "sweep directory: one folder per setting and seed, sweep.json, table.md, figure.png")
    seeds: int = option(3, "training seeds per setting (0 .. seeds-1)", within="[1, inf)")
    ray: bool = option(True,
                       "run on Ray (a local Ray started in-process unless --address); --no-ray: --jobs at a time "
                       "in local worker processes")
    jobs: int = option(0, "with --no-ray: runs at a time, each in its own process on cpus_per_run torch threads (0: "
                          "one per cpus_per_run usable CPU cores; 1: one after another in this process)",
                       within="[0, inf)")
    address: str = option("", "address of an existing Ray cluster (paths must be on storage every node sees)")
    cpus_per_run: float = option(1.0, "CPUs Ray reserves for each run (also its torch threads)", within="(0, inf)")
    episodes_per_code: int = option(50, "evaluation rollouts per latent code (and task) at the end of each run",
                                    within="[1, inf)")

    def __post_init__(self) -> None:
        check_fields(self)


def parse_grid(entries: list[str]) -> dict[str, list[Any]]:
    """``["lr=1e-4,2e-4", "mi_weight=5,10"]`` -> {"lr": [1e-4, 2e-4], "mi_weight": [5, 10]}."""
    grid: dict[str, list[Any]] = {}
    for entry in entries:
        key, sep, values = entry.partition("=")
        if not sep or not values.strip():
            raise PomilError(f"--grid: expected key=v1,v2,..., got {entry!r}")
        grid[key.strip().replace("-", "_")] = [parse_kwargs([f"v={v.strip()}"])["v"] for v in values.split(",")]
    return grid


def setting_name(values: dict[str, Any]) -> str:
    return ",".join(f"{k}={v}" for k, v in values.items()) or "base"


def run_one(learner: str, values: dict[str, Any], run_dir: str, seed: int, episodes_per_code: int) -> dict[str, Any]:
    """Train one run and evaluate it; writes ``run_dir/result.json`` last (the run's "finished" mark)."""
    from pomil.api import TrainedPolicy
    from pomil.data import Demonstrations
    from pomil.envs import evaluation_kind

    trainer = LEARNERS[learner]
    cfg = trainer.make_config({**values, "out": run_dir, "seed": seed, "progress": False},
                              source=f"sweep run {run_dir}")
    t0 = time.perf_counter()
    # A checkpoint without result.json is a run whose worker died (Ray retries it) or that
    # was interrupted: continue it from its last checkpoint instead of starting over.
    resume = (Path(run_dir) / "checkpoint.pt").exists()
    if resume:
        print(f"{run_dir}: resuming from its checkpoint", file=sys.stderr, flush=True)
    ckpt = trainer.train(cfg, resume=resume)
    wall = time.perf_counter() - t0
    policy = TrainedPolicy.load(ckpt)
    result: dict[str, Any] = {"learner": learner, "seed": seed, "settings": values, "wall_s": wall,
                              "checkpoint": str(ckpt)}
    demos = Demonstrations.load(cfg.demos)
    kind = evaluation_kind(policy.env.get("id", ""), demos.metadata)
    if kind == "circles" and policy.code_dim:  # continuous codes: code against fitted radius
        from pomil.eval.circles import evaluate_code_radius

        metrics, _ = evaluate_code_radius(policy, episodes_per_value=episodes_per_code, seed=1000 + seed)
        result.update(kind="code-radius", metrics=metrics)
    elif kind == "circles":
        from pomil.eval.circles import evaluate_circles

        metrics, roll = evaluate_circles(policy, episodes_per_code, seed=1000 + seed)
        atomic_write(Path(run_dir) / "rollouts.npz",
                     lambda f: np.savez_compressed(f, positions=roll["positions"], codes=roll["codes"]))
        result.update(kind="circles", metrics=metrics)
    elif kind == "tasks":
        from pomil.eval.tasks import evaluate_tasks, reference_of
        from pomil.reproduce import _curve

        metrics = evaluate_tasks(policy, reference_of(demos.metadata, cfg.demos), episodes_per_code, seed=1000 + seed)
        result.update(kind="tasks", metrics=metrics, curve=_curve(Path(run_dir), list(demos.metadata["tasks"])))
    else:
        result.update(kind="none", metrics={})
    write_json(Path(run_dir) / "result.json", result)
    return result


def _sweep_plan(config_path: str, grid_entries: list[str]) -> tuple[str, dict[str, Any], dict[str, list], list[dict]]:
    """(learner, base config, grid, settings) of a sweep file and its ``--grid`` entries, every setting checked
    to make a valid config before anything runs."""
    base = load_config_file(config_path)
    learner = str(base.pop("learner", "infogail-pomdp"))
    trainer = learner_named(learner, f"{config_path}: 'learner'")
    for key in ("out", "seed"):
        if key in base:
            raise PomilError(f"{config_path}: '{key}' is set by the sweep for each run; remove it")
    if not base.get("demos"):
        raise PomilError(f"{config_path}: 'demos' is required (the demonstrations every run imitates)")
    base["demos"] = str(Path(base["demos"]).resolve())
    grid = parse_grid(grid_entries)
    settings = [dict(zip(grid, combo, strict=True)) for combo in itertools.product(*grid.values())] or [{}]
    for s in settings:
        trainer.make_config({**base, **s}, source=f"{config_path} + {setting_name(s)}")
    return learner, base, grid, settings


def sweep(cfg: SweepConfig, config_path: str, grid_entries: list[str]) -> dict[str, Any]:
    from pomil.parallel import run_jobs, usable_cpus

    learner, base, grid, settings = _sweep_plan(config_path, grid_entries)
    out = Path(cfg.out).resolve()
    t_start = time.perf_counter()
    jobs, names, finished = [], [], {}
    for s in settings:
        for seed in range(cfg.seeds):
            run_dir = out / setting_name(s) / f"seed{seed}"
            name = f"{setting_name(s)} seed {seed}"
            done = run_dir / "result.json"
            if done.exists():
                finished[name] = json.loads(done.read_text())
                continue
            jobs.append((learner, {**base, **s}, str(run_dir), seed, cfg.episodes_per_code))
            names.append(name)
    workers = 1 if cfg.ray else max(1, min(cfg.jobs or int(usable_cpus() // cfg.cpus_per_run), len(jobs)))
    where = ("on Ray" + (f" at {cfg.address}" if cfg.address else " (local)") if cfg.ray else
             f"{workers} at a time in local worker processes" if workers > 1 else "one after another")
    print(f"sweep: {len(settings)} setting(s) x {cfg.seeds} seed(s) = {len(settings) * cfg.seeds} runs; "
          f"{len(finished)} finished before, skipped; {len(jobs)} to run {where}", flush=True)

    def report(r, n, total) -> None:
        state = f"done in {r.wall_s:.0f} s" if r.ok else f"FAILED: {r.error}"
        print(f"[{n}/{total}] {r.name}: {state}", flush=True)

    results = run_jobs(run_one, jobs, names, ray=cfg.ray, address=cfg.address or None,
                       cpus_per_job=cfg.cpus_per_run, on_done=report, workers=workers) if jobs else []
    runs = {**{n: {"status": "skipped (finished before)", **r} for n, r in finished.items()},
            **{r.name: ({"status": "done", **r.value} if r.ok else {"status": "failed", "error": r.error,
                                                                    "details": r.details[-4000:]})
               for r in results}}
    failed = [n for n, r in runs.items() if r["status"] == "failed"]
    summary = {setting_name(s): _summarise([runs[f"{setting_name(s)} seed {k}"] for k in range(cfg.seeds)
                                            if runs[f"{setting_name(s)} seed {k}"]["status"] != "failed"])
               for s in settings}
    report_data = {"config": str(config_path), "learner": learner, "base": base, "grid": grid, "seeds": cfg.seeds,
                   "ray": cfg.ray, "address": cfg.address, "wall_time_s": time.perf_counter() - t_start,
                   "runs": runs, "failed": failed, "summary": summary}
    write_json(out / "sweep.json", report_data)
    table = sweep_table(report_data)
    atomic_write(out / "table.md", lambda f: f.write(table.encode()))
    _figure(report_data, out / "figure.png")
    print(table)
    print(f"wrote {out}/sweep.json, table.md, figure.png in {report_data['wall_time_s']:.0f} s")
    if failed:
        print(f"sweep: {len(failed)} run(s) FAILED: " + "; ".join(f"{n}: {runs[n]['error']}" for n in failed),
              flush=True)
    return report_data


def _summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    from pomil.reproduce import summarise, task_summary

    if not runs:
        return {"kind": "none", "seeds": 0}
    kind = runs[0]["kind"]
    if kind == "circles":
        return {"kind": kind, "seeds": len(runs), **summarise([r["metrics"] for r in runs])}
    if kind == "code-radius":
        from pomil.reproduce import CONTINUOUS_SUCCESS

        rho = np.abs([r["metrics"]["spearman"] for r in runs])
        return {"kind": kind, "seeds": len(runs), "abs_spearman": [float(rho.mean()), float(rho.std())],
                "successes": int((rho >= CONTINUOUS_SUCCESS).sum())}
    if kind == "tasks":
        tasks = list(runs[0]["metrics"]["tasks"])
        return {"kind": kind, "seeds": len(runs), "tasks": task_summary([r["metrics"] for r in runs], tasks)}
    return {"kind": kind, "seeds": len(runs)}


def sweep_table(data: dict[str, Any]) -> str:
    from pomil.reproduce import METRICS, SUMMARY_KEYS

    lines: list[str] = []
    kinds = {s["kind"] for s in data["summary"].values() if s["seeds"]}
    if "circles" in kinds:
        lines += ["| setting | seeds | " + " | ".join(SUMMARY_KEYS) + " |", "|---|---|" + "---|" * len(SUMMARY_KEYS)]
        for name, s in data["summary"].items():
            cells = [f"{s[k][0]:.2f} ± {s[k][1]:.2f}" if s["seeds"] else "-" for k in SUMMARY_KEYS]
            lines.append(f"| {name} | {s['seeds']} | " + " | ".join(cells) + " |")
    elif "code-radius" in kinds:
        lines += ["| setting | seeds | abs Spearman(code, radius) | seeds with abs Spearman >= 0.9 |",
                  "|---|---|---|---|"]
        for name, s in data["summary"].items():
            cells = ([f"{s['abs_spearman'][0]:.3f} ± {s['abs_spearman'][1]:.3f}", str(s["successes"])] if s["seeds"]
                     else ["-", "-"])
            lines.append(f"| {name} | {s['seeds']} | " + " | ".join(cells) + " |")
    elif "tasks" in kinds:
        tasks = next(list(s["tasks"]) for s in data["summary"].values() if s["seeds"])
        lines += ["| setting | seeds | " + " | ".join(f"{t}: {m}" for t in tasks for m in METRICS) + " |",
                  "|---|---|" + "---|" * (len(tasks) * len(METRICS))]
        for name, s in data["summary"].items():
            cells = [f"{s['tasks'][t][m][0]:.2f} ± {s['tasks'][t][m][1]:.2f}" if s["seeds"] else "-"
                     for t in tasks for m in METRICS]
            lines.append(f"| {name} | {s['seeds']} | " + " | ".join(cells) + " |")
    else:
        lines += ["| setting | seeds |", "|---|---|"] + [f"| {n} | {s['seeds']} |" for n, s in data["summary"].items()]
    failed = f" ({', '.join(data['failed'])})" if data["failed"] else ""
    lines += ["", f"mean ± std over the seeds that finished ({data['learner']}, {data['seeds']} seed(s) per setting); "
              f"failed runs: {len(data['failed'])}{failed}."]
    return "\n".join(lines) + "\n"


def _figure(data: dict[str, Any], path: Path) -> None:
    """Circles: first seed's trajectories per setting, coloured by code.  Tasks: curves per setting."""
    ok = {n: r for n, r in data["runs"].items() if r["status"] != "failed"}
    kinds = {r["kind"] for r in ok.values()}
    if kinds == {"circles"}:
        from pomil.eval.plots import figure1

        panels = []
        for setting in data["summary"]:
            first = next((r for n, r in ok.items() if n.startswith(f"{setting} seed")), None)
            if first is not None:
                with np.load(Path(first["checkpoint"]).parent / "rollouts.npz", allow_pickle=False) as roll:
                    panels.append((f"{setting} (seed {first['seed']})", roll["positions"], roll["codes"], "code"))
        if panels:
            figure1(panels, path)
    elif kinds == {"tasks"}:
        from pomil.data import Demonstrations
        from pomil.eval.plots import learning_curves
        from pomil.eval.tasks import reference_of

        demos = Demonstrations.load(data["base"]["demos"])
        learners = {s: {"curves": [r["curve"] for n, r in ok.items() if n.startswith(f"{s} seed")],
                        "summary": v["tasks"]}
                    for s, v in data["summary"].items() if v["seeds"]}
        learning_curves({"tasks": list(demos.metadata["tasks"]), "learners": learners,
                         "env_id": demos.metadata["env_id"],
                         "setting": demos.metadata.get("setting", ""), "reference": reference_of(demos.metadata)}, path)
