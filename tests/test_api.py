import numpy as np
import pytest
import torch

from pomil.api import TrainedPolicy
from pomil.errors import PomilError
from pomil.nn.policy import GaussianPolicy, PolicyArch


def _policy(num_codes=0, encoder="gru"):
    torch.manual_seed(0)
    return TrainedPolicy(GaussianPolicy(PolicyArch(2, 2, encoder, 16, num_codes)), "test", {"id": "pomil/Circles-v0", "kwargs": {}})


def test_act_numpy_in_numpy_out_and_seeded_sampling_repeats():
    p = _policy()
    obs = np.zeros((3, 2), np.float32)
    p.reset(3, seed=1)
    a1 = [p.act(obs) for _ in range(4)]
    p.reset(3, seed=1)
    a2 = [p.act(obs) for _ in range(4)]
    assert isinstance(a1[0], np.ndarray) and a1[0].shape == (3, 2)
    np.testing.assert_array_equal(np.stack(a1), np.stack(a2))
    assert isinstance(p.act(torch.zeros(3, 2)), torch.Tensor)


def test_deterministic_actions_are_the_mean_and_depend_on_history():
    p = _policy()
    p.reset(1)
    obs = np.zeros((1, 2), np.float32)
    first = p.act(obs, deterministic=True)
    second = p.act(obs, deterministic=True)
    assert not np.allclose(first, second)  # the GRU state moved on
    p.reset(1)
    np.testing.assert_array_equal(p.act(obs, deterministic=True), first)


def test_codes_select_behaviour_and_are_checked():
    p = _policy(num_codes=2)
    p.reset(2, codes=[0, 1])
    a = p.act(np.zeros((2, 2), np.float32), deterministic=True)
    assert not np.allclose(a[0], a[1])
    with pytest.raises(PomilError, match="codes must be"):
        p.reset(2, codes=[0, 2])


def test_act_before_reset_and_bad_shapes_are_errors():
    p = _policy()
    with pytest.raises(RuntimeError, match="reset"):
        p.act(np.zeros((1, 2)))
    p.reset(2)
    with pytest.raises(ValueError, match=r"shape \(2, 2\)"):
        p.act(np.zeros((3, 2)))


def test_loading_a_foreign_file_is_a_one_line_error(tmp_path):
    bad = tmp_path / "x.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(PomilError, match="not a pomil checkpoint"):
        TrainedPolicy.load(bad)
    with pytest.raises(PomilError, match="no such checkpoint"):
        TrainedPolicy.load(tmp_path / "missing.pt")


def test_public_names_import_from_the_package():
    from pomil import Demonstrations as D, TrainedPolicy as T

    assert T is TrainedPolicy and D.__name__ == "Demonstrations"


def test_previous_action_is_fed_back_as_the_environment_executed_it():
    from pomil.envs.circles import executed_actions
    from pomil.nn.policy import shift_actions

    p = _policy()
    p.reset(2)
    obs = np.random.default_rng(0).normal(size=(4, 2, 2)).astype(np.float32)
    acts = torch.as_tensor(np.stack([p.act(o, deterministic=True) for o in obs]))
    starts = torch.zeros(4, 2, dtype=torch.bool)
    starts[0] = True
    with torch.no_grad():
        dist, _ = p.policy.unroll(torch.as_tensor(obs), shift_actions(executed_actions(acts, "vector")),
                                  p.policy.initial_state(2), starts)
        raw, _ = p.policy.unroll(torch.as_tensor(obs), shift_actions(acts), p.policy.initial_state(2), starts)
    torch.testing.assert_close(dist.mean, acts)
    assert not torch.allclose(raw.mean, acts)


def test_saved_policy_loads_and_acts_the_same(tmp_path):
    p = _policy(num_codes=2)
    p.save(tmp_path / "p.pt")
    q = TrainedPolicy.load(tmp_path / "p.pt")
    assert q.algo == "test" and q.num_codes == 2 and q.env == p.env
    obs = np.random.default_rng(0).normal(size=(3, 4, 2)).astype(np.float32)
    for pol in (p, q):
        pol.reset(4, codes=[0, 1, 1, 0], seed=3)
    for o in obs:
        np.testing.assert_array_equal(p.act(o), q.act(o))
