"""Experiments: one spec file, runs over rows x seeds, one results directory.

A spec (TOML; the shipped ones are ``pomil/experiments/*.toml``, ``pomil reproduce --list``
names them) says which demonstrations to imitate (and how to record them when missing),
the rows (a learner with its settings, optionally its own demonstrations), the seeds and
the evaluation.  ``pomil reproduce SPEC`` trains every (row, seed) run, evaluates it the way
its demonstrations ask, and writes into ``--out``::

    metrics.json   the spec, the machine, every run's figures and each row's summary over seeds
    table.md       mean ± std over seeds and the success count of each row
    figure.png     circles: trajectories by code; continuous codes: code against radius;
                   multi-task demonstrations: learning curves per task
    rollouts.npz   (circles) the trajectories the figure is drawn from
    policies/      the policies the spec keeps (``policies``: all, first seed, none)

The evaluation follows the demonstrations: circles are scored by mode metrics
(:func:`pomil.eval.circles.evaluate_circles`), a continuous code on circles by code against
fitted radius, demonstrations that name their tasks (Hopper, any ``pomil demos merge``) by
per-task scores of the code matched to each task.  ``pomil sweep`` runs a spec made from a
config file and a grid of settings; ``pomil reproduce merge`` joins results of one spec run
on other seeds or rows.  Spec keys::

    description = "..."          what it measures (shown in the table)
    results = "results/circles"  where its committed results live
    seeds = 10                   training seeds 0 .. seeds-1
    learners = ["bc-mlp", ...]   rows named after their learner, at its defaults
    row_label = "learner"        the table's name for a row ("case", "setting")
    policies = "first"           policies kept: all, first (seed), none
    policy_rows = ["..."]        the rows whose policies are kept (default: every row)
    [demos]                      file = "data/x.npz", record = "pomil demos arguments"
    [evaluation]                 episodes_per_code, code_values, episodes_per_value
    [settings.adversarial]       settings of every adversarial row ([settings.bc], [settings.diffusion]: every
                                 BC, diffusion row)
    [[rows]]                     name, learner, settings = {...}, demos = {file, record}
    [grid]                       key = [v1, v2]: every row once per combination ("ROW key=v1 ...")
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import math
import platform
import shlex
import shutil
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch

from pomil.config import check_fields, load_config_file, option, parse_kwargs, resolved, to_dict
from pomil.data import Demonstrations, atomic_write
from pomil.errors import PomilError
from pomil.eval.metrics import shares_coverage
from pomil.learners import ADVERSARIAL, DIFFUSION, LEARNERS
from pomil.learners import learner as learner_named
from pomil.parallel import run_jobs, usable_cpus
from pomil.training import write_json

SPEC_DIR = Path(__file__).parent / "experiments"
"""The shipped specs: ``pomil reproduce NAME`` runs ``SPEC_DIR / NAME.toml``."""

MODES_SUCCESS = {"min_purity": 0.95, "nmi": 0.9}
"""Circles: a seed succeeds when every code is >= 95% one mode, every mode is some code's and NMI >= 0.9."""
CONTINUOUS_SUCCESS = 0.9
"""Continuous codes: a seed succeeds when |Spearman rho| between code value and fitted radius is at least this."""
TASKS_SUCCESS = {"normalised_return": 0.7, "progress": 0.7}
"""Tasks: a seed succeeds when, on every task, the code matched to it reaches these figures."""
SUMMARY_KEYS = ("mean_purity", "min_purity", "modes_covered", "nmi", "overall_none_share")
EPISODE_KEYS = ("coverage", "episode_purity", "switch_share")
"""Circles figures over all of a policy's episodes (``evaluate_circles``), in results measured since pomil had them."""
METRICS = ("normalised_return", "progress", "displacement_ratio")
SPEED_METRICS = ("on_task_share", "speed_error")
REFERENCE_RTOL = 0.01
"""How far (relative) merged results' expert and zero-action returns may differ: the same experts
recorded again give slightly other demonstrations where floats differ (another CPU or build)."""


# ====================================================================== the spec
RECORDERS_WITH_PROGRESS = frozenset({"hopper", "record"})
"""The ``pomil demos`` commands that show a progress bar (``--no-progress`` hides it); the rest are quick."""


@dataclass(frozen=True)
class DemosSource:
    """A demonstrations file, and the ``pomil demos`` arguments that record it when it is missing."""

    file: str
    record: tuple[str, ...] = ()

    def ensure(self, progress: bool = True) -> Path:
        """The file, recorded first when missing (``progress``: the recording's progress bar, where it has one)."""
        path = Path(self.file)
        if path.exists():
            return path
        if not self.record:
            raise PomilError(f"{path}: demonstrations not found, and the spec has no recipe to record them: "
                             "record them (pomil demos) or give others with --demos")
        from pomil.cli import main

        quiet = not progress and self.record[0] in RECORDERS_WITH_PROGRESS
        args = ["demos", *self.record, "--out", str(path), *(["--no-progress"] if quiet else [])]
        print(f"recording {path}: pomil {shlex.join(args)}", flush=True)
        if main(args) != 0:
            raise PomilError(f"{path}: recording it (pomil {shlex.join(args)}) failed")
        return path


@dataclass(frozen=True)
class Row:
    """One row of an experiment: a learner, its settings over its defaults, its demonstrations."""

    name: str
    learner: str
    demos: DemosSource
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def kind(self) -> Literal["adversarial", "diffusion", "bc"]:
        return "adversarial" if self.learner in ADVERSARIAL else "diffusion" if self.learner in DIFFUSION else "bc"


@dataclass(frozen=True)
class Spec:
    """An experiment: rows x seeds, and how each run is evaluated and kept."""

    name: str
    source: str
    rows: tuple[Row, ...]
    seeds: int = 1
    first_seed: int = 0
    description: str = ""
    results: str = ""
    row_label: str = "learner"
    episodes_per_code: int = 50
    code_values: int = 9
    episodes_per_value: int = 20
    policies: Literal["all", "first", "none"] = "none"
    policy_rows: tuple[str, ...] = ()
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Settings of every row of a kind (``adversarial``, ``diffusion``, ``bc``), under the row's own."""
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Settings given on the command line for every row of a kind, over the row's own."""

    @property
    def seed_list(self) -> list[int]:
        return list(range(self.first_seed, self.first_seed + self.seeds))

    def values(self, row: Row) -> dict[str, Any]:
        """The learner config values of ``row`` (its defaults fill the rest)."""
        return {**self.settings.get(row.kind, {}), **row.settings, **self.overrides.get(row.kind, {}),
                "demos": str(Path(row.demos.file).resolve())}

    def keeps_policy(self, row: str, seed: int) -> bool:
        return keeps_policy({"policies": self.policies, "first_seed": self.first_seed,
                             "policy_rows": self.policy_rows}, row, seed)

    def to_dict(self) -> dict[str, Any]:
        d = json.loads(json.dumps(dataclasses.asdict(self)))
        d["rows"] = {r["name"]: {k: v for k, v in r.items() if k != "name"} for r in d["rows"]}
        return d


def keeps_policy(spec: dict[str, Any], row: str, seed: int) -> bool:
    """Whether a spec (as metrics.json records it) keeps the policy of ``row``'s run of ``seed``."""
    return (spec["policies"] == "all" or (spec["policies"] == "first" and seed == spec["first_seed"])) and (
        not spec["policy_rows"] or row in spec["policy_rows"])


def spec_names() -> list[str]:
    return sorted(p.stem for p in SPEC_DIR.glob("*.toml"))


def load_spec(name_or_path: str) -> Spec:
    """A shipped spec by name, or a spec file; a one-line PomilError for a bad one."""
    path = Path(name_or_path)
    if not path.suffix and not path.exists():
        path = SPEC_DIR / f"{name_or_path}.toml"
        if not path.is_file():
            raise PomilError(f"no experiment {name_or_path!r}: give a spec file or one of {', '.join(spec_names())}")
    try:
        data = tomllib.loads(path.read_text())
    except OSError as err:
        raise PomilError(f"{path}: cannot read the spec ({err.strerror})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise PomilError(f"{path}: not valid TOML ({err})") from None
    return spec_from_dict(data, name=path.stem, source=str(path))


_SPEC_KEYS = ("description", "results", "seeds", "learners", "rows", "demos", "settings", "grid", "evaluation",
              "policies", "policy_rows", "row_label")


def spec_from_dict(data: dict[str, Any], name: str, source: str) -> Spec:
    """Build and check a spec: every row's settings make a valid config of its learner."""
    _known(data, _SPEC_KEYS, source)
    demos = _demos(data.get("demos"), f"{source}: key 'demos'") if "demos" in data else None
    rows = [_row({"learner": n}, demos, f"{source}: learners") for n in _list(data, "learners", source)]
    rows += [_row(table, demos, f"{source}: rows[{i}]") for i, table in enumerate(_list(data, "rows", source))]
    if not rows:
        raise PomilError(f"{source}: no rows (give 'learners' or [[rows]])")
    rows = expand_grid(rows, data.get("grid", {}), source)
    evaluation = data.get("evaluation", {})
    _known(evaluation, ("episodes_per_code", "code_values", "episodes_per_value"), f"{source}: [evaluation]")
    settings = data.get("settings", {})
    _known(settings, ("adversarial", "diffusion", "bc"), f"{source}: [settings]")
    spec = Spec(name=name, source=source, rows=tuple(rows), seeds=data.get("seeds", 1),
                description=data.get("description", ""), results=data.get("results", ""),
                row_label=data.get("row_label", "learner"), policies=data.get("policies", "none"),
                policy_rows=tuple(_list(data, "policy_rows", source)),
                settings={k: dict(v) for k, v in settings.items()}, **evaluation)
    return check_spec(spec)


def check_spec(spec: Spec) -> Spec:
    """PomilError unless the spec's values are in range and each row makes a valid learner config."""
    names = [r.name for r in spec.rows]
    if len(set(names)) != len(names):
        raise PomilError(f"{spec.source}: rows named twice: {sorted({n for n in names if names.count(n) > 1})}")
    for key in ("seeds", "episodes_per_code", "code_values", "episodes_per_value"):
        value = getattr(spec, key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise PomilError(f"{spec.source}: key '{key}': expected an integer >= 1, got {value!r}")
    if spec.policies not in ("all", "first", "none"):
        raise PomilError(f"{spec.source}: key 'policies': expected all, first or none, got {spec.policies!r}")
    unknown = sorted(set(spec.policy_rows) - set(names))
    if unknown:
        raise PomilError(f"{spec.source}: key 'policy_rows': no rows {unknown}")
    for row in spec.rows:
        LEARNERS[row.learner].make_config({**spec.values(row), "out": "x", "progress": False},
                                          source=f"{spec.source}: row {row.name!r}")
    return spec


def _known(table: Any, keys: tuple[str, ...], where: str) -> None:
    if not isinstance(table, dict):
        raise PomilError(f"{where}: expected a table, got {table!r}")
    unknown = sorted(set(table) - set(keys))
    if unknown:
        raise PomilError(f"{where}: unknown key(s) {unknown}; valid keys are: {', '.join(keys)}")


def _list(data: dict[str, Any], key: str, source: str) -> list[Any]:
    value = data.get(key, [])
    if not isinstance(value, list):
        raise PomilError(f"{source}: key '{key}': expected a list, got {value!r}")
    return value


def _demos(table: Any, where: str) -> DemosSource:
    _known(table, ("file", "record"), where)
    if not isinstance(table.get("file"), str) or not table["file"]:
        raise PomilError(f"{where}: key 'file': expected the demonstrations' path")
    record = table.get("record", "")
    return DemosSource(table["file"], tuple(shlex.split(record) if isinstance(record, str) else record))


def _row(table: Any, demos: DemosSource | None, where: str) -> Row:
    _known(table, ("name", "learner", "settings", "demos"), where)
    learner = table.get("learner", "")
    if learner not in LEARNERS:
        raise PomilError(f"{where}: key 'learner': expected one of {sorted(LEARNERS)}, got {learner!r}")
    own = _demos(table["demos"], f"{where}.demos") if "demos" in table else demos
    if own is None:
        raise PomilError(f"{where}: no demonstrations (give [demos] or the row's demos)")
    settings = table.get("settings", {})
    _known(settings, tuple(settings), where)
    return Row(str(table.get("name", learner)), learner, own, dict(settings))


def expand_grid(rows: list[Row], grid: Any, source: str) -> list[Row]:
    """Every row once per combination of the grid's values, named ``row key=value ...``."""
    _known(grid, tuple(grid) if isinstance(grid, dict) else (), f"{source}: [grid]")
    if not grid:
        return rows
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise PomilError(f"{source}: grid key '{key}': expected a non-empty list of values")
    combos = [dict(zip(grid, c, strict=True)) for c in itertools.product(*grid.values())]
    def named(row: Row, c: dict[str, Any]) -> str:
        return " ".join([row.name] * (len(rows) > 1) + [f"{k}={v}" for k, v in c.items()])

    return [dataclasses.replace(row, name=named(row, c), settings={**row.settings, **c})
            for row in rows for c in combos]


# ================================================================ one run
@dataclass(frozen=True)
class RunJob:
    """One (row, seed) run: the learner, its config values, where it goes, and how it is evaluated."""

    learner: str
    values: dict[str, Any]
    run_dir: str
    seed: int
    evaluation: dict[str, int]
    progress: bool
    resume: bool
    """A finished run of the same values is not run again, and a run with a checkpoint but no result.json
    (stopped, or its worker died) continues from its checkpoint."""


def run_one(job: RunJob) -> dict[str, Any]:
    """Train one run and evaluate it; ``run_dir/result.json`` is written last (the run's "finished" mark)."""
    from pomil.api import TrainedPolicy

    out, seed = Path(job.run_dir), job.seed
    done = out / "result.json"
    if job.resume and finished(out, job.values):
        return json.loads(done.read_text())
    trainer = LEARNERS[job.learner]
    cfg = resolved(trainer.make_config({**job.values, "out": job.run_dir, "seed": seed, "progress": job.progress,
                                        "overwrite": True},  # the experiment's own runs: a new run replaces one
                                       source=f"run {job.run_dir}"))  # the results record the preset run
    again = job.resume and (out / "checkpoint.pt").exists()
    if again:
        print(f"{job.run_dir}: resuming from its checkpoint", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    ckpt = trainer.train(cfg, resume=again)
    wall = time.perf_counter() - t0
    kind, metrics = evaluate_run(TrainedPolicy.load(ckpt), Demonstrations.load(cfg.demos), seed, run_dir=out,
                                 evaluation=job.evaluation)
    metrics.update(checkpoint=str(ckpt), train_seed=seed)
    result = {"learner": job.learner, "seed": seed, "settings": job.values, "wall_s": wall, "kind": kind,
              "metrics": metrics, "config": {k: v for k, v in to_dict(cfg).items() if k not in _RUN_FIELDS}}
    write_json(done, result)
    return result


def finished(run_dir: Path, values: dict[str, Any]) -> bool:
    """Whether ``run_dir`` holds a finished run (its result.json) of these config values."""
    try:
        return json.loads((run_dir / "result.json").read_text()).get("settings") == values
    except (OSError, ValueError):
        return False


_RUN_FIELDS = ("out", "seed", "progress", "demos", "overwrite")
"""Config fields that differ between the runs of one row (or between machines), not settings."""


def evaluate_run(policy: Any, demos: Demonstrations, seed: int, *, run_dir: Path,
                 evaluation: dict[str, int]) -> tuple[str, dict[str, Any]]:
    """(kind, metrics with ``success``) of a trained policy; circles rollouts go to ``run_dir/rollouts.npz``."""
    from pomil.envs import evaluation_kind
    from pomil.eval.circles import evaluate_circles, evaluate_code_radius
    from pomil.eval.tasks import evaluate_tasks, reference_of

    kind = evaluation_kind(policy.env.get("id", ""), demos.metadata)
    if kind == "circles" and policy.code_dim:
        metrics, roll = evaluate_code_radius(policy, evaluation["code_values"], evaluation["episodes_per_value"],
                                             seed=1000 + seed)
        _save_rollouts(run_dir, roll)
        metrics.update(success=bool(abs(metrics["spearman"]) >= CONTINUOUS_SUCCESS),
                       warm_start_spearman=_warm_start_value(run_dir / "metrics.csv", "eval/spearman"))
        return "code-radius", metrics
    if kind == "circles":
        metrics, roll = evaluate_circles(policy, evaluation["episodes_per_code"], seed=1000 + seed)
        _save_rollouts(run_dir, {"positions": roll["positions"], "groups": roll["codes"]})
        return "circles", {**metrics, "success": modes_success(metrics)}
    if kind == "tasks":
        metrics = evaluate_tasks(policy, reference_of(demos.metadata), evaluation["episodes_per_code"],
                                 seed=1000 + seed)
        return "tasks", {**metrics, "success": tasks_success(metrics),
                         "curve": _curve(run_dir, list(demos.metadata["tasks"]))}
    return "none", {"success": False}


def _save_rollouts(run_dir: Path, roll: dict[str, np.ndarray]) -> None:
    atomic_write(run_dir / "rollouts.npz", lambda f: np.savez_compressed(f, **roll))


def modes_success(m: dict[str, Any]) -> bool:
    """Every code >= 95% in one mode, every mode covered, NMI >= 0.9."""
    return bool(m["min_purity"] >= MODES_SUCCESS["min_purity"] and m["nmi"] >= MODES_SUCCESS["nmi"]
                and m["modes_covered"] == len(m["per_code"][0]["mode_share"]))


def tasks_success(m: dict[str, Any]) -> bool:
    """Whether one run's task scores meet :data:`TASKS_SUCCESS` on every task."""
    return all(t[k] >= v for t in m["tasks"].values() for k, v in TASKS_SUCCESS.items())


def _csv_rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _warm_start_value(csv_path: Path, key: str) -> float | None:
    """``key`` in a run's metrics.csv at iteration 0 (the evaluation after the warm start), None when not logged."""
    rows = [r for r in _csv_rows(csv_path) if r.get("iteration") == "0" and r.get(key)]
    return float(rows[0][key]) if rows else None


def _curve(run_dir: Path, tasks: list[str]) -> dict[str, list[float]]:
    """Evaluation rows of a run's metrics.csv: env steps and normalised return per task."""
    rows = [r for r in _csv_rows(run_dir / "metrics.csv") if r.get("eval/env_steps")]
    return {"env_steps": [float(r["eval/env_steps"]) for r in rows],
            **{t: [float(r[f"eval/{t}/normalised_return"]) for r in rows] for t in tasks}}


# ================================================================ all runs
@dataclass(frozen=True)
class Execution:
    """Where an experiment's runs go and how they are run."""

    out: Path
    runs: Path
    jobs: int = 0
    """Runs at a time in local worker processes, each on ``cpus_per_run`` torch threads (0: one per usable
    core; 1: one after another in this process)."""
    ray: bool = False
    address: str = ""
    cpus_per_run: float = 1.0
    resume: bool = False
    keep_going: bool = False
    """A failed run is reported in the results (else the first failure stops the experiment)."""
    progress: bool = True


def run_experiment(spec: Spec, how: Execution) -> dict[str, Any]:
    """Every (row, seed) run of ``spec``, then metrics.json, table.md, figure.png (and rollouts.npz,
    policies/) in ``how.out``."""
    t_start = time.perf_counter()
    for demos in dict.fromkeys(r.demos for r in spec.rows):
        demos.ensure(how.progress)
    keys = [(row, seed) for row in spec.rows for seed in spec.seed_list]
    workers = 1 if how.ray else max(1, min(how.jobs or int(usable_cpus() // how.cpus_per_run), len(keys)))
    progress = how.progress and workers == 1 and not how.ray  # bars side by side would overwrite each other
    evaluation = {k: getattr(spec, k) for k in ("episodes_per_code", "code_values", "episodes_per_value")}
    jobs = [RunJob(row.learner, spec.values(row), str((how.runs / row.name / f"seed{seed}").resolve()), seed,
                   evaluation, progress, how.resume) for row, seed in keys]
    names = [f"[{row.name}] seed {seed}" for row, seed in keys]
    where = ("on Ray" + (f" at {how.address}" if how.address else " (local)") if how.ray else
             f"{workers} at a time in local worker processes" if workers > 1 else "one after another")
    reused = sum(finished(Path(job.run_dir), job.values) for job in jobs) if how.resume else 0
    again = f"; {reused} finished before, reused; {len(keys) - reused} to run" if how.resume else ""
    print(f"{spec.name}: {len(spec.rows)} row(s) x {spec.seeds} seed(s) = {len(keys)} runs{again}, {where}", flush=True)

    def report(r, n, total) -> None:
        line = f"FAILED: {r.error}" if not r.ok else _one_line_result(r.value)
        print(f"[{n}/{total}] {r.name}: {line} ({r.wall_s:.0f} s)", flush=True)

    done = run_jobs(run_one, [(job,) for job in jobs], names, ray=how.ray, address=how.address or None,
                    cpus_per_job=how.cpus_per_run, capture_errors=how.keep_going, on_done=report,
                    costs=[LEARNERS[row.learner].cost for row, _ in keys], workers=workers)
    results = {(row.name, seed): r for (row, seed), r in zip(keys, done, strict=True)}
    data = collect(spec, results)
    data.update(execution={"ray": how.ray, "address": how.address, "workers": workers},
                wall_time_s=time.perf_counter() - t_start)
    for (row, seed), r in results.items():
        if r.ok and spec.keeps_policy(row, seed):
            from pomil.api import TrainedPolicy

            TrainedPolicy.load(r.value["metrics"]["checkpoint"]).save(how.out / "policies" / f"{row}-seed{seed}.pt")
    write_results(how.out, data, gather_rollouts(spec, data, how.runs))
    return data


def _one_line_result(result: dict[str, Any]) -> str:
    m, kind = result["metrics"], result["kind"]
    if kind == "circles":
        text = (f"purity {m['mean_purity']:.2f} (min {m['min_purity']:.2f}), modes covered {m['modes_covered']}, "
                f"NMI {m['nmi']:.2f}, none {m['overall_none_share']:.2f}")
    elif kind == "code-radius":
        text = f"Spearman rho {m['spearman']:+.3f}, radius {m['radius_covered'][0]:.2f} .. {m['radius_covered'][1]:.2f}"
    elif kind == "tasks":
        text = "; ".join(f"{t} (code {s['code']}): norm {s['normalised_return']:.2f}, progress {s['progress']:.2f}"
                         for t, s in m["tasks"].items())
    else:
        return "done (no evaluation for these demonstrations)"
    return text + ("" if m["success"] else " (below target)")


def machine() -> dict[str, str]:
    return {"python": sys.version.split()[0], "platform": platform.platform(), "torch": torch.__version__}


def collect(spec: Spec, results: dict[tuple[str, int], Any]) -> dict[str, Any]:
    """metrics.json's content: the spec, the machine, every row's runs (in seed order) and its summary."""
    data: dict[str, Any] = {"spec": spec.to_dict(), "machine": machine(), "rows": {}, "failed": []}
    for row in spec.rows:
        ok = [results[row.name, s].value for s in spec.seed_list if results[row.name, s].ok]
        data["failed"] += [f"{row.name} seed {s}: {results[row.name, s].error}" for s in spec.seed_list
                           if not results[row.name, s].ok]
        data["rows"][row.name] = {
            "learner": row.learner, "kind": ok[0]["kind"] if ok else "none", "settings": row.settings,
            "config": ok[0]["config"] if ok else {}, "demos": row.demos.file,
            "runs": [r["metrics"] for r in ok], "wall_s": [r["wall_s"] for r in ok]}
    # tasks: the first tasks row's demonstrations' reference (tasks, expert and zero-action returns)
    row = next((spec.rows[i] for i, r in enumerate(data["rows"].values()) if r["kind"] == "tasks"), None)
    if row is not None:
        from pomil.eval.tasks import reference_of

        md = Demonstrations.load(row.demos.file).metadata
        data.update(reference=reference_of(md, row.demos.file), env_id=md.get("env_id"), setting=md.get("setting", ""))
    return summarise(data)


def summarise(data: dict[str, Any]) -> dict[str, Any]:
    """Each row's summary (mean and std over its seeds) and success count, from its runs."""
    for r in data["rows"].values():
        runs = r["runs"]
        r["successes"] = int(sum(bool(run.get("success")) for run in runs))
        if not runs:
            r["summary"] = {}
        elif r["kind"] == "circles":
            keys = SUMMARY_KEYS + tuple(k for k in EPISODE_KEYS if all(k in run for run in runs))
            r["summary"] = {k: _mean_std([run[k] for run in runs]) for k in keys}
            if "coverage" not in r["summary"]:  # measured before it was recorded: the same from the modes' shares
                r["summary"]["coverage"] = _mean_std([shares_coverage(run["overall_mode_share"]) for run in runs])
        elif r["kind"] == "code-radius":
            r["summary"] = {"abs_spearman": _mean_std(np.abs([run["spearman"] for run in runs]))}
        elif r["kind"] == "tasks":  # the speed figures too where every run has them
            metrics = METRICS + (SPEED_METRICS if all("behaviour" in run for run in runs) else ())
            r["summary"] = {t: {m: _mean_std([run["tasks"][t][m] for run in runs]) for m in metrics}
                            for t in data["reference"]["tasks"]}
    return data


def _mean_std(x: Any) -> list[float]:
    """[mean, std] over seeds (population std: 0 for one seed)."""
    return [float(np.mean(x)), float(np.std(x))]


# ================================================================ the files
def gather_rollouts(spec: Spec, data: dict[str, Any], runs: Path) -> dict[str, np.ndarray]:
    """The figure's trajectories: the demonstrations' (when every row shares them) and, per circles row, its
    first seed's; per continuous-code row, every seed's."""
    rollouts: dict[str, np.ndarray] = {}
    shared = {r.demos.file for r in spec.rows}
    for row in spec.rows:
        r = data["rows"][row.name]
        seeds = [run["train_seed"] for run in r["runs"]][: 1 if r["kind"] == "circles" else None]
        for seed in seeds if r["kind"] in ("circles", "code-radius") else ():
            with np.load(runs / row.name / f"seed{seed}" / "rollouts.npz", allow_pickle=False) as roll:
                prefix = row.name if r["kind"] == "circles" else f"{row.name}/seed{seed}"
                rollouts.update({f"{prefix}/{k}": roll[k] for k in roll.files})
    if rollouts and len(shared) == 1:
        demos = Demonstrations.load(next(iter(shared)))
        if demos.states is not None:
            steps = int(demos.episode_lengths[0])
            rollouts["experts/positions"] = demos.states.reshape(demos.num_episodes, steps, -1)[:, 1:, :2]
            rollouts["experts/groups"] = demos.labels if demos.labels is not None else np.zeros(0, np.int64)
            if "episode_radii" in demos.metadata:
                rollouts["experts/radii"] = np.asarray(demos.metadata["episode_radii"], dtype=np.float64)
    return rollouts


def write_results(out: Path, data: dict[str, Any], rollouts: dict[str, np.ndarray]) -> None:
    """metrics.json, table.md, rollouts.npz (when there are any) and figure.png in ``out``; prints the table."""
    write_json(out / "metrics.json", data)
    table = results_table(data)
    atomic_write(out / "table.md", lambda f: f.write(table.encode()))
    if rollouts:
        atomic_write(out / "rollouts.npz", lambda f: np.savez_compressed(f, **rollouts))
    drew = draw_figure(data, out / "rollouts.npz", out / "figure.png")
    print(table)
    print(f"wrote {out}/metrics.json, table.md{', figure.png' if drew else ''} ({data['wall_time_s']:.0f} s of runs)")
    if data["failed"]:
        print(f"{len(data['failed'])} run(s) FAILED: " + "; ".join(data["failed"]), flush=True)


def draw_figure(data: dict[str, Any], rollouts_path: Path, path: Path) -> bool:
    """The figure of the first row's kind; False when that kind has none."""
    kinds = [r["kind"] for r in data["rows"].values() if r["runs"]]
    if not kinds:
        return False
    from pomil.eval.plots import code_radius_figure, figure1, grid_axis, grid_figure, learning_curves

    if kinds[0] == "tasks":  # a grid over one number (demonstrations per mode): returns against it; else curves
        tasks = {n: r for n, r in data["rows"].items() if r["kind"] == "tasks" and r["runs"]}
        if (key := grid_axis(tasks)) is not None:
            grid_figure(tasks, list(data["reference"]["tasks"]), key, path)
            return True
        rows = {n: {"curves": [run["curve"] for run in r["runs"]], "summary": r["summary"]} for n, r in tasks.items()}
        learning_curves({**data, "tasks": list(data["reference"]["tasks"]), "learners": rows}, path)
        return True
    if not rollouts_path.exists():
        return False
    if kinds[0] == "code-radius":
        row = next(n for n, r in data["rows"].items() if r["kind"] == "code-radius")
        code_radius_figure(rollouts_path, path, row=row)
        return True
    with np.load(rollouts_path, allow_pickle=False) as r:
        names = [n for n in ["experts", *data["rows"]] if f"{n}/positions" in r.files]
        figure1([(n, r[f"{n}/positions"], r[f"{n}/groups"], "mode" if n == "experts" else "code") for n in names], path)
    return True


def results_table(data: dict[str, Any]) -> str:
    """One table per kind of row, each with its footnote."""
    spec = data["spec"]
    head = [spec["description"], ""] if spec.get("description") else []
    parts = []
    for kind, table in (("circles", _circles_table), ("code-radius", _code_radius_table), ("tasks", _tasks_table)):
        rows = {n: r for n, r in data["rows"].items() if r["kind"] == kind and r["runs"]}
        if rows:
            parts.append(table(data, rows, spec.get("row_label", "learner")))
    failed = f"\nFailed runs: {'; '.join(data['failed'])}.\n" if data["failed"] else ""
    return "\n".join(head + parts) + failed


def _cell(s: list[float], p: int = 2) -> str:
    return f"{s[0]:.{p}f} ± {s[1]:.{p}f}"


def _seeds_note(data: dict[str, Any]) -> str:
    seeds = sorted({run["train_seed"] for r in data["rows"].values() for run in r["runs"]})
    return f"mean ± std over {len(seeds)} seed(s) ({', '.join(map(str, seeds))})"


def _circles_table(data: dict[str, Any], rows: dict[str, Any], label: str) -> str:
    episodes = any(k in r["summary"] for r in rows.values() for k in EPISODE_KEYS)  # "-": measured before them
    more = " coverage | episode purity | switching |" if episodes else ""
    lines = [f"| {label} | modes | successes | per-code purity | min purity | modes covered | NMI(code, mode) "
             f"| none share |{more} wall s / seed |", "|---" * (9 + 3 * episodes) + "|"]
    for name, r in rows.items():
        s = r["summary"]
        cells = "".join(f" {_cell(s[k]) if k in s else '-'} |" for k in EPISODE_KEYS) if episodes else ""
        lines.append(f"| {name} | {len(r['runs'][0]['per_code'][0]['mode_share'])} | {r['successes']}/{len(r['runs'])} "
                     f"| {_cell(s['mean_purity'])} | {_cell(s['min_purity'])} | {_cell(s['modes_covered'], 1)} "
                     f"| {_cell(s['nmi'])} | {_cell(s['overall_none_share'])} |{cells} {np.mean(r['wall_s']):.0f} |")
    lines += ["", f"{_seeds_note(data)}; {data['spec']['episodes_per_code']} stochastic rollouts per code; learners "
              "without latent codes are scored as a single code (NMI 0 by definition). A seed succeeds when its min "
              f"purity is >= {MODES_SUCCESS['min_purity']}, every mode is covered and NMI >= {MODES_SUCCESS['nmi']}."]
    if episodes:
        lines[-1] += (" Over all episodes, the codes drawn evenly (free sampling): coverage is the entropy of the "
                      "modes' shares over log M (1: every mode equally often); episode purity the share of episodes "
                      "whose three thirds are each in the same mode, switching the share whose thirds visit two "
                      "modes or more.")
    return "\n".join(lines) + "\n"


def _code_radius_table(data: dict[str, Any], rows: dict[str, Any], label: str) -> str:
    lines = [f"| {label} | seed | Spearman rho(code, radius) | after the warm start | median radius per code value, "
             "low .. high | success | wall s |", "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        for run, wall in zip(r["runs"], r["wall_s"], strict=True):
            warm = "-" if run.get("warm_start_spearman") is None else f"{run['warm_start_spearman']:+.3f}"
            lo, hi = run["radius_covered"]
            lines.append(f"| {name} | {run['train_seed']} | {run['spearman']:+.3f} | {warm} | {lo:.2f} .. {hi:.2f} | "
                         f"{'yes' if run['success'] else 'no'} | {wall:.0f} |")
    lines.append("")
    spec = data["spec"]
    for name, r in rows.items():
        lines.append(f"{name}: |rho| {_cell(r['summary']['abs_spearman'], 3)} over {len(r['runs'])} seeds, "
                     f"{r['successes']}/{len(r['runs'])} with |rho| >= {CONTINUOUS_SUCCESS}; the largest |rho| these "
                     f"tied code values allow is {r['runs'][0].get('spearman_max', float('nan')):.3f}.")
    lines += ["", f"Each seed: {spec['code_values']} code values evenly over the prior, {spec['episodes_per_value']} "
              "stochastic rollouts each, a least-squares circle fitted to every trajectory."]
    return "\n".join(lines) + "\n"


def _tasks_table(data: dict[str, Any], rows: dict[str, Any], label: str) -> str:
    tasks, reference = list(data["reference"]["tasks"]), data["reference"]
    lines = [f"| {label} | successes | " + " | ".join(f"{t}: norm. return | {t}: progress | {t}: displacement"
                                                      for t in tasks) + " | wall s / seed |",
             "|---|---|" + "---|" * (3 * len(tasks)) + "---|"]
    for name, r in rows.items():
        cells = [_cell(r["summary"][t][m]) for t in tasks for m in METRICS]
        lines.append(f"| {name} | {r['successes']}/{len(r['runs'])} | " + " | ".join(cells)
                     + f" | {np.mean(r['wall_s']):.0f} |")
    setting = f", {data['setting']} setting" if data.get("setting") else ""
    lines += ["", f"{_seeds_note(data)}{setting}; each task scored for the code matched to it "
              f"({data['spec']['episodes_per_code']} deterministic episodes per code and task). A seed succeeds when "
              "on every task its matched code reaches a normalised return and a progress of at least "
              f"{TASKS_SUCCESS['normalised_return']:g}. Expert returns: "
              + ", ".join(f"{t} {v:.1f}" for t, v in reference["expert_returns"].items()) + "; zero-action returns: "
              + ", ".join(f"{t} {v:.1f}" for t, v in reference["still_returns"].items()) + "."]
    speed = {n: r for n, r in rows.items() if "on_task_share" in r["summary"][tasks[0]]}
    if speed:
        lines += ["", f"| {label} | " + " | ".join(f"{t}: on-task share | {t}: speed error (m/s)" for t in tasks)
                  + " | purity of the matched codes |", "|---|" + "---|" * (2 * len(tasks) + 1)]
        for name, r in speed.items():
            purity = [np.mean([run["behaviour"][f"code{run['tasks'][t]['code']}"]["purity"] for t in tasks])
                      for run in r["runs"]]
            cells = [_cell(r["summary"][t][m]) for t in tasks for m in SPEED_METRICS]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {_cell(_mean_std(purity))} |")
        lines += ["", "Each evaluation episode is assigned to the task whose expert mean speed is nearest its own. "
                  "On-task share: the share of the matched code's episodes nearest its task; speed error: |the code's "
                  "mean speed - the expert's|; purity: a code's largest share. Expert speeds: "
                  + ", ".join(f"{t} {v:.2f} m/s" for t, v in reference["expert_speed"].items()) + "."]
    free = {n: r for n, r in rows.items() if all("free" in run for run in r["runs"])}
    if free:
        lines += ["", f"| {label} | " + " | ".join(f"{t}: share" for t in tasks) + " | standing | coverage | "
                  "episode purity | switching |", "|---|" + "---|" * (len(tasks) + 4)]
        for name, r in free.items():
            runs = [run["free"] for run in r["runs"]]
            cells = [_cell(_mean_std([f["mode_share"][t] for f in runs])) for t in tasks]
            cells += [_cell(_mean_std([f[k] for f in runs])) for k in ("still_share", *EPISODE_KEYS)]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines += ["", "Free sampling: the first task's evaluation episodes, the codes drawn evenly (the tasks share "
                  "their dynamics), each assigned to the task whose expert's signed displacement per step is nearest "
                  "its own, or to standing when 0 is nearer; coverage: the tasks' entropy over log J; episode purity: "
                  "the share of episodes whose three thirds are each on the same task; switching: on two or more."]
    return "\n".join(lines) + "\n"


# ================================================================ merge
def merge_results(sources: list[Path], out: Path, policies: bool = True) -> dict[str, Any]:
    """Join results of one spec run on other seeds (``--first-seed``), or of other rows of it (``--rows``), into
    ``out``: every row's runs in seed order, its policies, the rollouts, the table and figure over all seeds.

    The sources must agree on what they measured: the rows they share, their learners and resolved settings (a
    setting only one of them records, a field added since the other ran, is named in a note and not
    compared), the evaluation, and the demonstrations' reference returns (within :data:`REFERENCE_RTOL`;
    each source's is kept in ``merged_from``); a row's seeds must not repeat.  ``policies=False`` copies
    no policy (for results committed without them).  Anything else is a one-line error before a file
    is written."""
    loaded = sorted(_load_results(sources), key=lambda s: s[1]["spec"]["first_seed"])
    (first_src, first), rest = loaded[0], loaded[1:]
    merged = json.loads(json.dumps(first))
    merged["merged_from"] = [{"results": str(first_src), "spec": first["spec"], "reference": first.get("reference")}]
    for src, r in rest:
        _check_same(first_src, first, src, r)
        for name, row in r["rows"].items():
            if name not in merged["rows"]:  # a row the sources before had not run: its spec's description names it
                merged["rows"][name] = json.loads(json.dumps(row))
                merged["spec"]["rows"][name] = r["spec"]["rows"][name]
                merged["spec"]["description"] = r["spec"].get("description", "")
                continue
            to = merged["rows"][name]
            repeated = sorted({x["train_seed"] for x in to["runs"]} & {x["train_seed"] for x in row["runs"]})
            if repeated:
                raise PomilError(f"{src}/metrics.json: row {name} seed(s) {repeated} are already in the merge")
            to["runs"] += row["runs"]
            to["wall_s"] += row["wall_s"]
        merged["merged_from"].append({"results": str(src), "spec": r["spec"], "reference": r.get("reference")})
        merged["wall_time_s"] += r["wall_time_s"]
        merged["failed"] += r["failed"]
    counts = {name: len(row["runs"]) for name, row in merged["rows"].items()}
    if len(set(counts.values())) > 1:
        raise PomilError(f"the merged rows have different numbers of seeds ({counts}); merge results of the same rows")
    copies = _policy_copies(loaded, out) if policies else []
    for row in merged["rows"].values():
        order = np.argsort([run["train_seed"] for run in row["runs"]], kind="stable")
        row["runs"], row["wall_s"] = [row["runs"][i] for i in order], [row["wall_s"][i] for i in order]
    merged["spec"]["seeds"] = max(counts.values())
    rollouts: dict[str, np.ndarray] = {}
    for src, _ in reversed(loaded):  # the lowest seeds' trajectories win
        if (src / "rollouts.npz").exists():
            with np.load(src / "rollouts.npz", allow_pickle=False) as roll:
                rollouts.update({k: roll[k] for k in roll.files})
    out.mkdir(parents=True, exist_ok=True)
    for policy, dest in copies:
        dest.parent.mkdir(exist_ok=True)
        if policy.resolve() != dest.resolve():
            shutil.copyfile(policy, dest)
    merged["policies_merged"] = policies
    write_results(out, summarise(merged), rollouts)
    return merged


def _load_results(sources: list[Path]) -> list[tuple[Path, dict[str, Any]]]:
    loaded = []
    for src in map(Path, sources):
        path = src / "metrics.json"
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise PomilError(f"{path}: cannot read an experiment's metrics ({err})") from None
        if not isinstance(data, dict) or "spec" not in data or "rows" not in data:
            raise PomilError(f"{path}: not the results of an experiment spec (no 'spec' and 'rows')")
        loaded.append((src, data))
    return loaded


_FREE = ("seeds", "first_seed", "source", "results", "description", "policies", "policy_rows", "rows")


def _check_same(first_src: Path, first: dict[str, Any], src: Path, r: dict[str, Any]) -> None:
    """PomilError unless results ``r`` measured what ``first`` did (see :func:`merge_results`)."""
    def same(key: str, a: Any, b: Any) -> None:
        if a != b:
            raise PomilError(f"{src}/metrics.json: {key} differs from {first_src}'s ({b!r} against {a!r}); "
                             "only runs of the same experiment and settings on other seeds can be merged")

    def measured(spec: dict[str, Any]) -> dict[str, Any]:  # no overrides of a kind = none at all
        return {k: ({kind: o for kind, o in v.items() if o} if k == "overrides" else v) for k, v in spec.items()
                if k not in _FREE}

    same("spec", measured(first["spec"]), measured(r["spec"]))
    for name, row in ((n, row) for n, row in r["rows"].items() if n in first["rows"]):
        mine = first["rows"][name]
        same(f"rows.{name}.learner", mine["learner"], row["learner"])
        one_sided = sorted(set(mine["config"]) ^ set(row["config"]))
        if one_sided:
            print(f"pomil: note: row {name}: settings {', '.join(one_sided)} recorded by only one of {first_src} and "
                  f"{src}: not compared", file=sys.stderr)
        same(f"rows.{name}.config", {k: v for k, v in mine["config"].items() if k not in one_sided},
             {k: v for k, v in row["config"].items() if k not in one_sided})
    if "reference" in first or "reference" in r:
        same("reference.tasks", first["reference"]["tasks"], r["reference"]["tasks"])
        for key in ("expert_returns", "still_returns"):
            a, b = first["reference"][key], r["reference"][key]
            drift = max(abs(a[t] - b[t]) / max(1.0, abs(a[t])) for t in a) if set(a) == set(b) else math.inf
            if drift > REFERENCE_RTOL:
                same(f"reference.{key}", a, b)
            if drift > 1e-9:
                print(f"pomil: note: {src}: reference.{key} differs from {first_src}'s by up to {100 * drift:.2f}% "
                      f"(within {100 * REFERENCE_RTOL:g}%: the same experts recorded again, where floats differ); "
                      "each source's reference stays in merged_from", file=sys.stderr)


def _policy_copies(loaded: list[tuple[Path, dict[str, Any]]], out: Path) -> list[tuple[Path, Path]]:
    """(policy file, its place in ``out``) for every kept policy of every source; PomilError for a missing one."""
    copies = []
    for src, r in loaded:
        spec = r["spec"]
        for name, row in r["rows"].items():
            for seed in (run["train_seed"] for run in row["runs"] if keeps_policy(spec, name, run["train_seed"])):
                policy = src / "policies" / f"{name}-seed{seed}.pt"
                if not policy.is_file():
                    raise PomilError(f"{policy}: missing (every kept policy is merged with it; --no-policies joins "
                                     "the metrics alone)")
                copies.append((policy, out / "policies" / policy.name))
    return copies


# ================================================================ the commands
@dataclass(frozen=True)
class ReproduceOptions:
    """``pomil reproduce SPEC``'s flags: where the results go, which part of the spec runs, and how."""

    out: str = option("", "results directory (default: runs/results/SPEC; a spec's committed results are where its "
                          "'results' key says: pass --out there to update them)")
    runs: str = option("", "where each run's checkpoint and logs go (default: runs/ and the name of --out, or SPEC)")
    seeds: int = option(0, "training seeds per row (0: the spec's)", within="[0, inf)")
    first_seed: int = option(0, "the first training seed (to add seeds to results; `pomil reproduce merge` joins "
                                "them)", within="[0, inf)")
    rows: tuple[str, ...] = option((), "comma-separated rows of the spec to run (default: every row); a row's name "
                                       "also selects the grid's rows made from it")
    demos: str = option("", "demonstrations for every row instead of the spec's (recorded the spec's way if missing)")
    experts: str = option("", "a folder of Hopper experts for recording missing demonstrations instead of the "
                              "shipped ones (pomil demos hopper --experts)")
    episodes_per_code: int = option(0, "evaluation episodes per code (and task); 0: the spec's", within="[0, inf)")
    adversarial_iterations: int = option(0, "iterations of the adversarial rows (0: the spec's)", within="[0, inf)")
    bc_iterations: int = option(0, "gradient steps of the BC rows (0: the spec's)", within="[0, inf)")
    adversarial_config: str = option("", "JSON file of AdversarialConfig settings over every adversarial row's")
    bc_config: str = option("", "JSON file of BCConfig settings over every BC row's")
    jobs: int = option(0, "without --ray: runs at a time, each in its own process on one torch thread (0: one per "
                          "usable CPU core; 1: one after another in this process on every core)", within="[0, inf)")
    ray: bool = option(False, "run on Ray (optional extra; 1 CPU each)")
    ray_address: str = option("", "with --ray: address of an existing Ray cluster (default: a local Ray started here)")
    resume: bool = option(False, "reuse each finished run of the same settings under --runs and continue each "
                                 "stopped one from its checkpoint")
    progress: bool = option(True, "show progress bars (one run at a time only)")

    RENAMED: ClassVar[dict[str, str]] = {"learners": "rows", "cases": "rows", "resume_runs": "resume"}
    """Flags the experiment commands had before specs, still read."""

    def __post_init__(self) -> None:
        check_fields(self)


def select_rows(spec: Spec, names: tuple[str, ...]) -> list[Row]:
    """The rows named (all when none are): a row, or every grid row made from it ("NAME key=value ...")."""
    def chosen(row: Row, name: str) -> bool:
        return row.name == name or row.name.startswith(f"{name} ")

    unknown = [n for n in names if not any(chosen(r, n) for r in spec.rows)]
    if unknown:
        raise PomilError(f"--rows: no rows {unknown} in {spec.source}; its rows are {[r.name for r in spec.rows]}")
    return [r for r in spec.rows if not names or any(chosen(r, n) for n in names)]


def reproduce(spec_name: str, opts: ReproduceOptions) -> dict[str, Any]:
    """``pomil reproduce SPEC``: the spec with the options' changes, run."""
    spec = load_spec(spec_name)
    rows = select_rows(spec, opts.rows)
    if opts.demos:  # recorded the spec's way when missing
        rows = [dataclasses.replace(r, demos=DemosSource(opts.demos, r.demos.record)) for r in rows]
    if opts.experts:
        if not any(r.demos.record[:1] == ("hopper",) for r in rows):
            raise PomilError(f"--experts: {spec.source} records no Hopper demonstrations (its rows' recipes: "
                             f"{sorted({shlex.join(r.demos.record) or 'none' for r in rows})})")
        rows = [dataclasses.replace(r, demos=DemosSource(r.demos.file, (*r.demos.record, "--experts", opts.experts)))
                if r.demos.record[:1] == ("hopper",) else r for r in rows]
    overrides: dict[str, dict[str, Any]] = {"adversarial": {}, "bc": {}}
    for kind in overrides:
        path, iterations = getattr(opts, f"{kind}_config"), getattr(opts, f"{kind}_iterations")
        overrides[kind].update(load_config_file(path) if path else {})
        overrides[kind].update({"iterations": iterations} if iterations else {})
    kept = tuple(n for n in spec.policy_rows if n in {r.name for r in rows})
    spec = check_spec(dataclasses.replace(
        spec, rows=tuple(rows), seeds=opts.seeds or spec.seeds, first_seed=opts.first_seed,
        episodes_per_code=opts.episodes_per_code or spec.episodes_per_code, overrides=overrides,
        policy_rows=kept, policies=spec.policies if kept or not spec.policy_rows else "none"))
    out = Path(opts.out or f"runs/results/{spec.name}")
    runs = Path(opts.runs or f"runs/{out.name if opts.out else spec.name}")
    return run_experiment(spec, Execution(out=out, runs=runs, jobs=opts.jobs, ray=opts.ray, address=opts.ray_address,
                                          resume=opts.resume, progress=opts.progress))


@dataclass(frozen=True)
class SweepConfig:
    out: str = option("runs/sweep",
                      "sweep directory: one folder per setting and seed, metrics.json, table.md, figure.png")
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


def sweep_spec(cfg: SweepConfig, config_path: str, grid_entries: list[str]) -> Spec:
    """The experiment a sweep file and its ``--grid`` entries make, every setting checked before anything runs."""
    base = load_config_file(config_path)
    learner = str(base.pop("learner", "infogail-pomdp"))
    learner_named(learner, f"{config_path}: 'learner'")
    for key in ("out", "seed"):
        if key in base:
            raise PomilError(f"{config_path}: '{key}' is set by the sweep for each run; remove it")
    if not base.get("demos"):
        raise PomilError(f"{config_path}: 'demos' is required (the demonstrations every run imitates)")
    row = Row("base", learner, DemosSource(str(base.pop("demos"))), base)
    rows = expand_grid([row], parse_grid(grid_entries), config_path)
    return check_spec(Spec(name=Path(config_path).stem, source=config_path, rows=tuple(rows), seeds=cfg.seeds,
                           row_label="setting", episodes_per_code=cfg.episodes_per_code))


def sweep(cfg: SweepConfig, config_path: str, grid_entries: list[str]) -> dict[str, Any]:
    """``pomil sweep CONFIG``: the config's learner over seeds and a grid of settings, each (setting, seed) a run in
    ``OUT/<setting>/seed<k>/``; a finished run of the same settings is not run again, a stopped one resumes from its
    checkpoint, a failed one is reported while the others go on."""
    spec = sweep_spec(cfg, config_path, grid_entries)
    out = Path(cfg.out).resolve()
    return run_experiment(spec, Execution(out=out, runs=out, jobs=cfg.jobs, ray=cfg.ray, address=cfg.address,
                                          cpus_per_run=cfg.cpus_per_run, resume=True, keep_going=True, progress=False))
