"""The environment registry: each family declared once, and no environment id outside envs/."""

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pomil.envs import (
    FAMILIES,
    default_num_codes,
    ends_on_failure,
    env_dims,
    env_family,
    evaluation_kind,
    executed_actions_fn,
    make_vec_env,
    state_dim,
)
from pomil.envs.batch import GymSim
from pomil.envs.circles import ENV_ID as CIRCLES_ID
from pomil.envs.circles import CirclesVecEnv
from pomil.envs.locomotion import HOPPER_ID, HopperSim
from pomil.envs.vec import BatchedEnv, BatchedSim

SRC = Path(__file__).resolve().parents[2] / "src" / "pomil"


@pytest.mark.parametrize("env_id, family, sim, dims, states", [
    (CIRCLES_ID, "circles", None, (2, 2), 2),
    (HOPPER_ID, "hopper", HopperSim, (11, 3), 11),
    ("Pendulum-v1", "gymnasium", GymSim, (3, 1), 3),
])
def test_each_id_is_run_by_its_family(env_id, family, sim, dims, states):
    assert env_family(env_id).name == family
    kwargs = {"circles": [[0.0, 5.0, 5.0, 1], [0.0, -5.0, 5.0, -1]]} if family == "circles" else {}
    env = make_vec_env(env_id, kwargs, 2)
    try:
        assert isinstance(env, CirclesVecEnv) if sim is None else isinstance(env.sim, sim)
        assert isinstance(env, BatchedEnv) and (sim is None or isinstance(env.sim, BatchedSim))
        assert (env.obs_dim, env.act_dim) == dims
    finally:
        if sim is not None:
            env.close()
    assert env_dims(env_id, kwargs) == dims
    assert state_dim(env_id, kwargs) == states


def test_families_declare_evaluation_actions_and_codes():
    assert [f.name for f in FAMILIES] == ["circles", "hopper", "gymnasium"]
    assert evaluation_kind(CIRCLES_ID, {}) == "circles"
    assert evaluation_kind(HOPPER_ID, {"tasks": {}}) == "tasks"
    assert evaluation_kind("Pendulum-v1", {}) is None  # no tasks named: nothing to score against
    assert default_num_codes({"env_id": CIRCLES_ID, "env_kwargs": {"circles": [[0, 1, 1, 1]] * 3}}) == 3
    assert default_num_codes({"env_id": HOPPER_ID, "env_kwargs": {}}) is None
    clamp = executed_actions_fn(HOPPER_ID, {})
    assert clamp(torch.tensor([[2.0, -3.0, 0.5]])).tolist() == [[1.0, -1.0, 0.5]]
    assert executed_actions_fn("Pendulum-v1", {})(torch.tensor([[5.0]])).tolist() == [[5.0]]  # not MuJoCo: as given


def test_families_say_whether_episodes_end_on_failure():
    from pomil.envs.locomotion import HOPPER_SPEED_ID, SETTINGS

    assert not ends_on_failure(CIRCLES_ID, {})
    assert ends_on_failure(HOPPER_ID, {})  # gymnasium's default: terminate_when_unhealthy
    assert ends_on_failure(HOPPER_ID, SETTINGS["standard"]) and not ends_on_failure(HOPPER_ID, SETTINGS["paper"])
    assert ends_on_failure(HOPPER_SPEED_ID, {}) and not ends_on_failure(HOPPER_SPEED_ID, SETTINGS["paper"])
    assert ends_on_failure("Walker2d-v5", {}) and not ends_on_failure("HalfCheetah-v5", {})  # no such keyword
    assert not ends_on_failure("Pendulum-v1", {})


def test_no_environment_id_appears_outside_envs():
    ids = re.compile(r"Circles-v\d|Hopper-v\d")
    found = [f"{p.relative_to(SRC)}:{n}" for p in SRC.rglob("*.py") if p.parent.name != "envs"
             for n, line in enumerate(p.read_text().splitlines(), 1) if ids.search(line)]
    assert found == []


def test_sim_warp_without_the_gpu_extra_is_a_one_line_error(monkeypatch):
    import sys

    from pomil.errors import PomilError

    monkeypatch.setitem(sys.modules, "mujoco_warp", None)  # as if the gpu extra were not installed
    with pytest.raises(PomilError, match=r"^--sim warp needs MuJoCo Warp.*pip install 'pomil\[gpu\]'") as err:
        make_vec_env(HOPPER_ID, {}, 2, sim="warp")
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="--sim warp runs .* not 'Pendulum-v1'"):
        make_vec_env("Pendulum-v1", {}, 2, sim="warp")
    with pytest.raises(ValueError, match="unknown sim 'gpu'"):
        make_vec_env(HOPPER_ID, {}, 2, sim="gpu")


def test_a_mujoco_warning_is_shown_once_per_process_not_once_per_copy():
    # gymnasium's HalfCheetah XML warns (deprecated settotalmass) at every model load: 1,136 lines in one
    # 3-seed reproduction before.  A fresh process: the hook is process-wide, as MuJoCo's own printing is.
    def warnings(code: str) -> list[str]:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        return [line for line in r.stderr.splitlines() if "settotalmass" in line]

    raw = warnings("import gymnasium as gym\n[gym.make('HalfCheetah-v5') for _ in range(3)]\n")
    if not raw:
        pytest.skip("this gymnasium's HalfCheetah model no longer warns")
    assert len(raw) == 3  # MuJoCo's own: one per load
    lines = warnings("from pomil.envs.batch import GymSim\nGymSim('HalfCheetah-v5', 3); GymSim('HalfCheetah-v5', 2)\n")
    assert len(lines) == 1 and lines[0].startswith("WARNING (MuJoCo; repeats of it are not shown):"), lines


@pytest.mark.parametrize("env_id", [HOPPER_ID, "Pendulum-v1"])
def test_an_envs_state_dict_carries_its_generators_into_a_new_env(env_id):
    """What a checkpoint keeps of a batched env: a new env loaded with it starts its next episodes from the
    states the original would have drawn, and a seed not yet taken is still taken."""
    fresh = make_vec_env(env_id, {}, 3, seed=7)
    pending = fresh.state_dict()
    assert pending["seed"] == 7
    original = make_vec_env(env_id, {}, 3, seed=7)
    original.reset()
    original.step(torch.zeros(3, original.act_dim))
    state = original.state_dict()
    assert state["seed"] is None and len(state["generators"]) == 3 and all(isinstance(g, str) for g in
                                                                          state["generators"])
    copy = make_vec_env(env_id, {}, 3, seed=123)
    copy.load_state_dict(state)
    expected = original.reset()
    assert torch.equal(copy.reset(), expected)
    assert not torch.equal(original.reset(), expected)  # the generators moved on
    other = make_vec_env(env_id, {}, 3, seed=123)
    other.load_state_dict(pending)
    assert torch.equal(other.reset(), fresh.reset())
    with pytest.raises(ValueError, match="not 3 texts"):
        other.load_state_dict({"seed": None, "generators": state["generators"][:2]})
    with pytest.raises(ValueError, match="not an integer"):
        other.load_state_dict({"seed": 1.5, "generators": state["generators"]})
    for env in (fresh, original, copy, other):
        env.close()


def test_the_circles_env_keeps_no_state():
    env = make_vec_env(CIRCLES_ID, {}, 2)
    assert env.state_dict() == {}
    env.load_state_dict({})
    with pytest.raises(ValueError, match="keeps no state"):
        env.load_state_dict({"seed": 1})
