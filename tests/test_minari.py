"""Minari import/export on datasets built here (nothing is downloaded)."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("minari")
pytest.importorskip("h5py")

from pomil.data import Demonstrations  # noqa: E402
from pomil.errors import PomilError  # noqa: E402
from pomil.minari_io import export_minari, import_minari  # noqa: E402
from tests.inprocess import pomil  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _subset(demos, n):
    b = demos.episode_bounds[n]
    return Demonstrations(demos.observations[:b], demos.actions[:b], demos.episode_bounds[:n + 1], demos.labels[:n],
                          demos.states[:b], demos.metadata)


def test_pomil_demos_round_trip_through_minari_exactly(tmp_path, monkeypatch):
    demos = _subset(Demonstrations.load(ROOT / "data" / "hopper-paper.npz"), 12)
    path = export_minari(demos, "pomil/hopper-test-v0", root=tmp_path)
    assert (path / "data").is_dir()
    import minari

    with monkeypatch.context() as m:
        m.setenv("MINARI_DATASETS_PATH", str(tmp_path))
        ds = minari.load_dataset("pomil/hopper-test-v0")  # a regular Minari dataset
        assert ds.total_episodes == 12 and ds.spec.env_spec.id == "Hopper-v5"
        ep = next(ds.iterate_episodes())
        assert ep.observations.shape == (129, 11) and ep.actions.shape == (128, 3) and bool(ep.truncations[-1])
    back = import_minari("pomil/hopper-test-v0", root=tmp_path)
    for name in ("observations", "actions", "episode_bounds", "labels", "states"):
        np.testing.assert_array_equal(getattr(back, name), getattr(demos, name), err_msg=name)
    assert back.metadata == demos.metadata
    with pytest.raises(PomilError, match="already exists"):
        export_minari(demos, "pomil/hopper-test-v0", root=tmp_path)
    for bad in ("pomil/hopper-test", "pomil/hopper test-v0"):
        with pytest.raises(PomilError, match="Minari dataset id|needs a version"):
            export_minari(demos, bad, root=tmp_path)


def test_import_a_dataset_recorded_with_minaris_own_collector(tmp_path, monkeypatch):
    """A dataset pomil did not write (Minari's own writer): env from its spec, learner's view from the mask,
    full obs kept as states."""
    import minari
    from minari.data_collector import EpisodeBuffer

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    env = gym.make("HalfCheetah-v5", max_episode_steps=10)
    episodes = []
    for seed in range(3):  # random actions, recorded the way Minari stores them (T + 1 observations)
        obs, _ = env.reset(seed=seed)
        ep = {"observations": [obs], "actions": [], "rewards": [], "terminations": [], "truncations": []}
        done = False
        while not done:
            act = env.action_space.sample()
            obs, rew, term, trunc, _ = env.step(act)
            for key, value in zip(("observations", "actions", "rewards", "terminations", "truncations"),
                                  (obs, act, rew, term, trunc), strict=True):
                ep[key].append(value)
            done = term or trunc
        episodes.append(EpisodeBuffer(id=seed, **{k: np.asarray(v) for k, v in ep.items()}))
    minari.create_dataset_from_buffers("test/cheetah-random-v0", episodes, env=env.spec, eval_env=env.spec,
                                       algorithm_name="random", author="test", author_email="t@t",
                                       code_permalink="none")
    monkeypatch.delenv("MINARI_DATASETS_PATH")
    demos = import_minari("test/cheetah-random-v0", root=tmp_path, observation_mask="positions-only")
    assert demos.num_episodes == 3 and demos.episode_lengths.tolist() == [10, 10, 10]
    assert demos.metadata["env_id"] == "HalfCheetah-v5" and demos.metadata["env_kwargs"]["max_episode_steps"] == 10
    assert demos.metadata["observation_mask"] == list(range(8)) and demos.labels is None
    np.testing.assert_array_equal(demos.observations, demos.states[:, :8])
    # the learner trains on it: CLI import, then a tiny InfoGAIL-POMDP run on HalfCheetah
    out = tmp_path / "c.npz"
    r = pomil("demos", "import-minari", "test/cheetah-random-v0", "--out", out, "--minari-root", tmp_path,
              "--observation-mask", "positions-only")
    assert r.returncode == 0 and "3 episodes of HalfCheetah-v5" in r.stdout, r.stderr
    r = pomil("train", "infogail-pomdp", "--demos", out, "--iterations", 1, "--num-envs", 2, "--minibatches", 2,
              "--warm-start-iterations", 1, "--posterior-init-iterations", 1, "--out", tmp_path / "run",
              "--no-progress")
    assert r.returncode == 0, r.stderr
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["num_codes"] == -1


def test_cli_minari_errors_are_one_line(tmp_path):
    r = pomil("demos", "import-minari", "nope/none-v0", "--out", tmp_path / "x.npz", "--minari-root", tmp_path)
    assert r.returncode == 2, r.stderr
    assert "no local Minari dataset 'nope/none-v0'" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "x.npz").exists()
