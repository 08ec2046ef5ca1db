"""The ``pomil`` command line: demos, train, evaluate, plot, reproduce, docs.

Every option of ``train`` (and of ``demos`` and ``reproduce``) is a field of a
typed config dataclass; ``--config FILE.json`` sets any of them and flags
override the file.  Problems with the user's input end with one line on
stderr and exit status 2; a run that diverged (NaN or inf) ends the same way
with exit status 3.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import typing
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import numpy as np

from pomil.config import check_values, field_help, field_interval, field_names, from_dict, load_config_file, option
from pomil.errors import PomilError
from pomil.parallel import require_ray


# ----------------------------------------------------------- configs <-> flags
def add_config_flags(parser: argparse.ArgumentParser, cls: type, fixed: dict[str, Any] | None = None) -> None:
    """One flag per config field, except the ``fixed`` ones (set by the subcommand)."""
    fixed = fixed or {}
    parser.add_argument("--config", metavar="FILE.json", help="JSON object of config keys; flags override it")
    parser.set_defaults(**fixed)
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in fixed:
            continue
        tp = hints[f.name]
        flag = "--" + f.name.replace("_", "-")
        interval = field_interval(f)
        words = "".join(f" or {word}" for word in field_names(f))
        help_text = f"{field_help(f)} (default: {f.default!r}{'; in ' + interval.text + words if interval else ''})"
        help_text = help_text.replace("%", "%%")  # argparse formats help with %; a field's docs may say "9%"
        if tp is bool:
            kind: dict[str, Any] = {"action": argparse.BooleanOptionalAction}
        elif get_origin(tp) is Literal:
            kind = {"choices": list(get_args(tp))}
        else:
            kind = {"metavar": f.name.upper()}
        parser.add_argument(flag, dest=f.name, default=None, help=help_text, **kind)
    for old, new in getattr(cls, "RENAMED", {}).items():  # deprecated flags, still read
        if new not in fixed:
            parser.add_argument("--" + old.replace("_", "-"), dest=new, default=None, help=argparse.SUPPRESS)


def config_from_args(cls: type, args: argparse.Namespace, run_resumed: bool = False) -> Any:
    """Defaults, then (``run_resumed``: a training run's --resume) the run's own config.json, then the --config
    file, then flags; unknown keys are an error, and every key of the file is checked, also where a flag
    overrides it."""
    values: dict[str, Any] = load_config_file(args.config) if getattr(args, "config", None) else {}
    if values:
        check_values(cls, values, args.config)
    if run_resumed:
        renamed: dict[str, str] = getattr(cls, "RENAMED", {})
        saved = _resumed_config(cls, args)
        values = {**{k: v for k, v in saved.items() if k not in {renamed.get(n, n) for n in values}}, **values}
    for f in dataclasses.fields(cls):
        v = getattr(args, f.name, None)
        if v is not None:
            values[f.name] = v
    return from_dict(cls, values, getattr(args, "config", None) or "config")


def _resumed_config(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """The config a run in --out was started with (its config.json, the keys of ``cls``), so that ``--resume``
    needs no flag but those it changes; {} where there is no config.json (resume then says what is missing)."""
    from pomil.config import saved_config

    default_out = next((f.default for f in dataclasses.fields(cls) if f.name == "out"), "")
    path = Path(getattr(args, "out", None) or default_out) / "config.json"
    if not path.is_file():
        return {}
    saved = load_config_file(path)
    algo = getattr(args, "algo", None)  # pomil train's subcommand, the name its runs record
    if algo is not None and saved.get("algo", algo) != algo:
        raise PomilError(f"{path}: the run there is {saved['algo']}'s, not {algo}'s (resume it with pomil train "
                         f"{saved['algo']} --resume)")
    names = {f.name for f in dataclasses.fields(cls)} - {"out", "overwrite"}
    return {k: v for k, v in saved_config(cls, saved).items() if k in names}


@contextmanager
def _reported(prefix: str) -> Iterator[None]:
    """A ValueError raised inside becomes a one-line PomilError ``prefix: message``."""
    try:
        yield
    except ValueError as err:
        raise PomilError(f"{prefix}: {err}") from None


# ------------------------------------------------------------------ commands
@dataclass(frozen=True)
class CirclesDemosConfig:
    out: str = option("data/circles.npz", "output .npz file (written atomically)")
    episodes: int = option(400, "episodes in total, split equally between the modes", within="[1, inf)")
    modes: Literal["one", "two", "four"] = option("two", "circles preset: one (anti-clockwise around (0, r)), two "
                                                         "(the paper's) or four")
    radius: float = option(5.0, "radius of every circle", within="(0, inf)")
    circles: tuple[str, ...] = option((), "circles of your own instead of --modes: ANGLE:RADIUS:DIRECTION for each, "
                                          "centred at ANGLE degrees from the x axis and through the origin, "
                                          "travelled anti-clockwise (1) or clockwise (-1), e.g. 90:4:1,210:5:-1")
    radius_range: tuple[float, ...] = option((), "R1,R2: each episode's circle gets its own radius, uniform in "
                                                 "[R1, R2] (same tangent and direction; for continuous codes); "
                                                 "the environment's circles take the middle radius", within="(0, inf)")
    episode_length: int = option(33, "steps per episode (33 = one loop of a radius-5 circle)", within="[1, inf)")
    history: int = option(1, "positions observed per step: 1 = position only (the POMDP); k = last k positions",
                          within="[1, inf)")
    action_type: Literal["vector", "angle"] = option("vector", "action format: 2-D direction vector or heading angle")
    noise_std: float = option(0.36787944117144233, "std of the experts' heading noise in radians (exp(-1))",
                              within="[0, inf)")
    seed: int = option(0, "random seed", within="[0, 4294967295]")


def cmd_demos(args: argparse.Namespace) -> int:
    from pomil.demos import record_circles_demos
    from pomil.envs.circles import make_spec

    cfg: CirclesDemosConfig = config_from_args(CirclesDemosConfig, args)
    radius_range = None
    if cfg.radius_range:
        if len(cfg.radius_range) != 2 or cfg.radius_range[0] > cfg.radius_range[1]:
            raise PomilError(f"config key 'radius_range': expected two radii R1,R2 with R1 <= R2, got "
                             f"{','.join(map(str, cfg.radius_range))}")
        radius_range = (float(cfg.radius_range[0]), float(cfg.radius_range[1]))
    with _reported("demos circles"):
        radius = cfg.radius if radius_range is None else sum(radius_range) / 2
        spec = make_spec(cfg.modes, radius, cfg.episode_length, history=cfg.history, action_type=cfg.action_type)
        if cfg.circles:
            spec = dataclasses.replace(spec, circles=tuple(map(_circle, cfg.circles)))
        demos = record_circles_demos(spec, cfg.episodes, cfg.noise_std, seed=cfg.seed, radius_range=radius_range)
    demos.save(cfg.out)
    rets = ", ".join(f"mode {k}: {v:.2f}" for k, v in demos.metadata["expert_returns"].items())
    radii = "" if radius_range is None else f", radius uniform in [{radius_range[0]:g}, {radius_range[1]:g}]"
    print(f"wrote {cfg.out}: {demos.num_episodes} episodes x {spec.episode_length} steps, "
          f"{spec.num_modes} modes{radii} (mean expert return {rets})")
    return 0


def _circle(text: str) -> Any:
    """``"90:4:1"`` -> the circle through the origin centred at 90 degrees, radius 4, anti-clockwise."""
    from pomil.envs.circles import Circle

    try:
        angle, radius, direction = text.split(":")
        return Circle.through_origin(float(angle), float(radius), int(direction))
    except ValueError as err:
        raise PomilError(f"config key 'circles': expected ANGLE:RADIUS:DIRECTION (e.g. 90:4:1), got {text!r}"
                         + (f" ({err})" if str(err).startswith("circle") else "")) from None


@dataclass(frozen=True)
class HopperDemosConfig:
    out: str = option("", "output .npz file (written atomically); default data/hopper-SETTING.npz")
    episodes: int = option(-1, "episodes per task; -1: the setting's, paper 200, standard 100", within="[-1, inf)")
    setting: Literal["paper", "standard"] = option("paper", "paper: 128 steps, no unhealthy termination; "
                                                            "standard: Hopper's own 1000 steps")
    forward_expert: str = option("", "forward expert checkpoint (pomil experts hopper); default the setting's "
                                     "shipped one, pomil/experts/hopper[-standard]-forward.pt in the package")
    backward_expert: str = option("", "backward expert checkpoint; default the setting's shipped one")
    experts: str = option("", "a folder of both experts instead of the shipped ones: the package's names "
                              "(hopper[-standard]-TASK.pt) or what pomil experts hopper writes into runs/ "
                              "(expert-hopper-TASK-SETTING/checkpoint.pt)")
    observation_mask: str = option("positions-only",
                                   "what the learner observes: positions-only, velocities, or comma-separated indices")
    seed: int = option(0, "random seed (reset noise, episode order)", within="[0, 4294967295]")
    action_noise: float = option(-1.0, "std of Gaussian noise added to the executed actions while the expert's own "
                                       "actions are recorded (DART: demonstrations with recoveries); 0: none; -1: the "
                                       "setting's, paper 0, standard 0.1", within="[-1, inf)")
    progress: bool = option(True, "show a progress bar of the recorded episodes")


def _mask_arg(text: str) -> str | list[int] | None:
    from pomil.envs.wrappers import parse_mask

    with _reported("--observation-mask"):
        return parse_mask(text)


@dataclass(frozen=True)
class RecordDemosConfig:
    expert: str = option("",
                         "expert checkpoint (pomil experts ...); demonstrations come from its environment and keywords")
    out: str = option("", "output .npz file (written atomically)")
    episodes: int = option(200, "episodes to record", within="[1, inf)")
    task: str = option("",
                       "task name kept as the episodes' label (default: forward/backward from forward_reward_weight)")
    observation_mask: str = option("positions-only",
                                   "what the learner observes: positions-only, velocities, comma-separated indices, or "
                                   "'' (all)")
    seed: int = option(0, "random seed (reset noise)", within="[0, 4294967295]")
    action_noise: float = option(0.0, "std of Gaussian noise added to the executed actions while the expert's own "
                                      "actions are recorded (DART: demonstrations with recoveries); 0: none",
                                 within="[0, inf)")
    progress: bool = option(True, "show a progress bar of the recorded episodes")


def cmd_demos_record(args: argparse.Namespace) -> int:
    from pomil.demos import record_expert_demos

    cfg: RecordDemosConfig = config_from_args(RecordDemosConfig, args)
    if not cfg.expert or not cfg.out:
        raise PomilError("demos record: --expert and --out are required")
    if not Path(cfg.expert).is_file():
        raise PomilError(f"{cfg.expert}: no expert checkpoint there (train one: pomil experts train --env-id ...)")
    with _reported("demos record"):
        demos = record_expert_demos(cfg.expert, cfg.episodes, cfg.task or None,
                                    observation_mask=_mask_arg(cfg.observation_mask), seed=cfg.seed,
                                    action_noise=cfg.action_noise, progress=cfg.progress)
    demos.save(cfg.out)
    md = demos.metadata
    task = md["label_names"][0]
    print(f"wrote {cfg.out}: {demos.num_episodes} episodes of {md['env_id']} task {task!r} "
          f"(mean length {demos.episode_lengths.mean():.0f}), observation {md['observation_mask']}; expert return "
          f"{md['expert_returns'][task]:.1f}, zero actions {md['still_returns'][task]:.1f}")
    return 0


@dataclass(frozen=True)
class MergeDemosConfig:
    out: str = option("", "output .npz file (written atomically)")
    proportions: tuple[float, ...] = option((), "share of each file's episodes, e.g. 1,1 (default: equal)",
                                            within="[0, inf)")
    episodes: int = option(0, "episodes in total (0: as many as the files allow in these proportions)",
                           within="[0, inf)")
    seed: int = option(0, "random seed (which episodes, their order)", within="[0, 4294967295]")


def cmd_demos_merge(args: argparse.Namespace) -> int:
    from pomil.data import Demonstrations
    from pomil.demos import merge_demos

    cfg: MergeDemosConfig = config_from_args(MergeDemosConfig, args)
    if not cfg.out:
        raise PomilError("demos merge: --out is required")
    sources = [Demonstrations.load(f) for f in args.files]
    with _reported("demos merge"):
        demos = merge_demos(sources, list(cfg.proportions) or None, cfg.episodes or None, seed=cfg.seed,
                            names=list(args.files))
    demos.save(cfg.out)
    counts = np.bincount(demos.labels, minlength=len(demos.metadata["label_names"]))
    print(f"wrote {cfg.out}: {demos.num_episodes} episodes, unlabeled for training; labels kept for evaluation: "
          + ", ".join(f"{n} {c}" for n, c in zip(demos.metadata["label_names"], counts, strict=False)))
    return 0


def cmd_demos_minari(args: argparse.Namespace) -> int:
    from pomil.data import Demonstrations
    from pomil.minari_io import export_minari, import_minari

    if args.env == "import-minari":
        demos = import_minari(args.dataset_id, args.minari_root, _mask_arg(args.observation_mask))
        demos.save(args.out)
        print(f"wrote {args.out}: {demos.num_episodes} episodes of {demos.metadata['env_id']} from Minari dataset "
              f"{args.dataset_id}, observation {demos.metadata.get('observation_mask')}, "
              f"{'labelled' if demos.labels is not None else 'no labels'}")
    else:
        demos = Demonstrations.load(args.demos)
        path = export_minari(demos, args.dataset_id, args.minari_root)
        print(f"wrote Minari dataset {args.dataset_id} at {path}: {demos.num_episodes} episodes")
    return 0


def experts_in(folder: str, task: str, setting: str) -> str:
    """The ``task`` expert of ``setting`` in ``folder``: named as the package names its own, or as ``pomil experts
    hopper`` names its run directory; PomilError naming both when neither is there."""
    from pomil.envs.locomotion import HOPPER_EXPERTS

    names = (Path(HOPPER_EXPERTS[setting][task]).name, f"expert-hopper-{task}-{setting}/checkpoint.pt")
    for name in names:
        if (Path(folder) / name).is_file():
            return str(Path(folder) / name)
    raise PomilError(f"--experts {folder}: no {task} expert of the {setting} setting there (expected {names[0]} or "
                     f"{names[1]}; train one: pomil experts hopper --task {task} --setting {setting})")


def cmd_demos_hopper(args: argparse.Namespace) -> int:
    from pomil.demos import record_hopper_demos
    from pomil.envs.locomotion import HOPPER_EXPERTS, demo_recording

    cfg: HopperDemosConfig = config_from_args(HopperDemosConfig, args)
    shipped = HOPPER_EXPERTS[cfg.setting]
    if cfg.experts:
        shipped = {task: experts_in(cfg.experts, task, cfg.setting) for task in shipped}
    experts = {task: getattr(cfg, f"{task}_expert") or shipped[task] for task in ("forward", "backward")}
    out = cfg.out or f"data/hopper-{cfg.setting}.npz"
    with _reported("demos hopper"):
        episodes, noise = demo_recording(cfg.setting, cfg.episodes, cfg.action_noise, ("--episodes", "--action-noise"))
        for task, path in experts.items():
            if not Path(path).is_file():
                raise PomilError(f"{path}: no {task} expert checkpoint there (train one: pomil experts hopper --task "
                                 f"{task} --setting {cfg.setting}; then pass --{task}-expert "
                                 f"runs/expert-hopper-{task}-{cfg.setting}/checkpoint.pt)")
        demos = record_hopper_demos(experts, episodes, cfg.setting, seed=cfg.seed,
                                    observation_mask=_mask_arg(cfg.observation_mask), action_noise=noise,
                                    progress=cfg.progress)
    demos.save(out)
    md = demos.metadata
    print(f"wrote {out}: {demos.num_episodes} episodes ({episodes} per task, {cfg.setting} setting), "
          f"observation {md['observation_mask']}; expert returns "
          + ", ".join(f"{t} {md['expert_returns'][t]:.1f} (zero actions {md['still_returns'][t]:.1f})"
                      for t in experts))
    return 0


def cmd_experts(args: argparse.Namespace) -> int:
    from pomil.algos.expert import ExpertConfig, train_expert
    from pomil.api import TrainedPolicy
    from pomil.config import parse_kwargs
    from pomil.envs.locomotion import locomotion_kwargs
    from pomil.eval.tasks import rollout_locomotion
    from pomil.training import write_json

    cfg: ExpertConfig = config_from_args(ExpertConfig, args, run_resumed=args.resume)
    ckpt = train_expert(cfg, resume=args.resume)
    policy = TrainedPolicy.load(ckpt)
    # Deterministic returns in both settings (locomotion tasks) or in the trained one.
    settings = ("paper", "standard") if cfg.task != "none" else (cfg.setting,)
    report = {}
    for setting in settings:
        kwargs = {**locomotion_kwargs(cfg.env_id, cfg.task, setting), **parse_kwargs(cfg.env_kwargs)}
        roll = rollout_locomotion(policy, kwargs, 20, seed=10_000, observation_mask=policy.env.get("observation_mask"))
        report[setting] = {"return": float(roll["returns"].mean()), "return_std": float(roll["returns"].std()),
                           "length": float(roll["length"].mean()), "displacement": float(roll["displacement"].mean())}
    write_json(Path(cfg.out) / "evaluation.json",
               {"env_id": cfg.env_id, "task": cfg.task, "deterministic": True, "episodes": 20, **report})
    print(f"wrote {ckpt}; deterministic return over 20 episodes: "
          + "; ".join(f"{s} setting {r['return']:.1f} ± {r['return_std']:.1f} ({r['length']:.0f} steps, "
                      f"moved {r['displacement']:+.2f} m)" for s, r in report.items()))
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from pomil.learners import LEARNERS

    learner = LEARNERS[args.algo]
    ckpt = learner.train(config_from_args(learner.config, args, run_resumed=args.resume), resume=args.resume)
    print(f"wrote {ckpt}")
    return 0


def _format_metrics(m: dict[str, Any]) -> str:
    lines = [f"algo {m['algo']}  codes {m['num_codes']}  episodes/code {m['episodes_per_code']}  "
             f"{'deterministic' if m['deterministic'] else 'stochastic'}"]
    k = len(m["overall_mode_share"])
    lines.append("code  " + "  ".join(f"mode{j:<3d}" for j in range(k)) + "  none    purity")
    for pc in m["per_code"]:
        code = str(pc["code"]) if m["num_codes"] else "-"
        shares = "  ".join(f"{s:7.2f}" for s in pc["mode_share"])
        lines.append(f"{code:<4s}  {shares}  {pc['none_share']:5.2f}   {pc['purity']:.2f}")
    lines.append(f"modes covered {m['modes_covered']}/{k}   NMI(code, mode) {m['nmi']:.3f}   "
                 f"mean purity {m['mean_purity']:.3f}   mean return {m['mean_return']:.2f}")
    return "\n".join(lines)


def matching_demos(path: str, policies: list[tuple[str, Any]]) -> Any:
    """Demonstrations checked against their own environment and against every (checkpoint,
    policy)'s: the same environment id and the same observation and action sizes."""
    from pomil.data import Demonstrations, check_demos_env

    demos = Demonstrations.load(path)
    env_id, _ = check_demos_env(demos, path)
    for checkpoint, policy in policies:
        if env_id != policy.env.get("id"):
            raise PomilError(f"{path}: demonstrations of {env_id}, but {checkpoint} was trained on "
                             f"{policy.env.get('id')}")
        if (demos.obs_dim, demos.act_dim) != (policy.obs_dim, policy.act_dim):
            raise PomilError(f"{path}: observations {demos.obs_dim} / actions {demos.act_dim} wide, but {checkpoint}'s "
                             f"policy takes {policy.obs_dim} / {policy.act_dim}")
    return demos


def cmd_evaluate(args: argparse.Namespace) -> int:
    from pomil.api import TrainedPolicy
    from pomil.envs import env_family
    from pomil.eval.circles import evaluate_circles, evaluate_code_radius

    if args.episodes_per_code < 1:
        raise PomilError(f"--episodes-per-code must be >= 1, got {args.episodes_per_code}")
    if args.code_values < 2:
        raise PomilError(f"--code-values must be >= 2, got {args.code_values}")
    policy = TrainedPolicy.load(args.checkpoint)
    demos = matching_demos(args.demos, [(args.checkpoint, policy)]) if args.demos else None
    if env_family(policy.env.get("id", "")).evaluation != "circles":
        return _evaluate_tasks(policy, args, demos)
    if demos is not None:
        print("pomil: note: --demos matches the checkpoint but circles evaluation does not use it", file=sys.stderr)
    if policy.code_dim:
        metrics, _ = evaluate_code_radius(policy, args.code_values, args.episodes_per_code, seed=args.seed,
                                          deterministic=args.deterministic)
    else:
        metrics, _ = evaluate_circles(policy, args.episodes_per_code, args.seed, deterministic=args.deterministic,
                                      threshold=args.none_threshold)
    print(json.dumps(metrics, indent=2) if args.json else (_format_code_radius if policy.code_dim else
                                                           _format_metrics)(metrics))
    return 0


def _format_code_radius(m: dict[str, Any]) -> str:
    lines = [f"algo {m['algo']}  continuous code, {m['code_dim']} dim(s), {m['code_prior']} prior  "
             f"{m['values']} code values x {m['episodes_per_value']} episodes  "
             f"{'deterministic' if m['deterministic'] else 'stochastic'}"]
    for d in m["dims"]:
        lines.append(f"dim {d['dim']}: Spearman rho(code, fitted radius) {d['spearman']:+.3f} (|rho| at most "
                     f"{d['spearman_max']:.3f} with these ties)   radius covered {d['radius_covered'][0]:.2f} .. "
                     f"{d['radius_covered'][1]:.2f}")
        lines.append("  code   " + " ".join(f"{v:6.2f}" for v in d["code_values"]))
        lines.append("  radius " + " ".join(f"{r:6.2f}" for r in d["median_radius"]) + "   (median per code value)")
    return "\n".join(lines)


def _evaluate_tasks(policy, args: argparse.Namespace, demos) -> int:
    from pomil.eval.tasks import evaluate_tasks, reference_of

    if demos is None:
        raise PomilError(f"evaluate: a {policy.env.get('id')} policy needs --demos (the demonstrations whose "
                         "expert returns normalise the scores)")
    reference = reference_of(demos.metadata, args.demos)
    m = evaluate_tasks(policy, reference, args.episodes_per_code, seed=args.seed, deterministic=not args.stochastic,
                       progress=args.progress)
    if args.json:
        print(json.dumps(m, indent=2))
        return 0
    print(f"algo {policy.algo}  codes {policy.num_codes}  episodes/code {args.episodes_per_code}  "
          f"{'deterministic' if m['deterministic'] else 'stochastic'}")
    for task, r in m["tasks"].items():
        print(f"{task:<9s} code {r['code']}  return {r['return']:7.1f}  normalised {r['normalised_return']:.2f}  "
              f"progress {r['progress']:.2f}  displacement ratio {r['displacement_ratio']:.2f}"
              + (f"  on-task share {r['on_task_share']:.2f}  speed error {r['speed_error']:.2f} m/s"
                 if "on_task_share" in r else ""))
    for code, b in (m.get("behaviour") or {}).items():
        print(f"{code:<9s} mean speed {b['mean_speed']:.2f} ± {b['speed_std']:.2f} m/s  nearest expert speed: "
              + ", ".join(f"{t} {v:.2f}" for t, v in b["shares"].items()) + f"  purity {b['purity']:.2f}")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from pomil.api import TrainedPolicy
    from pomil.envs import env_family
    from pomil.eval.circles import rollout_circles
    from pomil.eval.plots import figure1
    from pomil.nn.codes import prior_grid

    panels = []
    policies = [(ckpt, TrainedPolicy.load(ckpt)) for ckpt in args.checkpoints]
    for ckpt, policy in policies:
        if env_family(policy.env.get("id", "")).evaluation != "circles":
            raise PomilError(f"{ckpt}: plot draws circles policies; this one was trained on {policy.env.get('id')}")
    if args.demos:
        demos = matching_demos(args.demos, policies)
        if env_family(str(demos.metadata.get("env_id"))).evaluation != "circles":
            raise PomilError(f"{args.demos}: plot draws circles demonstrations; these are of "
                             f"{demos.metadata.get('env_id')}")
        if demos.states is None or demos.labels is None:
            raise PomilError(f"{args.demos}: field 'states'/'labels': expected both for plotting experts")
        if len(set(demos.episode_lengths.tolist())) != 1:
            raise PomilError(f"{args.demos}: field 'episode_bounds': expected episodes of one length for plotting "
                             "experts")
        # states hold the position *before* each action: shift by one to show visited points
        pos = demos.states.reshape(demos.num_episodes, int(demos.episode_lengths[0]), -1)[:, 1:, :2]
        panels.append(("experts", pos, demos.labels, "mode"))
    for ckpt, policy in policies:
        codes = None
        if policy.code_dim:  # continuous: 5 code values over the prior in the first dimension, the rest at 0
            codes = np.zeros((5 * args.episodes_per_code, policy.code_dim), dtype=np.float32)
            codes[:, 0] = np.repeat(prior_grid(policy.code_prior, 5).numpy(), args.episodes_per_code)
        roll = rollout_circles(policy, args.episodes_per_code, args.seed, deterministic=args.deterministic, codes=codes)
        groups = roll["codes"] if codes is None else np.repeat(np.arange(5), args.episodes_per_code)
        panels.append((f"{policy.algo}: {Path(ckpt).parent.name or ckpt}", roll["positions"], groups,
                       "code" if codes is None else "code value #"))
    if not panels:
        raise PomilError("plot: give at least one checkpoint or --demos")
    figure1(panels, args.out)
    print(f"wrote {args.out}")
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    from pomil.experiment import ReproduceOptions, load_spec, merge_results, reproduce, spec_names

    if args.list:
        for name in spec_names():
            spec = load_spec(name)
            print(f"{name}: {spec.description}" + (f" (results: {spec.results})" if spec.results else ""))
        return 0
    if args.spec is None:
        raise PomilError("reproduce: give an experiment (a spec file or a name from `pomil reproduce --list`)")
    if args.spec == "merge":
        if not args.sources or not args.out:
            raise PomilError("reproduce merge: give the results directories to join and --out")
        merge_results([Path(r) for r in args.sources], Path(args.out), policies=args.policies)
        return 0
    if args.sources:
        raise PomilError(f"reproduce {args.spec}: unexpected arguments {args.sources} (one experiment at a time)")
    opts: ReproduceOptions = config_from_args(ReproduceOptions, args)
    if opts.ray:
        require_ray()  # before any demonstrations or runs are written
    data = reproduce(args.spec, opts)
    return 1 if data["failed"] else 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from pomil.experiment import SweepConfig, sweep

    cfg: SweepConfig = config_from_args(SweepConfig, args)
    if cfg.ray:
        require_ray()
    data = sweep(cfg, args.sweep_config, args.grid or [])
    return 1 if data["failed"] else 0


# -------------------------------------------------------------------- parser
def _add_demos(sub: argparse._SubParsersAction) -> None:
    """``pomil demos``: circles, hopper, record, import-minari, export-minari, merge."""
    demos = sub.add_parser("demos", help="record expert demonstrations")
    demos_sub = demos.add_subparsers(dest="env", required=True, metavar="ENV")
    for name, text, cls, func in (
            ("circles", "scripted circle experts, equal numbers per mode", CirclesDemosConfig, cmd_demos),
            ("hopper", "Hopper forward + backward experts, equal numbers per task, positions-only view",
             HopperDemosConfig, cmd_demos_hopper),
            ("record", "one expert checkpoint on its own environment (any task), one label", RecordDemosConfig,
             cmd_demos_record)):
        dp = demos_sub.add_parser(name, help=text)
        add_config_flags(dp, cls)
        dp.set_defaults(func=func)
    root = "Minari datasets folder (default: $MINARI_DATASETS_PATH or ~/.minari/datasets)"
    di = demos_sub.add_parser("import-minari",
                              help="a local Minari dataset as pomil demonstrations (needs the minari extra)")
    di.add_argument("dataset_id", help="Minari dataset id, e.g. pomil/hopper-paper-v0")
    di.add_argument("--out", required=True, help="output .npz file (written atomically)")
    di.add_argument("--observation-mask", default="",
                    help="what the learner observes, for datasets not written by pomil: positions-only or indices "
                         "(default: all)")
    di.add_argument("--minari-root", help=root)
    di.set_defaults(func=cmd_demos_minari)
    de = demos_sub.add_parser("export-minari",
                              help="pomil demonstrations as a local Minari dataset (needs the minari extra)")
    de.add_argument("demos", help="demonstrations .npz")
    de.add_argument("--dataset-id", required=True, help="Minari dataset id to create, [namespace/]name-vN")
    de.add_argument("--minari-root", help=root)
    de.set_defaults(func=cmd_demos_minari)
    dm = demos_sub.add_parser("merge", help="several recordings (experts / tasks) into one unlabeled training set")
    dm.add_argument("files", nargs="+", help="demonstrations .npz files to merge")
    add_config_flags(dm, MergeDemosConfig)
    dm.set_defaults(func=cmd_demos_merge)


def _add_training(sub: argparse._SubParsersAction) -> None:
    """``pomil experts ENV`` (hopper; train: any Gymnasium id) and ``pomil train ALGO`` (a subcommand per learner of
    the learner table): a config's flags and --resume each."""
    from pomil.algos.expert import ExpertConfig
    from pomil.envs.locomotion import HOPPER_ID
    from pomil.learners import LEARNERS

    ex = sub.add_parser("experts", help="train a PPO expert (MLP policy, pomil's PPO) on a task's reward")
    ex_sub = ex.add_subparsers(dest="env", required=True, metavar="ENV")
    train = sub.add_parser("train", help="train a learner on demonstrations")
    train_sub = train.add_subparsers(dest="algo", required=True, metavar="ALGO")
    commands = [(ex_sub, "hopper", f"{HOPPER_ID} forward or backward", ExpertConfig,
                 {"demos": "", "env_id": HOPPER_ID}, cmd_experts),
                (ex_sub, "train", "any Gymnasium id (--env-id) with 1-D Box spaces", ExpertConfig, {"demos": ""},
                 cmd_experts)]
    commands += [(train_sub, name, learner.help, learner.config, learner.fixed or None, cmd_train)
                 for name, learner in LEARNERS.items() if learner.command]
    for parent, name, text, cls, fixed, func in commands:
        # --demos is required, unless --config's file names it: the usage line says so (argparse's would not)
        usage = f"pomil train {name} --demos FILE.npz [--config FILE.json] [options]" if parent is train_sub else None
        p = parent.add_parser(name, help=text, usage=usage)
        add_config_flags(p, cls, fixed=fixed)
        p.add_argument("--resume", action="store_true",
                       help="continue the run in --out from its last checkpoint, with the settings in its config.json "
                            "(flags need only say what changes, e.g. --iterations)")
        p.set_defaults(func=func)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    ev = sub.add_parser("evaluate",
                        help="roll a checkpoint out: mode metrics (circles) or per-task scores (other tasks)")
    ev.add_argument("checkpoint", help="checkpoint.pt (or its run directory)")
    ev.add_argument("--episodes-per-code", type=int, default=100, help="rollouts per latent code (default: 100; "
                                                                       "continuous codes: per code value)")
    ev.add_argument("--code-values", type=int, default=9, help="continuous codes: code values evenly over the "
                                                               "prior, per dimension (default: 9)")
    ev.add_argument("--seed", type=int, default=0, help="rollout seed (default: 0)")
    ev.add_argument("--deterministic", action="store_true", help="act with the policy mean instead of sampling")
    ev.add_argument("--none-threshold", type=float, default=1.0,
                    help="mean distance to every circle above which a trajectory is in no mode (default: 1.0)")
    ev.add_argument("--demos", help="tasks (Hopper, any recorded task): demonstrations .npz whose metadata hold the "
                                    "expert and zero-action returns")
    ev.add_argument("--stochastic", action="store_true", help="tasks: sample actions (default there: the policy mean)")
    ev.add_argument("--json", action="store_true", help="print machine-readable JSON")
    ev.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                    help="tasks: show a progress bar of the episodes (default: True)")
    ev.set_defaults(func=cmd_evaluate)


def _add_plot(sub: argparse._SubParsersAction) -> None:
    pl = sub.add_parser("plot", help="Figure-1-style trajectories: experts and policies coloured by code")
    pl.add_argument("checkpoints", nargs="*", help="checkpoints to roll out, one panel each")
    pl.add_argument("--demos", help="demonstrations .npz: adds a panel of expert trajectories coloured by mode")
    pl.add_argument("--out", default="figure.png", help="output image (default: figure.png)")
    pl.add_argument("--episodes-per-code", type=int, default=20, help="trajectories drawn per code (default: 20)")
    pl.add_argument("--seed", type=int, default=0, help="rollout seed (default: 0)")
    pl.add_argument("--deterministic", action="store_true", help="act with the policy mean")
    pl.set_defaults(func=cmd_plot)


def _add_sweep(sub: argparse._SubParsersAction) -> None:
    from pomil.experiment import SweepConfig

    sw = sub.add_parser("sweep", help="one training config over seeds and a grid of settings, in parallel on Ray")
    sw.add_argument("sweep_config", metavar="CONFIG",
                    help='JSON object: "learner" and its config keys ("demos" at least)')
    sw.add_argument("--grid", action="append", metavar="KEY=V1,V2",
                    help="a config key and its values; repeat for more keys (their product is swept)")
    add_config_flags(sw, SweepConfig)
    sw.set_defaults(func=cmd_sweep)


def _add_reproduce(sub: argparse._SubParsersAction) -> None:
    """``pomil reproduce SPEC`` and ``pomil reproduce merge``."""
    from pomil.experiment import ReproduceOptions

    rp = sub.add_parser("reproduce", help="run an experiment spec end to end: demonstrations, every run, table and "
                                          "figure (--list names the shipped ones)")
    rp.add_argument("spec", nargs="?", metavar="SPEC",
                    help="a spec file (.toml) or a shipped experiment's name; 'merge' joins results run on other "
                         "seeds or rows: pomil reproduce merge DIR DIR ... --out DIR")
    rp.add_argument("sources", nargs="*", metavar="DIR", help="with merge: the results directories to join")
    rp.add_argument("--list", action="store_true", help="name the shipped experiments and what each measures")
    rp.add_argument("--policies", action=argparse.BooleanOptionalAction, default=True,
                    help="with merge: copy every kept policy into OUT/policies (each must exist); --no-policies "
                         "joins the metrics alone (default: %(default)s)")
    add_config_flags(rp, ReproduceOptions)
    rp.set_defaults(func=cmd_reproduce)


def docs_dir() -> Any:
    """The documentation's folder: the one the package ships (``pomil/docs``, put there by the build), else the
    source checkout's ``docs/`` (an editable install)."""
    from importlib.resources import files

    shipped = files("pomil") / "docs"
    return shipped if shipped.is_dir() else Path(__file__).resolve().parents[2] / "docs"


def cmd_docs(args: argparse.Namespace) -> int:
    """``pomil docs``: the topics and their titles; ``pomil docs TOPIC``: that document's text."""
    folder = docs_dir()
    topics = {p.name.removesuffix(".md"): p for p in folder.iterdir() if p.name.endswith(".md")}
    if not topics:
        raise PomilError(f"{folder}: no documentation there (a pomil installed without its docs)")
    if args.topic is None:
        for name, path in sorted(topics.items()):
            title = path.read_text(encoding="utf-8").splitlines()[0].lstrip("# ")
            print(f"{name:<10} {title}")
        return 0
    if args.topic not in topics:
        raise PomilError(f"no documentation topic '{args.topic}': choose from {', '.join(sorted(topics))}")
    sys.stdout.write(topics[args.topic].read_text(encoding="utf-8"))
    return 0


def _add_docs(sub: argparse._SubParsersAction) -> None:
    """``pomil docs [TOPIC]``."""
    dc = sub.add_parser("docs", help="the documentation shipped with the package: the topics, or one topic's text")
    dc.add_argument("topic", nargs="?", metavar="TOPIC", help="a topic's name (pomil docs lists them)")
    dc.set_defaults(func=cmd_docs)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pomil",
                                description="Multi-modal imitation learning in partially observable environments.")
    from pomil import __version__

    p.add_argument("--version", action="version", version=f"pomil {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_demos, _add_training, _add_evaluate, _add_plot, _add_sweep, _add_reproduce, _add_docs):
        add(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        from pomil.envs.batch import mujoco_warnings_once

        mujoco_warnings_once()  # gymnasium's HalfCheetah model warns at each load: once is enough
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # here, where a reader that left is caught below, not at the interpreter's exit
        return status
    except PomilError as err:
        print(f"pomil: error: {err}", file=sys.stderr)
        return err.exit_status
    except KeyboardInterrupt:
        print("pomil: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of stdout left (`pomil docs method | head`): stop quietly, as a shell tool
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error as Python flushes at exit
        return 141


if __name__ == "__main__":
    sys.exit(main())
