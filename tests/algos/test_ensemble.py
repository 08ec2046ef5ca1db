"""Policies acting as one (``policy_members``): the ensemble's actions, its warm start and its codes' renaming."""

import csv
import subprocess
import sys

import pytest
import torch

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.algos.warm_start import code_renaming, most_likely_codes, rename_codes
from pomil.api import TrainedPolicy
from pomil.data import Demonstrations
from pomil.envs import executed_actions_fn
from pomil.errors import ConfigError
from pomil.nn.policy import EnsemblePolicy, GaussianPolicy, PolicyArch, make_policy, shift_actions
from pomil.training import load_checkpoint


def _inputs(n=4, steps=3, obs_dim=3, act_dim=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(steps, n, obs_dim, generator=g), torch.randn(steps, n, act_dim, generator=g)


@pytest.mark.parametrize("tanh_mean", [False, True])
def test_the_ensemble_acts_with_the_mean_of_its_members_means(tanh_mean):
    torch.manual_seed(0)
    arch = PolicyArch(3, 2, hidden_size=8, num_codes=2, tanh_mean=tanh_mean, members=3)
    ensemble = make_policy(arch)
    assert isinstance(ensemble, EnsemblePolicy) and type(make_policy(PolicyArch(3, 2))) is GaussianPolicy
    with torch.no_grad():
        ensemble.log_std.fill_(-0.7)
    obs, prev = _inputs()
    codes = torch.eye(2)[torch.tensor([0, 1, 1, 0])]
    h = ensemble.initial_state(4)
    assert h.shape == (4, 3 * ensemble.members[0].initial_state(1).shape[-1])
    own = [p.initial_state(4) for p in ensemble.members]
    for t in range(3):
        start = torch.full((4,), t == 0)
        dist, h = ensemble.step(obs[t], prev[t], h, start, codes)
        means = []
        for i, member in enumerate(ensemble.members):
            d, own[i] = member.step(obs[t], prev[t], own[i], start, codes)
            means.append(d.mean)
        torch.testing.assert_close(dist.mean, torch.stack(means).mean(0), rtol=0, atol=1e-6)
        torch.testing.assert_close(h, torch.cat(own, dim=-1), rtol=0, atol=0)
        assert torch.equal(dist.stddev, torch.full((4, 2), -0.7).exp())
    # an unroll over the block is the same computation as the steps
    unrolled, _ = ensemble.unroll(obs, prev, ensemble.initial_state(4), torch.arange(3).unsqueeze(1).expand(3, 4) == 0,
                                  codes)
    torch.testing.assert_close(unrolled.mean[-1], dist.mean, rtol=0, atol=1e-6)
    every = ensemble.unroll_every_code(obs, prev, ensemble.initial_state(4), torch.zeros(3, 4, dtype=torch.bool))
    assert every.mean.shape == (2, 3, 4, 2)


def test_copies_of_one_policy_act_as_that_policy():
    torch.manual_seed(1)
    ensemble = make_policy(PolicyArch(3, 2, hidden_size=8, members=2))
    ensemble.members[1].load_state_dict(ensemble.members[0].state_dict())
    with torch.no_grad():
        ensemble.log_std.copy_(ensemble.members[0].log_std)
    obs, prev = _inputs(seed=2)
    starts = torch.zeros(3, 4, dtype=torch.bool)
    a, _ = ensemble.unroll(obs, prev, ensemble.initial_state(4), starts)
    b, _ = ensemble.members[0].unroll(obs, prev, ensemble.members[0].initial_state(4), starts)
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-6)


def test_the_ensembles_architecture_is_recorded_only_when_it_is_one():
    assert "members" not in PolicyArch(3, 2).to_dict()
    assert PolicyArch(3, 2, members=3).to_dict()["members"] == 3
    with pytest.raises(ValueError, match="members"):
        PolicyArch(3, 2, members=0)


def test_the_renaming_that_agrees_most_is_found():
    reference = torch.tensor([0, 0, 1, 1, 2, 2, 2])
    swapped = torch.tensor([2, 2, 0, 0, 1, 1, 0])  # code 2 is reference's 0, 0 is 1, 1 is 2; one episode disagrees
    assert code_renaming(reference, swapped, 3).tolist() == [1, 2, 0]
    assert code_renaming(reference, reference, 3).tolist() == [0, 1, 2]
    big = torch.arange(16) % 8  # eight codes: the greedy path
    assert code_renaming(big, (big + 3) % 8, 8).tolist() == [(j - 3) % 8 for j in range(8)]


def test_renaming_a_policys_codes_moves_what_each_code_does():
    torch.manual_seed(3)
    policy = GaussianPolicy(PolicyArch(3, 2, hidden_size=8, num_codes=3))
    obs, prev = _inputs(seed=4)
    feats, _ = policy.features(obs, prev, policy.initial_state(4), torch.zeros(3, 4, dtype=torch.bool))
    before = policy.dist_every_code(feats).mean
    renaming = torch.tensor([2, 0, 1])
    rename_codes(policy, renaming)
    after = policy.dist_every_code(feats).mean
    for j in range(3):
        torch.testing.assert_close(after[renaming[j]], before[j], rtol=0, atol=0)


def _cfg(demos_path, out, **kw):
    base = dict(demos=str(demos_path), out=str(out), iterations=0, num_envs=8, hidden_size=16, critic_steps=1,
                critic_batch=8, ppo_epochs=1, minibatches=2, eval_every=1, eval_episodes=2, progress=False, log_every=1,
                warm_start_iterations=20, posterior_init_iterations=5, policy_warmup_iterations=0, lr=3e-3)
    base.update(kw)
    return AdversarialConfig(**base)


@pytest.fixture(scope="module")
def plain_and_ensemble(demos_path, tmp_path_factory):
    root = tmp_path_factory.mktemp("ensemble")
    plain = load_checkpoint(train_adversarial(_cfg(demos_path, root / "plain")))
    ensemble = load_checkpoint(train_adversarial(_cfg(demos_path, root / "three", policy_members=3)))
    return root, plain, ensemble


def test_the_first_member_is_the_runs_own_warm_start_and_the_others_their_own(plain_and_ensemble):
    _, plain, ensemble = plain_and_ensemble
    weights = ensemble["nets"]["policy"]
    for k, v in plain["nets"]["policy"].items():  # member 1 is the one-policy run's warm start, bit for bit
        assert torch.equal(weights[f"members.0.{k}"], v), k
    for net in ("critic", "value"):  # and the rest of the run starts from the same numbers
        assert all(torch.equal(v, plain["nets"][net][k]) for k, v in ensemble["nets"][net].items()), net
    key = "encoder.core.gru.weight_hh_l0"
    members = [weights[f"members.{i}.{key}"] for i in range(3)]
    assert not torch.equal(members[0], members[1]) and not torch.equal(members[1], members[2])
    assert ensemble["policy_arch"]["members"] == 3 and "members" not in plain["policy_arch"]


def test_the_members_codes_agree_with_the_first_members(plain_and_ensemble, demos_path):
    root, _, ensemble = plain_and_ensemble
    demos = Demonstrations.load(demos_path).padded("cpu")
    expert = demos.__class__(demos.observations, executed_actions_fn("pomil/Circles-v0", {})(demos.actions),
                             demos.mask)
    prev = shift_actions(expert.actions)
    policy = TrainedPolicy.load(root / "three" / "checkpoint.pt").policy
    codes = [most_likely_codes(m, expert, prev) for m in policy.members]
    agreement = min((c == codes[0]).float().mean().item() for c in codes[1:])
    with open(root / "three" / "metrics.csv", newline="") as f:
        row = next(csv.DictReader(f))
    assert float(row["init/bc_member_agreement"]) == pytest.approx(agreement)
    assert agreement > 0.9  # two circles: every member finds the two modes
    for c in codes[1:]:  # no other renaming agrees more
        assert code_renaming(codes[0], c, 2).tolist() == [0, 1]


def test_the_loaded_ensemble_acts_with_its_members_mean_and_trains_as_one(plain_and_ensemble, demos_path, tmp_path):
    root, _, _ = plain_and_ensemble
    loaded = TrainedPolicy.load(root / "three" / "checkpoint.pt")
    members = [TrainedPolicy(m, "infogail-pomdp", loaded.env) for m in loaded.policy.members]
    obs = torch.tensor([[0.1, -0.2], [0.3, 0.0]]).numpy()
    loaded.reset(num_envs=2, codes=[0, 1], seed=0)
    for m in members:
        m.reset(num_envs=2, codes=[0, 1], seed=0)
    torch.testing.assert_close(torch.as_tensor(loaded.act(obs)),
                               torch.stack([torch.as_tensor(m.act(obs)) for m in members]).mean(0), rtol=0, atol=1e-4)
    before = load_checkpoint(root / "three" / "checkpoint.pt")["nets"]["policy"]
    after = load_checkpoint(train_adversarial(_cfg(demos_path, tmp_path / "more", policy_members=3, iterations=1)))
    moved = {k for k, v in after["nets"]["policy"].items() if not torch.equal(v, before[k])}
    assert "log_std" in moved and all(any(k.startswith(f"members.{i}.mean") for k in moved) for i in range(3))


def test_an_ensemble_with_what_it_cannot_combine_is_refused(demos_path, tmp_path):
    with pytest.raises(ConfigError, match="policy_members.*warm_start_restarts 2"):
        _cfg(demos_path, tmp_path / "r", policy_members=2, warm_start_restarts=2)
    with pytest.raises(ConfigError, match="policy_members.*code_kind 'continuous'"):
        _cfg(demos_path, tmp_path / "c", policy_members=2, code_kind="continuous")
    with pytest.raises(ConfigError, match="policy_members.*belief 'shared'"):
        _cfg(demos_path, tmp_path / "s", policy_members=2, belief="shared")
    proc = subprocess.run([sys.executable, "-m", "pomil", "train", "infogail-pomdp", "--demos", str(demos_path),
                           "--policy-members", "2", "--warm-start-restarts", "2", "--out", str(tmp_path / "cli")],
                          capture_output=True, text=True, stdin=subprocess.DEVNULL)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "policy_members" in proc.stderr
    assert not (tmp_path / "cli").exists()
