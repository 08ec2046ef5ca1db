"""MuJoCo Warp physics (``pomil.envs.warp``) agrees with gymnasium and HopperSim step by step.

These tests run on Warp's **CPU device** when ``mujoco_warp`` is importable (the
optional ``gpu`` extra: ``pip install 'pomil[gpu]'``) and skip otherwise; the
project's CI venv does not install that extra, so there they skip.  A GPU run of
``benchmarks/warp_speed.py`` (which checks agreement before it times) is the check
of the CUDA path.  Warp compiles its kernels on first use: the first run takes a few
minutes on a CPU, later runs read them from Warp's kernel cache (~/.cache/warp).

Tolerances.  MuJoCo Warp computes in float32, MuJoCo (gymnasium, HopperSim) in
float64 (float32 resolves 1.2e-7 relative).  From the same state (qpos, qvel copied
from gymnasium), one env step differs in the observation by at most (measured on
Warp's CPU device, 4 envs x 100 random-action states each) 3.8e-6 on Hopper (4 RK4
steps of 2 ms), 6.2e-5 on Walker2d (4 RK4 steps) and 4.7e-4 on HalfCheetah (5 Euler
steps of 10 ms with stiff joint limits; its velocities reach 23, unclipped: 1e-4
relative); in the reward by at most 6e-6.  ``ONE_STEP_OBS_ATOL`` allows about ten times
each, ``ONE_STEP_REWARD_ATOL`` twenty.  Along a trajectory the difference grows as
contacts amplify it (chaos: MuJoCo against itself from a start rounded to float32 parts
as fast, see ``benchmarks/warp_speed.py``); in these tests Hopper keeps within 1.7e-5
over the paper's 128 steps, Walker2d within 7.2e-5 and HalfCheetah within 3.1e-4 over
their first 20 steps; ``TRAJECTORY_ATOL`` allows 1e-3, 1e-3 and 5e-3.
Terminations and truncations must agree exactly (with these seeds no health test
sits within float32 rounding of its threshold; on other hardware one could).
"""

import os

import gymnasium as gym
import numpy as np
import pytest
import torch

from pomil.envs import make_vec_env
from pomil.envs.locomotion import HOPPER_ID, HopperSim, hopper_kwargs, locomotion_kwargs
from pomil.envs.warp import SPECS, WarpSim, warp_available

pytestmark = pytest.mark.skipif(not warp_available(), reason="mujoco_warp is not installed (the optional 'gpu' "
                                                              "extra: pip install 'pomil[gpu]'); the CI venv does not "
                                                              "install it")

ONE_STEP_OBS_ATOL = {HOPPER_ID: 5e-5, "Walker2d-v5": 5e-4, "HalfCheetah-v5": 5e-3}
ONE_STEP_REWARD_ATOL = 1e-4
TRAJECTORY_ATOL = {HOPPER_ID: 1e-3, "Walker2d-v5": 1e-3, "HalfCheetah-v5": 5e-3}
DEVICE = os.environ.get("POMIL_WARP_DEVICE", "cpu")
"""Warp's device for these tests: ``cpu`` by default, ``cuda`` on a GPU machine (``POMIL_WARP_DEVICE=cuda pytest
tests/envs/test_warp.py``, as ``benchmarks/warp_cuda.sh`` runs them)."""


def _gym_envs(env_id, n, kwargs, seed):
    envs = [gym.make(env_id, **kwargs) for _ in range(n)]
    obs = np.stack([e.reset(seed=seed + i)[0] for i, e in enumerate(envs)])
    return envs, obs


def _run_against_gymnasium(env_id, kwargs, steps, n=4, seed=7, action_scale=0.5):
    """Step WarpSim and n gymnasium envs with the same actions from the same seeds.

    Returns (max |obs diff| per step, max |reward diff|, {env: (end step, kind)}, number of ends compared)."""
    rng = np.random.default_rng(0)
    sim = WarpSim(env_id, n, kwargs, DEVICE)
    envs, obs_gym = _gym_envs(env_id, n, kwargs, seed)
    obs = sim.reset(seed)
    assert obs.dtype == torch.float32 and obs.shape == (n, sim.obs_dim)
    np.testing.assert_allclose(obs.cpu().numpy(), obs_gym, atol=1e-6)  # the reset noise, rounded to float32
    done = np.zeros(n, dtype=bool)
    obs_err, rew_err, ends = [], 0.0, {}
    for t in range(steps):
        act = rng.uniform(-action_scale, action_scale, (n, sim.act_dim))
        obs, rew, term, trunc = sim.step(torch.as_tensor(act))
        err = 0.0
        for i, e in enumerate(envs):
            if done[i]:  # ended copies stay put and pay nothing
                assert rew[i] == 0.0 and not term[i] and not trunc[i]
                continue
            o, r, te, tr, _ = e.step(act[i])
            err = max(err, float(np.abs(obs[i].cpu().numpy() - o).max()))
            rew_err = max(rew_err, abs(float(rew[i]) - r))
            assert (bool(term[i]), bool(trunc[i])) == (te, tr), f"env {i} step {t + 1}"
            if te or tr:
                done[i] = True
                ends[i] = (t + 1, "terminated" if te else "truncated")
        obs_err.append(err)
        np.testing.assert_array_equal(sim.done.cpu().numpy(), done)
        if done.all():
            break
    return np.array(obs_err), rew_err, ends


def test_hopper_paper_setting_follows_gymnasium_for_128_steps_and_truncates():
    obs_err, rew_err, ends = _run_against_gymnasium(HOPPER_ID, hopper_kwargs("forward", "paper"), 200)
    assert ends == {i: (128, "truncated") for i in range(4)}
    assert obs_err.max() < TRAJECTORY_ATOL[HOPPER_ID] and rew_err < TRAJECTORY_ATOL[HOPPER_ID], (obs_err.max(), rew_err)


@pytest.mark.parametrize("env_id", ["Walker2d-v5", "HalfCheetah-v5"])
def test_walker_and_cheetah_follow_gymnasium_for_20_steps(env_id):
    kwargs = {**locomotion_kwargs(env_id, "backward", "paper"), "max_episode_steps": 20}
    obs_err, rew_err, ends = _run_against_gymnasium(env_id, kwargs, 20)
    assert ends == {i: (20, "truncated") for i in range(4)}
    assert obs_err.max() < TRAJECTORY_ATOL[env_id] and rew_err < TRAJECTORY_ATOL[env_id], (obs_err.max(), rew_err)


def test_standard_setting_terminates_and_resets_like_hopper_sim():
    """Random actions (beyond the control range: clamped by the physics) make every hopper fall
    within about 60 steps: each copy must terminate in the step HopperSim's does (HopperSim equals
    gymnasium exactly, test_locomotion.py), stay put with reward 0 until the reset, and the next
    unseeded reset must continue each copy's generator as HopperSim's does; two episodes."""
    kwargs = hopper_kwargs("forward", "standard")
    n = 6
    warp, cpu = WarpSim(HOPPER_ID, n, kwargs, DEVICE), HopperSim(n, kwargs, threads=1)
    np.testing.assert_allclose(warp.reset(3).cpu().numpy(), cpu.reset(3), atol=1e-6)
    rng = np.random.default_rng(1)
    terminations = 0
    for _ in range(2):
        while not cpu.done.all():
            act = rng.uniform(-1.5, 1.5, (n, 3))
            o_w, r_w, te_w, tr_w = warp.step(torch.as_tensor(act))
            o_c, r_c, te_c, tr_c = cpu.step(act)
            np.testing.assert_allclose(o_w.cpu().numpy(), o_c, atol=TRAJECTORY_ATOL[HOPPER_ID])
            np.testing.assert_allclose(r_w.cpu().numpy(), r_c, atol=TRAJECTORY_ATOL[HOPPER_ID])
            np.testing.assert_array_equal(te_w.cpu().numpy(), te_c)
            np.testing.assert_array_equal(tr_w.cpu().numpy(), tr_c)
            terminations += int(te_c.sum())
        assert warp.done.all()
        with pytest.raises(RuntimeError, match="reset"):
            warp.step(torch.zeros(n, 3, device=warp.device))
        np.testing.assert_allclose(warp.reset().cpu().numpy(), cpu.reset(), atol=1e-6)
    assert terminations == 2 * n


@pytest.mark.parametrize("env_id", sorted(SPECS))
def test_one_step_from_the_same_state_agrees_within_float32(env_id):
    """Put WarpSim in each state of gymnasium trajectories (qpos, qvel copied), step both with
    the same action and compare: the float32 error of one env step, without accumulation."""
    n, steps = 4, 25
    kwargs = locomotion_kwargs(env_id, "forward", "paper")
    envs, _ = _gym_envs(env_id, n, kwargs, 11)
    sim = WarpSim(env_id, n, kwargs, DEVICE)
    sim.reset(11)
    rng = np.random.default_rng(2)
    obs_err = rew_err = 0.0
    for _ in range(steps):
        qpos = np.stack([e.unwrapped.data.qpos for e in envs])
        qvel = np.stack([e.unwrapped.data.qvel for e in envs])
        sim.set_state(torch.as_tensor(qpos), torch.as_tensor(qvel))
        act = rng.uniform(-1.0, 1.0, (n, sim.act_dim))
        obs, rew, _, _ = sim.step(torch.as_tensor(act))
        ref = [e.step(a) for e, a in zip(envs, act, strict=True)]
        obs_err = max(obs_err, float(np.abs(obs.cpu().numpy() - np.stack([r[0] for r in ref])).max()))
        rew_err = max(rew_err, float(np.abs(rew.cpu().numpy() - np.array([r[1] for r in ref])).max()))
    assert obs_err < ONE_STEP_OBS_ATOL[env_id] and rew_err < ONE_STEP_REWARD_ATOL, (obs_err, rew_err)


def test_masked_observations_through_the_registry_match_the_cpu_path():
    kwargs = hopper_kwargs("backward", "paper")
    mask = [0, 1, 2, 3, 4]  # positions-only
    warp = make_vec_env(HOPPER_ID, kwargs, 3, device=DEVICE, observation_mask=mask, seed=5, sim="warp")
    cpu = make_vec_env(HOPPER_ID, kwargs, 3, observation_mask=mask, seed=5)
    o_w, o_c = warp.reset(), cpu.reset()
    assert o_w.shape == o_c.shape == (3, 5) and o_w.dtype == torch.float32 and warp.obs_dim == 5
    torch.testing.assert_close(o_w.cpu(), o_c, atol=1e-6, rtol=0)
    torch.testing.assert_close(warp.full_observation[:, :5], o_w, atol=0, rtol=0)
    gen = torch.Generator().manual_seed(0)
    for _ in range(10):
        act = 2 * torch.rand(3, 3, generator=gen) - 1
        (o_w, r_w, te_w, tr_w), (o_c, r_c, te_c, tr_c) = (x.cpu() for x in warp.step(act.to(DEVICE))), cpu.step(act)
        torch.testing.assert_close(o_w, o_c, atol=1e-4, rtol=0)
        torch.testing.assert_close(r_w, r_c, atol=1e-4, rtol=0)
        assert torch.equal(te_w, te_c) and torch.equal(tr_w, tr_c)


def test_x_position_and_state_are_views_of_the_simulation():
    sim = WarpSim(HOPPER_ID, 2, hopper_kwargs("forward", "paper"), DEVICE)
    sim.reset(0)
    x0 = sim.x_position
    sim.step(torch.zeros(2, 3, device=sim.device))
    assert torch.equal(sim.x_position, sim.qpos[:, 0]) and not torch.equal(sim.x_position, x0)


def test_warp_sim_and_env_are_the_batched_interfaces_and_resume_their_generators():
    from pomil.envs.vec import BatchedEnv, BatchedSim
    from pomil.envs.warp import WarpVecEnv

    env = WarpVecEnv(WarpSim(HOPPER_ID, 2, hopper_kwargs("forward", "paper"), DEVICE), seed=3)
    assert isinstance(env.sim, BatchedSim) and isinstance(env, BatchedEnv)
    env.reset()
    state = env.state_dict()
    copy = WarpVecEnv(WarpSim(HOPPER_ID, 2, hopper_kwargs("forward", "paper"), DEVICE), seed=9)
    copy.load_state_dict(state)
    assert torch.equal(copy.reset(), env.reset())


def test_rejects_what_it_cannot_run():
    with pytest.raises(ValueError, match="runs .*Hopper-v5.*not 'Ant-v5'"):
        WarpSim("Ant-v5", 2)
    with pytest.raises(ValueError, match="unsupported Hopper-v5 keyword"):
        WarpSim(HOPPER_ID, 2, {"forward_reward_wieght": 1.0})
    sim = WarpSim(HOPPER_ID, 2, device=DEVICE)
    with pytest.raises(RuntimeError, match="reset"):
        sim.step(torch.zeros(2, 3))
    sim.reset(0)
    with pytest.raises(ValueError, match="shape"):
        sim.step(torch.zeros(3, 3))


@pytest.mark.slow
def test_infogail_pomdp_trains_one_iteration_on_warp_physics(tmp_path):
    """The training loop runs on ``sim="warp"`` unchanged (one iteration, 4 envs; on Warp's CPU device ~25 s)."""
    import csv
    from pathlib import Path

    from pomil.algos.adversarial import AdversarialConfig, train_adversarial
    from pomil.config import from_dict
    from pomil.training import load_checkpoint

    demos = Path(__file__).resolve().parents[2] / "data" / "hopper-paper.npz"
    values = {"learner": "infogail-pomdp", "demos": str(demos), "out": str(tmp_path), "iterations": 1, "num_envs": 4,
              "warm_start_iterations": 0, "policy_warmup_iterations": 0, "eval_every": 0, "log_every": 1,
              "progress": False, "sim": "warp", "device": DEVICE}
    ckpt = train_adversarial(from_dict(AdversarialConfig, values, "test"))
    assert load_checkpoint(ckpt)["env_steps"] == 4 * 128  # paper setting: 128 steps per episode
    with open(tmp_path / "metrics.csv", newline="") as f:
        row = list(csv.DictReader(f))[-1]
    assert np.isfinite(float(row["env/true_return"]))
