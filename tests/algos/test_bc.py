import csv
import dataclasses
import math

import pytest
import torch

from pomil.algos.bc import BCConfig, train_bc
from pomil.api import TrainedPolicy
from pomil.eval.circles import evaluate_circles
from pomil.training import load_checkpoint


def _rows(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def _cfg(demos_path, out, **kw):
    base = dict(demos=str(demos_path), out=str(out), progress=False, log_every=10)
    base.update(kw)
    return BCConfig(**base)


@pytest.mark.parametrize("policy", ["mlp", "gru"])
def test_bc_loss_falls_and_rollouts_stay_on_the_circles(policy, demos_path, tmp_path):
    ckpt = train_bc(_cfg(demos_path, tmp_path / policy, policy=policy, iterations=250, hidden_size=64))
    rows = _rows(tmp_path / policy)
    first, last = float(rows[0]["bc/nll"]), float(rows[-1]["bc/nll"])
    assert rows[0]["iteration"] == "1" and rows[-1]["iteration"] == "250"
    assert last < first - 1.0, (first, last)
    metrics, _ = evaluate_circles(TrainedPolicy.load(ckpt), episodes_per_code=100, seed=0)
    # Both modes appear; few trajectories leave the circles altogether.
    assert metrics["overall_none_share"] <= 0.2, metrics
    assert min(metrics["overall_mode_share"]) >= 0.15, metrics


def test_same_seed_same_run(demos_path, tmp_path):
    a = train_bc(_cfg(demos_path, tmp_path / "a", iterations=30, hidden_size=32, seed=7))
    b = train_bc(_cfg(demos_path, tmp_path / "b", iterations=30, hidden_size=32, seed=7))
    c = train_bc(_cfg(demos_path, tmp_path / "c", iterations=30, hidden_size=32, seed=8))
    pa, pb, pc = (load_checkpoint(p)["policy"] for p in (a, b, c))
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    assert any(not torch.equal(pa[k], pc[k]) for k in pa)
    strip = lambda rows: [{k: v for k, v in r.items() if not k.startswith("time/")} for r in rows]  # noqa: E731
    assert strip(_rows(tmp_path / "a")) == strip(_rows(tmp_path / "b"))


def test_resume_continues_the_same_run(demos_path, tmp_path):
    full = train_bc(_cfg(demos_path, tmp_path / "full", iterations=40, hidden_size=32, checkpoint_every=20))
    half = _cfg(demos_path, tmp_path / "split", iterations=20, hidden_size=32, checkpoint_every=20)
    train_bc(half)
    resumed = train_bc(_cfg(demos_path, tmp_path / "split", iterations=40, hidden_size=32, checkpoint_every=20),
                       resume=True)
    pf, pr = load_checkpoint(full), load_checkpoint(resumed)
    assert pr["iteration"] == 40
    for k in pf["policy"]:
        assert torch.equal(pf["policy"][k], pr["policy"][k]), k
    full_rows, split_rows = _rows(tmp_path / "full"), _rows(tmp_path / "split")
    assert [r["iteration"] for r in split_rows] == [r["iteration"] for r in full_rows]
    assert [r["bc/nll"] for r in split_rows] == [r["bc/nll"] for r in full_rows]


def test_resume_refuses_a_changed_config(demos_path, tmp_path):
    from pomil.errors import PomilError

    train_bc(_cfg(demos_path, tmp_path / "r", iterations=5, hidden_size=32))
    with pytest.raises(PomilError, match="changed: batch_episodes"):
        train_bc(_cfg(demos_path, tmp_path / "r", iterations=10, hidden_size=32, batch_episodes=8), resume=True)
    with pytest.raises(PomilError, match="nothing to resume"):
        train_bc(_cfg(demos_path, tmp_path / "empty", iterations=5), resume=True)


def test_checkpoints_load_with_weights_only(demos_path, tmp_path):
    ckpt = train_bc(_cfg(demos_path, tmp_path / "w", iterations=3, hidden_size=16))
    payload = torch.load(ckpt, weights_only=True)
    assert payload["format"] == "pomil-checkpoint" and payload["algo"] == "bc"
    assert payload["env"]["id"] == "pomil/Circles-v0"


def test_balanced_responsibilities_are_a_balanced_soft_assignment():
    from pomil.algos.warm_start import balanced_responsibilities

    # every item prefers code 0, yet each code must take half of them: the two that prefer it least go to code 1
    scores = torch.tensor([[4.0, 3.0, 2.0, 1.0], [0.0, 0.0, 0.0, 0.0]])
    q = balanced_responsibilities(scores)
    torch.testing.assert_close(q.sum(0), torch.ones(4))
    torch.testing.assert_close(q.sum(1), torch.full((2,), 2.0))
    assert q[0, 0] > q[0, 1] > q[0, 2] > q[0, 3] and q[0, 0] > 0.8 and q[0, 3] < 0.2
    # clear clusters keep their hard assignment
    hard = balanced_responsibilities(torch.tensor([[50.0, -50.0, 50.0, -50.0], [-50.0, 50.0, -50.0, 50.0]]))
    torch.testing.assert_close(hard, torch.tensor([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]]), atol=1e-4, rtol=0)


def test_unroll_every_code_agrees_with_unroll_per_code():
    from pomil.nn.policy import GaussianPolicy, PolicyArch

    torch.manual_seed(0)
    policy = GaussianPolicy(PolicyArch(3, 2, "gru", 16, num_codes=3))
    T, N = 7, 5
    obs, prev = torch.randn(T, N, 3), torch.randn(T, N, 2)
    starts = torch.zeros(T, N, dtype=torch.bool)
    starts[0] = True
    every = policy.unroll_every_code(obs, prev, policy.initial_state(N), starts)
    assert every.mean.shape == (3, T, N, 2)
    for k in range(3):
        one = torch.nn.functional.one_hot(torch.full((N,), k), 3).float()
        dist, _ = policy.unroll(obs, prev, policy.initial_state(N), starts, codes=one)
        torch.testing.assert_close(every.mean[k], dist.mean)
        torch.testing.assert_close(every.stddev[k], dist.stddev)


def _two_clusters():
    """Episodes that look the same but half act +0.6 and half -0.6 (data, prev actions, cluster per episode)."""
    from pomil.data import PaddedEpisodes
    from pomil.nn.policy import shift_actions

    g = torch.Generator().manual_seed(0)
    T, E = 12, 64
    cluster = torch.arange(E) % 2
    obs = torch.randn(T, E, 2, generator=g)
    noise = 0.05 * torch.randn(T, E, 1, generator=g)
    actions = (torch.where(cluster == 0, 0.6, -0.6).view(1, E, 1) + noise).expand(T, E, 2).contiguous()
    return PaddedEpisodes(obs, actions, torch.ones(T, E, dtype=torch.bool)), shift_actions(actions), cluster


def test_dataset_assignment_keeps_an_over_sampled_cluster_on_its_own_code():
    """A batch of 6 episodes of one cluster and 2 of the other: balancing within the batch
    hands 2 of the 6 to the other cluster's code; the dataset-wide assignment does not."""
    from pomil.algos.warm_start import (
        MixtureAssignment,
        balanced_responsibilities,
        demonstration_pass,
        mixture_bc_loss,
    )
    from pomil.nn.policy import GaussianPolicy, PolicyArch

    torch.manual_seed(0)
    data, prev, cluster = _two_clusters()
    policy = GaussianPolicy(PolicyArch(2, 2, "mlp", 32, num_codes=2))
    ll = demonstration_pass(policy, data, prev, chunk=5)[0]  # chunked == whole
    torch.testing.assert_close(ll, demonstration_pass(policy, data, prev, chunk=64)[0])
    assert ll.shape == (2, 64)
    # scores as a trained mixture would give them: each cluster far more likely under its own code
    scores = torch.stack([torch.where(cluster == 0, 20.0, -20.0), torch.where(cluster == 0, -20.0, 20.0)])
    idx = torch.cat([torch.nonzero(cluster == 0).flatten()[:6], torch.nonzero(cluster == 1).flatten()[:2]])
    own = torch.nn.functional.one_hot(cluster[idx], 2).T.float()
    per_batch = balanced_responsibilities(scores[:, idx])
    wrong = per_batch * (1 - own)
    assert wrong.sum().item() == pytest.approx(2.0, abs=1e-3)  # two episodes' worth forced onto the other code
    torch.testing.assert_close(wrong[1, :6], torch.full((6,), 1 / 3), atol=1e-3, rtol=0)  # a third of each of the 6
    torch.testing.assert_close(balanced_responsibilities(scores)[:, idx], own, atol=1e-4, rtol=0)
    # MixtureAssignment recomputes from the policy every `refresh` calls and otherwise keeps its answer
    assignment = MixtureAssignment(data, prev, refresh=3)
    first = assignment.update(policy)
    torch.testing.assert_close(first, balanced_responsibilities(ll))
    torch.testing.assert_close(first.argmax(0), mixture_bc_loss(policy, data, prev)[1].argmax(0))
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.5)
    assert assignment.update(policy) is first and assignment.update(policy) is first
    assert not torch.equal(assignment.update(policy), first)
    # its state (what a checkpoint keeps): a new one refreshes at the same calls from the same answer
    state = assignment.state_dict()
    assert int(state["calls"]) == 4 and torch.equal(state["responsibilities"], assignment.responsibilities)
    again = MixtureAssignment(data, prev, refresh=3)
    again.load_state_dict(state)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.5)
    assert all(torch.equal(again.update(policy), state["responsibilities"]) for _ in range(2))  # calls 4, 5: kept
    torch.testing.assert_close(again.update(policy),  # call 6: recomputed from the policy
                               balanced_responsibilities(demonstration_pass(policy, data, prev)[0]), rtol=0, atol=0)
    empty = MixtureAssignment(data, prev).state_dict()
    assert int(empty["calls"]) == 0 and empty["responsibilities"].numel() == 0
    with pytest.raises(ValueError, match="covers 5 episodes, not the 64"):
        again.load_state_dict({"calls": torch.tensor(1), "responsibilities": torch.ones(2, 5)})
    with pytest.raises(ValueError, match="damaged"):
        again.load_state_dict({"calls": torch.tensor(-1), "responsibilities": torch.ones(2, 64)})


@pytest.mark.parametrize("balance", ["batch", "dataset"])
def test_mixture_bc_gives_each_cluster_of_episodes_its_own_code(balance):
    """Episodes look the same but half act +0.6 and half -0.6: a code per episode must
    explain the difference, and the mixture likelihood gives each cluster its own code."""
    from pomil.algos.warm_start import MixtureAssignment, bc_step, most_likely_codes
    from pomil.nn.policy import GaussianPolicy, PolicyArch

    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    data, prev, cluster = _two_clusters()
    obs, T, E = data.observations, *data.mask.shape
    policy = GaussianPolicy(PolicyArch(2, 2, "mlp", 32, num_codes=2))
    opt = torch.optim.Adam(policy.parameters(), lr=3e-3)
    assignment = MixtureAssignment(data, prev) if balance == "dataset" else None
    for _ in range(150):
        stats = bc_step(policy, opt, data, prev_actions=prev, batch_episodes=32, generator=g, num_codes=2,
                        mixture=True, assignment=assignment)
    codes = most_likely_codes(policy, data, prev)
    agreement = (codes == cluster).float().mean().item()
    assert max(agreement, 1 - agreement) == 1.0, codes  # codes are a relabelling of the clusters
    assert stats["bc/responsibility_max"] > 0.99
    with torch.no_grad():
        mean = policy.unroll_every_code(obs, prev, policy.initial_state(E), torch.zeros(T, E, dtype=torch.bool)).mean
    per_code = sorted(mean[k].mean().item() for k in range(2))
    assert per_code[0] == pytest.approx(-0.6, abs=0.05) and per_code[1] == pytest.approx(0.6, abs=0.05)


@pytest.mark.parametrize("encoder", ["gru", "lstm", "attention"])
def test_windows_from_stored_states_give_the_features_of_one_unroll(encoder):
    """Episodes of 23 steps (one 17 long) in windows of 5: the pass's features are one unroll's, and each
    window drawn, unrolled from its stored state, gives exactly that unroll's features at its steps."""
    from pomil.algos.warm_start import demo_windows, episode_features, window_features
    from pomil.data import PaddedEpisodes
    from pomil.nn.policy import GaussianPolicy, PolicyArch, shift_actions

    torch.manual_seed(0)
    T, E, window = 23, 6, 5
    obs, actions = torch.randn(T, E, 3), torch.randn(T, E, 2)
    mask = torch.ones(T, E, dtype=torch.bool)
    mask[17:, 2] = False
    data, prev = PaddedEpisodes(obs, actions, mask), shift_actions(actions)
    policy = GaussianPolicy(PolicyArch(3, 2, encoder, 16, num_codes=2, obs_delta=True, context=7))
    with torch.no_grad():
        whole = episode_features(policy, obs, prev, mask)
        feats, states = window_features(policy, obs, prev, mask=mask, window=window)
        torch.testing.assert_close(feats, whole, rtol=1e-5, atol=1e-6)
        assert states.shape[:2] == (5, E)  # ceil(23 / 5) window starts
        batch, w_prev, h0, starts, episode = demo_windows(data, prev, states, count=40, window=window,
                                                          generator=torch.Generator().manual_seed(1))
        got = policy.features(batch.observations, w_prev, h0, starts)[0]
    assert len(episode) == 29  # 40 asked, 29 windows hold demonstrated steps (episode 2 has 4 of 5)
    for n in range(len(episode)):  # the window's index: the stored state it starts from
        j = 0 if starts[0, n] else int((h0[n] - states[:, episode[n]]).abs().sum(1).argmin())
        steps = torch.arange(j * window, min((j + 1) * window, T))
        valid = batch.mask[:len(steps), n]
        assert valid.any() and torch.equal(valid, mask[steps, episode[n]]) and not batch.mask[len(steps):, n].any()
        torch.testing.assert_close(got[:len(steps), n][valid], whole[steps, episode[n]][valid], rtol=1e-5, atol=1e-6)


def test_the_whole_set_assignment_refreshes_every_10_steps_or_once_per_pass():
    from pomil.algos.adversarial import AdversarialConfig
    from pomil.algos.warm_start import mixture_assignment
    from pomil.data import PaddedEpisodes

    def episodes(n):
        return PaddedEpisodes(torch.zeros(3, n, 2), torch.zeros(3, n, 2), torch.ones(3, n, dtype=torch.bool))

    cfg = AdversarialConfig()  # warm_start_batch 64
    assert mixture_assignment(cfg, episodes(600), torch.zeros(3, 600, 2), True).refresh == 10
    assert mixture_assignment(cfg, episodes(2000), torch.zeros(3, 2000, 2), True).refresh == 32  # ceil(2000 / 64)
    assert mixture_assignment(cfg, episodes(600), torch.zeros(3, 600, 2),
                              False) is None  # no mixture: nothing to assign
    assert mixture_assignment(AdversarialConfig(mixture_balance="batch"), episodes(600), torch.zeros(3, 600, 2),
                              True) is None


def _constant_mean_policy(num_codes=0, offsets=None):
    """An MLP policy whose mean is (0.5, -1), plus ``offsets[k]`` on the first dimension under code k:
    a zeroed encoder (features 0), the code's embedding on feature 0, a linear mean head reading it."""
    from pomil.nn.policy import GaussianPolicy, PolicyArch

    policy = GaussianPolicy(PolicyArch(2, 2, "mlp", 8, num_codes=num_codes))
    policy.mean = torch.nn.Linear(8, 2)
    with torch.no_grad():
        for p in policy.encoder.parameters():
            p.zero_()
        policy.mean.weight.zero_()
        policy.mean.bias.copy_(torch.tensor([0.5, -1.0]))
        if num_codes:
            policy.code_embed.weight.zero_()
            policy.code_embed.weight[0] = torch.tensor(offsets)
            policy.mean.weight[0, 0] = 1.0
    return policy


def test_fit_log_std_is_the_masked_mean_squared_error_per_dimension():
    """Mean (0.5, -1) everywhere; the padded steps' actions (1000) must not count."""
    from pomil.algos.warm_start import fit_log_std
    from pomil.data import PaddedEpisodes
    from pomil.nn.policy import shift_actions

    actions = torch.tensor([[[0.5 + 0.3, -1.0], [0.5 - 0.1, -1.0 + 2.0]],
                            [[0.5 + 0.2, -1.0 - 1.0], [1000.0, 1000.0]]])  # (T 2, E 2, 2); step (1, 1) padded
    mask = torch.tensor([[True, True], [True, False]])
    data = PaddedEpisodes(torch.zeros(2, 2, 2), actions, mask)
    policy = _constant_mean_policy()
    stats = fit_log_std(policy, data, shift_actions(actions))
    expected = 0.5 * torch.tensor([(0.09 + 0.01 + 0.04) / 3, (0.0 + 4.0 + 1.0) / 3]).log()
    torch.testing.assert_close(policy.log_std.data, expected)
    assert stats["bc/log_std"] == pytest.approx(expected.mean().item())


def test_fit_log_std_weights_each_code_by_its_responsibility():
    """Two codes with means 0.5 + 2 and 0.5 - 2 on the first dimension; episode 0 acts 2.6 and
    episode 1 acts -1.3: with the mixture each is explained by its nearer code (errors 0.1 and
    0.2), without it (random codes) by both alike."""
    from pomil.algos.warm_start import fit_log_std, mixture_bc_loss
    from pomil.data import PaddedEpisodes
    from pomil.nn.policy import shift_actions

    actions = torch.tensor([[[2.6, -1.0], [-1.3, -1.0]]]).expand(3, 2, 2).contiguous()  # (T 3, E 2, 2)
    data = PaddedEpisodes(torch.zeros(3, 2, 2), actions, torch.ones(3, 2, dtype=torch.bool))
    prev = shift_actions(actions)
    policy = _constant_mean_policy(2, [2.0, -2.0])
    with torch.no_grad():
        policy.log_std.fill_(-2.0)  # sharp enough that each episode's responsibility is all on its nearer code
    resp = mixture_bc_loss(policy, data, prev)[1]
    torch.testing.assert_close(resp, torch.eye(2), atol=1e-6, rtol=0)
    stats = fit_log_std(policy, data, prev, mixture=True)
    assert policy.log_std[0].item() == pytest.approx(0.5 * math.log((0.1 ** 2 + 0.2 ** 2) / 2), abs=1e-5)
    assert policy.log_std[1].item() == pytest.approx(0.5 * math.log(1e-12), abs=1e-3)  # no error: the floor
    assert stats["bc/nll"] == pytest.approx(mixture_bc_loss(policy, data, prev)[0].item())
    fit_log_std(policy, data, prev, mixture=False)  # every code alike: errors 0.1, 4.1 (episode 0), 3.8, 0.2
    assert policy.log_std[0].item() == pytest.approx(0.5 * math.log((0.01 + 4.1 ** 2 + 3.8 ** 2 + 0.04) / 4), abs=1e-5)


def test_the_warm_start_steps_its_log_std_faster_and_decays_to_zero():
    """Adam's log-std group runs at warm_start_log_std_lr_scale x warm_start_lr; the rate falls linearly
    to 0 over the steps (the fast-warm-start preset), after a linear rise over warm_start_lr_warmup of them
    (deep-warm-start and the defaults, whose log std runs at 1x and is not fitted); paper-text: 1e-3, 1x, no
    decay, no fit."""
    from pomil.algos.adversarial import AdversarialConfig
    from pomil.algos.warm_start import warm_start_optimizer
    from pomil.config import from_dict
    from pomil.nn.policy import GaussianPolicy, PolicyArch

    policy = GaussianPolicy(PolicyArch(2, 2, "gru", 8, num_codes=2))
    cfg = from_dict(AdversarialConfig, {"preset": "fast-warm-start"})
    assert (cfg.warm_start_iterations, cfg.warm_start_lr, cfg.warm_start_log_std_lr_scale) == (600, 3e-3, 10.0)
    assert (cfg.warm_start_lr_decay, cfg.warm_start_fit_log_std) == (True, True)
    opt, decay = warm_start_optimizer(policy, dataclasses.replace(cfg, warm_start_iterations=4))
    assert [g["lr"] for g in opt.param_groups] == [3e-3, pytest.approx(3e-2)]
    assert opt.param_groups[1]["params"] == [policy.log_std]
    assert sum(p.numel() for g in opt.param_groups for p in g["params"]) == sum(p.numel() for p in policy.parameters())
    lrs = []
    for _ in range(4):
        opt.step()
        decay.step()
        lrs.append(opt.param_groups[0]["lr"])
    assert lrs == pytest.approx([2.25e-3, 1.5e-3, 0.75e-3, 0.0])
    opt, decay = warm_start_optimizer(policy, dataclasses.replace(cfg, warm_start_lr_decay=False))
    opt.step()
    decay.step()
    assert opt.param_groups[0]["lr"] == 3e-3
    for plain in (from_dict(AdversarialConfig, {"preset": "paper-text"}),
                  from_dict(AdversarialConfig, {"preset": "long-warm-start"})):
        assert (plain.warm_start_lr, plain.warm_start_lr_decay, plain.warm_start_log_std_lr_scale,
                plain.warm_start_fit_log_std) == (1e-3, False, 1.0, False)
    # deep-warm-start: 10 steps, the first 2 rising to the peak, then the decay to 0 over the other 8
    deep = from_dict(AdversarialConfig, {"preset": "deep-warm-start"})
    opt, schedule = warm_start_optimizer(policy, dataclasses.replace(deep, warm_start_iterations=10))
    lrs = []
    for _ in range(10):
        lrs.append(opt.param_groups[0]["lr"])
        assert opt.param_groups[1]["lr"] == pytest.approx(10 * lrs[-1])  # the log std's, at 10x throughout
        opt.step()
        schedule.step()
    assert lrs == pytest.approx([5e-3, 1e-2, 1e-2, 8.75e-3, 7.5e-3, 6.25e-3, 5e-3, 3.75e-3, 2.5e-3, 1.25e-3])
    # the defaults: the same schedule, the log std's group at the network's rate
    opt, schedule = warm_start_optimizer(policy, dataclasses.replace(AdversarialConfig(), warm_start_iterations=10))
    default_lrs = []
    for _ in range(10):
        default_lrs.append(opt.param_groups[0]["lr"])
        assert opt.param_groups[1]["lr"] == pytest.approx(default_lrs[-1])  # the log std at 1x
        opt.step()
        schedule.step()
    assert default_lrs == pytest.approx(lrs)
