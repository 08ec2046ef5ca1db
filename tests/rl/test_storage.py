import torch

from pomil.rl.storage import Rollout


def make_rollout(T=10, N=6, K=2):
    g = torch.Generator().manual_seed(0)
    starts = torch.zeros(T, N, dtype=torch.bool)
    starts[0] = True
    f = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Rollout(
        observations=torch.arange(T * N, dtype=torch.float32).view(T, N, 1).expand(T, N, 2).clone(),
        actions=f(T, N, 2), prev_actions=f(T, N, 2), starts=starts,
        codes=torch.nn.functional.one_hot(torch.arange(N) % K, K).float().expand(T, N, K), log_probs=f(T, N),
        values=f(T, N), terminated=torch.zeros(T, N, dtype=torch.bool), truncated=starts.roll(-1, 0),
        mask=torch.ones(T, N, dtype=torch.bool), h0_policy=f(N, 4), h0_value=f(N, 4),
    )


def test_sequence_batches_cover_every_env_once_with_their_initial_state():
    roll = make_rollout()
    seen = []
    for b in roll.sequence_batches(3, torch.Generator().manual_seed(1)):
        assert b.observations.shape[:2] == (10, 2) and b.starts[0].all() and not b.starts[1:].any()
        envs = (b.observations[0, :, 0] % 6).long()
        torch.testing.assert_close(b.h0_policy, roll.h0_policy[envs])
        seen += envs.tolist()
    assert sorted(seen) == list(range(6))


def test_windows_are_contiguous_start_from_zero_state_and_keep_codes():
    roll = make_rollout()
    b = roll.windows(4, 5, torch.Generator().manual_seed(2))
    assert b.observations.shape == (4, 5, 2) and b.mask.all()
    assert b.starts[0].all() and not b.starts[1:].any()
    assert (b.h0_policy == 0).all() and (b.h0_value == 0).all()
    flat = b.observations[:, :, 0]
    assert ((flat[1:] - flat[:-1]) == 6).all()  # consecutive time steps of one env
    envs = (flat[0] % 6).long()
    torch.testing.assert_close(b.codes[0], roll.codes[0, envs])


def test_window_batches_see_about_one_pass_of_steps():
    roll = make_rollout(T=32, N=8)
    batches = list(roll.window_batches(4, 8, torch.Generator().manual_seed(0)))
    assert len(batches) == 4 and sum(b.mask.sum().item() for b in batches) == 32 * 8


def test_rollout_rejects_mismatched_shapes():
    import pytest

    roll = make_rollout()
    with pytest.raises(ValueError, match="Rollout.values"):
        roll.with_(values=torch.zeros(9, 6))
