"""End-to-end reproductions of the paper's experiments.

``pomil reproduce circles`` makes the demonstrations if missing, trains every
learner for every seed, evaluates each trained policy (mode shares per code,
purity, modes covered, NMI), and writes into ``--out``::

    metrics.json   every run's metrics, and mean/std over seeds per learner
    table.md       the summary table (mean +- std over seeds)
    figure.png     Figure-1-style trajectories: experts, then one panel per learner
    rollouts.npz   the trajectories the figure is drawn from
    infogail-pomdp.pt   the InfoGAIL-POMDP policy of seed 0 (policy only)

``pomil reproduce circles-continuous`` records circles whose radius varies
continuously, trains InfoGAIL-POMDP with a continuous code over seeds and
measures how the code maps to the fitted radius (Spearman's rho): metrics.json,
table.md, figure.png, rollouts.npz.

``pomil reproduce hopper`` records the Hopper demonstrations from the shipped
experts if missing, trains every learner for every seed on them, scores each
task for the code matched to it (normalised return, progress score,
displacement ratio) and writes metrics.json (with learning curves), table.md,
figure.png (Figure-2c-style curves over env steps) and policies/.
"""

from __future__ import annotations

import dataclasses
import json
import math
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pomil.api import TrainedPolicy
from pomil.config import check_fields, option, to_dict
from pomil.data import Demonstrations, atomic_write
from pomil.demos import record_circles_demos
from pomil.envs import env_family
from pomil.envs.circles import ENV_ID as CIRCLES_ID
from pomil.envs.circles import Circle, CirclesSpec, circles_preset, make_spec
from pomil.envs.locomotion import HOPPER_EXPERTS, demo_recording
from pomil.errors import PomilError
from pomil.eval.circles import evaluate_circles
from pomil.eval.plots import figure1
from pomil.learners import ADVERSARIAL, LEARNERS
from pomil.training import write_json


@dataclass(frozen=True)
class RayOptions:
    """Where a reproduction's (learner, seed) runs go: in local worker processes, one after another, or on Ray."""

    jobs: int = option(0, "without --ray: runs at a time, each in its own process on one torch thread (0: one per "
                          "usable CPU core; 1: one after another in this process on every core)", within="[0, inf)")
    ray: bool = option(False, "run the (learner, seed) runs in parallel on Ray (optional extra; 1 CPU each)")
    ray_address: str = option("", "with --ray: address of an existing Ray cluster (default: a local Ray started here)")


@dataclass(frozen=True)
class LearnerRuns(RayOptions):
    """What a reproduction over learners has: which learners, and how long each trains."""

    learners: tuple[str, ...] = option(("bc-mlp", "bc-gru", "gail", "infogail", "infogail-pomdp"),
                                       "comma-separated learners: bc-mlp, bc-gru, gail, infogail, infogail-pomdp, "
                                       "and the ablations igp-warm-start, igp-no-mi, igp-shared-belief, "
                                       "igp-policy-belief, igp-no-bc")
    bc_iterations: int = option(0, "gradient steps for behaviour cloning (0: BCConfig's default)", within="[0, inf)")
    adversarial_iterations: int = option(0,
                                         "iterations for gail, infogail and infogail-pomdp (0: AdversarialConfig's "
                                         "default)",
                                         within="[0, inf)")
    adversarial_config: str = option("", "JSON file of AdversarialConfig settings that replace the defaults")
    bc_config: str = option("", "JSON file of BCConfig settings that replace the defaults (bc-mlp, bc-gru)")
    resume_runs: bool = option(False, "continue each (learner, seed) run from its checkpoint under --runs when it has "
                                      "one (a finished run is only evaluated again); its settings must not change")


def seed_list(cfg: Any) -> list[int]:
    """The training seeds of a reproduction: ``first_seed`` (0 where a config has none) and the ``seeds`` after it."""
    first = getattr(cfg, "first_seed", 0)
    return list(range(first, first + cfg.seeds))


@dataclass(frozen=True)
class CirclesReproConfig(LearnerRuns):
    out: str = option("runs/results/circles", "results directory (metrics.json, table.md, figure.png); the committed "
                                              "results are results/circles (pass --out results/circles to update them)")
    runs: str = option("runs/circles", "where each run's checkpoint and logs go")
    demos: str = option("data/circles.npz", "demonstrations; recorded (400 episodes, seed 0) if missing")
    seeds: int = option(10, "training seeds per learner (0 .. seeds-1)", within="[1, inf)")
    episodes_per_code: int = option(100, "evaluation rollouts per latent code", within="[1, inf)")
    progress: bool = option(True, "show progress bars")

    def __post_init__(self) -> None:
        check_runs(self)

    @property
    def demos_file(self) -> str:
        return self.demos


def check_runs(cfg: Any) -> None:
    """Seeds, iterations and learner names of a reproduction config."""
    check_fields(cfg)
    unknown = sorted(set(cfg.learners) - set(LEARNERS))
    if unknown or not cfg.learners:
        raise ValueError(f"unknown learners {unknown}; choose from {sorted(LEARNERS)}")


# Every learner trains with its library defaults (what `pomil train <learner> --demos D`
# runs) on a reproduction config (circles or Hopper: both have demos_file, bc_iterations,
# adversarial_iterations, adversarial_config, progress).
def train_learner(cfg: Any, name: str, seed: int, run_dir: Path) -> Path:
    """Train learner ``name`` (:data:`pomil.learners.LEARNERS`) for one seed of a reproduction."""
    learner = LEARNERS[name]
    resume = cfg.resume_runs and (run_dir / "checkpoint.pt").exists()
    if name in ADVERSARIAL:
        return learner.train(adversarial_config(cfg, name, seed, run_dir), resume=resume)
    return learner.train(bc_config(cfg, name, seed, run_dir), resume=resume)


def bc_config(cfg: Any, learner: str, seed: int, run_dir: Path):
    """The defaults, then the user's --bc-config file and --bc-iterations, then this run's own fields."""
    from pomil.config import load_config_file

    values = load_config_file(cfg.bc_config) if cfg.bc_config else {}
    values.update({"iterations": cfg.bc_iterations} if cfg.bc_iterations else {})
    values.update(demos=cfg.demos_file, out=str(run_dir), seed=seed, progress=cfg.progress)
    return LEARNERS[learner].make_config(values, source=cfg.bc_config or "the reproduction's settings")


def adversarial_config(cfg: Any, learner: str, seed: int, run_dir: Path, demos: str | None = None, **own: Any):
    """The defaults, then the user's --adversarial-config file, then this run's own fields
    (``demos``: default the reproduction's ``demos_file``; ``own``: the experiment's, e.g. code_kind)."""
    from pomil.algos.adversarial import AdversarialConfig
    from pomil.config import from_dict, load_config_file

    iterations = getattr(cfg, "adversarial_iterations", 0)
    values: dict[str, Any] = {"iterations": iterations} if iterations else {}
    if cfg.adversarial_config:
        values.update(load_config_file(cfg.adversarial_config))
    values.update(demos=demos or cfg.demos_file, out=str(run_dir), seed=seed, progress=cfg.progress,
                  **LEARNERS[learner].fixed, **own)  # the learner's name: its kind, an ablation's part taken away
    return from_dict(AdversarialConfig, values, source=cfg.adversarial_config or "the reproduction's settings")


SUMMARY_KEYS = ("mean_purity", "min_purity", "modes_covered", "nmi", "overall_none_share")
# A seed succeeds when every code is >= 95% one mode, every mode is some code's and NMI >= 0.9.
MODES_SUCCESS = {"min_purity": 0.95, "nmi": 0.9}


def modes_success(m: dict[str, Any]) -> bool:
    """Every code >= 95% in one mode, every mode covered, NMI >= 0.9."""
    return (m["min_purity"] >= MODES_SUCCESS["min_purity"] and m["nmi"] >= MODES_SUCCESS["nmi"]
            and m["modes_covered"] == len(m["per_code"][0]["mode_share"]))


def summarise(runs: list[dict[str, Any]]) -> dict[str, list[float]]:
    """[mean, std] over seeds (population std; 0 for one seed) of each key figure."""
    return {k: [float(np.mean([r[k] for r in runs])), float(np.std([r[k] for r in runs]))] for k in SUMMARY_KEYS}


def markdown_table(results: dict[str, Any]) -> str:
    n = results["seeds"]
    lines = [
        "| learner | successes | per-code purity | min purity | modes covered | NMI(code, mode) | none share "
        "| wall s / seed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results["learners"].items():
        s = r["summary"]
        fmt = lambda k, p=2, s=s: f"{s[k][0]:.{p}f} ± {s[k][1]:.{p}f}"  # noqa: E731
        wins = sum(modes_success(run) for run in r["runs"])
        lines.append(f"| {name} | {wins}/{len(r['runs'])} | {fmt('mean_purity')} | {fmt('min_purity')} | "
                     f"{fmt('modes_covered', 1)} | "
                     f"{fmt('nmi')} | {fmt('overall_none_share')} | {np.mean(r['wall_s']):.0f} |")
    lines.append("")
    lines.append(f"mean ± std over {n} seed(s); {results['episodes_per_code']} stochastic rollouts per code; "
                 f"learners without latent codes are scored as a single code (NMI 0 by definition). A seed succeeds "
                 f"when its min purity is >= {MODES_SUCCESS['min_purity']}, every mode is covered and NMI >= "
                 f"{MODES_SUCCESS['nmi']}.")
    return "\n".join(lines) + "\n"


def reproduce_circles(cfg: CirclesReproConfig) -> dict[str, Any]:
    t_start = time.perf_counter()
    demos_path = Path(cfg.demos)
    if not demos_path.exists():
        demos = record_circles_demos(make_spec(), 400, seed=0)
        demos.save(demos_path)
        print(f"recorded {demos_path}: {demos.num_episodes} expert episodes")
    demos = Demonstrations.load(demos_path)
    if demos.metadata.get("env_id") != CIRCLES_ID:
        raise PomilError(f"{demos_path}: field 'metadata.env_id': expected {CIRCLES_ID!r}, got "
                         f"{demos.metadata.get('env_id')!r}")
    results: dict[str, Any] = {
        "experiment": "circles", "config": to_dict(cfg), "seeds": cfg.seeds,
        "episodes_per_code": cfg.episodes_per_code, "demos": str(demos_path),
        "adversarial_settings": {
            k: v for k, v in to_dict(adversarial_config(cfg, "infogail-pomdp", 0, Path("."))).items()
            if k not in ("learner", "out", "seed", "progress")},
        "machine": {"python": sys.version.split()[0], "platform": platform.platform()},
        "learners": {},
    }
    rollouts: dict[str, np.ndarray] = {}
    T = int(demos.episode_lengths[0])
    rollouts["experts/positions"] = (demos.states.reshape(demos.num_episodes, T,
                                                          -1)[:, 1:, :2] if demos.states is not None
                                     else np.zeros((0, T - 1, 2)))
    rollouts["experts/groups"] = demos.labels if demos.labels is not None else np.zeros(0, np.int64)

    def report(r, n, total) -> None:
        m = r.value["metrics"]
        _say(f"[{n}/{total}] {r.name}: purity {m['mean_purity']:.2f}, modes covered {m['modes_covered']}, "
            f"NMI {m['nmi']:.2f}, none {m['overall_none_share']:.2f} ({r.wall_s:.0f} s)")

    done = _run_all(cfg, _circles_job, report)
    for name in cfg.learners:
        runs = [done[name, seed]["metrics"] for seed in range(cfg.seeds)]
        results["learners"][name] = {"runs": runs, "summary": summarise(runs),
                                     "wall_s": [done[name, seed]["wall_s"] for seed in range(cfg.seeds)]}
        rollouts[f"{name}/positions"] = done[name, 0]["positions"]
        rollouts[f"{name}/groups"] = done[name, 0]["codes"]
        if name == "infogail-pomdp":  # shipped, so `pomil evaluate` works without training
            TrainedPolicy.load(runs[0]["checkpoint"]).save(Path(cfg.out) / "infogail-pomdp.pt")
    results["wall_time_s"] = time.perf_counter() - t_start
    write_results(Path(cfg.out), results, markdown_table(results), rollouts, plot_from_rollouts)
    return results


def write_results(out: Path, results: dict[str, Any], table: str, rollouts: dict[str, np.ndarray],
                  figure: Callable[[Path, Path], None]) -> None:
    """A reproduction's files in ``out``: metrics.json, table.md, rollouts.npz and the figure
    that ``figure(rollouts path, figure path)`` draws from them; prints the table."""
    write_json(out / "metrics.json", results)
    atomic_write(out / "table.md", lambda f: f.write(table.encode()))
    atomic_write(out / "rollouts.npz", lambda f: np.savez_compressed(f, **rollouts))
    figure(out / "rollouts.npz", out / "figure.png")
    print(table)
    print(f"wrote {out}/metrics.json, table.md, figure.png in {results['wall_time_s']:.0f} s")


def _circles_job(cfg: CirclesReproConfig, name: str, seed: int) -> dict[str, Any]:
    _say(f"[{name}] seed {seed}: training")
    t0 = time.perf_counter()
    ckpt = train_learner(cfg, name, seed, Path(cfg.runs) / name / f"seed{seed}")
    wall = time.perf_counter() - t0
    metrics, roll = evaluate_circles(TrainedPolicy.load(ckpt), cfg.episodes_per_code, seed=1000 + seed)
    metrics.update(checkpoint=str(ckpt), train_seed=seed)
    return {"metrics": metrics, "wall_s": wall, "positions": roll["positions"], "codes": roll["codes"]}


def _say(line: str) -> None:
    """One write per line, flushed: runs in other processes print beside this one."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _run_all(cfg: Any, job: Callable[..., dict[str, Any]], report: Callable,
             names: tuple[str, ...] | None = None) -> dict[tuple[str, int], dict[str, Any]]:
    """Every (name, seed) of a reproduction, ``cfg.jobs`` at a time or on Ray; the first failure stops it.
    ``names``: the learners (default) or, for circles-modes, the cases."""
    from pomil.parallel import run_jobs, usable_cpus

    keys = [(name, seed) for name in (names or cfg.learners) for seed in seed_list(cfg)]
    workers = 1 if cfg.ray else min(cfg.jobs or usable_cpus(), len(keys))
    if workers > 1:  # bars of runs side by side would overwrite each other: a line per finished run instead
        cfg = dataclasses.replace(cfg, progress=False)
    if cfg.ray:  # workers may start elsewhere: every path absolute
        where = cfg.path if hasattr(cfg, "path") else (lambda k: getattr(cfg, k))  # Hopper's defaults live in path()
        absolute = {k: str(Path(where(k)).resolve()) for k in ("out", "runs", "demos") if hasattr(cfg, k)}
        for k in ("adversarial_config", "bc_config"):
            if getattr(cfg, k, ""):
                absolute[k] = str(Path(getattr(cfg, k)).resolve())
        cfg = dataclasses.replace(cfg, progress=False, **absolute)
    costs = None if names else [LEARNERS[name].cost for name, _ in keys]  # the cases of circles-modes cost alike
    results = run_jobs(job, [(cfg, name, seed) for name, seed in keys], [f"[{n}] seed {s}" for n, s in keys],
                       ray=cfg.ray, address=cfg.ray_address or None, capture_errors=False, on_done=report,
                       costs=costs, workers=workers)
    return {key: r.value for key, r in zip(keys, results, strict=True)}


def plot_from_rollouts(rollouts_path: Path, figure_path: Path) -> None:
    with np.load(rollouts_path, allow_pickle=False) as r:
        names = list(dict.fromkeys(k.split("/")[0] for k in r.files))
        panels = [(n, r[f"{n}/positions"], r[f"{n}/groups"], "mode" if n == "experts" else "code") for n in names]
    figure1(panels, figure_path)


# ================================================================ circles-modes
def _through(*circles: tuple[float, float, int]) -> tuple[Circle, ...]:
    return tuple(Circle.through_origin(*c) for c in circles)


# The cases of ``pomil reproduce circles-modes``: the two presets and three sets
# built through the Python API, each with different radii and directions.  In
# ``five`` two circles share their centre's ray (internally tangent at the origin)
# and are travelled the same way: they start in the same direction and part only
# by their curvature.  In every set, pairs of circles share the tangent at the origin.
MODES_CASES: dict[str, tuple[Circle, ...]] = {
    "two": circles_preset("two"),
    "four": circles_preset("four"),
    "three": _through((90, 4.0, 1), (210, 5.0, -1), (330, 6.0, 1)),
    "five": _through((90, 3.0, 1), (90, 6.0, 1), (270, 5.0, -1), (0, 4.0, 1), (180, 4.0, -1)),
    "six": _through((90, 3.0, 1), (90, 6.0, -1), (270, 4.0, -1), (270, 7.0, 1), (0, 5.0, 1), (180, 5.0, -1)),
}


@dataclass(frozen=True)
class CirclesModesConfig(RayOptions):
    out: str = option("runs/results/circles-modes", "results directory (metrics.json, table.md); "
                                                    "the committed results are results/circles-modes")
    runs: str = option("runs/circles-modes", "where each case's demonstrations and each run's checkpoint and logs go")
    cases: tuple[str, ...] = option(tuple(MODES_CASES), f"comma-separated cases: {', '.join(MODES_CASES)}")
    seeds: int = option(10, "training seeds per case (0 .. seeds-1)", within="[1, inf)")
    learner: Literal["infogail", "infogail-pomdp"] = option("infogail-pomdp", "the learner, with its default settings")
    adversarial_config: str = option("", "JSON file of AdversarialConfig settings that replace the defaults")
    episodes_per_mode: int = option(100, "demonstration episodes per mode (recorded with seed 0)", within="[1, inf)")
    episodes_per_code: int = option(100, "evaluation rollouts per latent code", within="[1, inf)")
    progress: bool = option(True, "show progress bars")

    def __post_init__(self) -> None:
        check_fields(self)
        unknown = sorted(set(self.cases) - set(MODES_CASES))
        if unknown or not self.cases:
            raise ValueError(f"unknown cases {unknown}; choose from {list(MODES_CASES)}")


def _modes_job(cfg: CirclesModesConfig, case: str, seed: int) -> dict[str, Any]:
    from pomil.algos.adversarial import train_adversarial

    t0 = time.perf_counter()
    run_dir = Path(cfg.runs) / case / f"seed{seed}"
    ckpt = train_adversarial(adversarial_config(cfg, cfg.learner, seed, run_dir,
                                                demos=str(Path(cfg.runs) / f"{case}.npz")))
    wall = time.perf_counter() - t0
    metrics, _ = evaluate_circles(TrainedPolicy.load(ckpt), cfg.episodes_per_code, seed=1000 + seed)
    metrics.update(checkpoint=str(ckpt), train_seed=seed, success=modes_success(metrics))
    return {"metrics": metrics, "wall_s": wall}


def modes_table(results: dict[str, Any]) -> str:
    lines = ["| case | modes | successes | min purity | mean purity | modes covered | NMI | none share "
             "| wall s / seed |",
             "|---|---|---|---|---|---|---|---|---|"]
    for case, r in results["cases"].items():
        runs = r["runs"]
        ms = lambda k, p=2, runs=runs: (  # noqa: E731
            f"{np.mean([x[k] for x in runs]):.{p}f} ± {np.std([x[k] for x in runs]):.{p}f}")
        lines.append(f"| {case} | {r['modes']} | {sum(x['success'] for x in runs)}/{len(runs)} | {ms('min_purity')} | "
                     f"{ms('mean_purity')} | {ms('modes_covered', 1)} | {ms('nmi')} | {ms('overall_none_share')} | "
                     f"{np.mean(r['wall_s']):.0f} |")
    lines += ["", f"{results['learner']} with its default settings; mean ± std over {results['seeds']} seeds, "
              f"{results['episodes_per_code']} stochastic rollouts per code. A seed succeeds when its min purity is "
              f">= {MODES_SUCCESS['min_purity']}, every mode is covered and NMI >= {MODES_SUCCESS['nmi']}."]
    return "\n".join(lines) + "\n"


def reproduce_circles_modes(cfg: CirclesModesConfig) -> dict[str, Any]:
    """Default-settings training on circle sets of 2 to 6 modes, over seeds: success counts and per-seed figures."""
    t_start = time.perf_counter()
    for case in cfg.cases:  # every case's demonstrations, recorded once (seed 0)
        path = Path(cfg.runs) / f"{case}.npz"
        if not path.exists():
            spec = CirclesSpec(MODES_CASES[case])
            record_circles_demos(spec, cfg.episodes_per_mode * spec.num_modes, seed=0).save(path)

    def report(r, n, total) -> None:
        m = r.value["metrics"]
        _say(f"[{n}/{total}] {r.name}: min purity {m['min_purity']:.2f}, modes covered {m['modes_covered']}, "
            f"NMI {m['nmi']:.2f}{'' if m['success'] else ' (below target)'} ({r.wall_s:.0f} s)")

    by_key = _run_all(cfg, _modes_job, report, names=cfg.cases)
    results: dict[str, Any] = {
        "experiment": "circles-modes", "config": to_dict(cfg), "learner": cfg.learner, "seeds": cfg.seeds,
        "episodes_per_code": cfg.episodes_per_code, "success_criteria": MODES_SUCCESS,
        "machine": {"python": sys.version.split()[0], "platform": platform.platform()}, "cases": {},
    }
    for case in cfg.cases:
        runs = [by_key[case, s]["metrics"] for s in range(cfg.seeds)]
        results["cases"][case] = {
            "modes": len(MODES_CASES[case]), "circles": CirclesSpec(MODES_CASES[case]).to_dict()["circles"],
            "successes": sum(r["success"] for r in runs), "runs": runs,
            "wall_s": [by_key[case, s]["wall_s"] for s in range(cfg.seeds)],
        }
    results["wall_time_s"] = time.perf_counter() - t_start
    out = Path(cfg.out)
    write_json(out / "metrics.json", results)
    table = modes_table(results)
    atomic_write(out / "table.md", lambda f: f.write(table.encode()))
    print(table)
    print(f"wrote {out}/metrics.json, table.md in {results['wall_time_s']:.0f} s")
    return results


# ========================================================== circles-continuous
CONTINUOUS_SUCCESS = 0.9
"""A seed succeeds when |Spearman rho| between code value and fitted radius is at least this."""


@dataclass(frozen=True)
class CirclesContinuousConfig(RayOptions):
    out: str = option("runs/results/circles-continuous", "results directory (metrics.json, table.md, figure.png); "
                                                         "the committed results are results/circles-continuous")
    runs: str = option("runs/circles-continuous", "where each run's checkpoint and logs go")
    demos: str = option("runs/circles-continuous/demos.npz",
                        "demonstrations; recorded if missing (one circle, radius uniform in radius_range, seed 0)")
    radius_range: tuple[float, ...] = option((3.0, 7.0), "R1,R2: the demonstrations' radii, uniform in [R1, R2]",
                                             within="(0, inf)")
    demo_episodes: int = option(400, "demonstration episodes when they are recorded", within="[1, inf)")
    seeds: int = option(3, "training seeds (0 .. seeds-1)", within="[1, inf)")
    learner: Literal["infogail", "infogail-pomdp"] = option("infogail-pomdp", "the learner, with its default "
                                                                              "settings and code_kind continuous")
    adversarial_iterations: int = option(0, "training iterations (0: AdversarialConfig's default)", within="[0, inf)")
    adversarial_config: str = option("", "JSON file of AdversarialConfig settings that replace the defaults "
                                         "(code_dim, code_prior, ...)")
    code_values: int = option(9, "evaluation: code values evenly over the prior", within="[2, inf)")
    episodes_per_value: int = option(20, "evaluation: stochastic rollouts per code value", within="[1, inf)")
    progress: bool = option(True, "show progress bars")

    def __post_init__(self) -> None:
        check_fields(self)
        if len(self.radius_range) != 2 or self.radius_range[0] > self.radius_range[1]:
            raise ValueError(f"radius_range: expected two radii R1,R2 with R1 <= R2, got {self.radius_range}")


def _continuous_job(cfg: CirclesContinuousConfig, learner: str, seed: int) -> dict[str, Any]:
    from pomil.algos.adversarial import train_adversarial
    from pomil.eval.circles import evaluate_code_radius

    _say(f"[{learner}] seed {seed}: training")
    t0 = time.perf_counter()
    ckpt = train_adversarial(adversarial_config(cfg, learner, seed, Path(cfg.runs) / learner / f"seed{seed}",
                                                demos=cfg.demos, code_kind="continuous"))
    wall = time.perf_counter() - t0
    metrics, roll = evaluate_code_radius(TrainedPolicy.load(ckpt), cfg.code_values, cfg.episodes_per_value,
                                         seed=1000 + seed)
    metrics.update(checkpoint=str(ckpt), train_seed=seed, success=abs(metrics["spearman"]) >= CONTINUOUS_SUCCESS,
                   warm_start_spearman=_warm_start_value(ckpt.parent / "metrics.csv", "eval/spearman"))
    return {"metrics": metrics, "wall_s": wall, "positions": roll["positions"], "code_values": roll["code_values"],
            "radii": roll["radii"]}


def _warm_start_value(csv_path: Path, key: str) -> float | None:
    """``key`` in a run's metrics.csv at iteration 0 (the evaluation after the warm start), None when not logged."""
    import csv

    if not csv_path.exists():
        return None
    with open(csv_path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("iteration") == "0" and r.get(key)]
    return float(rows[0][key]) if rows else None


def continuous_table(results: dict[str, Any]) -> str:
    runs = results["runs"]
    lines = ["| seed | Spearman rho(code, radius) | after the warm start | median radius per code value, low .. high "
             "| success | wall s |", "|---|---|---|---|---|---|"]
    for r, wall in zip(runs, results["wall_s"], strict=True):
        lo, hi = r["radius_covered"]
        warm = "-" if r.get("warm_start_spearman") is None else f"{r['warm_start_spearman']:+.3f}"
        lines.append(f"| {r['train_seed']} | {r['spearman']:+.3f} | {warm} | {lo:.2f} .. {hi:.2f} | "
                     f"{'yes' if r['success'] else 'no'} | {wall:.0f} |")
    rho = np.abs([r["spearman"] for r in runs])
    r1, r2 = results["radius_range"]
    settings = (f"the settings of {results['config']['adversarial_config']}" if results["config"]["adversarial_config"]
                else "its default settings")
    lines += ["", f"{results['learner']}, code_kind continuous ({results['code_prior']} prior, {results['code_dim']} "
              f"dim), otherwise {settings}. |rho| {rho.mean():.3f} ± {rho.std():.3f} over "
              f"{len(runs)} seeds; {sum(r['success'] for r in runs)}/{len(runs)} seeds with |rho| >= "
              f"{CONTINUOUS_SUCCESS}; the largest |rho| these tied code values allow (no two code values' radii "
              f"overlap) is {runs[0].get('spearman_max', float('nan')):.3f}. Each seed: {results['code_values']} "
              f"code values evenly over the prior, "
              f"{results['episodes_per_value']} stochastic rollouts each, a least-squares circle fitted to every "
              f"trajectory. Demonstrations: radius uniform in [{r1:g}, {r2:g}] (their middle 89% spans "
              f"{r1 + (r2 - r1) / 18:.2f} .. {r2 - (r2 - r1) / 18:.2f}, the range the code values' quantiles "
              f"cover). Total wall time {results['wall_time_s']:.0f} s."]
    return "\n".join(lines) + "\n"


def reproduce_circles_continuous(cfg: CirclesContinuousConfig) -> dict[str, Any]:
    """Continuous codes on circles whose radius varies: code against fitted radius over seeds."""
    from pomil.eval.plots import code_radius_figure

    t_start = time.perf_counter()
    path = Path(cfg.demos)
    radius_range = (float(cfg.radius_range[0]), float(cfg.radius_range[1]))
    if not path.exists():
        demos = record_circles_demos(make_spec("one", sum(radius_range) / 2), cfg.demo_episodes, seed=0,
                                     radius_range=radius_range)
        demos.save(path)
        print(f"recorded {path}: {demos.num_episodes} expert episodes, radius uniform in {list(radius_range)}")
    demos = Demonstrations.load(path)
    if "episode_radii" not in demos.metadata or demos.states is None:
        raise PomilError(f"{path}: field 'metadata.episode_radii': expected circles demonstrations of varying radius "
                         "(pomil demos circles --radius-range R1,R2)")

    def report(r, n, total) -> None:
        m = r.value["metrics"]
        _say(f"[{n}/{total}] {r.name}: Spearman rho {m['spearman']:+.3f}, radius {m['radius_covered'][0]:.2f} .. "
            f"{m['radius_covered'][1]:.2f}{'' if m['success'] else ' (below target)'} ({r.wall_s:.0f} s)")

    done = _run_all(cfg, _continuous_job, report, names=(cfg.learner,))
    runs = [done[cfg.learner, s]["metrics"] for s in range(cfg.seeds)]
    settings = adversarial_config(cfg, cfg.learner, 0, Path("."), demos=cfg.demos, code_kind="continuous")
    results: dict[str, Any] = {
        "experiment": "circles-continuous", "config": to_dict(cfg), "learner": cfg.learner, "seeds": cfg.seeds,
        "demos": str(path), "radius_range": demos.metadata.get("radius_range", list(radius_range)),
        "code_dim": settings.code_dim, "code_prior": settings.code_prior, "code_values": cfg.code_values,
        "episodes_per_value": cfg.episodes_per_value, "success_criterion": {"abs_spearman": CONTINUOUS_SUCCESS},
        "adversarial_settings": {k: v for k, v in to_dict(settings).items()
                                 if k not in ("learner", "out", "seed", "progress")},
        "machine": {"python": sys.version.split()[0], "platform": platform.platform()},
        "runs": runs, "wall_s": [done[cfg.learner, s]["wall_s"] for s in range(cfg.seeds)],
    }
    rho = np.abs([r["spearman"] for r in runs])
    results["summary"] = {"abs_spearman": [float(rho.mean()), float(rho.std())],
                          "successes": int(sum(r["success"] for r in runs))}
    out = Path(cfg.out)
    T = int(demos.episode_lengths[0])
    rollouts = {"experts/positions": demos.states.reshape(demos.num_episodes, T, -1)[:, 1:, :2],
                "experts/radii": np.asarray(demos.metadata["episode_radii"], dtype=np.float64)}
    for s in range(cfg.seeds):
        for key in ("positions", "code_values", "radii"):
            rollouts[f"seed{s}/{key}"] = done[cfg.learner, s][key]
    TrainedPolicy.load(runs[0]["checkpoint"]).save(out / f"{cfg.learner}.pt")
    results["wall_time_s"] = time.perf_counter() - t_start
    write_results(out, results, continuous_table(results), rollouts, code_radius_figure)
    return results


# ====================================================================== Hopper
METRICS = ("normalised_return", "progress", "displacement_ratio")
TASKS_SUCCESS = {"normalised_return": 0.7, "progress": 0.7}
"""A seed succeeds when, on every task, the code matched to it reaches these figures (per seed): it imitates every
task, each with its own code."""


def tasks_success(m: dict[str, Any]) -> bool:
    """Whether one run's task scores (:func:`pomil.eval.tasks.evaluate_tasks`) meet :data:`TASKS_SUCCESS`."""
    return all(t[k] >= v for t in m["tasks"].values() for k, v in TASKS_SUCCESS.items())



@dataclass(frozen=True)
class HopperReproConfig(LearnerRuns):
    setting: Literal["paper", "standard"] = option("paper", "paper: 128-step episodes, no unhealthy termination; "
                                                            "standard: Hopper's own 1000 steps")
    out: str = option("", "results directory (default: runs/results/hopper[-standard]; the committed results are "
                          "results/hopper[-standard])")
    runs: str = option("", "where each run's checkpoint and logs go (default: runs/hopper[-standard])")
    demos: str = option("", "demonstrations (default: data/hopper-SETTING.npz); recorded from the experts if missing")
    demo_episodes: int = option(-1, "episodes per task when the demonstrations are recorded; -1: the setting's, "
                                    "paper 200, standard 100", within="[-1, inf)")
    demo_action_noise: float = option(-1.0, "DART action noise when the demonstrations are recorded (pomil demos "
                                            "hopper --action-noise); -1: the setting's, paper 0, standard 0.1",
                                      within="[-1, inf)")
    seeds: int = option(5, "training seeds per learner (first_seed .. first_seed+seeds-1)", within="[1, inf)")
    first_seed: int = option(0, "the first training seed: runs seeds first_seed .. first_seed+seeds-1 (to add seeds "
                                "to a reproduction; `pomil reproduce merge` joins the results)", within="[0, inf)")
    episodes_per_code: int = option(50, "final evaluation episodes per latent code and task (deterministic policy)",
                                    within="[1, inf)")
    progress: bool = option(True, "show progress bars")

    def __post_init__(self) -> None:
        if self.setting not in ("paper", "standard"):
            raise ValueError(f"setting must be 'paper' or 'standard', got {self.setting!r}")
        demo_recording(self.setting, self.demo_episodes, self.demo_action_noise,
                       ("demo_episodes", "demo_action_noise"))  # the values' check
        check_runs(self)

    @property
    def demos_file(self) -> str:
        return str(self.path("demos"))

    def path(self, name: str) -> Path:
        suffix = "" if self.setting == "paper" else f"-{self.setting}"
        defaults = {"out": f"runs/results/hopper{suffix}",
                    "runs": f"runs/{Path(self.out).name}" if self.out else f"runs/hopper{suffix}",
                    "demos": f"data/hopper-{self.setting}.npz"}
        return Path(getattr(self, name) or defaults[name])


def hopper_demos(cfg: HopperReproConfig) -> Path:
    """The demonstrations file, recorded from the shipped experts if missing."""
    from pomil.demos import record_hopper_demos

    path = cfg.path("demos")
    if path.exists():
        return path
    experts = HOPPER_EXPERTS[cfg.setting]
    missing = [p for p in experts.values() if not Path(p).exists()]
    if missing:
        raise PomilError(f"{path} is missing and so are the experts to record it from ({', '.join(missing)}); "
                         f"train them with `pomil experts hopper --task forward|backward --setting {cfg.setting}`")
    episodes, noise = demo_recording(cfg.setting, cfg.demo_episodes, cfg.demo_action_noise)  # -1: the setting's
    demos = record_hopper_demos(experts, episodes, cfg.setting, action_noise=noise)
    demos.save(path)
    dart = f" (DART action noise {noise:g})" if noise else ""
    print(f"recorded {path}: {demos.num_episodes} expert episodes{dart}", flush=True)
    return path


def _curve(run_dir: Path, tasks: list[str]) -> dict[str, list[float]]:
    """Evaluation rows of a run's metrics.csv: env steps and normalised return per task."""
    import csv

    path = run_dir / "metrics.csv"
    rows: list[dict[str, str]] = []
    if path.exists():
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    rows = [r for r in rows if r.get("eval/env_steps")]
    curve = {"env_steps": [float(r["eval/env_steps"]) for r in rows]}
    for t in tasks:
        curve[t] = [float(r[f"eval/{t}/normalised_return"]) for r in rows]
    return curve


SPEED_METRICS = ("on_task_share", "speed_error")
"""Per-task figures of the behaviour by speed (:func:`pomil.eval.tasks.evaluate_tasks`, when the
demonstrations record the experts' speeds)."""


def task_summary(runs: list[dict[str, Any]], tasks: list[str]) -> dict[str, dict[str, list[float]]]:
    """[mean, std] over seeds of each task's three figures (and its speed figures where every run has them)."""
    metrics = METRICS + (SPEED_METRICS if all("behaviour" in r for r in runs) else ())
    return {t: {m: [float(np.mean([r["tasks"][t][m] for r in runs])), float(np.std([r["tasks"][t][m] for r in runs]))]
                for m in metrics} for t in tasks}


def hopper_table(results: dict[str, Any]) -> str:
    tasks = results["tasks"]
    head = ("| learner | successes | " + " | ".join(f"{t}: norm. return | {t}: progress | {t}: displacement"
                                                   for t in tasks) + " | wall s / seed |")
    lines = [head, "|---|---|" + "---|" * (3 * len(tasks)) + "---|"]
    for name, r in results["learners"].items():
        s = r["summary"]
        cells = [f"{s[t][m][0]:.2f} ± {s[t][m][1]:.2f}" for t in tasks for m in METRICS]
        wins = f"{sum(tasks_success(run) for run in r['runs'])}/{len(r['runs'])}"
        lines.append(f"| {name} | {wins} | " + " | ".join(cells) + f" | {np.mean(r['wall_s']):.0f} |")
    reference = results["reference"]
    lines += ["", f"mean ± std over {results['seeds']} seed(s), {results['setting']} setting; each task scored for "
              f"the code matched to it ({results['episodes_per_code']} deterministic episodes per code and task). "
              "A seed succeeds when on every task its matched code reaches a normalised return and a progress of "
              f"at least {TASKS_SUCCESS['normalised_return']:g}. "
              "Expert returns: " + ", ".join(f"{t} {v:.1f}" for t, v in reference["expert_returns"].items())
              + "; zero-action returns: " + ", ".join(f"{t} {v:.1f}" for t, v in reference["still_returns"].items())
              + "."]
    with_speed = [n for n, r in results["learners"].items() if "on_task_share" in r["summary"][tasks[0]]]
    if with_speed:
        lines += ["", "| learner | " + " | ".join(f"{t}: on-task share | {t}: speed error (m/s)" for t in tasks)
                  + " | purity of the matched codes |", "|---|" + "---|" * (2 * len(tasks) + 1)]
        for name in with_speed:
            r = results["learners"][name]
            purity = [np.mean([run["behaviour"][f"code{run['tasks'][t]['code']}"]["purity"] for t in tasks])
                      for run in r["runs"]]
            cells = [f"{r['summary'][t][m][0]:.2f} ± {r['summary'][t][m][1]:.2f}" for t in tasks for m in SPEED_METRICS]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {np.mean(purity):.2f} ± {np.std(purity):.2f} |")
        lines += ["", "Each evaluation episode (every task's rollouts of a code pooled: the tasks share dynamics) is "
                  "assigned to the task whose expert mean speed is nearest its own. On-task share: the share of the "
                  "matched code's episodes nearest its task; speed error: |the code's mean speed - the expert's|; "
                  "purity: a code's largest share. Expert speeds: "
                  + ", ".join(f"{t} {v:.2f} m/s" for t, v in reference["expert_speed"].items()) + "."]
    return "\n".join(lines) + "\n"


def _tasks_job(cfg: HopperReproConfig, name: str, seed: int) -> dict[str, Any]:
    from pomil.eval.tasks import evaluate_tasks, reference_of

    _say(f"[{name}] seed {seed}: training")
    t0 = time.perf_counter()
    run_dir = cfg.path("runs") / name / f"seed{seed}"
    ckpt = train_learner(cfg, name, seed, run_dir)
    wall = time.perf_counter() - t0
    demos_md = Demonstrations.load(cfg.demos_file).metadata
    reference = reference_of(demos_md, cfg.demos_file)
    metrics = evaluate_tasks(TrainedPolicy.load(ckpt), reference, cfg.episodes_per_code, seed=1000 + seed)
    metrics.update(checkpoint=str(ckpt), train_seed=seed, success=tasks_success(metrics))
    return {"metrics": metrics, "wall_s": wall, "curve": _curve(run_dir, list(reference["tasks"]))}


def reproduce_hopper(cfg: HopperReproConfig) -> dict[str, Any]:
    """The Hopper protocol; on any multi-task demonstrations (``pomil reproduce tasks``) when ``demos`` names them."""
    from pomil.eval.tasks import reference_of

    t_start = time.perf_counter()
    demos_path = hopper_demos(cfg)
    demos = Demonstrations.load(demos_path)
    reference = reference_of(demos.metadata, str(demos_path))
    tasks = list(reference["tasks"])
    out = cfg.path("out")
    results: dict[str, Any] = {
        "experiment": "hopper" if env_family(str(demos.metadata.get("env_id"))).name == "hopper" else "tasks",
        "env_id": demos.metadata.get("env_id"), "setting": demos.metadata.get("setting", cfg.setting),
                               "config": to_dict(cfg),
        "seeds": cfg.seeds, "tasks": tasks,
        "episodes_per_code": cfg.episodes_per_code, "demos": str(demos_path), "reference": reference,
        "success_criteria": TASKS_SUCCESS,
        "adversarial_settings": {
            k: v for k, v in to_dict(adversarial_config(cfg, "infogail-pomdp", 0, Path("."))).items()
            if k not in ("learner", "out", "seed", "progress")},
        "bc_settings": {k: v for k, v in to_dict(bc_config(cfg, "bc-gru", 0, Path("."))).items()
                        if k not in ("policy", "out", "seed", "progress")},
        "machine": {"python": sys.version.split()[0], "platform": platform.platform()},
        "learners": {},
    }

    def report(r, n, total) -> None:
        m = r.value["metrics"]
        _say(f"[{n}/{total}] {r.name}: " + "; ".join(
            f"{t} (code {m['tasks'][t]['code']}): norm {m['tasks'][t]['normalised_return']:.2f}, "
            f"progress {m['tasks'][t]['progress']:.2f}, displacement {m['tasks'][t]['displacement_ratio']:.2f}"
            + (f", on-task {m['tasks'][t]['on_task_share']:.2f}" if "on_task_share" in m["tasks"][t] else "")
            for t in tasks) + f" ({r.wall_s:.0f} s)")

    done = _run_all(cfg, _tasks_job, report)
    for name in cfg.learners:
        runs = [done[name, seed]["metrics"] for seed in seed_list(cfg)]
        for seed, r in zip(seed_list(cfg), runs, strict=True):
            TrainedPolicy.load(r["checkpoint"]).save(out / "policies" / f"{name}-seed{seed}.pt")
        results["learners"][name] = {"runs": runs,
                                     "wall_s": [done[name, seed]["wall_s"] for seed in seed_list(cfg)],
                                     "curves": [done[name, seed]["curve"] for seed in seed_list(cfg)]}
    results["wall_time_s"] = time.perf_counter() - t_start
    write_task_results(out, results)
    return results


def write_task_results(out: Path, results: dict[str, Any]) -> None:
    """metrics.json, table.md and figure.png of a Hopper/tasks reproduction in ``out``, each learner's
    summary and success count computed from its runs."""
    from pomil.eval.plots import learning_curves

    for r in results["learners"].values():
        r["summary"] = task_summary(r["runs"], results["tasks"])
        r["successes"] = int(sum(tasks_success(run) for run in r["runs"]))
    results["seeds"] = len(next(iter(results["learners"].values()))["runs"]) if results["learners"] else 0
    write_json(out / "metrics.json", results)
    table = hopper_table(results)
    atomic_write(out / "table.md", lambda f: f.write(table.encode()))
    learning_curves(results, out / "figure.png")
    print(table)
    print(f"wrote {out}/metrics.json, table.md, figure.png ({results['wall_time_s']:.0f} s of runs)")


# Settings that may differ between the reproductions `merge_task_results` joins: where the files
# were, and the name of a preset whose values the other settings record in full.
MERGE_FREE = {"config": ("out", "runs", "demos", "seeds", "first_seed", "jobs", "ray", "ray_address", "progress",
                         "adversarial_config", "bc_config", "resume_runs"),
              "adversarial_settings": ("demos", "preset"), "bc_settings": ("demos", "preset")}


REFERENCE_RTOL = 0.01
"""How far (relative) the sources' expert and zero-action returns may differ in a merge.  The same
experts recorded again with the same seed give slightly other demonstrations where floats differ
(another CPU, MuJoCo or torch build): Hopper's contacts amplify the last bits over an episode, and
the speed experts' mean return moved by 0.1% between two sessions.  Another expert, task or
setting moves it by far more."""


def merge_task_results(sources: list[Path], out: Path, policies: bool = True) -> dict[str, Any]:
    """Join Hopper/tasks reproductions run on other seeds (``--first-seed``) into one, in ``out``:
    every learner's runs in seed order, its policies, the table and curves over all seeds.

    The reproductions must agree on what they measured: the experiment, the environment, setting,
    tasks, evaluation episodes, the demonstrations' reference returns (within :data:`REFERENCE_RTOL`;
    each source's reference is kept in ``merged_from``), the success criteria, the
    learners' resolved adversarial settings and BC settings (where both record them; a setting that
    only one of them records, a field added to the config since the other ran, is named in a note
    and not compared) and the iterations; a learner's seeds must not repeat.  Success counts are
    recomputed from the runs (:data:`TASKS_SUCCESS`).  ``policies=False`` joins the metrics only
    and copies no policy (for results committed without their policies).  Anything else is a
    one-line error before a file is written."""
    import shutil

    loaded = _load_task_results(sources)
    (first_src, first), rest = loaded[0], loaded[1:]
    merged = json.loads(json.dumps(first))
    merged["success_criteria"] = TASKS_SUCCESS  # the success counts are recomputed from the runs with today's
    merged["merged_from"] = [{"results": str(first_src), "config": first["config"], "reference": first["reference"]}]
    for src, r in rest:
        _check_same_settings(first_src, first, src, r)
        _add_learner_runs(merged, src, r)
        merged["merged_from"].append({"results": str(src), "config": r["config"], "reference": r["reference"]})
        merged["wall_time_s"] = merged.get("wall_time_s", 0.0) + r.get("wall_time_s", 0.0)
    counts = {name: len(lr["runs"]) for name, lr in merged["learners"].items()}
    if len(set(counts.values())) > 1:
        raise PomilError(f"the merged learners have different numbers of seeds ({counts}); merge reproductions "
                         "of the same learners")
    copies = _policy_copies(loaded, out) if policies else []
    for lr in merged["learners"].values():
        order = np.argsort([run["train_seed"] for run in lr["runs"]], kind="stable")
        for k in ("runs", "wall_s", "curves"):
            lr[k] = [lr[k][i] for i in order]
    out.mkdir(parents=True, exist_ok=True)
    if copies:
        (out / "policies").mkdir(exist_ok=True)
    merged["policies_merged"] = policies
    for policy, dest in copies:
        if policy.resolve() != dest.resolve():
            shutil.copyfile(policy, dest)
    write_task_results(out, merged)
    return merged


def _load_task_results(sources: list[Path]) -> list[tuple[Path, dict[str, Any]]]:
    """Each source's metrics.json, which must be a Hopper/tasks reproduction's."""
    loaded = []
    for src in sources:
        path = Path(src) / "metrics.json"
        try:
            loaded.append((Path(src), json.loads(path.read_text())))
        except (OSError, ValueError) as err:
            raise PomilError(f"{path}: cannot read a reproduction's metrics ({err})") from None
    for src, r in loaded:
        if r.get("experiment") not in ("hopper", "tasks") or "learners" not in r:
            raise PomilError(f"{src}/metrics.json: not a Hopper/tasks reproduction (experiment "
                             f"{r.get('experiment')!r}); merge joins those")
    return loaded


def _check_same_settings(first_src: Path, first: dict[str, Any], src: Path, r: dict[str, Any]) -> None:
    """PomilError unless reproduction ``r`` measured what ``first`` did (see :func:`merge_task_results`)."""
    def same(key: str, a: Any, b: Any) -> None:
        if a != b:
            raise PomilError(f"{src}/metrics.json: {key} differs from {first_src}'s ({b!r} against {a!r}); "
                             "only runs of the same experiment and settings on other seeds can be merged")

    for key in ("experiment", "env_id", "setting", "tasks", "episodes_per_code"):
        same(key, first.get(key), r.get(key))
    for key in ("expert_returns", "still_returns"):  # the same experts and tasks: the same reference returns
        a, b = first["reference"][key], r["reference"][key]
        drift = max(abs(a[t] - b[t]) / max(1.0, abs(a[t])) for t in a) if set(a) == set(b) else math.inf
        if drift > REFERENCE_RTOL:
            same(f"reference.{key}", a, b)
        if drift > 1e-9:
            print(f"pomil: note: {src}: reference.{key} differs from {first_src}'s by up to {100 * drift:.2f}% "
                  f"(within {100 * REFERENCE_RTOL:g}%: the same experts recorded again, where floats differ); "
                  "each source's reference stays in merged_from", file=sys.stderr)
    for key in ("adversarial_iterations", "bc_iterations"):
        same(f"config.{key}", first["config"].get(key), r["config"].get(key))
    for key in ("adversarial_settings", "bc_settings"):
        if key in first and key in r:
            one_sided = sorted(set(first[key]) ^ set(r[key]))
            if one_sided:
                print(f"pomil: note: {key} {', '.join(one_sided)} recorded by only one of {first_src} and "
                      f"{src}: not compared", file=sys.stderr)
            drop = {*MERGE_FREE[key], *one_sided}
            same(key, {k: v for k, v in first[key].items() if k not in drop},
                 {k: v for k, v in r[key].items() if k not in drop})
        elif key in first or key in r:
            print(f"pomil: note: {src if key in first else first_src}/metrics.json records no {key}: "
                  "not compared", file=sys.stderr)


def _add_learner_runs(merged: dict[str, Any], src: Path, r: dict[str, Any]) -> None:
    """Every learner's runs, wall times and curves of reproduction ``r`` added to ``merged``; no seed twice."""
    for name, lr in r["learners"].items():
        to = merged["learners"].setdefault(name, {"runs": [], "wall_s": [], "curves": []})
        seeds = {run["train_seed"] for run in to["runs"]}
        repeated = sorted(seeds & {run["train_seed"] for run in lr["runs"]})
        if repeated:
            raise PomilError(f"{src}/metrics.json: {name} seed(s) {repeated} are already in the merge")
        for k in ("runs", "wall_s", "curves"):
            to[k] += lr[k]


def _policy_copies(loaded: list[tuple[Path, dict[str, Any]]], out: Path) -> list[tuple[Path, Path]]:
    """(policy file, its place in ``out``) for every run of every source; PomilError for one that is missing."""
    copies = []
    for src, r in loaded:
        for name, lr in r["learners"].items():
            for run in lr["runs"]:
                policy = src / "policies" / f"{name}-seed{run['train_seed']}.pt"
                if not policy.is_file():
                    raise PomilError(f"{policy}: missing (every run's policy is merged with it; --no-policies "
                                     "joins the metrics alone)")
                copies.append((policy, out / "policies" / policy.name))
    return copies
