"""Demonstrations: one frozen container, checked on construction, saved as .npz.

Episodes are stored back to back (flat arrays) with their boundaries, so
episodes of different lengths need no padding on disk.  ``labels`` (which
expert / task made each episode) and ``states`` (full simulator states) are
optional and for evaluation only: unsupervised learners never read them.

Files are plain ``.npz`` archives of numeric arrays plus one JSON string of
metadata; they load with ``allow_pickle=False``, so opening a file never runs
code from it.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import tempfile
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pomil.errors import DataError, PomilError

FORMAT_VERSION = 1
_ARRAYS = ("observations", "actions", "episode_bounds", "labels", "states")


def _check_finite(name: str, arr: np.ndarray) -> None:
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise DataError(name, f"expected finite values, found {bad} NaN/inf")


@dataclass(frozen=True)
class Demonstrations:
    """Expert demonstrations, E episodes of (observation, action) pairs.

    Shapes (S = total steps over all episodes):
      observations   (S, obs_dim) float32, what the learner sees at each step
      actions        (S, act_dim) float32, what the expert did
      episode_bounds (E + 1,) int64, episode i is rows bounds[i]:bounds[i+1]
      labels         (E,) int64 or None, expert / task id (evaluation only)
      states         (S, state_dim) float32 or None, full states (evaluation)
      metadata       JSON-able dict: env_id, env_kwargs, observation_mask,
                     source, expert_returns, ...
    """

    observations: np.ndarray
    actions: np.ndarray
    episode_bounds: np.ndarray
    labels: np.ndarray | None = None
    states: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        obs = np.asarray(self.observations)
        act = np.asarray(self.actions)
        bounds = np.asarray(self.episode_bounds)
        if obs.ndim != 2:
            raise DataError("observations", f"expected a 2-D array (steps, obs_dim), got shape {obs.shape}")
        if act.ndim != 2:
            raise DataError("actions", f"expected a 2-D array (steps, act_dim), got shape {act.shape}")
        for name, arr in (("observations", obs), ("actions", act)):
            if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
                raise DataError(name, f"expected real numbers, got dtype {arr.dtype}")
            _check_finite(name, arr.astype(np.float64))
        if act.shape[0] != obs.shape[0]:
            raise DataError("actions", f"expected {obs.shape[0]} rows (one per observation), got {act.shape[0]}")
        if bounds.ndim != 1 or not np.issubdtype(bounds.dtype, np.integer):
            raise DataError("episode_bounds",
                            f"expected a 1-D integer array, got shape {bounds.shape} dtype {bounds.dtype}")
        if bounds.size < 2:
            raise DataError("episode_bounds", "expected at least one episode, got zero")
        if bounds[0] != 0 or bounds[-1] != obs.shape[0]:
            raise DataError("episode_bounds", f"expected to start at 0 and end at {obs.shape[0]} (the number of "
                                              f"steps), got {bounds[0]}..{bounds[-1]}")
        if np.any(np.diff(bounds) <= 0):
            raise DataError("episode_bounds", "expected strictly increasing bounds (no empty episodes)")
        n_ep = bounds.size - 1
        if self.labels is not None:
            labels = np.asarray(self.labels)
            if labels.shape != (n_ep,) or not np.issubdtype(labels.dtype, np.integer):
                raise DataError("labels", f"expected ({n_ep},) integers (one per episode), got shape {labels.shape} "
                                          f"dtype {labels.dtype}")
            object.__setattr__(self, "labels", labels.astype(np.int64))
        if self.states is not None:
            states = np.asarray(self.states)
            if states.ndim != 2 or states.shape[0] != obs.shape[0]:
                raise DataError("states", f"expected ({obs.shape[0]}, state_dim), got shape {states.shape}")
            _check_finite("states", states.astype(np.float64))
            object.__setattr__(self, "states", states.astype(np.float32))
        if not isinstance(self.metadata, dict):
            raise DataError("metadata", f"expected a dict, got {type(self.metadata).__name__}")
        object.__setattr__(self, "observations", obs.astype(np.float32))
        object.__setattr__(self, "actions", act.astype(np.float32))
        object.__setattr__(self, "episode_bounds", bounds.astype(np.int64))

    # ------------------------------------------------------------------ views
    @property
    def num_episodes(self) -> int:
        return int(self.episode_bounds.size - 1)

    @property
    def num_steps(self) -> int:
        return int(self.observations.shape[0])

    @property
    def obs_dim(self) -> int:
        return int(self.observations.shape[1])

    @property
    def act_dim(self) -> int:
        return int(self.actions.shape[1])

    @property
    def episode_lengths(self) -> np.ndarray:
        return np.diff(self.episode_bounds)

    def episode(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.episode_bounds[i], self.episode_bounds[i + 1]
        return self.observations[lo:hi], self.actions[lo:hi]

    def subset(self, episodes: Sequence[int]) -> Demonstrations:
        """These episodes (indices, in the order given), with their labels and states."""
        steps = np.concatenate([np.arange(self.episode_bounds[i], self.episode_bounds[i + 1]) for i in episodes])
        bounds = np.concatenate([[0], np.cumsum(self.episode_lengths[list(episodes)])])
        labels = None if self.labels is None else self.labels[list(episodes)]
        states = None if self.states is None else self.states[steps]
        return Demonstrations(self.observations[steps], self.actions[steps], bounds, labels, states,
                              dict(self.metadata))

    def padded(self, device: torch.device | str = "cpu") -> PaddedEpisodes:
        """All episodes as time-major (T_max, E, ...) tensors with a validity mask."""
        lengths = self.episode_lengths
        step = np.arange(int(lengths.max()))[:, None]
        mask = step < lengths[None, :]
        rows = np.where(mask, self.episode_bounds[:-1][None, :] + step, 0)
        obs = np.where(mask[..., None], self.observations[rows], 0.0)
        act = np.where(mask[..., None], self.actions[rows], 0.0)
        return PaddedEpisodes(torch.as_tensor(obs, dtype=torch.float32, device=device),
                              torch.as_tensor(act, dtype=torch.float32, device=device),
                              torch.as_tensor(mask, device=device))

    def check_compatible(self, obs_dim: int, act_dim: int, source: str | None = None) -> None:
        """Raise a DataError unless the sizes match an environment's."""
        if self.obs_dim != obs_dim:
            raise DataError("observations", f"expected obs_dim {obs_dim} for this environment, got {self.obs_dim}",
                            source)
        if self.act_dim != act_dim:
            raise DataError("actions", f"expected act_dim {act_dim} for this environment, got {self.act_dim}", source)

    # -------------------------------------------------------------------- I/O
    def save(self, path: str | Path) -> None:
        """Write atomically: a temporary file in the same folder, then rename."""
        arrays = {"observations": self.observations, "actions": self.actions, "episode_bounds": self.episode_bounds,
                  "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
                  "metadata": np.array(json.dumps(self.metadata))}
        arrays.update({name: getattr(self, name) for name in ("labels", "states") if getattr(self, name) is not None})
        atomic_write(Path(path), lambda f: np.savez_compressed(f, **arrays))

    @classmethod
    def load(cls, path: str | Path) -> Demonstrations:
        """Load and validate; any problem is a DataError naming file and field."""
        path = Path(path)
        src = str(path)
        if not path.exists():
            raise DataError("(file)", "no such file", src)
        if not zipfile.is_zipfile(path):
            raise DataError("(file)", "expected an .npz archive (numpy.savez), but this is not a zip file", src)
        try:
            with np.load(path, allow_pickle=False) as archive:
                names = set(archive.files)
                for required in ("observations", "actions", "episode_bounds"):
                    if required not in names:
                        raise DataError(required, "missing from the archive", src)
                values: dict[str, Any] = {}
                for name in [n for n in _ARRAYS if n in names]:
                    try:
                        values[name] = archive[name]
                    except ValueError as err:
                        if "allow_pickle" in str(err):
                            raise DataError(name, "holds pickled Python objects; expected a numeric array",
                                            src) from None
                        raise DataError(name, f"unreadable ({err})", src) from None
                metadata: dict[str, Any] = {}
                if "metadata" in names:
                    try:
                        metadata = json.loads(str(archive["metadata"]))
                    except ValueError:  # json.JSONDecodeError too
                        raise DataError("metadata", "expected a JSON string", src) from None
                    if not isinstance(metadata, dict):
                        raise DataError("metadata", "expected a JSON object", src)
        except DataError:
            raise
        except Exception as err:  # a corrupted archive: zipfile, zlib and numpy raise many types
            first = (str(err).strip().splitlines() or [""])[0][:160]
            raise DataError("(file)", f"unreadable .npz archive ({type(err).__name__}: {first})", src) from None
        try:
            return cls(metadata=metadata, **values)
        except DataError as err:
            raise err.with_source(src) from None


@dataclass(frozen=True)
class PaddedEpisodes:
    """Episodes time-major: observations (T, E, obs_dim), actions (T, E, act_dim), mask (T, E)."""

    observations: torch.Tensor
    actions: torch.Tensor
    mask: torch.Tensor

    def __post_init__(self) -> None:
        t, e = self.mask.shape
        if self.observations.shape[:2] != (t, e) or self.actions.shape[:2] != (t, e):
            raise ValueError(f"padded shapes disagree: obs {tuple(self.observations.shape)}, "
                             f"actions {tuple(self.actions.shape)}, mask {tuple(self.mask.shape)}")

    def select(self, idx: torch.Tensor) -> PaddedEpisodes:
        return PaddedEpisodes(self.observations[:, idx], self.actions[:, idx], self.mask[:, idx])


_UMASK = os.umask(0)
os.umask(_UMASK)


class _RecordingFile:
    """A file object that remembers the first OSError its writes raised: writers such as
    ``torch.save`` turn a full disk into a RuntimeError that no longer says so."""

    def __init__(self, f) -> None:
        self._f = f
        self.error: OSError | None = None

    def write(self, data) -> int:
        try:
            return self._f.write(data)
        except OSError as err:
            self.error = self.error or err
            raise

    def __getattr__(self, name: str):
        return getattr(self._f, name)


def atomic_write(path: Path, write) -> None:
    """Call ``write(fileobj)`` on a temporary file next to ``path``, then rename over it.

    Either the whole new file is at ``path`` or the previous one is untouched: a
    failed write (no space, read-only folder) removes the temporary file and
    ends in a one-line PomilError that says so.
    """
    path = Path(path)
    tmp = rec = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
        with os.fdopen(fd, "wb") as f:
            rec = _RecordingFile(f)
            write(rec)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        cause = err if isinstance(err, OSError) else (rec.error if rec is not None else None)
        if cause is None:
            raise
        left = f"the previous {path.name} is unchanged" if path.exists() else "nothing was written"
        raise PomilError(f"{path}: cannot write ({cause.strerror or cause}); {left}") from None


def check_demos_env(demos: Demonstrations, source: str) -> tuple[str, dict[str, Any]]:
    """Check that the demos name their environment and fit its spaces.

    Returns (env_id, env_kwargs) from the metadata; ``metadata.observation_mask``
    (indices of the observed entries, or null) is checked against the env.
    """
    from pomil.envs import env_dims, state_dim

    env_id = demos.metadata.get("env_id")
    kwargs = demos.metadata.get("env_kwargs") or {}
    if not isinstance(env_id, str) or not env_id:
        raise DataError("metadata.env_id", "expected the id of the environment the demonstrations come from", source)
    if not isinstance(kwargs, dict):
        raise DataError("metadata.env_kwargs", f"expected a JSON object, got {type(kwargs).__name__}", source)
    mask = demos.metadata.get("observation_mask")
    if mask is not None and (not isinstance(mask, list) or not all(isinstance(i, int) for i in mask)):
        raise DataError("metadata.observation_mask", f"expected null or a list of observation indices, got {mask!r}",
                        source)
    try:
        obs_dim, act_dim = env_dims(env_id, kwargs)
    except Exception as err:  # unknown id, bad kwargs: gymnasium raises several types
        raise DataError("metadata.env_id", f"cannot build {env_id!r} with {kwargs} ({str(err).splitlines()[0][:160]})",
                        source) from None
    if mask is not None:
        try:
            obs_dim, act_dim = env_dims(env_id, kwargs, mask)
        except ValueError as err:
            raise DataError("metadata.observation_mask", str(err), source) from None
    demos.check_compatible(obs_dim, act_dim, source)
    if demos.states is not None and demos.states.shape[1] != (want := state_dim(env_id, kwargs)):
        raise DataError("states", f"expected {want} columns (the full state of {env_id}), got {demos.states.shape[1]}",
                        source)
    return env_id, kwargs


def per_mode(demos: Demonstrations, n: int, seed: int, source: str) -> Demonstrations:
    """``n`` episodes of each mode: drawn with ``seed`` from each label's episodes (kept in file order), or, without
    labels, the first ``n`` x modes episodes (modes from the metadata; a note says so).  One-line DataError when a
    mode has fewer than ``n`` episodes."""
    if demos.labels is None:
        from pomil.envs import default_num_codes

        modes = len(demos.metadata.get("label_names") or []) or default_num_codes(demos.metadata)
        if not modes:
            raise DataError("labels", "expected labels or a number of modes in the metadata, to take "
                                      f"{n} episodes per mode", source)
        if n * modes > demos.num_episodes:
            raise DataError("episodes", f"expected at least {n} x {modes} episodes for {n} per mode, got "
                                        f"{demos.num_episodes}", source)
        print(f"pomil: note: {source}: no labels, so the first {n * modes} episodes ({n} per mode x {modes} modes "
              "if they are balanced) are the training set", file=sys.stderr)
        return demos.subset(range(n * modes))
    counts = np.bincount(demos.labels)
    if counts[counts > 0].min() < n:
        raise DataError("labels", f"expected at least {n} episodes of every mode for {n} per mode, got "
                                  f"{counts[counts > 0].tolist()}", source)
    rng = np.random.default_rng(seed)
    chosen = [rng.choice(np.flatnonzero(demos.labels == k), n, replace=False) for k in np.flatnonzero(counts)]
    return demos.subset(np.sort(np.concatenate(chosen)).tolist())


def load_training_demos(path: str, env_kwargs: dict[str, Any] | None = None,
                        observation_mask: str | list[int] | None = None, *, per_mode_episodes: int = 0,
                        seed: int = 0) -> tuple[Demonstrations, str, dict[str, Any]]:
    """Demonstrations for a learner, with the run's overrides applied, checked
    against their environment: (demos, env_id, env_kwargs).

    ``env_kwargs`` replace keywords of the demonstrations' environment;
    ``observation_mask`` (a preset or indices into the full observation)
    re-masks the demonstrations' full observations (``states``);
    ``per_mode_episodes`` (0: all) keeps that many episodes of each mode (:func:`per_mode`, drawn with ``seed``).
    """
    demos = Demonstrations.load(path)
    if per_mode_episodes:
        demos = per_mode(demos, per_mode_episodes, seed, path)
    if env_kwargs or observation_mask is not None:
        md = dict(demos.metadata)
        if env_kwargs:
            md["env_kwargs"] = {**(md.get("env_kwargs") or {}), **env_kwargs}
        observations = demos.observations
        if observation_mask is not None:
            from pomil.envs import env_dims
            from pomil.envs.wrappers import resolve_observation_mask

            if demos.states is None:
                raise DataError("states", "expected the full observations, to apply an observation mask to", path)
            try:
                full_dim, _ = env_dims(str(md.get("env_id")), md.get("env_kwargs") or {})
                idx = resolve_observation_mask(str(md.get("env_id")), md.get("env_kwargs") or {}, observation_mask)
            except Exception as err:  # unknown env, bad keywords or mask
                raise DataError("metadata.env_id",
                                f"cannot apply the observation mask ({str(err).splitlines()[0][:160]})", path) from None
            if demos.states.shape[1] != full_dim:
                raise DataError("states",
                                f"expected full observations of size {full_dim} to mask, got {demos.states.shape[1]}",
                                path)
            observations = demos.states if idx is None else demos.states[:, idx]
            md["observation_mask"] = idx
        demos = Demonstrations(observations, demos.actions, demos.episode_bounds, demos.labels, demos.states, md)
    env_id, kwargs = check_demos_env(demos, path)
    return demos, env_id, kwargs
