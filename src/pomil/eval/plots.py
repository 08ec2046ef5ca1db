"""Figures from saved arrays only (no models): Figure-1-style trajectory panels."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pomil.data import atomic_write
from pomil.envs.locomotion import HOPPER_ID

COLOURS = ["tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:red", "tab:brown", "tab:pink", "tab:olive"]


def _pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path, dpi: int, fmt: str | None = None) -> None:
    """Write ``fig`` to ``path`` atomically (in the format its suffix names unless ``fmt``), then close it."""
    fmt = fmt or Path(path).suffix.lstrip(".") or "png"
    atomic_write(Path(path), lambda f: fig.savefig(f, format=fmt, dpi=dpi))
    _pyplot().close(fig)


def _panel(ax, positions: np.ndarray, groups: np.ndarray, *, title: str, group_name: str, max_per_group: int) -> None:
    for g in np.unique(groups):
        sel = np.flatnonzero(groups == g)[:max_per_group]
        colour = COLOURS[int(g) % len(COLOURS)]
        for j, e in enumerate(sel):
            path = np.concatenate([np.zeros((1, 2)), positions[e]], axis=0)
            ax.plot(path[:, 0], path[:, 1], color=colour, lw=0.8, alpha=0.6,
                    label=f"{group_name} {g}" if j == 0 else None)
    ax.plot(0, 0, "k.", ms=6)
    ax.set_title(title, fontsize=10)
    ax.set_aspect("equal")
    ax.set_xlim(-10, 10)
    ax.set_ylim(-12, 12)
    ax.legend(fontsize=7, loc="upper right")


def figure1(panels: Sequence[tuple[str, np.ndarray, np.ndarray, str]], path: str | Path,
            max_per_group: int = 20) -> None:
    """One panel per (title, positions (E, T, 2), groups (E,), group name)."""
    fig, axes = _pyplot().subplots(1, len(panels), figsize=(3.2 * len(panels), 3.8), squeeze=False)
    for ax, (title, pos, groups, name) in zip(axes[0], panels, strict=True):
        _panel(ax, np.asarray(pos), np.asarray(groups), title=title, group_name=name, max_per_group=max_per_group)
    fig.tight_layout()
    _save(fig, path, 120)


def grid_axis(rows: dict[str, dict]) -> str | None:
    """The one settings key with numeric values that a grid varies over every row ("ROW key=value ..."),
    the x axis of :func:`grid_figure`; None when there is no such key or more than one."""
    common = set.intersection(*[{t.split("=")[0] for t in name.split() if "=" in t} for name in rows] or [set()])
    keys = [k for k in common if all(type(r["settings"].get(k)) in (int, float) for r in rows.values())]
    return keys[0] if len(keys) == 1 else None


def grid_lines(rows: dict[str, dict], task: str, key: str) -> dict[str, tuple[list, list, list]]:
    """(values of ``key``, mean, std) of ``task``'s normalised return, ordered by value, for each row the grid was
    made from (its name without ``key=...``)."""
    points: dict[str, list[tuple[float, list[float]]]] = {}
    for name, r in rows.items():
        label = " ".join(t for t in name.split() if not t.startswith(f"{key}=")) or r["learner"]
        points.setdefault(label, []).append((r["settings"][key], r["summary"][task]["normalised_return"]))
    return {label: tuple(map(list, zip(*((x, *m) for x, m in sorted(p)), strict=True)))  # type: ignore[misc]
            for label, p in points.items()}


def grid_figure(rows: dict[str, dict], tasks: list[str], key: str, path: str | Path) -> None:
    """One panel per task: :func:`grid_lines` with their std as error bars, against the grid's ``key`` (the
    layout of GAIL's Figure 1)."""
    values = sorted({r["settings"][key] for r in rows.values()})
    fig, axes = _pyplot().subplots(1, len(tasks), figsize=(4.6 * len(tasks), 3.8), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        for i, (label, (x, mean, std)) in enumerate(grid_lines(rows, task, key).items()):
            ax.errorbar(x, mean, yerr=std, marker="o", capsize=3, color=COLOURS[i % len(COLOURS)], label=label)
        if values[0] > 0 and values[-1] >= 10 * values[0]:
            ax.set_xscale("log")
        ax.set_xticks(values, [f"{v:g}" for v in values], minor=False)
        ax.set(xlabel=key.replace("_", " "), ylabel="normalised return (matched code)", title=task)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path, 110, "png")


def learning_curves(results: dict, path: str | Path) -> None:
    """:func:`curves_figure`, written to ``path`` as a PNG."""
    _save(curves_figure(results), path, 110, "png")


def curves_figure(results: dict):
    """Figure-2c-style panels, one per task: normalised return of the code matched
    to the task over environment steps, mean +- std over seeds per adversarial
    learner, a dot at 0 env steps marking its warm start's level (a learner of 0
    iterations is that dot alone), ablations (``pomil.learners.ABLATIONS``) dashed;
    behaviour cloning (no environment steps) as a dotted level."""
    from pomil.learners import ABLATIONS

    tasks = results["tasks"]
    fig, axes = _pyplot().subplots(1, len(tasks), figsize=(6.5 * len(tasks), 5), squeeze=False)
    colours = COLOURS + ["tab:cyan", "tab:gray", "black", "gold"]
    for ax, task in zip(axes[0], tasks, strict=True):
        for i, (name, r) in enumerate(results["learners"].items()):
            colour = colours[i % len(colours)]
            curves = [c for c in r["curves"] if c["env_steps"]]
            if curves:
                n = min(len(c["env_steps"]) for c in curves)
                x = np.asarray(curves[0]["env_steps"][:n])
                y = np.asarray([c[task][:n] for c in curves])
                mean, std = y.mean(0), y.std(0)
                ax.plot(x, mean, color=colour, linestyle="--" if name in ABLATIONS else "-", marker="o",
                        markevery=[0], label=f"{name} ({len(curves)} seeds)")
                ax.fill_between(x, mean - std, mean + std, color=colour, alpha=0.12)
            else:
                level = r["summary"][task]["normalised_return"][0]
                ax.axhline(level, color=colour, linestyle=":", label=f"{name} (final)")
        ax.axhline(1.0, color="black", linewidth=0.8)
        ax.axhline(results["reference"]["still_returns"][task] / results["reference"]["expert_returns"][task],
                   color="grey", linestyle=":", linewidth=1, label="zero actions")
        env = str(results.get("env_id", HOPPER_ID)).split("-v")[0]  # results of before env_id was recorded: Hopper's
        ax.set_title(f"{env} {task}" + (f" ({results['setting']} setting)" if results.get("setting") else ""))
        ax.set_xlabel("environment steps")
        ax.set_ylabel("normalised return (code matched to task)")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="lower right", ncol=2)
    fig.tight_layout()
    return fig


def code_radius_figure(rollouts_path: str | Path, path: str | Path, row: str, max_paths: int = 120) -> None:
    """A continuous-code experiment's figure from its rollouts.npz: the demonstrations coloured by
    radius, ``row``'s first seed's trajectories coloured by code value, and code value against
    fitted radius for every seed of ``row`` (points; lines through each code value's median)."""
    import matplotlib

    with np.load(rollouts_path, allow_pickle=False) as r:
        data = {k.removeprefix(f"{row}/"): r[k] for k in r.files}
    seeds = sorted({k.split("/")[0] for k in data if k.startswith("seed")}, key=lambda s: int(s[4:]))
    fig, axes = _pyplot().subplots(1, 3, figsize=(14, 4.4))

    def paths(ax, positions, values, label, title):
        norm = matplotlib.colors.Normalize(values.min(), values.max())
        step = max(1, len(values) // max_paths)
        for e in np.argsort(values)[::step]:
            p = np.concatenate([np.zeros((1, 2)), positions[e]], axis=0)
            ax.plot(p[:, 0], p[:, 1], color=matplotlib.cm.viridis(norm(values[e])), lw=0.7, alpha=0.7)
        fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=ax, label=label)
        ax.plot(0, 0, "k.", ms=6)
        ax.set_aspect("equal")
        ax.set_xlim(-9, 9)
        ax.set_ylim(-3, 15)
        ax.set_title(title, fontsize=10)

    paths(axes[0], data["experts/positions"], data["experts/radii"], "radius", "demonstrations")
    if seeds:
        paths(axes[1], data[f"{seeds[0]}/positions"], data[f"{seeds[0]}/code_values"], "code value",
              f"policy, {seeds[0]}")
    ax = axes[2]
    top = 1.5 * float(data["experts/radii"].max())  # straight paths fit huge radii: clipped
    for i, s in enumerate(seeds):
        c, rad = data[f"{s}/code_values"], data[f"{s}/radii"]
        colour = COLOURS[i % len(COLOURS)]
        jitter = (np.random.default_rng(i).random(len(c)) - 0.5) * 0.03
        ax.scatter(c + jitter, np.clip(rad, 0, top), s=5, alpha=0.35, color=colour)
        values = np.unique(c)
        ax.plot(values, [np.median(rad[c == v]) for v in values], color=colour, marker="o", label=s)
    lo, hi = np.percentile(data["experts/radii"], [0, 100])
    ax.axhspan(lo, hi, color="grey", alpha=0.12, label="demonstrations' radii")
    ax.set_ylim(0, top)
    ax.set_xlabel("code value")
    ax.set_ylabel(f"fitted radius (clipped to {top:.1f})")
    ax.set_title("code value vs fitted radius", fontsize=10)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path, 110)
