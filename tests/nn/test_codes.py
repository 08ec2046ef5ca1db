import math

import pytest
import torch

from pomil.nn.codes import (
    LOG_STD_RANGE,
    code_log_likelihood,
    draw_codes,
    prior_grid,
    prior_quantile,
    sample_prior,
    spread_as_prior,
)


def test_continuous_code_log_likelihood_is_the_diagonal_gaussians_exact_value():
    # posterior output [mean (2), log std (2)] for one step; code c = (1, -1)
    out = torch.tensor([[0.0, 0.5, 0.0, math.log(2.0)]])
    c = torch.tensor([[1.0, -1.0]])
    # dim 0: N(1; 0, 1) -> -0.5 - 0.5 log(2 pi); dim 1: N(-1; 0.5, 2) -> -0.5 (1.5 / 2)^2 - log 2 - 0.5 log(2 pi)
    expected = (-0.5 - 0.5 * math.log(2 * math.pi)) + (-0.5 * 0.75 ** 2 - math.log(2.0) - 0.5 * math.log(2 * math.pi))
    got = code_log_likelihood(out, c, "continuous")
    assert got.shape == (1,)
    assert got.item() == pytest.approx(expected, abs=1e-6)
    reference = torch.distributions.Normal(out[0, :2], out[0, 2:].exp()).log_prob(c[0]).sum().item()
    assert got.item() == pytest.approx(reference, abs=1e-6)


def test_continuous_posterior_log_std_is_clamped_so_the_likelihood_stays_bounded():
    lo, hi = LOG_STD_RANGE
    exact = torch.tensor([[0.3, -50.0]])  # mean = c exactly, log std far below the floor
    assert code_log_likelihood(exact, torch.tensor([[0.3]]), "continuous").item() == pytest.approx(
        -lo - 0.5 * math.log(2 * math.pi), abs=1e-5)
    wide = torch.tensor([[0.0, 50.0]])
    assert code_log_likelihood(wide, torch.tensor([[0.0]]), "continuous").item() == pytest.approx(
        -hi - 0.5 * math.log(2 * math.pi), abs=1e-5)


def test_discrete_code_log_likelihood_is_the_log_softmax_of_the_codes_logit():
    logits = torch.tensor([[[0.0, math.log(3.0)]], [[math.log(3.0), 0.0]]])  # (T=2, N=1, K=2)
    got = code_log_likelihood(logits, torch.tensor([[1], [1]]), "discrete")
    assert got.shape == (2, 1)
    assert got[:, 0].tolist() == pytest.approx([math.log(0.75), math.log(0.25)], abs=1e-6)


def test_prior_grid_and_quantiles():
    assert prior_grid("uniform", 4).tolist() == [-0.75, -0.25, 0.25, 0.75]
    g = prior_grid("gaussian", 3)
    assert g[1].item() == pytest.approx(0.0, abs=1e-6) and g[2].item() == pytest.approx(0.9674216, abs=1e-5)
    assert prior_quantile("gaussian", torch.tensor([0.975])).item() == pytest.approx(1.959964, abs=1e-4)
    with pytest.raises(ValueError, match="unknown code prior"):
        prior_grid("laplace", 3)


def test_spread_as_prior_keeps_the_order_and_takes_the_priors_quantiles():
    codes = torch.tensor([[10.0, 0.0], [-3.0, 2.0], [0.5, 1.0], [7.0, -5.0]])
    out = spread_as_prior(codes, "uniform")
    assert out[:, 0].tolist() == [0.75, -0.75, -0.25, 0.25]
    assert out[:, 1].tolist() == [-0.25, 0.75, 0.25, -0.75]


def test_codes_drawn_for_rollouts_have_the_kinds_shapes_and_the_priors_support():
    gen = torch.Generator().manual_seed(0)
    idx, vec = draw_codes("discrete", "uniform", 5, width=3, generator=gen)
    assert idx.shape == (5,) and vec.shape == (5, 3) and torch.equal(vec.argmax(-1), idx)
    c, v = draw_codes("continuous", "uniform", 1000, width=2, generator=gen)
    assert c.shape == (1000, 2) and torch.equal(c, v) and c.abs().max() <= 1 and c.min() < -0.9
    g = sample_prior("gaussian", 4000, 1, gen)
    assert abs(g.mean().item()) < 0.1 and abs(g.std().item() - 1) < 0.1
    # discrete draws are those of before continuous codes existed
    gen_a, gen_b = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(draw_codes("discrete", "uniform", 7, width=4, generator=gen_a)[0], torch.randint(4, (7,),
                                                                                                        generator=gen_b))
