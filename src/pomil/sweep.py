"""``pomil sweep``: one training config over seeds and a grid of settings, in parallel on Ray.

The sweep config is a JSON object: ``"learner"`` (any of :data:`pomil.learners.LEARNERS`)
and that learner's config keys (``demos`` at least).  Each grid point is a *setting*, a row
of an experiment (:mod:`pomil.experiment`) run over the seeds: each (setting, seed) a run
in ``OUT/<setting>/seed<k>/`` with its checkpoint, logs and ``result.json`` (the final
evaluation).  A run whose ``result.json`` exists for the same settings is finished and is
not run again; one with a checkpoint but no ``result.json`` (its worker died, and Ray
retries it, or the sweep was stopped) resumes from its checkpoint.  A failed run is
reported and the others go on.  The sweep writes the experiment's ``OUT/metrics.json``,
``OUT/table.md`` (mean +- std over seeds per setting) and ``OUT/figure.png``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pomil.config import check_fields, load_config_file, option, parse_kwargs
from pomil.errors import PomilError
from pomil.experiment import DemosSource, Execution, Row, Spec, check_spec, expand_grid, run_experiment
from pomil.learners import learner as learner_named


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
    spec = sweep_spec(cfg, config_path, grid_entries)
    out = Path(cfg.out).resolve()
    return run_experiment(spec, Execution(out=out, runs=out, jobs=cfg.jobs, ray=cfg.ray, address=cfg.address,
                                          cpus_per_run=cfg.cpus_per_run, resume=True, keep_going=True,
                                          progress=False))
