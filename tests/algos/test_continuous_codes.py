"""Continuous latent codes: shapes, the posterior's likelihood, the warm start, config errors."""

import math

import numpy as np
import pytest
import torch

from pomil.algos.adversarial import AdversarialConfig, build_modules, posterior_loss, rewards, train_adversarial
from pomil.algos.warm_start import EpisodeCodes, principal_components
from pomil.api import TrainedPolicy
from pomil.demos import record_circles_demos
from pomil.envs import executed_actions_fn, make_vec_env
from pomil.envs.circles import make_spec
from pomil.errors import ConfigError
from pomil.eval.metrics import spearman
from pomil.rl.collect import collect
from pomil.training import load_checkpoint


@pytest.fixture(scope="module")
def radius_demos():
    return record_circles_demos(make_spec("one", 5.0), 60, seed=0, radius_range=(3.0, 7.0))


@pytest.fixture(scope="module")
def radius_demos_path(radius_demos, tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "radius.npz"
    radius_demos.save(path)
    return path


def _cfg(demos_path, out, **kw):
    base = dict(demos=str(demos_path), out=str(out), iterations=2, num_envs=8, hidden_size=16, critic_steps=1,
                critic_batch=8, ppo_epochs=1, minibatches=2, eval_every=2, eval_episodes=2, progress=False,
                log_every=1, warm_start_iterations=20, posterior_init_iterations=5, warm_start_batch=16,
                code_kind="continuous", code_dim=2)
    base.update(kw)
    return AdversarialConfig(**base)


def test_networks_take_and_give_continuous_codes_of_their_dimension(radius_demos_path):
    m, arch = build_modules(_cfg(radius_demos_path, "unused"), 2, 2, num_codes=2, device="cpu")
    assert arch.continuous_codes and arch.num_codes == 2 and arch.code_prior == "uniform"
    assert m.policy.code_embed.in_features == 2
    assert m.posterior.out_dim == 4  # mean and log std per dimension
    env = make_vec_env("pomil/Circles-v0", {}, 5, device="cpu")
    gen = torch.Generator().manual_seed(0)
    roll, next_values, codes, _ = collect(env, m.policy, m.value, num_codes=2,
                                          execute=executed_actions_fn("pomil/Circles-v0", {}),
                                          generator=gen, device=torch.device("cpu"), code_kind="continuous",
                                          code_prior="uniform")
    assert codes.shape == (5, 2) and codes.dtype == torch.float32 and codes.abs().max() <= 1
    assert roll.codes.shape == (33, 5, 2) and torch.equal(roll.codes[7], codes)
    out, _ = m.posterior.unroll(roll.observations, roll.prev_actions, m.posterior.initial_state(5), roll.starts,
                                extra=roll.executed_actions)
    assert out.shape == (33, 5, 4)
    r, stats = rewards(m, roll, codes, cfg=_cfg(radius_demos_path, "unused"), objective="wasserstein")
    assert r.shape == (33, 5) and math.isfinite(stats["reward/log_posterior"])


def test_continuous_posterior_loss_and_reward_are_the_gaussians_log_likelihood_on_a_constructed_case(
        radius_demos_path):
    """A posterior whose last layer is zero but for its bias outputs mean (0.5, -1) and log std
    (0, log 2) at every step; for code c = (1, 1) the log-likelihood per step is
    log N(1; 0.5, 1) + log N(1; -1, 2) = -0.125 - 0.5 - log 2 - log(2 pi)."""
    cfg = _cfg(radius_demos_path, "unused", normalize_reward=False, mi_weight=2.0)
    m, _ = build_modules(cfg, 2, 2, num_codes=2, device="cpu")
    with torch.no_grad():
        last = m.posterior.mlp[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0.5, -1.0, 0.0, math.log(2.0)]))
        crit_last = m.critic.mlp[-1]
        crit_last.weight.zero_()
        crit_last.bias.fill_(0.25)
    env = make_vec_env("pomil/Circles-v0", {}, 3, device="cpu")
    roll, _, _, _ = collect(env, m.policy, m.value, num_codes=2, execute=executed_actions_fn("pomil/Circles-v0", {}),
                            generator=torch.Generator().manual_seed(1), device=torch.device("cpu"),
                            code_kind="continuous")
    codes = torch.ones(3, 2)
    expected = -0.125 - 0.5 - math.log(2.0) - math.log(2 * math.pi)
    loss, stats = posterior_loss(m.posterior, roll, codes.expand(33, 3, 2), "continuous")
    assert loss.item() == pytest.approx(-expected, abs=1e-5)
    assert stats["posterior/code_error"] == pytest.approx((0.5 + 2.0) / 2, abs=1e-6)
    assert stats["posterior/log_std"] == pytest.approx(math.log(2.0) / 2, abs=1e-6)
    r, _ = rewards(m, roll, codes, cfg=cfg, objective="wasserstein")
    assert torch.allclose(r, torch.full((33, 3), 0.25 + 2.0 * expected), atol=1e-5)


def test_discrete_posterior_loss_is_unchanged_by_the_code_kind_argument(radius_demos_path):
    cfg = _cfg(radius_demos_path, "unused", code_kind="discrete", code_dim=1)
    m, _ = build_modules(cfg, 2, 2, num_codes=3, device="cpu")
    env = make_vec_env("pomil/Circles-v0", {}, 4, device="cpu")
    roll, _, idx, _ = collect(env, m.policy, m.value, num_codes=3, execute=executed_actions_fn("pomil/Circles-v0", {}),
                              generator=torch.Generator().manual_seed(2), device=torch.device("cpu"))
    logits, _ = m.posterior.unroll(roll.observations, roll.prev_actions, m.posterior.initial_state(4), roll.starts,
                                   extra=roll.executed_actions)
    loss, _ = posterior_loss(m.posterior, roll, idx.expand(33, 4))
    manual = torch.nn.functional.cross_entropy(logits.flatten(0, 1), idx.expand(33, 4).flatten())
    assert loss.item() == pytest.approx(manual.item(), abs=1e-6)


def test_episode_codes_start_at_the_principal_components_spread_as_the_prior(radius_demos):
    data = radius_demos.padded("cpu")
    radii = np.asarray(radius_demos.metadata["episode_radii"])
    assert abs(spearman(principal_components(data, 1)[:, 0].numpy(), radii)) > 0.95
    codes = EpisodeCodes(data, 2, "uniform")
    e = radius_demos.num_episodes
    for j in range(2):  # every dimension holds exactly the prior's quantiles at (i + 0.5) / E
        assert torch.allclose(codes.codes[:, j].sort().values, (torch.arange(e) + 0.5) / e * 2 - 1, atol=1e-6)
    with torch.no_grad():
        codes.codes.mul_(7.0).add_(3.0)
    codes.spread_()
    assert codes.codes.abs().max() < 1


def test_continuous_warm_start_fits_the_episode_codes_and_the_run_resumes_them(radius_demos_path, tmp_path):
    a = train_adversarial(_cfg(radius_demos_path, tmp_path / "a", iterations=2, checkpoint_every=1))
    b = train_adversarial(_cfg(radius_demos_path, tmp_path / "b", iterations=1, checkpoint_every=1))
    b = train_adversarial(_cfg(radius_demos_path, tmp_path / "b", iterations=2, checkpoint_every=1), resume=True)
    na, nb = load_checkpoint(a)["nets"], load_checkpoint(b)["nets"]
    assert set(na) == {"policy", "value", "critic", "posterior", "episode_codes"}
    for net in na:
        for k in na[net]:
            assert torch.equal(na[net][k], nb[net][k]), (net, k)
    codes = na["episode_codes"]["codes"]
    assert codes.shape == (60, 2) and codes.abs().max() < 1
    ckpt = load_checkpoint(a)
    assert ckpt["policy_arch"]["code_kind"] == "continuous" and ckpt["policy_arch"]["num_codes"] == 2
    policy = TrainedPolicy.load(a)
    assert (policy.num_codes, policy.code_dim, policy.code_prior) == (0, 2, "uniform")


def test_infogails_random_code_warm_start_works_with_continuous_codes_too(radius_demos_path, tmp_path):
    ckpt = train_adversarial(_cfg(radius_demos_path, tmp_path / "r", learner="infogail", warm_start_codes="random",
                                  code_prior="gaussian", code_dim=1, warm_start_fit_log_std=True))
    nets = load_checkpoint(ckpt)["nets"]
    assert "episode_codes" not in nets
    assert TrainedPolicy.load(ckpt).code_prior == "gaussian"


@pytest.mark.parametrize("changes, text", [
    ({"num_codes": 3}, "config key 'num_codes': discrete codes only, got 3 with code_kind continuous"),
    ({"num_codes": 0}, "config key 'num_codes': discrete codes only, got auto"),
    ({"code_kind": "discrete", "code_dim": 2}, "config key 'code_dim': continuous codes only"),
    ({"code_kind": "discrete", "code_dim": 1, "code_prior": "gaussian"},
     "config key 'code_prior': continuous codes only"),
    ({"code_dim": 0}, "config key 'code_dim'"),
])
def test_invalid_code_settings_are_one_line_config_errors(changes, text, radius_demos_path):
    with pytest.raises(ConfigError, match=text.replace("(", r"\(")):
        _cfg(radius_demos_path, "unused", **changes)


def test_gail_ignores_the_code_kind(radius_demos_path, tmp_path):
    ckpt = train_adversarial(_cfg(radius_demos_path, tmp_path / "g", learner="gail", iterations=1, eval_every=0))
    policy = TrainedPolicy.load(ckpt)
    assert (policy.num_codes, policy.code_dim) == (0, 0)
    assert set(load_checkpoint(ckpt)["nets"]) == {"policy", "value", "critic"}


@pytest.mark.slow
def test_default_continuous_warm_start_maps_the_code_monotonically_to_the_radius(tmp_path):
    """The warm start alone (default settings, 400 episodes of radius 3-7): |Spearman| >= 0.9 (measured 0.994)."""
    from pomil.eval.circles import evaluate_code_radius

    path = tmp_path / "radius.npz"
    record_circles_demos(make_spec("one", 5.0), 400, seed=0, radius_range=(3.0, 7.0)).save(path)
    ckpt = train_adversarial(AdversarialConfig(demos=str(path), out=str(tmp_path / "run"), iterations=0,
                                               code_kind="continuous", progress=False, eval_every=0))
    metrics, _ = evaluate_code_radius(TrainedPolicy.load(ckpt), episodes_per_value=10, seed=7)
    assert abs(metrics["spearman"]) >= 0.9
    lo, hi = metrics["radius_covered"]
    assert lo < 4.0 and hi > 6.0


def test_principal_components_of_a_single_episode_are_zero_codes_not_nan(radius_demos):
    one = radius_demos.padded("cpu").select(torch.tensor([0]))
    scores = principal_components(one, 2)
    assert scores.shape == (1, 2) and torch.equal(scores, torch.zeros(1, 2))
    assert EpisodeCodes(one, 2, "gaussian").codes.abs().max() == 0  # the prior's median
