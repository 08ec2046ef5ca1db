import pytest
import torch

from pomil.rl.gae import gae


def col(*xs):
    return torch.tensor(xs, dtype=torch.float32).unsqueeze(1)


def flags(*xs):
    return torch.tensor(xs, dtype=torch.bool).unsqueeze(1)


def test_gae_hand_computed_with_truncation_and_termination():
    # Steps 0-1: one episode truncated at step 1 (bootstrapped from V(s_2') = 10);
    # step 2: a new episode that terminates at once (nothing bootstrapped).
    gamma, lam = 0.5, 0.5
    r = col(1.0, 2.0, 3.0)
    v = col(4.0, 5.0, 6.0)
    nv = col(5.0, 10.0, 99.0)
    term = flags(False, False, True)
    trunc = flags(False, True, False)
    adv, ret = gae(r, v, nv, terminated=term, truncated=trunc, gamma=gamma, lam=lam)
    d2 = 3.0 - 6.0                      # terminated: no bootstrap
    d1 = 2.0 + 0.5 * 10.0 - 5.0         # truncated: bootstrap from the final observation
    d0 = 1.0 + 0.5 * 5.0 - 4.0
    expected = [d0 + gamma * lam * d1, d1, d2]
    assert adv[:, 0].tolist() == pytest.approx(expected)
    assert ret[:, 0].tolist() == pytest.approx([e + b for e, b in zip(expected, [4.0, 5.0, 6.0], strict=True)])


def test_gae_lambda_one_gives_discounted_returns_minus_values():
    r = col(1.0, 1.0, 1.0)
    v = col(0.0, 0.0, 0.0)
    nv = col(0.0, 0.0, 2.0)
    adv, ret = gae(r, v, nv, terminated=flags(False, False, False), truncated=flags(False, False, True), gamma=0.9,
                   lam=1.0)
    assert ret[:, 0].tolist() == pytest.approx([1 + 0.9 + 0.81 + 0.729 * 2, 1 + 0.9 + 0.81 * 2, 1 + 0.9 * 2])


def test_gae_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="share one"):
        gae(torch.zeros(3, 2), torch.zeros(3, 2), torch.zeros(3, 1), terminated=torch.zeros(3, 2, dtype=torch.bool),
            truncated=torch.zeros(3, 2, dtype=torch.bool))
