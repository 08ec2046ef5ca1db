import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pomil.data import Demonstrations
from pomil.errors import DataError, PomilError


def test_round_trip_keeps_every_array_and_metadata(demos, tmp_path):
    path = tmp_path / "d.npz"
    demos.save(path)
    back = Demonstrations.load(path)
    for name in ("observations", "actions", "episode_bounds", "labels", "states"):
        np.testing.assert_array_equal(getattr(back, name), getattr(demos, name))
    assert back.metadata == demos.metadata
    assert back.metadata["env_id"] == "pomil/Circles-v0"
    assert set(back.metadata["expert_returns"]) == {"0", "1"}


def test_demos_are_balanced_and_labelled(demos, spec):
    assert demos.num_episodes == 200 and demos.num_steps == 200 * spec.episode_length
    assert np.bincount(demos.labels).tolist() == [100, 100]
    # observations are the positions before each action; first one is the origin
    np.testing.assert_array_equal(demos.observations, demos.states)
    assert np.all(demos.observations[demos.episode_bounds[:-1]] == 0)


def test_padded_view_is_time_major_with_mask():
    d = Demonstrations(
        observations=np.arange(10, dtype=np.float32).reshape(5, 2),
        actions=np.ones((5, 1), np.float32),
        episode_bounds=np.array([0, 3, 5]),
    )
    p = d.padded()
    assert p.observations.shape == (3, 2, 2)
    assert p.mask.tolist() == [[True, True], [True, True], [True, False]]
    assert p.observations[:, 1, 0].tolist() == [6.0, 8.0, 0.0]


def _write(path, **arrays):
    np.savez(path, **arrays)
    return path


def _valid_arrays():
    return {
        "observations": np.zeros((6, 2), np.float32),
        "actions": np.ones((6, 2), np.float32),
        "episode_bounds": np.array([0, 3, 6]),
    }


BAD_CASES = {
    "missing": (None, "(file)", "no such file"),
    "not_npz": ("text", "(file)", "not a zip file"),
    "pickled": ({"observations": np.array([{"a": 1}] * 6, dtype=object)}, "observations", "pickled"),
    "nan": ({"observations": np.full((6, 2), np.nan, np.float32)}, "observations", "NaN"),
    "inf": ({"actions": np.full((6, 2), np.inf, np.float32)}, "actions", "NaN/inf"),
    "length_mismatch": ({"actions": np.ones((5, 2), np.float32)}, "actions", "expected 6 rows"),
    "bounds_mismatch": ({"episode_bounds": np.array([0, 3, 7])}, "episode_bounds", "end at 6"),
    "zero_episodes": ({"observations": np.zeros((0, 2), np.float32), "actions": np.zeros((0, 2), np.float32),
                       "episode_bounds": np.array([0])}, "episode_bounds", "zero"),
    "missing_field": ({"actions": None}, "actions", "missing"),
    "strings": ({"actions": np.array([["a", "b"]] * 6)}, "actions", "real numbers"),
}


def make_bad(case, tmp_path) -> Path:
    change, _, _ = BAD_CASES[case]
    path = tmp_path / f"{case}.npz"
    if change is None:
        return path
    if change == "text":
        path.write_text("observations,actions\n1,2\n")
        return path
    arrays = _valid_arrays()
    for k, v in change.items():
        if v is None:
            del arrays[k]
        else:
            arrays[k] = v
    return _write(path, **arrays)


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_files_raise_a_data_error_naming_file_and_field(case, tmp_path):
    path = make_bad(case, tmp_path)
    _, field, text = BAD_CASES[case]
    with pytest.raises(DataError) as info:
        Demonstrations.load(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and f"field '{field}'" in msg and text in msg
    assert "\n" not in msg


def test_sizes_that_do_not_match_the_environment_are_rejected(demos):
    demos.check_compatible(2, 2)
    with pytest.raises(DataError, match="field 'observations': expected obs_dim 4"):
        demos.check_compatible(4, 2, source="x.npz")
    with pytest.raises(DataError, match="field 'actions': expected act_dim 1"):
        demos.check_compatible(2, 1)


def test_labels_must_match_episode_count():
    with pytest.raises(DataError, match="field 'labels'"):
        Demonstrations(**_valid_arrays(), labels=np.array([0, 1, 0]))


def test_container_is_frozen(demos):
    with pytest.raises(AttributeError):  # dataclasses.FrozenInstanceError
        demos.observations = None


def test_failed_save_leaves_nothing_behind(demos, tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(PomilError, match=r"out.npz: cannot write \(disk full\); nothing was written$"):
        demos.save(tmp_path / "out.npz")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("case", ["missing", "not_npz", "pickled", "nan", "length_mismatch", "zero_episodes"])
def test_cli_reports_bad_demos_in_one_line_and_writes_nothing(case, tmp_path):
    path = make_bad(case, tmp_path)
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "pomil.cli", "train", "bc", "--demos", str(path), "--out", str(out),
         "--iterations", "2"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pomil: error: ") and str(path) in lines[0]
    assert "Traceback" not in proc.stderr
    assert not out.exists()


def test_cli_rejects_demos_whose_sizes_do_not_match_the_env(tmp_path):
    """A history-2 policy cannot be evaluated on position-only demos' env and vice versa."""
    arrays = _valid_arrays()
    arrays["observations"] = np.zeros((6, 3), np.float32)
    path = tmp_path / "odd.npz"
    np.savez(path, **arrays, metadata=np.array(json.dumps({"env_id": "pomil/Circles-v0", "env_kwargs": {}})))
    proc = subprocess.run(
        [sys.executable, "-m", "pomil.cli", "train", "bc", "--demos", str(path), "--out", str(tmp_path / "r"),
         "--iterations", "2"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert "field 'observations': expected obs_dim 2" in proc.stderr and "Traceback" not in proc.stderr


def test_demos_per_mode_draws_a_balanced_subset_with_the_seed(demos_path, capsys):
    from pomil.data import load_training_demos, per_mode

    full = Demonstrations.load(demos_path)
    a = per_mode(full, 3, seed=5, source="d.npz")
    assert np.bincount(a.labels).tolist() == [3, 3] and a.num_episodes == 6
    b = per_mode(full, 3, seed=5, source="d.npz")
    np.testing.assert_array_equal(a.observations, b.observations)  # the same seed, the same episodes
    c = per_mode(full, 3, seed=6, source="d.npz")
    assert not np.array_equal(a.observations, c.observations)
    first = a.episode(0)[0]  # each kept episode is one of the file's, whole
    assert any(np.array_equal(first, full.episode(i)[0]) for i in range(full.num_episodes))
    loaded, _, _ = load_training_demos(str(demos_path), per_mode_episodes=3, seed=5)
    np.testing.assert_array_equal(loaded.observations, a.observations)
    with pytest.raises(DataError, match=r"d.npz: field 'labels': expected at least 101 episodes of every mode for "
                                        r"101 per mode, got \[100, 100\]"):
        per_mode(full, 101, seed=0, source="d.npz")
    unlabelled = Demonstrations(full.observations, full.actions, full.episode_bounds, None, full.states,
                                full.metadata)
    capsys.readouterr()
    u = per_mode(unlabelled, 2, seed=0, source="u.npz")  # the circles' metadata name two modes
    assert u.num_episodes == 4 and "no labels, so the first 4 episodes" in capsys.readouterr().err
    np.testing.assert_array_equal(u.observations, full.subset(range(4)).observations)


def test_demos_per_mode_is_a_training_option_recorded_with_the_run(demos_path, tmp_path):
    from tests.inprocess import pomil

    r = pomil("train", "bc", "--demos", demos_path, "--demos-per-mode", 2, "--iterations", 2, "--out", tmp_path / "r",
              "--no-progress")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "r" / "config.json").read_text())["demos_per_mode"] == 2
    r = pomil("train", "gail", "--demos", demos_path, "--demos-per-mode", 500, "--out", tmp_path / "x",
              "--no-progress")
    assert r.returncode == 2 and "expected at least 500 episodes of every mode" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
