import numpy as np
import pytest
import torch

from pomil.api import TrainedPolicy
from pomil.errors import PomilError
from pomil.nn.policy import GaussianPolicy, PolicyArch


def _policy(num_codes=0, encoder="gru"):
    torch.manual_seed(0)
    return TrainedPolicy(GaussianPolicy(PolicyArch(2, 2, encoder, 16, num_codes)), "test",
                         {"id": "pomil/Circles-v0", "kwargs": {}})


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
    from pomil import Demonstrations as D
    from pomil import TrainedPolicy as T

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


@pytest.mark.parametrize("num_envs", [0, -1, 2.5, "3", True, None])
def test_reset_refuses_a_bad_num_envs_naming_it(num_envs):
    from pomil.errors import InvalidArgument

    with pytest.raises(InvalidArgument, match=f"num_envs must be a positive integer, got {num_envs!r}"):
        _policy().reset(num_envs)


@pytest.mark.parametrize("codes", [[0.5, 1.7], [0.0, 1.0], ["0", "1"], "01", [True, False], [[0, 1], [1]], [0, 1, 1]])
def test_reset_refuses_codes_that_are_not_integers_in_range(codes):
    p = _policy(num_codes=2)
    with pytest.raises(ValueError, match=r"codes must be 2 integers in \[0, 2\)"):
        p.reset(2, codes=codes)
    p.reset(2, codes=np.array([1, 0], dtype=np.int32))  # any integer dtype, and tensors, are fine
    p.reset(2, codes=torch.tensor([1, 1]))


def test_a_bad_device_is_named_as_a_device(tmp_path):
    _policy().save(tmp_path / "p.pt")
    with pytest.raises(PomilError, match=r"^device 'tpu': expected cpu, cuda, cuda:N, mps or auto$"):
        TrainedPolicy.load(tmp_path / "p.pt", device="tpu")


def test_nan_observations_are_refused_before_they_touch_the_recurrent_state():
    p = _policy()
    p.reset(2, seed=0)
    obs = np.zeros((2, 2), np.float32)
    first = p.act(obs, deterministic=True)
    h = p._h.clone()
    bad = obs.copy()
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match=r"observations must be finite; rows \[1\] hold NaN/inf"):
        p.act(bad)
    with pytest.raises(ValueError, match="observations must be finite"):
        p.act(torch.full((2, 2), float("inf")))
    with pytest.raises(ValueError, match=r"observations must be a \(2, 2\) array of numbers"):
        p.act([["a", "b"], ["c", "d"]])
    assert torch.equal(p._h, h)  # the state is as before the refused call
    q = _policy()
    q.reset(2, seed=0)
    q.act(obs, deterministic=True)
    np.testing.assert_array_equal(p.act(obs, deterministic=True), q.act(obs, deterministic=True))
    assert np.isfinite(first).all()


def test_nan_observations_are_refused_under_python_O(tmp_path):
    """No assert statements: the checks hold with optimisations on."""
    import os
    import subprocess
    import sys

    code = ("import numpy as np, torch; from pomil.api import TrainedPolicy; from pomil.nn.policy import "
            "GaussianPolicy, "
            "PolicyArch\np = TrainedPolicy(GaussianPolicy(PolicyArch(2, 2, 'gru', 8, 2)), 't', {'id': "
            "'pomil/Circles-v0'})\n"
            "p.reset(2, seed=0)\ntry:\n    p.act(np.array([[0, 0], [np.nan, 0]], np.float32))\nexcept ValueError as "
            "e:\n"
            "    print('refused:', e)\ntry:\n    p.reset(0)\nexcept ValueError as e:\n    print('refused:', e)\n")
    src = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "src")
    r = subprocess.run([sys.executable, "-O", "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": src})
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["refused: observations must be finite; rows [1] hold NaN/inf (state unchanged)",
                                     "refused: num_envs must be a positive integer, got 0"]


def _continuous_policy(dim=2, prior="uniform"):
    torch.manual_seed(0)
    arch = PolicyArch(2, 2, "gru", 16, dim, code_kind="continuous", code_prior=prior)
    return TrainedPolicy(GaussianPolicy(arch), "test", {"id": "pomil/Circles-v0", "kwargs": {}})


def test_continuous_codes_are_float_arrays_that_select_behaviour():
    p = _continuous_policy()
    assert (p.num_codes, p.code_dim, p.code_prior) == (0, 2, "uniform")
    obs = np.zeros((3, 2), np.float32)
    p.reset(3, codes=np.array([[-1.0, 0.0], [0.0, 0.0], [1.0, 0.5]], np.float32))
    a = p.act(obs, deterministic=True)
    assert not np.allclose(a[0], a[2])
    p.reset(3, codes=torch.tensor([[-1.0, 0.0], [0.0, 0.0], [1.0, 0.5]]))
    np.testing.assert_allclose(p.act(obs, deterministic=True), a, atol=1e-6)
    p.reset(2, codes=[[0, 1], [1, 0]])  # integers are numbers too
    p.reset(4)  # default: the prior's quantiles, low to high, in every dimension
    assert p._codes[:, 0].tolist() == [-0.75, -0.25, 0.25, 0.75] and torch.equal(p._codes[:, 0], p._codes[:, 1])


@pytest.mark.parametrize("codes, text", [
    ([0, 1, 0], r"codes must be a \(3, 2\) array of finite numbers \(this policy has a continuous code\), got shape"),
    ([[0.0], [1.0], [2.0]], r"got shape \(3, 1\)"),
    ([[0.0, np.nan], [1.0, 0], [2.0, 0]], "got NaN/inf"),
    ([["a", "b"]] * 3, "got dtype"),
    ([[True, False]] * 3, "got dtype bool"),
])
def test_continuous_codes_of_the_wrong_kind_or_shape_are_errors(codes, text):
    p = _continuous_policy()
    with pytest.raises(PomilError, match=text):
        p.reset(3, codes=codes)


def test_discrete_policy_refuses_continuous_codes_by_name():
    p = _policy(num_codes=2)
    assert p.code_dim == 0 and p.code_prior is None
    with pytest.raises(PomilError, match=r"this policy has 2 discrete codes\), got an array of shape \(2, 1\)"):
        p.reset(2, codes=[[0.5], [0.1]])


def test_continuous_policy_saves_and_loads_its_code_kind_and_old_archs_load_as_discrete(tmp_path):
    p = _continuous_policy(1, "gaussian")
    p.save(tmp_path / "c.pt")
    q = TrainedPolicy.load(tmp_path / "c.pt")
    assert (q.code_dim, q.code_prior, q.num_codes) == (1, "gaussian", 0)
    d = PolicyArch(2, 2, "gru", 16, 3).to_dict()
    assert "code_kind" not in d and "code_prior" not in d  # discrete checkpoints as before continuous codes
    assert PolicyArch(**d).code_kind == "discrete"
