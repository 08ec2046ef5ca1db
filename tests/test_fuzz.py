"""Property-based fuzzing of everything pomil reads from users: demonstrations (.npz),
checkpoints (.pt) and config files (.json), corrupted at random.

The property, for every input: it loads, or it is refused with a one-line PomilError
naming the file; never another exception (a traceback), never a half-written file.
The default suite tries a modest number of cases per category (derandomized, so CI
sees the same ones); ``-m slow`` runs many more, with fresh random cases.
"""

from __future__ import annotations

import collections
import contextlib
import io
import json
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

from pomil.algos.bc import BCConfig, train_bc  # noqa: E402
from pomil.api import TrainedPolicy  # noqa: E402
from pomil.cli import main  # noqa: E402
from pomil.config import from_dict, load_config_file  # noqa: E402
from pomil.data import Demonstrations, load_training_demos  # noqa: E402
from pomil.errors import PomilError  # noqa: E402

QUICK = dict(max_examples=40, deadline=None, derandomize=True, database=None,
             suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
DEEP = dict(max_examples=600, deadline=None, database=None,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
COUNTS: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)


def _one_line(err: PomilError, source: Path) -> None:
    text = str(err)
    assert "\n" not in text and text, text
    assert str(source) in text or source.name in text, text


def _no_tmp_files(folder: Path) -> None:
    assert not [p.name for p in folder.rglob("*.tmp")], list(folder.rglob("*"))


# -------------------------------------------------------------- byte mutations
@st.composite
def corrupted(draw, data: bytes) -> bytes:
    """``data`` truncated, with bytes flipped, or with random bytes spliced in."""
    kind = draw(st.sampled_from(["truncate", "flip", "splice", "garbage"]))
    if kind == "truncate":
        return data[:draw(st.integers(0, len(data) - 1))]
    if kind == "garbage":
        return draw(st.binary(max_size=2000))
    buf = bytearray(data)
    if kind == "flip":
        for _ in range(draw(st.integers(1, 16))):
            i = draw(st.integers(0, len(buf) - 1))
            buf[i] ^= draw(st.integers(1, 255))
        return bytes(buf)
    i = draw(st.integers(0, len(buf)))
    return bytes(buf[:i]) + draw(st.binary(min_size=1, max_size=64)) + bytes(buf[i:])


# --------------------------------------------------------------- demonstrations
@pytest.fixture(scope="module")
def small_demos(tmp_path_factory, demos):
    path = tmp_path_factory.mktemp("fuzz") / "small.npz"
    d = demos
    n = int(d.episode_bounds[6])
    Demonstrations(d.observations[:n], d.actions[:n], d.episode_bounds[:7], d.labels[:6], d.states[:n],
                   d.metadata).save(path)
    return path


def _check_demos_file(path: Path, category: str) -> None:
    try:
        load_training_demos(str(path))
        COUNTS[category]["loaded"] += 1
    except PomilError as err:
        _one_line(err, path)
        COUNTS[category]["refused in one line"] += 1


def _arrays():
    dtypes = st.sampled_from([np.float32, np.float64, np.int64, np.int8, np.bool_, np.complex64, np.uint8])
    return st.one_of(
        hnp.arrays(dtypes, hnp.array_shapes(min_dims=0, max_dims=3, max_side=8),
                   elements=None),
        hnp.arrays(np.float32, st.tuples(st.integers(0, 40), st.integers(0, 4)),
                   elements=st.floats(width=32, allow_nan=True, allow_infinity=True)),
        hnp.arrays(np.int64, st.integers(0, 12), elements=st.integers(-5, 60)),
        st.just(np.array(["text"])),
    )


@st.composite
def demo_archives(draw, base: Path) -> dict[str, np.ndarray]:
    """The valid file's arrays, some dropped or replaced by random arrays, metadata perhaps random."""
    with np.load(base, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    for key in list(arrays):
        action = draw(st.sampled_from(["keep", "keep", "drop", "replace"]))
        if action == "drop":
            del arrays[key]
        elif action == "replace":
            arrays[key] = draw(_arrays())
    if draw(st.booleans()):
        md = draw(st.one_of(st.text(max_size=50), st.dictionaries(st.sampled_from(
            ["env_id", "env_kwargs", "observation_mask", "tasks", "expert_returns"]), _json_values(),
                                                                  max_size=4).map(json.dumps)))
        arrays["metadata"] = np.array(md)
    return arrays


def _demos_bytes_property(small_demos, settings_):
    data = small_demos.read_bytes()

    @settings(**settings_)
    @given(corrupted(data))
    def prop(blob):
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "demos.npz"
            path.write_bytes(blob)
            _check_demos_file(path, "demos: bytes")

    prop()


def _demos_arrays_property(small_demos, settings_):
    @settings(**settings_)
    @given(demo_archives(small_demos))
    def prop(arrays):
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "demos.npz"
            np.savez(path, **arrays)
            _check_demos_file(path, "demos: arrays")
            # a training run on it either starts or leaves nothing behind
            out = Path(d) / "run"
            try:
                train_bc(BCConfig(demos=str(path), out=str(out), iterations=1, hidden_size=4, policy="mlp",
                                  progress=False))
            except PomilError as err:
                _one_line(err, path)
                assert not out.exists()

    prop()


def test_fuzzed_demonstrations_load_or_are_refused_in_one_line(small_demos):
    _demos_bytes_property(small_demos, QUICK)
    _demos_arrays_property(small_demos, {**QUICK, "max_examples": 25})
    print(dict(COUNTS))


@pytest.mark.slow
def test_fuzzed_demonstrations_deep(small_demos):
    _demos_bytes_property(small_demos, DEEP)
    _demos_arrays_property(small_demos, {**DEEP, "max_examples": 300})
    print(dict(COUNTS))


# ------------------------------------------------------------------ checkpoints
@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, demos_path):
    out = tmp_path_factory.mktemp("fuzz") / "run"
    train_bc(BCConfig(demos=str(demos_path), out=str(out), iterations=2, hidden_size=4, policy="gru", progress=False))
    return out


def _leaves(obj, path=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _leaves(v, (*path, i))
    else:
        yield path


def _set(obj, path, value):
    for k in path[:-1]:
        obj = obj[k]
    if value is _DROP:
        del obj[path[-1]]
    else:
        obj[path[-1]] = value


_DROP = object()


@st.composite
def mutated_payloads(draw, payload: dict) -> dict:
    import copy

    payload = copy.deepcopy(payload)
    leaves = list(_leaves(payload))
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(leaves))
        old = payload
        for k in path:
            old = old[k]
        value = draw(st.one_of(
            st.just(_DROP),
            st.none(), st.integers(-3, 3), st.text(max_size=5), st.floats(),
            st.just(torch.full((3,), math.nan)),
            st.builds(lambda s: torch.zeros(s), st.lists(st.integers(0, 3), max_size=3).map(tuple)),
            st.just(old.float() * math.inf) if isinstance(old, torch.Tensor) and old.numel() else st.just([]),
        ))
        with contextlib.suppress(KeyError, IndexError, TypeError):
            _set(payload, path, value)
        leaves = list(_leaves(payload))
        if not leaves:
            break
    return payload


def _check_checkpoint(path: Path, run: Path, demos_path: Path, category: str) -> None:
    try:
        policy = TrainedPolicy.load(path)
        policy.reset(2, seed=0)
        policy.act(np.zeros((2, policy.obs_dim), np.float32))
        COUNTS[category]["loaded"] += 1
    except PomilError as err:
        _one_line(err, path)
        COUNTS[category]["refused in one line"] += 1
    before = path.read_bytes()
    try:  # resuming from it either continues or leaves the checkpoint as it was
        train_bc(BCConfig(demos=str(demos_path), out=str(run), iterations=3, hidden_size=4, policy="gru",
                          progress=False),
                 resume=True)
        COUNTS[category]["resumed"] += 1
    except PomilError as err:
        _one_line(err, path)
        assert path.read_bytes() == before
        COUNTS[category]["resume refused in one line"] += 1
    _no_tmp_files(run)


def _checkpoint_property(run_dir, demos_path, settings_, structured: bool):
    data = (run_dir / "checkpoint.pt").read_bytes()
    payload = torch.load(run_dir / "checkpoint.pt", weights_only=True)

    @settings(**settings_)
    @given(mutated_payloads(payload) if structured else corrupted(data))
    def prop(mutation):
        with tempfile.TemporaryDirectory() as d:
            run = Path(d) / "run"
            shutil.copytree(run_dir, run)
            path = run / "checkpoint.pt"
            if structured:
                torch.save(mutation, path)
            else:
                path.write_bytes(mutation)
            _check_checkpoint(path, run, demos_path, "checkpoints: " + ("payload" if structured else "bytes"))

    prop()


def test_fuzzed_checkpoints_load_or_are_refused_in_one_line(run_dir, demos_path):
    _checkpoint_property(run_dir, demos_path, {**QUICK, "max_examples": 25}, structured=False)
    _checkpoint_property(run_dir, demos_path, {**QUICK, "max_examples": 25}, structured=True)
    print(dict(COUNTS))


@pytest.mark.slow
def test_fuzzed_checkpoints_deep(run_dir, demos_path):
    _checkpoint_property(run_dir, demos_path, {**DEEP, "max_examples": 300}, structured=False)
    _checkpoint_property(run_dir, demos_path, {**DEEP, "max_examples": 300}, structured=True)
    print(dict(COUNTS))


# ------------------------------------------------------------------ config files
def _json_values():
    scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.floats(), st.text(max_size=8),
                        st.sampled_from([0, 1, -1, 2.5, 1e400, "nan", "inf", "-1", "cpu", "tpu", "gru", ""]))
    return st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                         st.dictionaries(st.text(max_size=5), inner, max_size=3)),
                        max_leaves=5)


@st.composite
def config_texts(draw) -> str | bytes:
    names = [*BCConfig.__dataclass_fields__, "nope", "learning-rate", "hidden-size", "batch-episodes"]
    kind = draw(st.sampled_from(["object", "object", "object", "json", "bytes"]))
    if kind == "bytes":
        return draw(st.binary(max_size=200))
    if kind == "json":
        return json.dumps(draw(_json_values()))
    obj = draw(st.dictionaries(st.sampled_from(names), _json_values(), max_size=5))
    return json.dumps(obj)  # NaN and Infinity are written as JSON's non-standard NaN / Infinity


def _config_property(settings_):
    @settings(**settings_)
    @given(config_texts())
    def prop(text):
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "c.json"
            path.write_bytes(text if isinstance(text, bytes) else text.encode())
            try:
                from_dict(BCConfig, load_config_file(path), str(path))
                COUNTS["configs"]["accepted"] += 1
            except PomilError as err:
                _one_line(err, path) if "config key" not in str(err) else None
                assert "\n" not in str(err)
                COUNTS["configs"]["refused in one line"] += 1
            err = io.StringIO()
            with contextlib.redirect_stderr(err):
                code = main(["train", "bc", "--config", str(path), "--demos", str(Path(d) / "missing.npz"),
                             "--out", str(Path(d) / "run"), "--no-progress"])
            assert code == 2 and err.getvalue().count("\n") == 1 and "Traceback" not in err.getvalue(), err.getvalue()
            assert sorted(p.name for p in Path(d).iterdir()) == ["c.json"]  # nothing written

    prop()


def test_fuzzed_config_files_build_or_are_refused_in_one_line():
    _config_property({**QUICK, "max_examples": 60})
    print(dict(COUNTS))


@pytest.mark.slow
def test_fuzzed_config_files_deep():
    _config_property({**DEEP, "max_examples": 1500})
    print(dict(COUNTS))
