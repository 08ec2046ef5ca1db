"""Typed configuration: frozen dataclasses whose fields carry their own help.

Every config field is declared with :func:`option`, which stores a one-line
description in the field's metadata and, for numbers, the interval of allowed
values (``within="(0, 1]"``).  The CLI turns the fields into flags
(``--batch-episodes 32``) and a JSON config file may set any of them; an
unknown key is an error that lists the valid ones.

Why the intervals live on the fields: one generic check (:func:`check_fields`)
then covers every field of every config, whether it came from a flag, a JSON
file or Python, and ``--help`` shows the same interval the check enforces.  A
value outside it (NaN and inf are outside every interval) is refused when the
config is built, before anything is written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import sys
import types
import typing
from pathlib import Path
from typing import Any, Literal, NamedTuple, TypeVar, get_args, get_origin

from pomil.errors import ConfigError, PomilError

T = TypeVar("T")


class Interval(NamedTuple):
    """Allowed values of a numeric field, parsed from interval notation such as ``"(0, 1]"``."""

    low: float
    high: float
    low_open: bool
    high_open: bool
    text: str

    @classmethod
    def parse(cls, text: str) -> Interval:
        m = re.fullmatch(r"\s*([\[(])\s*([^,\s]+)\s*,\s*([^\]\s)]+)\s*([\])])\s*", text)
        if not m:
            raise ValueError(f"interval {text!r}: expected e.g. '(0, 1]' or '[1, inf)'")
        low, high = float(m.group(2)), float(m.group(3))
        if math.isnan(low) or math.isnan(high) or low > high:
            raise ValueError(f"interval {text!r}: bounds out of order")
        return cls(low, high, m.group(1) == "(", m.group(4) == ")",
                   f"{m.group(1)}{m.group(2)}, {m.group(3)}{m.group(4)}")

    def __contains__(self, x: object) -> bool:
        if not isinstance(x, (int, float)) or not math.isfinite(x):  # NaN and inf are in no interval
            return False
        above = x > self.low if self.low_open else x >= self.low
        below = x < self.high if self.high_open else x <= self.high
        return above and below


def option(default: Any, help: str, within: str | None = None, named: dict[str, int] | None = None,
           **kwargs: Any) -> Any:
    """A dataclass field with a default, its one-line description and, for a number
    (or a tuple of numbers), the interval its values must lie in: ``within="[1, inf)"``
    (a count), ``"(0, inf)"`` (a learning rate), ``"(0, 1]"`` (a discount),
    ``"(-inf, inf)"`` (any finite value).  Every int and float field declares one.

    ``named``: words that a flag or JSON file may give for reserved values of an int field
    (``{"auto": 0}``); the field holds the value, and config.json and checkpoints record the word."""
    if isinstance(default, (list, dict, set)):
        raise TypeError("use a tuple for sequence defaults")
    metadata = {"help": help, **kwargs}
    if named:
        if within is None or any(not isinstance(v, int) or v not in Interval.parse(within) for v in named.values()):
            raise ValueError(f"named values {named} must be integers in the field's interval {within}")
        metadata["named"] = dict(named)
    if within is not None:
        interval = Interval.parse(within)
        for v in default if isinstance(default, tuple) else (default,):
            if v not in interval:
                raise ValueError(f"default {default!r} is not in {within}")
        metadata["within"] = interval
    return dataclasses.field(default=default, metadata=metadata)


def field_help(f: dataclasses.Field) -> str:
    return str(f.metadata.get("help", ""))


def field_interval(f: dataclasses.Field) -> Interval | None:
    return f.metadata.get("within")


def field_names(f: dataclasses.Field) -> dict[str, int]:
    """The words a flag or JSON file may give for the field's reserved values (``{"auto": 0}``), if any."""
    return f.metadata.get("named", {})


def _type_name(tp: Any) -> str:
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}.get(tp, str(tp))


def _check_value(name: str, value: Any, tp: Any, interval: Interval | None) -> None:
    """Raise ConfigError unless ``value`` has type ``tp`` (after coercion) and lies in ``interval``."""
    origin = get_origin(tp)
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(f"config key '{name}': expected one of {list(get_args(tp))}, got {value!r}")
        return
    if origin is tuple:
        if not isinstance(value, tuple):
            raise ConfigError(f"config key '{name}': expected a list, got {value!r}")
        for v in value:
            _check_value(name, v, get_args(tp)[0], interval)
        return
    if tp in (int, float, bool, str):
        ok = isinstance(value, tp) and not (tp is not bool and isinstance(value, bool))
        if tp is float and isinstance(value, int) and not isinstance(value, bool):
            ok = True
        if not ok:
            raise ConfigError(f"config key '{name}': expected {_type_name(tp)}, got {value!r}")
    if tp in (int, float):
        if interval is None:
            raise TypeError(f"config field '{name}' declares no interval (option(..., within=...))")
        if value not in interval:
            what = "an integer" if tp is int else "a finite number"
            raise ConfigError(f"config key '{name}': expected {what} in {interval.text}, got {value!r}")


def check_fields(config: Any) -> None:
    """Type- and range-check every field of a config dataclass (see :func:`option`)."""
    hints = typing.get_type_hints(type(config))
    for f in dataclasses.fields(config):
        _check_value(f.name, getattr(config, f.name), hints[f.name], field_interval(f))


_BOOL_WORDS = {"1": True, "true": True, "yes": True, "on": True, "0": False, "false": False, "no": False, "off": False}


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
            if isinstance(value, str) and value.lower() in _BOOL_WORDS:
                return _BOOL_WORDS[value.lower()]
            if isinstance(value, bool) or (isinstance(value, int) and value in (0, 1)):
                return bool(value)
            raise ValueError(value)
        if tp in (int, float):
            if isinstance(value, bool) or not isinstance(value, (int, float, str)) or (
                    tp is int and isinstance(value, float) and not value.is_integer()):
                raise ValueError(value)
            return tp(value)
        if tp is str:
            if not isinstance(value, str):
                raise ValueError(value)
            return value
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"config key '{key}': expected {tp.__name__}, got {value!r}") from None
    return value


def _coerce_named(value: Any, tp: Any, key: str, named: dict[str, int]) -> Any:
    """:func:`_coerce`, with the field's words for reserved values (``"auto"``) read as those values."""
    if not named or not isinstance(value, str):
        return _coerce(value, tp, key)
    if value.strip().lower() in named:
        return named[value.strip().lower()]
    try:
        return _coerce(value, tp, key)
    except ConfigError:
        raise ConfigError(f"config key '{key}': expected an integer or {' or '.join(map(repr, named))}, "
                          f"got {value!r}") from None


def _reject_unknown(values: dict[str, Any], names: list[str], source: str) -> None:
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise PomilError(f"{source}: unknown key(s) {unknown}; valid keys are: {', '.join(names)}")


def check_values(cls: type, values: dict[str, Any], source: str) -> None:
    """Check every key of ``values`` (a config file's) on its own, before flags override any of them: a
    known key (old names read), a value of the field's type within its interval; one-line ConfigError or
    PomilError naming ``source`` otherwise."""
    values = _renamed(cls, values, source, note=False)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    _reject_unknown(values, list(fields), source)
    hints = typing.get_type_hints(cls)
    for key, value in values.items():
        if key == "preset" and value == AUTO:
            continue
        try:
            _check_value(key, _coerce_named(value, hints[key], key, field_names(fields[key])), hints[key],
                         field_interval(fields[key]))
        except PomilError as err:
            raise type(err)(f"{source}: {err}") from None
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{source}: config key '{key}': {err}") from None


def from_dict(cls: type[T], values: dict[str, Any], source: str = "config") -> T:
    """Build ``cls`` from a dict, rejecting unknown keys and coercing types.

    A config class with named presets (a ``PRESETS`` table of ``{name: {field: value}}``
    and a ``preset`` field) gets the named preset's values first; the dict's own
    values override them.  Preset ``auto`` stays as it is, with the keys given noted,
    until :func:`resolved` replaces it when training starts."""
    values = _renamed(cls, values, source)
    _reject_unknown(values, [f.name for f in dataclasses.fields(cls)], source)  # type: ignore[arg-type]
    presets: dict[str, dict[str, Any]] = getattr(cls, "PRESETS", {})
    default = next((f.default for f in dataclasses.fields(cls) if f.name == "preset"), None)  # type: ignore[arg-type]
    name = values.get("preset", default) if presets else None
    if name is not None and name != AUTO:
        if not isinstance(name, str) or name not in presets:
            raise ConfigError(f"config key 'preset': expected one of {[AUTO, *presets]}, got {name!r}")
        values = {**presets[name], **values}
    hints = typing.get_type_hints(cls)
    named = {f.name: field_names(f) for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    where = "" if source == "config" else f"{source}: "
    try:
        coerced = {k: _coerce_named(v, hints[k], k, named[k]) for k, v in values.items()}
        config = cls(**coerced)
        check_fields(config)  # also for configs without a __post_init__ that calls it
        if name == AUTO:
            object.__setattr__(config, "_given", frozenset(values))  # for resolved(): the values given win
        return config
    except ConfigError as err:
        raise ConfigError(f"{where}{err}") from None
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{source}: {err}") from None


AUTO = "auto"
"""The ``preset`` that stands for another, chosen from the demonstrations (:meth:`RunConfig.auto_preset`)."""


def resolved(config: T) -> T:
    """``config`` with ``preset`` auto replaced by the preset it stands for (the class's ``auto_preset``,
    which reads the demonstrations), called once where training starts; the run records the preset it ran.
    The preset's values go under the values given to :func:`from_dict` (for a config built in Python, under
    those that differ from their defaults)."""
    if getattr(config, "preset", None) != AUTO:
        return config
    given = getattr(config, "_given", None)
    explicit = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)  # type: ignore[arg-type]
                if (f.name in given if given is not None else getattr(config, f.name) != f.default)}
    explicit = json.loads(json.dumps({k: v for k, v in explicit.items() if k != "preset"}))
    cls = type(config)
    return from_dict(cls, {**explicit, "preset": cls.auto_preset(explicit)}, source=cls.__name__)  # type: ignore[attr-defined]


def _renamed(cls: type, values: dict[str, Any], source: str, note: bool = True) -> dict[str, Any]:
    """``values`` with the class's old key names (its ``RENAMED`` table, old -> new) under their new
    names, so that saved config.json files and checkpoints keep loading; a note asks to rename them."""
    values = _folded(cls, values, source, note)
    renamed: dict[str, str] = getattr(cls, "RENAMED", {})
    old = [k for k in values if k in renamed]
    if not old:
        return values
    values = dict(values)
    for key in old:
        if renamed[key] in values:
            raise ConfigError(f"{source}: config keys '{key}' and '{renamed[key]}' are the same setting "
                              f"('{key}' is its old name); keep '{renamed[key]}'")
        values[renamed[key]] = values.pop(key)
        if note:
            print(f"pomil: note: {source}: config key '{key}' is now called '{renamed[key]}' (the old name is "
                  "deprecated and still read)", file=sys.stderr)
    return values


def _folded(cls: type, values: dict[str, Any], source: str, note: bool) -> dict[str, Any]:
    """``values`` with the class's retired keys (its ``FOLDED`` table: old key -> (its type, a function of its
    value and the other values giving the new keys' values)) replaced, so that saved config files and
    checkpoints keep loading; a note names the replacement."""
    folded: dict[str, tuple[type, Any]] = getattr(cls, "FOLDED", {})
    for key in [k for k in values if k in folded]:
        values = dict(values)
        tp, fold = folded[key]
        new = fold(_coerce(values.pop(key), tp, key), values)
        values.update(new)
        if note:
            now = ", ".join(f"{k} {v!r}" for k, v in new.items()) or "the default"
            print(f"pomil: note: {source}: config key '{key}' is retired; read as {now}", file=sys.stderr)
    return values


def saved_config(cls: type, saved: dict[str, Any]) -> dict[str, Any]:
    """A config dict saved by an earlier version (in a checkpoint) as this version writes it:
    old key names renamed, and the keys added since then at their defaults (which reproduce
    what that version computed)."""
    values = _renamed(cls, saved, "checkpoint", note=False)
    defaults = {f.name: f.default for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING}
    if defaults.get("preset") == AUTO:
        defaults["preset"] = "default"  # a version without presets ran no preset's values (auto resolves to one)
    if defaults.get("policy_members") == 0:
        defaults["policy_members"] = 1  # a version without ensembles ran one policy (auto resolves to 1 or 3)
    return {**values, **json.loads(json.dumps({k: v for k, v in defaults.items() if k not in values}))}


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a JSON config file into a dict (one flat object of key: value)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise PomilError(f"{path}: cannot read config file ({err.strerror})") from None
    except UnicodeDecodeError:
        raise PomilError(f"{path}: not valid JSON (not UTF-8 text)") from None
    try:
        data = json.loads(text)
    except RecursionError:
        raise PomilError(f"{path}: not valid JSON (nested too deeply)") from None
    except json.JSONDecodeError as err:
        raise PomilError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    if not isinstance(data, dict):
        raise PomilError(f"{path}: expected a JSON object of key: value pairs")
    return {k.replace("-", "_"): v for k, v in data.items()}


def to_dict(config: Any) -> dict[str, Any]:
    """Plain JSON-able dict of a config dataclass (tuples become lists; a reserved value of a field
    with ``named`` values as its word, e.g. ``"auto"``, so that :func:`from_dict` reads it back)."""
    values = json.loads(json.dumps(dataclasses.asdict(config)))
    for f in dataclasses.fields(config):
        words = {v: word for word, v in field_names(f).items()}
        if words and type(values[f.name]) is int and values[f.name] in words:
            values[f.name] = words[values[f.name]]
    return values


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


DEVICE = re.compile(r"cpu|auto|cuda(:\d+)?|mps")


def check_device(name: str) -> None:
    """Refuse a device name torch does not know (``tpu``) when the config is built."""
    if not isinstance(name, str) or not DEVICE.fullmatch(name):
        raise ConfigError(f"config key 'device': expected cpu, cuda, cuda:N, mps or auto, got {name!r}")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Options every learner's run has (the one thin base of the learner configs).

    Subclasses may redeclare a field to change its default.
    """

    demos: str = option("", "demonstrations .npz to imitate (required)")
    env_kwargs: tuple[str, ...] = option((), "environment keywords key=value that replace the demonstrations' "
                                             "(training rollouts, evaluation), e.g. max_episode_steps=200")
    observation_mask: str = option("",
                                   "re-mask the demonstrations' full observations (their states): positions-only, "
                                   "velocities or indices; '' keeps the demonstrations' own view")
    demos_per_mode: int = option(0, "train on N demonstration episodes of each mode (0: all), drawn with the run's "
                                    "seed from each labelled mode; unlabelled demonstrations: the first N x modes "
                                    "episodes", within="[0, inf)")
    out: str = option("", "run directory: checkpoint.pt, metrics.csv, tb/, config.json ('': runs/ and the learner's "
                          "name, an expert's runs/expert-ENV-TASK-SETTING)")
    overwrite: bool = option(False, "replace the run already in --out (its checkpoint, metrics.csv, config.json and "
                                    "tb/ go first); without it (or --resume) a run into a directory that holds one "
                                    "is refused")
    seed: int = option(0, "random seed (same seed, same run on CPU)", within="[0, 4294967295]")
    log_every: int = option(25, "iterations between log rows", within="[1, inf)")
    checkpoint_every: int = option(500, "iterations between checkpoints (one is always written at the end)",
                                   within="[1, inf)")
    device: str = option("cpu", "cpu, cuda, cuda:N or auto")
    progress: bool = option(True, "show a progress bar")

    def default_out(self) -> str:
        """The run directory when ``out`` is empty."""
        return "runs/run"

    TERMINATING: typing.ClassVar[str] = "terminating"
    """The preset that ``preset`` auto stands for when the demonstrations' environment ends episodes on failure."""

    @classmethod
    def auto_preset(cls, values: dict[str, Any]) -> str:
        """The preset ``auto`` stands for, given a config's ``values``: ``terminating`` when the demonstrations
        they name come from an environment (with the values' env_kwargs) that ends an episode when the agent
        fails, such as Hopper's own setting; ``default`` otherwise (the circles, the paper's Hopper), and
        when the demonstrations cannot be read (the run reports that when it loads them)."""
        from pomil.data import load_training_demos
        from pomil.envs import ends_on_failure

        try:
            _, env_id, env_kwargs = load_training_demos(str(values.get("demos") or ""),
                                                        parse_kwargs(values.get("env_kwargs") or ()))
            ends = ends_on_failure(env_id, env_kwargs)
        except PomilError:  # no file, a bad file or an unknown environment: the run says which when it loads them
            return "default"
        return cls.TERMINATING if ends and cls.TERMINATING in getattr(cls, "PRESETS", {}) else "default"

    def __post_init__(self) -> None:
        check_fields(self)
        check_device(self.device)
        from pomil.envs.wrappers import parse_mask

        parse_mask(self.observation_mask)  # ValueError for a malformed mask
        parse_kwargs(self.env_kwargs)
