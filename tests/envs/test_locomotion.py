"""The batched Hopper equals gymnasium's Hopper-v5, number for number."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from pomil.envs import env_dims, executed_actions_fn, make_vec_env
from pomil.envs.locomotion import HOPPER_ID, HOPPER_SPEED_ID, HopperSim, hopper_kwargs, locomotion_kwargs
from pomil.envs.wrappers import ObservationMask, resolve_observation_mask


def _gym_envs(n, kwargs, seed, env_id=HOPPER_ID):
    envs = [gym.make(env_id, **kwargs) for _ in range(n)]
    obs = np.stack([e.reset(seed=seed + i)[0] for i, e in enumerate(envs)])
    return envs, obs


def _compare(kwargs, steps, n=3, seed=7, action_scale=1.5, env_id=HOPPER_ID):
    """Step HopperSim and n gymnasium envs with the same actions; compare every output."""
    rng = np.random.default_rng(0)
    sim = HopperSim(n, kwargs, threads=2, env_id=env_id)
    envs, obs_gym = _gym_envs(n, kwargs, seed, env_id)
    obs = sim.reset(seed)
    np.testing.assert_array_equal(obs, obs_gym)
    done = np.zeros(n, dtype=bool)
    ends = {}
    for t in range(steps):
        act = rng.uniform(-action_scale, action_scale, (n, 3))  # beyond the control range on purpose
        obs, rew, term, trunc = sim.step(act)
        for i, e in enumerate(envs):
            if done[i]:
                assert rew[i] == 0.0 and not term[i] and not trunc[i]
                continue
            o, r, te, tr, _ = e.step(act[i])
            np.testing.assert_array_equal(obs[i], o)
            np.testing.assert_allclose(rew[i], r, rtol=1e-12, atol=1e-12)
            assert (term[i], trunc[i]) == (te, tr), f"env {i} step {t}"
            if te or tr:
                done[i] = True
                ends[i] = (t + 1, "terminated" if te else "truncated")
        if done.all():
            break
    sim.close()
    return ends


def test_paper_setting_matches_gymnasium_and_truncates_at_128():
    ends = _compare(hopper_kwargs("backward", "paper"), 200)
    assert ends == {i: (128, "truncated") for i in range(3)}


def test_standard_setting_terminations_match_gymnasium():
    ends = _compare(hopper_kwargs("forward", "standard"), 1000)
    assert all(kind == "terminated" for _, kind in ends.values()) and len(ends) == 3


def test_truncation_at_1000_steps_matches_gymnasium():
    kwargs = {**hopper_kwargs("forward", "standard"), "terminate_when_unhealthy": False}
    ends = _compare(kwargs, 1000, n=2, action_scale=0.5)
    assert ends == {0: (1000, "truncated"), 1: (1000, "truncated")}


def test_speed_task_matches_its_gymnasium_env_and_pays_for_the_target_speed():
    kwargs = {**locomotion_kwargs(HOPPER_SPEED_ID, "none", "paper"), "target_velocity": 1.5}
    assert kwargs == {"terminate_when_unhealthy": False, "max_episode_steps": 128, "target_velocity": 1.5}
    ends = _compare(kwargs, 200, env_id=HOPPER_SPEED_ID)
    assert ends == {i: (128, "truncated") for i in range(3)}
    # the reward by hand, one step: healthy 1 - |v - 1.5| - 1e-3 * |a|^2 (Hopper-v5's ctrl_cost_weight)
    sim = HopperSim(1, kwargs, env_id=HOPPER_SPEED_ID)
    sim.reset(0)
    x0, act = sim.x_position[0], np.array([[0.2, -0.1, 0.3]])
    _, rew, _, _ = sim.step(act)
    v = (sim.x_position[0] - x0) / sim.dt
    assert rew[0] == pytest.approx(1.0 - abs(v - 1.5) - 1e-3 * 0.14, abs=1e-12)
    with pytest.raises(ValueError, match="task 'none'"):
        locomotion_kwargs(HOPPER_SPEED_ID, "forward", "paper")
    with pytest.raises(ValueError, match="unsupported Hopper-v5 keyword.*target_velocity"):
        HopperSim(1, kwargs)  # Hopper-v5 itself has no target speed


def test_unseeded_reset_continues_the_generators_like_gymnasium():
    kwargs = hopper_kwargs("forward", "paper")
    sim = HopperSim(2, kwargs)
    envs, _ = _gym_envs(2, kwargs, 3)
    sim.reset(3)
    np.testing.assert_array_equal(sim.reset(), np.stack([e.reset()[0] for e in envs]))


def test_rejects_unknown_keyword_and_bad_actions():
    with pytest.raises(ValueError, match="unsupported Hopper-v5 keyword"):
        HopperSim(2, {"forward_reward_wieght": 1.0})
    sim = HopperSim(2)
    with pytest.raises(RuntimeError, match="reset"):
        sim.step(np.zeros((2, 3)))
    sim.reset(0)
    with pytest.raises(ValueError, match="shape"):
        sim.step(np.zeros((3, 3)))


def test_positions_only_mask_on_hopper_keeps_height_and_angles():
    kwargs = hopper_kwargs("forward", "paper")
    idx = resolve_observation_mask(HOPPER_ID, kwargs, "positions-only")
    assert idx == [0, 1, 2, 3, 4]
    env = ObservationMask(gym.make(HOPPER_ID, **kwargs), idx)
    obs, _ = env.reset(seed=0)
    full = env.unwrapped.data.qpos[1:]  # height + 4 angles
    np.testing.assert_array_equal(obs, full)
    assert env.observation_space.shape == (5,)
    vec = make_vec_env(HOPPER_ID, kwargs, 4, observation_mask=idx, seed=0)
    o = vec.reset()
    assert o.shape == (4, 5) and o.dtype == torch.float32
    np.testing.assert_allclose(o.numpy(), vec.full_observation[:, :5].astype(np.float32))
    assert env_dims(HOPPER_ID, kwargs, idx) == (5, 3)


def test_observation_mask_on_another_env():
    env = ObservationMask(gym.make("Pendulum-v1"), [1, 0])
    obs, _ = env.reset(seed=0)
    full = env.unwrapped._get_obs()
    np.testing.assert_array_equal(obs, full[[1, 0]])
    np.testing.assert_array_equal(env.observation_space.low, np.array([-1.0, -1.0], dtype=np.float32))
    with pytest.raises(ValueError, match=r"lie in \[0, 3\)"):
        ObservationMask(gym.make("Pendulum-v1"), [3])
    with pytest.raises(ValueError, match="MuJoCo locomotion"):
        resolve_observation_mask("Pendulum-v1", {}, "positions-only")
    with pytest.raises(ValueError, match="MuJoCo locomotion"):
        resolve_observation_mask("Pendulum-v1", {}, "velocities")
    with pytest.raises(ValueError, match="unknown observation mask preset"):
        resolve_observation_mask("Pendulum-v1", {}, "speed")


def test_executed_actions_clamp_to_the_control_range():
    execute = executed_actions_fn(HOPPER_ID, hopper_kwargs("forward", "paper"))
    a = torch.tensor([[-2.0, 0.3, 1.5]])
    assert torch.equal(execute(a), torch.tensor([[-1.0, 0.3, 1.0]]))
