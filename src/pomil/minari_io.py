"""Minari datasets (the Farama standard for offline RL data) <-> pomil demonstrations.

Optional extra: ``pip install 'pomil[minari]'`` (minari with its HDF5 backend; in a source checkout
``pip install -e '.[minari]'``).
Nothing is downloaded: datasets are read from and written to Minari's local
folder (``MINARI_DATASETS_PATH``, default ``~/.minari/datasets``) or the
``root`` given here.

How the two formats meet:

* A Minari episode holds T + 1 observations (the last one after the final
  action); pomil keeps the observation *before* each action (T rows).
  Import drops the final observation; export repeats the last recorded one
  (pomil never records the state after the final action).
* pomil does not record rewards (imitation needs none): export writes zeros.
  An episode is exported as terminated when it is shorter than the time
  limit, truncated otherwise.
* Export writes the full observation (``states``) when the demonstrations
  have it, so the Minari dataset matches its environment's observation
  space; the learner's mask, the labels (per step in ``infos["pomil_label"]``)
  and all pomil metadata travel with it, and import restores them exactly.
* A dataset from elsewhere: environment id and keywords come from its
  ``env_spec``; ``observation_mask`` picks the learner's view, and the full
  observations are kept as ``states``.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from pomil.data import Demonstrations
from pomil.errors import PomilError

LABEL_KEY = "pomil_label"
METADATA_KEY = "pomil_metadata"


def _minari():
    try:
        import minari
    except ImportError:
        raise PomilError("Minari support is an optional extra: pip install 'pomil[minari]' (in a source checkout: "
                         "pip install -e '.[minari]')") from None
    return minari


@contextmanager
def _datasets_path(root: str | Path | None) -> Iterator[None]:
    """Point Minari at ``root`` for the duration (it reads the path from the environment)."""
    if root is None:
        yield
        return
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(root).resolve())
    try:
        yield
    finally:
        os.environ.pop("MINARI_DATASETS_PATH", None)
        if old is not None:
            os.environ["MINARI_DATASETS_PATH"] = old


def export_minari(demos: Demonstrations, dataset_id: str, root: str | Path | None = None, *, author: str = "pomil",
                  description: str | None = None) -> Path:
    """Write ``demos`` as the local Minari dataset ``dataset_id``; returns its folder.

    Refuses to overwrite an existing dataset; a failure part-way removes what
    it wrote, so no half-written dataset is left behind.
    """
    import gymnasium as gym

    minari = _minari()  # first: without the extra, its one-line hint rather than an import error
    from minari.data_collector import EpisodeBuffer
    from minari.dataset.minari_storage import MinariStorage

    md = demos.metadata
    env_id, kwargs = md.get("env_id"), dict(md.get("env_kwargs") or {})
    if not env_id:
        raise PomilError("export: the demonstrations' metadata name no environment (metadata.env_id)")
    _check_id(dataset_id)
    full = demos.states if demos.states is not None and md.get("observation_mask") is not None else demos.observations
    with _datasets_path(root):
        from minari.storage.datasets_root_dir import get_dataset_path

        target = Path(get_dataset_path(dataset_id))
        if (target / "data").exists():
            raise PomilError(f"export: Minari dataset {dataset_id!r} already exists at {target}; choose another id or "
                             "delete it")
        env = gym.make(env_id, **kwargs)
        try:
            limit = env.spec.max_episode_steps
            buffers = []
            for e in range(demos.num_episodes):
                lo, hi = demos.episode_bounds[e], demos.episode_bounds[e + 1]
                obs = np.concatenate([full[lo:hi], full[hi - 1:hi]]).astype(env.observation_space.dtype)
                n = int(hi - lo)
                ended = np.arange(n) == n - 1
                early = limit is None or n < limit
                label = -1 if demos.labels is None else int(demos.labels[e])
                buffers.append(EpisodeBuffer(
                    id=e, observations=obs, actions=demos.actions[lo:hi].astype(env.action_space.dtype),
                    rewards=np.zeros(n), terminations=ended & early, truncations=ended & (not early),
                    infos={LABEL_KEY: np.full(n + 1, label, dtype=np.int64)}))
            try:
                minari.create_dataset_from_buffers(
                    dataset_id, buffers, env=env.spec, eval_env=env.spec, algorithm_name="pomil experts",
                    author=author, author_email="", code_permalink="https://github.com/pomil/pomil",
                    description=description or f"pomil demonstrations: {md.get('source', '')}")
                MinariStorage.read(target / "data").update_metadata({METADATA_KEY: json.dumps(md)})
            except BaseException:
                shutil.rmtree(target, ignore_errors=True)  # nothing half-written stays
                raise
        finally:
            env.close()
    return target


def _check_id(dataset_id: str) -> None:
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        _, _, version = parse_dataset_id(dataset_id)
    except Exception:
        raise PomilError(f"export: {dataset_id!r} is not a Minari dataset id (expected [namespace/]name-vN, e.g. "
                         "pomil/hopper-v0)") from None
    if version is None:
        raise PomilError(f"export: {dataset_id!r} needs a version (expected [namespace/]name-vN, e.g. pomil/hopper-v0)")


def _foreign_metadata(dataset: Any, dataset_id: str, meta: dict[str, Any],
                      observation_mask: str | list[int] | None) -> dict[str, Any]:
    """pomil's metadata for a dataset not written by :func:`export_minari`: its environment (id and keywords,
    with the episode limit) and the observation mask asked for."""
    spec = dataset.spec.env_spec
    if spec is None:
        raise PomilError(f"import: {dataset_id!r} names no environment (env_spec); pomil needs one to train in")
    kwargs = dict(spec.kwargs or {})
    if spec.max_episode_steps is not None:
        kwargs["max_episode_steps"] = spec.max_episode_steps
    from pomil.envs.wrappers import resolve_observation_mask

    try:
        mask = resolve_observation_mask(spec.id, kwargs, observation_mask)
    except ValueError as err:
        raise PomilError(f"import: {err}") from None
    return {"env_id": spec.id, "env_kwargs": kwargs, "observation_mask": mask,
            "source": f"Minari dataset {dataset_id} ({meta.get('algorithm_name')}, {meta.get('author')})"}


def import_minari(dataset_id: str, root: str | Path | None = None,
                  observation_mask: str | list[int] | None = None) -> Demonstrations:
    """Read the local Minari dataset ``dataset_id`` as pomil demonstrations.

    Datasets written by :func:`export_minari` come back exactly (mask,
    labels, metadata).  For others, ``observation_mask`` (a preset name or
    indices) sets what the learner sees; episode labels are read from
    ``infos["pomil_label"]`` when present.
    """
    import gymnasium as gym

    minari = _minari()
    with _datasets_path(root):
        try:
            dataset = minari.load_dataset(dataset_id)
        except (FileNotFoundError, ValueError) as err:
            where = os.environ.get("MINARI_DATASETS_PATH", "~/.minari/datasets")
            raise PomilError(f"import: no local Minari dataset {dataset_id!r} under {where} "
                             f"({str(err).splitlines()[0][:160]})") from None
        meta = dataset.storage.metadata
        obs_space = dataset.observation_space
        if not isinstance(obs_space, gym.spaces.Box) or len(obs_space.shape) != 1 or \
                not isinstance(dataset.action_space, gym.spaces.Box) or len(dataset.action_space.shape) != 1:
            raise PomilError(f"import: {dataset_id!r} has spaces {obs_space} / {dataset.action_space}; "
                             "pomil needs 1-D Box observations and actions")
        obs, act, lengths, labels = [], [], [], []
        for ep in dataset.iterate_episodes():
            obs.append(np.asarray(ep.observations)[:-1])
            act.append(np.asarray(ep.actions))
            lengths.append(len(ep.actions))
            info_label = (ep.infos or {}).get(LABEL_KEY)
            labels.append(int(np.asarray(info_label)[0]) if info_label is not None else -1)
    full = np.concatenate(obs).astype(np.float32)
    stored = meta.get(METADATA_KEY)
    metadata = json.loads(stored) if stored else _foreign_metadata(dataset, dataset_id, meta, observation_mask)
    mask = metadata.get("observation_mask")
    has_labels = all(label >= 0 for label in labels)
    if has_labels and "label_names" not in metadata:
        metadata["label_names"] = [f"label{i}" for i in range(max(labels) + 1)]
    return Demonstrations(
        observations=full if mask is None else full[:, mask], actions=np.concatenate(act).astype(np.float32),
        episode_bounds=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        labels=np.asarray(labels, dtype=np.int64) if has_labels else None,
        states=full if mask is not None else None, metadata=metadata)
