"""collect: the rollout's values against the value network run step by step."""

import pytest
import torch

from pomil.envs import executed_actions_fn, make_vec_env
from pomil.envs.locomotion import HOPPER_ID, hopper_kwargs
from pomil.nn import heads
from pomil.nn.policy import GaussianPolicy, PolicyArch
from pomil.rl.collect import collect, torch_threads


class Recorder:
    """An env that keeps the last observation it returned."""

    def __init__(self, env):
        self.env, self.num_envs = env, env.num_envs

    def reset(self):
        return self.env.reset()

    def step(self, action):
        out = self.env.step(action)
        self.last_obs = out[0]
        return out


def test_values_from_one_unroll_match_stepping_through_episodes_of_different_lengths():
    torch.manual_seed(0)
    env = Recorder(make_vec_env(HOPPER_ID, hopper_kwargs("forward", "standard"), 6, seed=3))
    policy = GaussianPolicy(PolicyArch(11, 3, "gru", 16, 2, 1.0))  # wide noise: falls early, each copy at its own step
    value = heads.value(11, 3, 2, encoder="gru", hidden_size=16)
    threads = torch.get_num_threads()
    roll, next_values, code_idx, _ = collect(env, policy, value, num_codes=2, execute=executed_actions_fn(HOPPER_ID,
                                                                                                          {}),
                                            generator=torch.Generator().manual_seed(0), device=torch.device("cpu"))
    assert torch.get_num_threads() == threads  # the rollout's one thread is given back
    lengths = roll.mask.sum(0)
    assert len(set(lengths.tolist())) > 1 and roll.num_steps == int(lengths.max())
    torch.testing.assert_close(roll.codes[0].argmax(-1), code_idx)
    # The value network stepped along the same inputs, as a rollout without the unroll would.
    h = value.initial_state(6)
    stepped = []
    for t in range(roll.num_steps):
        v, h = value.step(roll.observations[t], roll.prev_actions[t], h, roll.starts[t], roll.codes[t])
        stepped.append(v)
    stepped = torch.stack(stepped)
    torch.testing.assert_close(roll.values, stepped)
    torch.testing.assert_close(next_values[:-1], stepped[1:])
    # The last one: V of the observation that the last step returned, after the last executed action.
    v_last, _ = value.step(env.last_obs, roll.executed_actions[-1], h, torch.zeros(6, dtype=torch.bool), roll.codes[0])
    torch.testing.assert_close(next_values[-1], v_last)
    ended = roll.terminated | roll.truncated
    assert (ended.sum(0) == 1).all()  # every episode ended exactly once, at its last masked step
    for i, n in enumerate(lengths.tolist()):
        assert bool(ended[n - 1, i])


@pytest.mark.usefixtures("torch_default_threads")
def test_torch_threads_sets_and_restores():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with torch_threads(0):
        assert torch.get_num_threads() == before
