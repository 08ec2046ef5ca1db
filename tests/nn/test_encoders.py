"""Every encoder: one 2-D state, unroll = repeated steps, resets at starts; the attention window's bounds."""

import pytest
import torch

from pomil.nn.encoders import ENCODERS, AttentionEncoder, make_encoder
from pomil.nn.policy import GaussianPolicy, PolicyArch

OBS, ACT = 3, 2
RECURRENT = [("gru", 32), ("lstm", 32), ("attention", 1), ("attention", 4), ("attention", 32)]


def _encoder(kind, context=32, hidden=8, query_chunk=None):
    torch.manual_seed(0)
    enc = make_encoder(kind, OBS, ACT, hidden_size=hidden, context=context)
    if query_chunk is not None:
        enc.query_chunk = query_chunk  # several attention blocks per unroll
    return enc


def _block(T, N, seed, start_rate=0.15):
    gen = torch.Generator().manual_seed(seed)
    starts = torch.rand(T, N, generator=gen) < start_rate
    starts[0, 0] = True
    return torch.randn(T, N, OBS, generator=gen), torch.randn(T, N, ACT, generator=gen), starts


def _carried_state(enc, N, seed):
    """A state from an earlier block (no starts in it): nonzero, and for attention a full window."""
    obs, prev, _ = _block(40, N, seed)
    return enc.unroll(obs, prev, enc.initial_state(N), torch.zeros(40, N, dtype=torch.bool))[1].detach()


@pytest.mark.parametrize("kind", ENCODERS)
def test_every_encoder_keeps_one_2d_state_and_gives_out_size_features(kind):
    enc = _encoder(kind, context=5)
    T, N = 6, 4
    h0 = enc.initial_state(N)
    assert h0.ndim == 2 and h0.shape[0] == N and not h0.any()
    size = {"mlp": 0, "gru": 8, "lstm": 16, "attention": 4 * (2 * 8 + 1)}[kind]
    assert h0.shape[1] == size
    obs, prev, starts = _block(T, N, 0)
    f, h = enc.step(obs[0], prev[0], h0, starts[0])
    assert f.shape == (N, enc.out_size) and h.shape == h0.shape
    f, h = enc.unroll(obs, prev, h0, starts)
    assert f.shape == (T, N, enc.out_size) and h.shape == h0.shape


@pytest.mark.parametrize("kind, context", RECURRENT)
def test_unroll_matches_repeated_steps_with_mid_block_starts_and_a_carried_state(kind, context):
    enc = _encoder(kind, context, query_chunk=7)
    T, N = 30, 5
    h0 = _carried_state(enc, N, 1)
    assert h0.numel() == 0 or h0.abs().sum() > 0  # context 1 keeps no window
    obs, prev, starts = _block(T, N, 2)
    assert starts[1:].any()
    feats, h_last = enc.unroll(obs, prev, h0, starts)
    h = h0
    for t in range(T):
        f, h = enc.step(obs[t], prev[t], h, starts[t])
        torch.testing.assert_close(f, feats[t], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(h, h_last, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("kind, context", RECURRENT)
def test_two_blocks_with_the_state_carried_equal_one_block(kind, context):
    enc = _encoder(kind, context, query_chunk=4)
    T, N = 24, 4
    obs, prev, starts = _block(T, N, 3)
    h0 = _carried_state(enc, N, 4)
    whole, h_whole = enc.unroll(obs, prev, h0, starts)
    first, h = enc.unroll(obs[:10], prev[:10], h0, starts[:10])
    second, h = enc.unroll(obs[10:], prev[10:], h, starts[10:])
    torch.testing.assert_close(torch.cat([first, second]), whole, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(h, h_whole, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("kind, context", RECURRENT)
def test_a_start_erases_everything_before_it(kind, context):
    enc = _encoder(kind, context)
    T, N, at = 20, 3, 9
    obs, prev, _ = _block(T, N, 5)
    starts = torch.zeros(T, N, dtype=torch.bool)
    starts[at] = True
    feats, _ = enc.unroll(obs, prev, _carried_state(enc, N, 6), starts)
    other_obs, other_prev, _ = _block(at, N, 7)  # another past, another carried state
    feats2, _ = enc.unroll(torch.cat([other_obs, obs[at:]]), torch.cat([other_prev, prev[at:]]),
                           _carried_state(enc, N, 8), starts)
    fresh_prev = prev[at:].clone()
    fresh_prev[0] = 0
    fresh, _ = enc.unroll(obs[at:], fresh_prev, enc.initial_state(N), starts[at:])
    torch.testing.assert_close(feats[at:], fresh, atol=1e-5, rtol=1e-5)  # a_{t-1} ignored at the start too
    torch.testing.assert_close(feats2[at:], fresh, atol=1e-5, rtol=1e-5)
    assert (feats[at - 1] - feats2[at - 1]).abs().max() > 1e-3  # before the start the past matters


@pytest.mark.parametrize("context", [1, 4, 6])
def test_attention_sees_the_last_context_steps_of_the_episode_and_nothing_else(context):
    """Feature t depends on input s exactly when t - context < s <= t and no episode starts in (s, t]
    (the gradient of each step's features with respect to each step's observation)."""
    enc = _encoder("attention", context, query_chunk=5)
    T, N = 16, 2
    obs, prev, _ = _block(T, N, 9)
    starts = torch.zeros(T, N, dtype=torch.bool)
    starts[0, :] = True
    starts[7, 0] = True
    starts[12, 1] = True
    obs.requires_grad_(True)
    feats, _ = enc.unroll(obs, prev, enc.initial_state(N), starts)
    w = torch.randn(enc.out_size)  # not all ones: the final LayerNorm's outputs always sum to the same
    for n in range(N):
        for t in range(T):
            (grad,) = torch.autograd.grad(feats[t, n] @ w, obs, retain_graph=True)
            seen = grad[:, n].abs().sum(-1) > 0
            first = max(t - context + 1, int(starts[: t + 1, n].nonzero().max()))
            expected = torch.zeros(T, dtype=torch.bool)
            expected[first:t + 1] = True
            assert torch.equal(seen, expected), (n, t)
            assert grad[:, 1 - n].abs().sum() == 0  # nor another environment's steps


def test_attention_carried_window_reaches_exactly_context_minus_one_steps_into_the_next_block():
    context, N = 5, 2
    enc = _encoder("attention", context)
    obs, prev, _ = _block(10, N, 10)
    no_start = torch.zeros(10, N, dtype=torch.bool)
    h0 = _carried_state(enc, N, 11)
    base, _ = enc.unroll(obs, prev, h0, no_start)
    other, _ = enc.unroll(obs, prev, _carried_state(enc, N, 12), no_start)
    differs = (base - other).abs().amax(dim=(1, 2)) > 1e-6
    assert differs.tolist() == [True] * (context - 1) + [False] * (10 - context + 1)


def test_attention_state_is_reset_to_zero_at_a_start():
    enc = _encoder("attention", 4)
    h = _carried_state(enc, 2, 13)
    _, h_new = enc.step(torch.randn(2, OBS), torch.randn(2, ACT), h, torch.tensor([True, False]))
    keys, values, valid = enc._unpack(h_new)
    assert valid.tolist() == [[False, False, True], [True, True, True]]
    assert not keys[0, :, :2].any() and not values[0, :, :2].any()


def test_attention_heads_divide_the_width():
    assert AttentionEncoder(2, 2, 8).heads == 4
    assert AttentionEncoder(2, 2, 6).heads == 2
    assert AttentionEncoder(2, 2, 5).heads == 1
    with pytest.raises(ValueError, match="at least 1"):
        AttentionEncoder(2, 2, 8, context=0)


def test_unknown_encoder_names_the_choices():
    with pytest.raises(ValueError, match="'mlp', 'gru', 'lstm', 'attention'"):
        make_encoder("transformer", 2, 2, hidden_size=8)


def test_policy_arch_records_the_context_for_attention_only():
    assert "context" not in PolicyArch(2, 2, "gru").to_dict()  # GRU checkpoints as before the field existed
    assert "context" not in PolicyArch(2, 2, "lstm").to_dict()
    arch = PolicyArch(2, 2, "attention", 8, context=7)
    assert arch.to_dict()["context"] == 7
    assert PolicyArch(**arch.to_dict()) == arch
    assert GaussianPolicy(PolicyArch(**arch.to_dict())).encoder.context == 7


class _Echo(torch.nn.Module):
    """An inner encoder whose features are its inputs [x, a] (and that keeps no state)."""

    out_size = 2 * OBS + ACT

    def initial_state(self, n, device=None):
        return torch.zeros(n, 0, device=device)

    def step(self, x, a, h, start):
        return torch.cat([x, a], -1), h

    def unroll(self, x, a, h0, starts):
        return torch.cat([x, a], -1), h0


def test_input_view_sees_the_scaled_observation_change_and_zeros_for_the_previous_action():
    from pomil.nn.encoders import InputView

    view = InputView(_Echo(), OBS, obs_delta=True, prev_action=False)
    view.delta_scale.copy_(torch.tensor([1.0, 2.0, 10.0]))
    obs = torch.tensor([[[1.0, 1.0, 1.0]], [[2.0, 0.0, 1.5]], [[4.0, 0.0, 1.0]], [[0.0, 0.0, 0.0]]])  # (T 4, N 1, 3)
    starts = torch.tensor([[False], [False], [False], [True]])
    h0 = torch.tensor([[0.5, 1.0, 1.0]])  # the observation before this block
    feats, h = view.unroll(obs, torch.ones(4, 1, ACT), h0, starts)
    torch.testing.assert_close(feats[:, 0, OBS:2 * OBS], torch.tensor(
        [[0.5, 0.0, 0.0], [1.0, -2.0, 5.0], [2.0, 0.0, -5.0], [0.0, 0.0, 0.0]]))  # no change across a start
    assert not feats[..., 2 * OBS:].any()  # a_{t-1} replaced by zeros
    torch.testing.assert_close(h, obs[-1])


@pytest.mark.parametrize("kind", ["mlp", "gru", "attention"])
def test_input_view_unroll_matches_repeated_steps_with_mid_block_starts_and_a_carried_state(kind):
    torch.manual_seed(0)
    enc = make_encoder(kind, OBS, ACT, hidden_size=8, context=4, obs_delta=True, prev_action=False)
    enc.delta_scale.copy_(torch.tensor([3.0, 0.5, 2.0]))
    N = 5
    h0 = _carried_state(enc, N, 1)
    assert h0.shape == (N, enc.inner.initial_state(N).shape[1] + OBS)
    obs, prev, starts = _block(30, N, 2)
    feats, h_last = enc.unroll(obs, prev, h0, starts)
    h = h0
    for t in range(30):
        f, h = enc.step(obs[t], prev[t], h, starts[t])
        torch.testing.assert_close(f, feats[t], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(h, h_last, atol=1e-5, rtol=1e-5)
    # the previous action is not seen at all: any other actions give the same features
    torch.testing.assert_close(enc.unroll(obs, torch.randn_like(prev), h0, starts)[0], feats)


def test_fit_input_scale_is_one_over_the_std_of_the_in_episode_changes():
    from pomil.nn.encoders import fit_input_scale

    enc = make_encoder("gru", 1, ACT, hidden_size=8, obs_delta=True)
    obs = torch.tensor([[0.0, 5.0], [1.0, 5.0], [3.0, 100.0]]).unsqueeze(-1)  # (T 3, E 2, 1)
    mask = torch.tensor([[True, True], [True, True], [True, False]])  # episode 1 ends after step 1
    fit_input_scale(enc, obs, mask)
    changes = torch.tensor([1.0, 2.0, 0.0])  # episode 0: 1, 2; episode 1: 0 (its padded step does not count)
    torch.testing.assert_close(enc.delta_scale, 1 / changes.std().reshape(1))
    plain = make_encoder("gru", 1, ACT, hidden_size=8)
    fit_input_scale(plain, obs, mask)  # no view: nothing to set
    assert not hasattr(plain, "delta_scale")


def test_policy_arch_records_the_input_view_only_when_it_is_not_the_default():
    assert "obs_delta" not in PolicyArch(3, 2).to_dict() and "prev_action" not in PolicyArch(3, 2).to_dict()
    arch = PolicyArch(3, 2, obs_delta=True, prev_action=False)
    assert arch.to_dict()["obs_delta"] is True and arch.to_dict()["prev_action"] is False
    assert PolicyArch(**arch.to_dict()) == arch
