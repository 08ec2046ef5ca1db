"""Typed configuration: frozen dataclasses whose fields carry their own help.

Every config field is declared with :func:`option`, which stores a one-line
description in the field's metadata.  The CLI turns the fields into flags
(``--batch-episodes 32``) and a JSON config file may set any of them; an
unknown key is an error that lists the valid ones.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

from pomil.errors import PomilError

T = TypeVar("T")


def option(default: Any, help: str, **kwargs: Any) -> Any:
    """A dataclass field with a default and its one-line description."""
    if isinstance(default, (list, dict, set)):
        raise TypeError("use a tuple for sequence defaults")
    return dataclasses.field(default=default, metadata={"help": help, **kwargs})


def field_help(f: dataclasses.Field) -> str:
    return str(f.metadata.get("help", ""))


def _resolved_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Convert ``value`` (from JSON or a flag string) to the annotated type."""
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if value is None or (isinstance(value, str) and value.lower() == "none"):
            return None
        return _coerce(value, args[0], key)
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices:
            raise PomilError(f"config key '{key}': expected one of {list(choices)}, got {value!r}")
        return value
    if origin is tuple:
        inner = get_args(tp)[0]
        if isinstance(value, dict):  # JSON object for a key=value list (env_kwargs)
            value = [f"{k}={json.dumps(v)}" for k, v in value.items()]
        if isinstance(value, str):
            value = [v for v in value.split(",") if v.strip()]
        return tuple(_coerce(v, inner, key) for v in value)
    try:
        if tp is bool:
            if isinstance(value, str):
                low = value.lower()
                if low in ("1", "true", "yes", "on"):
                    return True
                if low in ("0", "false", "no", "off"):
                    return False
                raise ValueError(value)
            return bool(value)
        if tp is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            return int(value)
        if tp is float:
            return float(value)
        if tp is str:
            return str(value)
    except (TypeError, ValueError):
        raise PomilError(f"config key '{key}': expected {tp.__name__}, got {value!r}") from None
    return value


def from_dict(cls: type[T], values: dict[str, Any], source: str = "config") -> T:
    """Build ``cls`` from a dict, rejecting unknown keys and coercing types.

    A config class with named presets (a ``PRESETS`` table of ``{name: {field: value}}``
    and a ``preset`` field) gets the named preset's values first; the dict's own
    values override them."""
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise PomilError(
            f"{source}: unknown key(s) {unknown}; valid keys are: {', '.join(names)}"
        )
    presets: dict[str, dict[str, Any]] = getattr(cls, "PRESETS", {})
    if presets and values.get("preset") is not None:
        if values["preset"] not in presets:
            raise PomilError(f"config key 'preset': expected one of {list(presets)}, got {values['preset']!r}")
        values = {**presets[values["preset"]], **values}
    hints = _resolved_types(cls)
    coerced = {k: _coerce(v, hints[k], k) for k, v in values.items()}
    try:
        return cls(**coerced)
    except (TypeError, ValueError) as err:
        raise PomilError(f"{source}: {err}") from None


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a JSON config file into a dict (one flat object of key: value)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise PomilError(f"{path}: cannot read config file ({err.strerror})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise PomilError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    if not isinstance(data, dict):
        raise PomilError(f"{path}: expected a JSON object of key: value pairs")
    return {k.replace("-", "_"): v for k, v in data.items()}


def to_dict(config: Any) -> dict[str, Any]:
    """Plain JSON-able dict of a config dataclass (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def parse_kwargs(entries: tuple[str, ...] | list[str], name: str = "env_kwargs") -> dict[str, Any]:
    """``("forward_reward_weight=-1", "max_episode_steps=128")`` -> dict; values
    are read as JSON (numbers, true/false, null, lists), else kept as strings."""
    out: dict[str, Any] = {}
    for entry in entries:
        key, sep, raw = str(entry).partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            raise PomilError(f"config key '{name}': expected key=value entries, got {entry!r}")
        try:
            out[key] = json.loads(raw)
        except json.JSONDecodeError:
            out[key] = raw.strip()
    return out


def check_positive(config: Any, *names: str) -> None:
    """Raise ValueError unless every named field is >= 1."""
    for name in names:
        if getattr(config, name) < 1:
            raise ValueError(f"{name} must be >= 1, got {getattr(config, name)}")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Options every learner's run has (the one thin base of the learner configs).

    Subclasses may redeclare a field to change its default.
    """

    demos: str = option("", "demonstrations .npz to imitate (required)")
    env_kwargs: tuple[str, ...] = option((), "environment keywords key=value that replace the demonstrations' "
                                             "(training rollouts, evaluation), e.g. max_episode_steps=200")
    observation_mask: str = option("", "re-mask the demonstrations' full observations (their states): positions-only or "
                                       "indices; '' keeps the demonstrations' own view")
    out: str = option("runs/run", "run directory: checkpoint.pt, metrics.csv, tb/, config.json")
    seed: int = option(0, "random seed (same seed, same run on CPU)")
    log_every: int = option(25, "iterations between log rows")
    checkpoint_every: int = option(500, "iterations between checkpoints (one is always written at the end)")
    device: str = option("cpu", "cpu, cuda, cuda:N or auto")
    progress: bool = option(True, "show a progress bar")

    def __post_init__(self) -> None:
        check_positive(self, "log_every", "checkpoint_every")
        from pomil.envs.wrappers import parse_mask

        parse_mask(self.observation_mask)  # ValueError for a malformed mask
        parse_kwargs(self.env_kwargs)
