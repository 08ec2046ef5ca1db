import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import pomil  # noqa: F401  (registers the env)
from pomil.envs.circles import (
    Circle,
    CircleExperts,
    CirclesEnv,
    CirclesVecEnv,
    classify_modes,
    distance_to_circles,
    make_spec,
)


def run_experts(spec, modes, noise_std, seed=0):
    env = CirclesVecEnv(spec, len(modes))
    experts = CircleExperts(spec, noise_std)
    gen = torch.Generator().manual_seed(seed)
    env.reset()
    positions = []
    for _ in range(spec.episode_length):
        env.step(experts.act(env.positions, modes, gen))
        positions.append(env.positions.clone())
    return torch.stack(positions, 1)


def test_every_step_moves_exactly_one_unit():
    spec = make_spec()
    env = CirclesVecEnv(spec, 64)
    env.reset()
    gen = torch.Generator().manual_seed(1)
    for _ in range(spec.episode_length):
        before = env.positions.clone()
        env.step(torch.randn(64, 2, generator=gen) * 3.0)
        torch.testing.assert_close((env.positions - before).norm(dim=-1), torch.ones(64), atol=1e-5, rtol=0)


def test_step_follows_the_direction_and_zero_action_stays_put():
    env = CirclesVecEnv(make_spec(), 3)
    env.reset()
    env.step(torch.tensor([[3.0, 4.0], [0.0, 0.0], [0.0, -1e-12]]))
    torch.testing.assert_close(env.positions, torch.tensor([[0.6, 0.8], [0.0, 0.0], [0.0, 0.0]]))


def test_angle_actions_move_one_unit_along_the_heading():
    env = CirclesVecEnv(make_spec(action_type="angle"), 2)
    env.reset()
    env.step(torch.tensor([[math.pi / 2], [math.pi + 2 * math.pi]]))
    torch.testing.assert_close(env.positions, torch.tensor([[0.0, 1.0], [-1.0, 0.0]]), atol=1e-6, rtol=0)


def test_episode_truncates_at_its_length_and_never_terminates():
    spec = make_spec(episode_length=5)
    env = CirclesVecEnv(spec, 2)
    env.reset()
    for t in range(1, 6):
        _, _, terminated, truncated = env.step(torch.ones(2, 2))
        assert not terminated.any()
        assert bool(truncated.all()) == (t == 5)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(torch.ones(2, 2))


def test_history_observation_stacks_last_positions_oldest_first():
    env = CirclesVecEnv(make_spec(history=3), 1)
    obs = env.reset()
    assert obs.tolist() == [[0.0] * 6]
    env.step(torch.tensor([[1.0, 0.0]]))
    obs, *_ = env.step(torch.tensor([[0.0, 1.0]]))
    assert obs.tolist() == [[0.0, 0.0, 1.0, 0.0, 1.0, 1.0]]


def test_reward_is_minus_distance_to_nearest_circle():
    env = CirclesVecEnv(make_spec(), 1)
    env.reset()
    _, reward, *_ = env.step(torch.tensor([[-1.0, 0.0]]))  # to (-1, 0): |(-1,-5)| - 5 = 0.0990
    assert reward.item() == pytest.approx(-(math.sqrt(26) - 5), abs=1e-6)


def test_zero_noise_experts_stay_on_their_circle_and_close_the_loop(spec):
    modes = torch.tensor([0, 1])
    pos = run_experts(spec, modes, noise_std=0.0)
    centres, radii, _ = spec.tensors()
    dist = distance_to_circles(pos, centres, radii)  # (2, T, K)
    assert dist[0, :, 0].max() < 1e-4 and dist[1, :, 1].max() < 1e-4
    # Chord steps of length 1 on a radius-5 circle: 31.4 of them make a loop.
    to_origin = pos.norm(dim=-1)
    assert to_origin[:, 30].tolist() == pytest.approx([0.364, 0.364], abs=2e-3)
    assert (to_origin[:, 28:].min(dim=1).values < 0.5).all()
    # Mode 0 goes anti-clockwise above the x axis, mode 1 clockwise below it.
    assert (pos[0, 1:30, 1] > 0).all() and (pos[1, 1:30, 1] < 0).all()


def test_noisy_experts_are_classified_as_their_own_mode(spec):
    modes = torch.arange(400) % 2
    pos = run_experts(spec, modes, noise_std=math.exp(-1))
    assert (classify_modes(pos, spec) == modes.numpy()).all()
    centres, radii, _ = spec.tensors()
    own = distance_to_circles(pos, centres, radii).mean(1)[torch.arange(400), modes]
    assert own.max() < 0.6  # far inside the 1.0 "none" threshold


def test_classifier_says_none_for_a_straight_line(spec):
    straight = np.stack([np.stack([np.arange(1, 34), np.zeros(33)], -1)], 0).astype(float)
    assert classify_modes(straight, spec).tolist() == [-1]


def test_four_mode_preset_experts_are_distinct():
    spec = make_spec("four")
    modes = torch.arange(4)
    pos = run_experts(spec, modes, noise_std=0.0)
    assert classify_modes(pos, spec).tolist() == [0, 1, 2, 3]


def test_circle_must_pass_through_origin():
    with pytest.raises(ValueError, match="origin"):
        Circle((0.0, 4.0), 5.0, 1)
    with pytest.raises(ValueError, match="direction"):
        Circle((0.0, 5.0), 5.0, 0)


@pytest.mark.parametrize("kwargs", [{}, {"history": 4}, {"action_type": "angle"}])
def test_gymnasium_env_passes_check_env(kwargs):
    check_env(gym.make("pomil/Circles-v0", **kwargs).unwrapped, skip_render_check=True)


@pytest.mark.parametrize("action_type", ["vector", "angle"])
def test_gymnasium_env_agrees_with_batched_env_step_for_step(action_type):
    spec = make_spec(history=2, action_type=action_type)
    gen = torch.Generator().manual_seed(3)
    actions = torch.randn(spec.episode_length, 4, spec.act_dim, generator=gen)
    vec = CirclesVecEnv(spec, 4)
    vec_obs = [vec.reset()]
    vec_out = [vec.step(a) for a in actions]
    for i in range(4):
        env = gym.make("pomil/Circles-v0", history=2, action_type=action_type)
        obs, _ = env.reset(seed=i)
        np.testing.assert_array_equal(obs, vec_obs[0][i].numpy())
        for t in range(spec.episode_length):
            obs, reward, terminated, truncated, _ = env.step(actions[t, i].numpy())
            v_obs, v_rew, v_term, v_trunc = vec_out[t]
            np.testing.assert_allclose(obs, v_obs[i].numpy(), rtol=0, atol=1e-6)
            assert reward == pytest.approx(v_rew[i].item(), abs=1e-6)
            assert (terminated, truncated) == (bool(v_term[i]), bool(v_trunc[i]))
        assert truncated


def test_gymnasium_env_uses_the_spec_options():
    env = CirclesEnv(circles=[[0, 3, 3, 1]], episode_length=7, history=2)
    assert env.observation_space.shape == (4,)
    assert env.spec_.num_modes == 1 and env.spec_.circles[0].radius == 3


def test_executed_actions_are_what_the_environment_carries_out():
    from pomil.envs import executed_actions_fn

    raw = torch.tensor([[3.0, 4.0], [0.0, 0.0], [-0.1, 0.0]])
    vec = executed_actions_fn("pomil/Circles-v0", {})(raw)
    torch.testing.assert_close(vec, torch.tensor([[0.6, 0.8], [0.0, 0.0], [-1.0, 0.0]]))
    env = CirclesVecEnv(make_spec(), 3)
    env.reset()
    before = env.positions.clone()
    env.step(raw)
    torch.testing.assert_close(env.positions - before, vec)  # the env moved exactly by the executed actions
    ang = executed_actions_fn("pomil/Circles-v0",
                              {"action_type": "angle"})(torch.tensor([[0.5], [0.5 + 2 * math.pi], [-3 * math.pi / 2]]))
    torch.testing.assert_close(ang, torch.tensor([[0.5], [0.5], [math.pi / 2]]))


def test_fit_circles_recovers_centre_and_radius_of_points_on_a_circle_through_the_origin():
    from pomil.envs.circles import fit_circles

    angles = np.linspace(-np.pi / 2, np.pi, 20)[1:]  # from the origin (angle -pi/2 around (0, 3)) onwards
    on = np.stack([3 * np.cos(angles), 3 + 3 * np.sin(angles)], -1)
    big = np.stack([np.linspace(1, 5, 10), 0.01 * np.linspace(1, 5, 10) ** 2], -1)  # nearly straight
    centres, radii = fit_circles(np.stack([on, on[::-1] * [1, -1]])[:, :, :])
    np.testing.assert_allclose(radii, [3.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(centres, [[0.0, 3.0], [0.0, -3.0]], atol=1e-9)
    assert fit_circles(big[None])[1][0] > 40


def test_radius_range_demos_follow_their_own_circle_with_the_same_tangent_and_direction():
    from pomil.demos import record_circles_demos
    from pomil.envs.circles import fit_circles

    d = record_circles_demos(make_spec("one", 5.0), 40, noise_std=0.0, seed=1, radius_range=(3.0, 7.0))
    radii = np.asarray(d.metadata["episode_radii"])
    assert d.metadata["radius_range"] == [3.0, 7.0] and radii.shape == (40,)
    assert radii.min() >= 3.0 and radii.max() <= 7.0 and radii.max() - radii.min() > 2.5
    pos = d.states.reshape(40, 33, 2)[:, 1:]
    centres, fitted = fit_circles(pos)
    np.testing.assert_allclose(fitted, radii, rtol=1e-4)  # noise-free experts stay exactly on their circle
    np.testing.assert_allclose(centres[:, 0], 0.0, atol=1e-3)
    assert (d.actions.reshape(40, 33, 2)[:, 0, 0] > 0).all()  # anti-clockwise around (0, r): first step to +x
    assert d.metadata["env_kwargs"]["circles"] == [[0.0, 5.0, 5.0, 1]]
    with pytest.raises(ValueError, match="radius_range"):
        record_circles_demos(make_spec("one"), 4, radius_range=(5.0, 2.0))


def test_circle_with_radius_keeps_tangent_and_direction():
    c = Circle.through_origin(210, 5.0, -1).with_radius(2.0)
    assert c.radius == 2.0 and c.direction == -1
    assert c.center == pytest.approx((2.0 * math.cos(math.radians(210)), 2.0 * math.sin(math.radians(210))))
