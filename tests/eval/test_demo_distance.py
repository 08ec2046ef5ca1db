import math

import pytest
import torch

from pomil.eval.demo_distance import ABSORBING_WIDTHS, DemoReference, mmd, step_features


def test_step_features_pair_each_observation_with_its_change_and_pad_to_the_horizon():
    obs = torch.tensor([[[1.0], [5.0]], [[2.0], [6.0]], [[4.0], [0.0]]])  # (T=3, B=2, D=1)
    mask = torch.tensor([[1, 1], [1, 1], [1, 0]], dtype=torch.bool)  # episode 1 ends after two steps
    feats, live = step_features(obs, mask, horizon=4)
    assert feats.shape == (3, 2, 2)
    assert feats[:, 0].tolist() == [[1.0, 1.0], [2.0, 2.0], [4.0, -4.0]]
    assert feats[0, 1].tolist() == [5.0, 1.0]
    assert live.tolist() == [[True, True], [True, False], [False, False]]


def test_mmd_is_zero_on_one_sample_and_exact_between_two_points():
    x = torch.randn(50, 3, generator=torch.Generator().manual_seed(0))
    assert mmd(x, x, 1.0) == pytest.approx(0.0, abs=1e-6)
    a = torch.zeros(1, 2)
    b = torch.tensor([[3.0, 4.0]])  # 5 apart
    assert mmd(a, b, 2.0) == pytest.approx(math.sqrt(2 - 2 * math.exp(-25 / 8)), rel=1e-6)


def test_mmd_orders_nearer_distributions_first():
    gen = torch.Generator().manual_seed(1)
    ref = torch.randn(400, 2, generator=gen)
    same, near, far = (torch.randn(400, 2, generator=gen) + s for s in (0.0, 0.5, 2.0))
    assert mmd(same, ref, 1.0) < mmd(near, ref, 1.0) < mmd(far, ref, 1.0)


def reference_of_ramps(episodes: int = 6, steps: int = 20) -> DemoReference:
    t = torch.arange(steps, dtype=torch.float32)[:, None, None]
    obs = t * torch.linspace(0.5, 1.5, episodes)[None, :, None]  # (T, E, 1) ramps of several slopes
    return DemoReference.of(obs, torch.ones(steps, episodes, dtype=torch.bool), samples=256)


def test_the_reference_standardises_the_demonstrations_live_steps():
    ref = reference_of_ramps()
    z = ref.features[ref.live]
    assert ref.horizon == 20 and z.shape == (19 * 6, 2)
    assert z.mean(0).abs().max() < 1e-5 and (z.std(0) - 1).abs().max() < 1e-5
    assert ref.width > 0


def test_an_episode_that_ends_early_is_sampled_as_the_absorbing_point():
    ref = reference_of_ramps()
    gen = torch.Generator().manual_seed(0)
    dead = ref.sample(ref.features, torch.zeros_like(ref.live), 64, gen)
    assert torch.equal(dead[:, :-1], torch.zeros(64, 2))
    assert torch.allclose(dead[:, -1], torch.full((64,), ABSORBING_WIDTHS * ref.width))
    live = ref.sample(ref.features, ref.live, 64, gen)
    assert torch.equal(live[:, -1], torch.zeros(64))
    # the absorbing point lies ABSORBING_WIDTHS kernel widths from every live step, so that
    # MMD^2 >= k(dead, dead) + mean k(live, live) - 2 exp(-ABSORBING_WIDTHS^2 / 2)
    k_live = torch.exp(-torch.cdist(live, live).pow(2) / (2 * ref.width ** 2)).mean()
    assert mmd(dead, live, ref.width) ** 2 >= 1 + float(k_live) - 2 * math.exp(-ABSORBING_WIDTHS ** 2 / 2) - 1e-6
