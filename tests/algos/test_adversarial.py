
import pytest
import torch

from pomil.algos.adversarial import AdversarialConfig, build_modules, critic_loss, posterior_loss, train_adversarial
from pomil.cli import main
from pomil.config import from_dict, to_dict
from pomil.envs import executed_actions_fn, make_vec_env
from pomil.errors import ConfigError
from pomil.nn import heads
from pomil.rl.collect import collect
from pomil.rl.storage import Rollout
from pomil.training import load_checkpoint


def seq_batch(obs, act):
    T, N, _ = obs.shape
    starts = torch.zeros(T, N, dtype=torch.bool)
    starts[0] = True
    prev = torch.cat([torch.zeros_like(act[:1]), act[:-1]])
    return obs, prev, act, starts, torch.ones(T, N, dtype=torch.bool)


def as_rollout(obs, act, codes=None):
    o, prev, a, starts, mask = seq_batch(obs, act)
    T, N, _ = obs.shape
    z = torch.zeros(T, N)
    codes = torch.zeros(T, N, 0) if codes is None else codes
    return Rollout(observations=o, actions=a, prev_actions=prev, starts=starts, codes=codes, log_probs=z, values=z,
                   terminated=starts & False, truncated=starts & False, mask=mask,
                   h0_policy=torch.zeros(N, 1), h0_value=torch.zeros(N, 1))


@pytest.mark.parametrize("encoder, clip, gp, opt", [("gru", 0.01, 0.0, "rmsprop"), ("mlp", 0.0, 10.0, "adam")])
def test_critic_steps_increase_the_wasserstein_estimate(encoder, clip, gp, opt):
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    expert = seq_batch(torch.randn(12, 32, 2, generator=g) + 1.0, torch.randn(12, 32, 2, generator=g))
    policy = as_rollout(torch.randn(12, 32, 2, generator=g) - 1.0, torch.randn(12, 32, 2, generator=g))
    critic = heads.critic(2, 2, encoder, hidden_size=32)
    optim = torch.optim.RMSprop(critic.parameters(),
                                lr=5e-3) if opt == "rmsprop" else torch.optim.Adam(critic.parameters(), lr=1e-3)
    _, first = critic_loss(critic, expert, policy, objective="wasserstein", gp_weight=gp, generator=g)
    for _ in range(30):
        loss, _ = critic_loss(critic, expert, policy, objective="wasserstein", gp_weight=gp, generator=g)
        optim.zero_grad()
        loss.backward()
        optim.step()
        if clip:
            with torch.no_grad():
                for p in critic.parameters():
                    p.clamp_(-clip, clip)
    _, last = critic_loss(critic, expert, policy, objective="wasserstein", gp_weight=0.0, generator=g)
    assert last["critic/wasserstein"] > first["critic/wasserstein"] + 1e-3, (first, last)
    assert last["critic/wasserstein"] > 0


def test_posterior_learns_codes_from_code_dependent_sequences():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    T, N, K = 10, 64, 3
    codes = torch.arange(N) % K
    # the code shows only in the drift of the observations over time, not in any single step
    drift = torch.tensor([-1.0, 0.0, 1.0])[codes]
    noise = torch.randn(T, N, 1, generator=g) * 0.3
    obs = (torch.arange(T).view(T, 1, 1) * drift.view(1, N, 1) * 0.3 + noise).expand(T, N, 2).contiguous()
    act = torch.randn(T, N, 2, generator=g)
    batch = as_rollout(obs, act)
    post = heads.posterior(2, 2, K, encoder="gru", hidden_size=32)
    optim = torch.optim.Adam(post.parameters(), lr=3e-3)
    code_steps = codes.unsqueeze(0).expand(T, -1)
    for _ in range(150):
        loss, stats = posterior_loss(post, batch, code_steps)
        optim.zero_grad()
        loss.backward()
        optim.step()
    assert stats["posterior/loss"] < 0.5 * torch.log(torch.tensor(3.0)).item()
    assert stats["posterior/accuracy"] > 0.8


def _cfg(demos_path, out, **kw):
    base = dict(demos=str(demos_path), out=str(out), iterations=3, num_envs=8, hidden_size=16, critic_steps=1,
                critic_batch=8, ppo_epochs=1, minibatches=2, eval_every=2, eval_episodes=4, progress=False, log_every=1,
                warm_start_iterations=0)
    base.update(kw)
    return AdversarialConfig(**base)


@pytest.mark.parametrize("learner", ["gail", "infogail", "infogail-pomdp"])
@pytest.mark.parametrize("mode", ["sequence", "window"])
def test_every_learner_runs_a_few_iterations_through_the_cli(learner, mode, demos_path, tmp_path):
    out = tmp_path / learner
    code = main(["train", learner, "--demos", str(demos_path), "--out", str(out), "--iterations", "3",
                 "--num-envs", "8",
                 "--hidden-size", "16", "--critic-steps", "1", "--ppo-epochs", "1", "--update-mode", mode,
                 "--window-length", "5", "--eval-every", "2", "--eval-episodes", "4", "--warm-start-iterations", "2",
                 "--no-progress"])
    assert code == 0
    ckpt = load_checkpoint(out / "checkpoint.pt")
    assert ckpt["algo"] == learner and ckpt["iteration"] == 3
    assert ckpt["policy_arch"]["num_codes"] == (0 if learner == "gail" else 2)
    assert ckpt["policy_arch"]["encoder"] == ("gru" if learner == "infogail-pomdp" else "mlp")
    assert (set(ckpt["nets"]) == {"policy", "value", "critic"} | (set() if learner == "gail" else {"posterior"}))
    assert main(["evaluate", str(out), "--episodes-per-code", "3", "--json"]) == 0


def test_adversarial_same_seed_same_run_and_resume(demos_path, tmp_path):
    a = train_adversarial(_cfg(demos_path, tmp_path / "a", iterations=4, checkpoint_every=2))
    b = train_adversarial(_cfg(demos_path, tmp_path / "b", iterations=2, checkpoint_every=2))
    b = train_adversarial(_cfg(demos_path, tmp_path / "b", iterations=4, checkpoint_every=2), resume=True)
    na, nb = load_checkpoint(a)["nets"], load_checkpoint(b)["nets"]
    for net in na:
        for k in na[net]:
            assert torch.equal(na[net][k], nb[net][k]), (net, k)


def test_rollout_feeds_executed_actions_to_critic_and_as_previous_action(demos_path):
    m, _ = build_modules(_cfg(demos_path, "unused", learner="infogail-pomdp"), 2, 2, num_codes=2, device="cpu")
    env = make_vec_env("pomil/Circles-v0", {}, 8)
    roll, _, _, env_rewards = collect(env, m.policy, m.value, num_codes=2,
                                      execute=executed_actions_fn("pomil/Circles-v0", {}),
                                      generator=torch.Generator().manual_seed(0),
                                     device=torch.device("cpu"))
    norms = roll.executed_actions.norm(dim=-1)
    torch.testing.assert_close(norms, torch.ones_like(norms))  # expert demonstrations hold unit vectors too
    assert not torch.allclose(roll.actions.norm(dim=-1), norms)  # the raw Gaussian samples do not
    torch.testing.assert_close(roll.prev_actions[1:], roll.executed_actions[:-1])
    assert (roll.prev_actions[0] == 0).all()
    positions = roll.observations[-1] + roll.executed_actions[-1]  # where the episode ended
    torch.testing.assert_close(positions, env.positions)
    assert env_rewards.shape == (33, 8) and (env_rewards <= 0).all()


def test_bc_warm_start_puts_the_policy_on_the_circles(demos_path, tmp_path):
    from pomil.api import TrainedPolicy
    from pomil.eval.circles import evaluate_circles

    none = {}
    for warm in (0, 250):
        ckpt = train_adversarial(_cfg(demos_path, tmp_path / str(warm), learner="infogail", iterations=1,
                                      hidden_size=64,
                                      warm_start_iterations=warm, num_envs=32, eval_every=0))
        metrics, _ = evaluate_circles(TrainedPolicy.load(ckpt), 20, seed=0)
        none[warm] = metrics["overall_none_share"]
    assert none[250] <= 0.1 < none[0], none


def test_mixture_warm_start_ties_codes_to_modes_and_trains_the_posterior(demos_path, tmp_path):
    """Random codes in the warm start leave the codes meaningless (NMI ~0); the mixture
    warm start gives each circle its own code before any adversarial step, and the
    posterior already tells the codes apart on the policy's own rollouts."""
    import csv

    from pomil.api import TrainedPolicy
    from pomil.eval.circles import evaluate_circles

    nmi = {}
    for codes in ("random", "mixture"):
        ckpt = train_adversarial(_cfg(demos_path, tmp_path / codes, iterations=1, hidden_size=32,
                                      warm_start_iterations=150,
                                      posterior_init_iterations=50, warm_start_codes=codes, eval_every=0))
        nmi[codes] = evaluate_circles(TrainedPolicy.load(ckpt), 100, seed=0)[0]["nmi"]
        with open(tmp_path / codes / "metrics.csv", newline="") as f:
            warm, first = list(csv.DictReader(f))[:2]
    assert nmi["random"] < 0.1 and nmi["mixture"] > 0.5, nmi
    assert warm["iteration"] == "0" and first["iteration"] == "1"  # row 0: the warm start
    assert float(warm["init/bc_code_share_min"]) == pytest.approx(0.5,
                                                                  abs=0.05)  # codes split the demonstrations evenly
    assert float(warm["init/posterior_accuracy"]) > 0.9  # on the demonstrations, labelled by their most likely code
    # on the policy's first rollout: the codes already behave differently
    assert float(first["posterior/accuracy"]) > 0.7


def test_policy_warmup_leaves_the_policy_alone_while_value_critic_and_posterior_learn(demos_path, tmp_path):
    cfg = _cfg(demos_path, tmp_path / "warm", iterations=2, policy_warmup_iterations=2, warm_start_iterations=5,
               eval_every=0)
    warm = load_checkpoint(train_adversarial(cfg))
    start = load_checkpoint(train_adversarial(_cfg(demos_path, tmp_path / "start", iterations=1,
                                                   policy_warmup_iterations=2,
                                                   warm_start_iterations=5, eval_every=0)))
    init = {k: v.clone() for k, v in start["nets"]["value"].items()}
    for k, v in warm["policy"].items():  # same seed, same warm start: the policy is exactly the warm-started one
        torch.testing.assert_close(v, start["policy"][k], rtol=0, atol=0)
    assert any(not torch.equal(v, init[k]) for k, v in warm["nets"]["value"].items())
    moved = train_adversarial(_cfg(demos_path, tmp_path / "moved", iterations=2, warm_start_iterations=5, eval_every=0,
                                   policy_warmup_iterations=0))
    assert any(not torch.equal(v, warm["policy"][k]) for k, v in load_checkpoint(moved)["policy"].items())


def test_bc_weight_adds_the_demonstrations_likelihood_to_the_policy_loss(demos_path, tmp_path):
    import csv

    train_adversarial(_cfg(demos_path, tmp_path / "bc", iterations=2, bc_weight=1.0, warm_start_codes="mixture",
                           eval_every=0))
    with open(tmp_path / "bc" / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert all(r["ppo/bc_nll"] and torch.isfinite(torch.tensor(float(r["ppo/bc_nll"]))) for r in rows)
    with pytest.raises(ValueError, match="bc_weight"):
        _cfg(demos_path, tmp_path / "bad", bc_weight=-1.0)


def test_gan_critic_is_never_weight_clipped(demos_path, tmp_path):
    ckpt = train_adversarial(_cfg(demos_path, tmp_path / "gail", learner="gail", weight_clip=0.01, critic_steps=2))
    assert max(p.abs().max().item() for p in load_checkpoint(ckpt)["nets"]["critic"].values()) > 0.01
    ckpt = train_adversarial(_cfg(demos_path, tmp_path / "wgan", learner="infogail", weight_clip=0.01, critic_steps=2))
    assert max(p.abs().max().item() for p in load_checkpoint(ckpt)["nets"]["critic"].values()) <= 0.01


def test_value_on_policy_is_one_module_trained_once_and_the_retired_flag_reads_as_it(demos_path, tmp_path, capsys):
    cfg = _cfg(demos_path, tmp_path / "s", learner="infogail-pomdp", belief="value-on-policy")
    old = from_dict(AdversarialConfig, {**to_dict(cfg), "belief": "separate", "shared_value_encoder": "true"}, "old")
    assert old == cfg  # preset auto until training starts
    assert "config key 'shared_value_encoder' is retired; read as belief 'value-on-policy'" in capsys.readouterr().err
    assert from_dict(AdversarialConfig, {"shared_value_encoder": False}, "old").belief == "separate"
    with pytest.raises(ConfigError, match="true with belief 'policy' has no equivalent"):
        from_dict(AdversarialConfig, {"shared_value_encoder": True, "belief": "policy"}, "old")
    m, _ = build_modules(cfg, 2, 2, num_codes=2, device="cpu")
    assert m.value.encoder is m.policy.encoder
    ckpt = load_checkpoint(train_adversarial(cfg))
    policy_enc = {k: v for k, v in ckpt["nets"]["policy"].items() if k.startswith("encoder.")}
    for k, v in policy_enc.items():
        assert torch.equal(ckpt["nets"]["value"][k], v)
    # the value optimiser holds only the value head's parameters
    assert len(ckpt["optimizers"]["value"]["param_groups"][0]["params"]) == len(list(m.value.mlp.parameters()))


def test_a_shared_belief_is_one_encoder_stepped_by_every_loss(demos_path, tmp_path):
    def run(belief):
        cfg = _cfg(demos_path, tmp_path / belief, learner="infogail-pomdp", belief=belief, iterations=2,
                   policy_warmup_iterations=5)  # the policy's own optimiser never steps
        return cfg, load_checkpoint(train_adversarial(cfg))

    cfg, shared = run("shared")
    m, _ = build_modules(cfg, 2, 2, num_codes=2, device="cpu")
    assert m.value.encoder is m.critic.encoder is m.posterior.encoder is m.policy.encoder
    enc = {k: v for k, v in shared["nets"]["policy"].items() if k.startswith("encoder.")}
    for net in ("value", "critic", "posterior"):
        assert all(torch.equal(shared["nets"][net][k], v) for k, v in enc.items())
    assert len(shared["optimizers"]["value"]["param_groups"][0]["params"]) == len(list(m.value.mlp.parameters()))
    # same seed, same initial policy: separate, its encoder waits out the warm-up; shared, the critic's and
    # posterior's losses move it
    _, separate = run("separate")
    assert any(not torch.equal(v, separate["nets"]["policy"][k]) for k, v in enc.items())


def test_a_policy_only_belief_gives_feed_forward_value_critic_and_posterior(demos_path, tmp_path):
    cfg = _cfg(demos_path, tmp_path / "p", learner="infogail-pomdp", belief="policy")
    m, _ = build_modules(cfg, 2, 2, num_codes=2, device="cpu")
    recurrent = {name: any(isinstance(x, torch.nn.GRU | torch.nn.GRUCell) for x in net.modules())
                 for name, net in (("policy", m.policy), ("value", m.value), ("critic", m.critic),
                                   ("posterior", m.posterior))}
    assert recurrent == {"policy": True, "value": False, "critic": False, "posterior": False}
    assert load_checkpoint(train_adversarial(cfg))["iteration"] == 3


def test_zero_iterations_is_the_warm_start_alone_evaluated_and_saved(demos_path, tmp_path):
    import csv

    cfg = _cfg(demos_path, tmp_path / "w", learner="infogail-pomdp", iterations=0, warm_start_iterations=20,
               posterior_init_iterations=5)
    ckpt = load_checkpoint(train_adversarial(cfg))
    assert ckpt["iteration"] == 0 and ckpt["env_steps"] == 0
    with open(tmp_path / "w" / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["iteration"] for r in rows] == ["0"] and float(rows[0]["eval/nmi"]) >= 0.0
    assert rows[0]["init/bc_nll"] != ""
    # resuming it is nothing to do; a longer run continues from it, without a second warm start: its
    # first iteration leaves the policy as the warm start left it (policy_warmup_iterations)
    assert load_checkpoint(train_adversarial(cfg, resume=True))["iteration"] == 0
    longer = load_checkpoint(train_adversarial(_cfg(demos_path, tmp_path / "w", learner="infogail-pomdp", iterations=1,
                                                    warm_start_iterations=20, posterior_init_iterations=5),
                                               resume=True))
    assert longer["iteration"] == 1
    assert all(torch.equal(longer["policy"][k], v) for k, v in ckpt["policy"].items())
    with open(tmp_path / "w" / "metrics.csv", newline="") as f:
        assert [r["iteration"] for r in csv.DictReader(f)] == ["0", "1"]
    straight = load_checkpoint(train_adversarial(_cfg(demos_path, tmp_path / "s", learner="infogail-pomdp",
                                                      iterations=1, warm_start_iterations=20,
                                                      posterior_init_iterations=5)))
    for name in ("policy", "value", "critic", "posterior"):  # the same as one run straight through
        assert all(torch.equal(straight["nets"][name][k], v) for k, v in longer["nets"][name].items()), name


def test_noisy_expert_actions_carry_the_policy_noise_and_stay_shifted(demos_path, tmp_path):
    import math

    from pomil.algos.adversarial import noisy_expert_actions
    from pomil.data import Demonstrations
    from pomil.nn.policy import shift_actions

    expert = Demonstrations.load(demos_path).padded()
    m, _ = build_modules(_cfg(demos_path, "unused", learner="infogail-pomdp"), expert.observations.shape[-1],
                         expert.actions.shape[-1], num_codes=2, device="cpu")
    identity = lambda a: a  # noqa: E731
    with torch.no_grad():
        m.policy.log_std.fill_(math.log(0.3))
    act, prev = noisy_expert_actions(expert, m.policy, identity, torch.Generator().manual_seed(0))
    noise = (act - expert.actions)[expert.mask]
    assert abs(noise.std().item() - 0.3) < 0.01 and abs(noise.mean().item()) < 0.01
    torch.testing.assert_close(prev, shift_actions(act))
    again, _ = noisy_expert_actions(expert, m.policy, identity, torch.Generator().manual_seed(0))
    assert torch.equal(act, again)
    clamped, _ = noisy_expert_actions(expert, m.policy, lambda a: a.clamp(-0.1, 0.1), torch.Generator().manual_seed(1))
    assert clamped.abs().max() <= 0.1
    with torch.no_grad():
        m.policy.log_std.fill_(-30.0)
    quiet, _ = noisy_expert_actions(expert, m.policy, identity, torch.Generator().manual_seed(0))
    torch.testing.assert_close(quiet, expert.actions)
    train_adversarial(_cfg(demos_path, tmp_path / "noisy", iterations=2, expert_action_noise=True, eval_every=0))
    assert (tmp_path / "noisy" / "checkpoint.pt").exists()


@pytest.mark.parametrize("demo_steps", [12, 9])
def test_bc_term_through_the_minibatch_unroll_equals_its_own_unroll(demo_steps):
    """The BC term's demonstrations share the PPO minibatch's encoder pass when their lengths
    agree (12), and get their own otherwise (9): the loss and its gradients are those of
    the separate computation, up to rounding."""
    from pomil.algos.adversarial import policy_and_demo_features
    from pomil.algos.warm_start import demo_bc_loss, demo_nll
    from pomil.data import PaddedEpisodes
    from pomil.nn.policy import GaussianPolicy, PolicyArch, shift_actions

    torch.manual_seed(0)
    policy = GaussianPolicy(PolicyArch(2, 2, "gru", 16, 2))
    codes = torch.eye(2)[torch.arange(6) % 2].expand(12, -1, -1)
    b = as_rollout(torch.randn(12, 6, 2), torch.randn(12, 6, 2), codes)
    b = b.with_(h0_policy=torch.randn(6, 16),
                starts=torch.zeros(12, 6, dtype=torch.bool))  # carries on from a stored state
    mask = torch.ones(demo_steps, 10, dtype=torch.bool)
    mask[demo_steps - 3:, :4] = False  # some shorter episodes
    demos = PaddedEpisodes(torch.randn(demo_steps, 10, 2), torch.randn(demo_steps, 10, 2), mask)
    prev = shift_actions(demos.actions)

    def losses(joint: bool, mixture: bool):
        policy.zero_grad()
        g = torch.Generator().manual_seed(1)
        if joint:
            from pomil.algos.warm_start import demo_batch
            demo, demo_prev, _ = demo_batch(demos, prev, 8, g)
            feats, demo_feats = policy_and_demo_features(policy, b, demo, demo_prev)
            bc, _ = demo_nll(policy, demo_feats, demo, generator=g, num_codes=2, mixture=mixture)
        else:
            feats, _ = policy.features(b.observations, b.prev_actions, b.h0_policy, b.starts)
            bc, _ = demo_bc_loss(policy, demos, prev, batch_episodes=8, generator=g, num_codes=2, mixture=mixture)
        ppo_term = policy.dist(feats, b.codes).log_prob(b.actions).sum()
        (ppo_term + bc).backward()
        return ppo_term.detach(), bc.detach(), [p.grad.clone() for p in policy.parameters()]

    for mixture in (False, True):
        a, c = losses(True, mixture), losses(False, mixture)
        torch.testing.assert_close(a[0], c[0])
        torch.testing.assert_close(a[1], c[1])
        for ga, gc in zip(a[2], c[2], strict=True):
            torch.testing.assert_close(ga, gc, rtol=1e-4, atol=1e-6)


def test_rollout_threads_must_not_be_negative(demos_path, tmp_path):
    with pytest.raises(ValueError, match="rollout_threads"):
        _cfg(demos_path, tmp_path / "bad", rollout_threads=-1)


@pytest.mark.parametrize("belief_encoder", ["gru", "lstm", "attention"])
def test_belief_encoder_goes_to_every_recurrent_network_and_only_there(belief_encoder):
    from dataclasses import replace

    from pomil.nn.encoders import AttentionEncoder, BeliefEncoder, LSTMEncoder, MLPEncoder

    kind = {"gru": BeliefEncoder, "lstm": LSTMEncoder, "attention": AttentionEncoder}[belief_encoder]
    cfg = AdversarialConfig(learner="infogail-pomdp", belief_encoder=belief_encoder, attention_context=5,
                            hidden_size=8)
    m, arch = build_modules(cfg, 2, 2, num_codes=3, device="cpu")
    assert arch.encoder == belief_encoder and arch.context == 5
    assert all(type(net.encoder) is kind for net in (m.policy, m.value, m.critic, m.posterior))
    if belief_encoder == "attention":
        assert {net.encoder.context for net in (m.policy, m.value, m.critic, m.posterior)} == {5}
    m, _ = build_modules(replace(cfg, belief="policy"), 2, 2, num_codes=3,
                         device="cpu")  # the ablation keeps feed-forward heads
    assert type(m.policy.encoder) is kind
    assert all(type(net.encoder) is MLPEncoder for net in (m.value, m.critic, m.posterior))
    for learner in ("gail", "infogail"):  # feed-forward learners whatever the option says
        m, arch = build_modules(replace(cfg, learner=learner), 2, 2, num_codes=3 if learner == "infogail" else 0,
                                device="cpu")
        assert arch.encoder == "mlp" and type(m.critic.encoder) is MLPEncoder


def test_the_warm_start_can_hand_over_a_floor_on_the_policys_action_noise(demos_path, tmp_path):
    def log_std(out, **kw):
        ckpt = train_adversarial(_cfg(demos_path, tmp_path / out, iterations=0, warm_start_iterations=5,
                                      warm_start_fit_log_std=True, **kw))
        return load_checkpoint(ckpt)["policy"]["log_std"]

    fitted = log_std("fitted")
    assert bool((fitted < 0.5).all())  # the circles experts' noise: a fitted std well below e^0.5
    assert torch.equal(log_std("floor", warm_start_min_log_std=0.5), torch.full_like(fitted, 0.5))


def _separable_demos(episodes: int = 16, steps: int = 12):
    """Demonstrations whose first half shows observations +1, the second half -1: codes 0 and 1."""
    from pomil.data import PaddedEpisodes

    sign = torch.cat([torch.ones(episodes // 2), -torch.ones(episodes // 2)])
    obs = sign.view(1, -1, 1).expand(steps, episodes, 2).clone()
    acts = torch.zeros(steps, episodes, 2)
    codes = (sign < 0).long()
    return PaddedEpisodes(obs, acts, torch.ones(steps, episodes, dtype=torch.bool)), codes


@pytest.mark.parametrize("tolerance", [0.01, 0.0])
def test_posterior_warm_start_stops_once_it_tells_the_codes_apart(tolerance):
    from pomil.algos.adversarial import POSTERIOR_INIT_PATIENCE, warm_start_posterior

    demos, codes = _separable_demos()
    cfg = AdversarialConfig(demos="x.npz", hidden_size=16, posterior_init_iterations=300, warm_start_batch=8,
                            posterior_init_tolerance=tolerance, progress=False)
    post = build_modules(cfg, 2, 2, num_codes=2, device="cpu")[0].posterior
    stats = warm_start_posterior(post, demos, torch.zeros_like(demos.actions), codes=codes, cfg=cfg,
                                 gen=torch.Generator().manual_seed(0))
    if tolerance:
        steps = stats["posterior/stopped_after"]
        assert POSTERIOR_INIT_PATIENCE <= steps < 300 and stats["posterior/loss"] < tolerance
        assert stats["posterior/accuracy"] == 1.0
    else:  # all the steps
        assert "posterior/stopped_after" not in stats and stats["posterior/loss"] < 0.01


def test_continuous_codes_posterior_warm_start_takes_all_its_steps():
    from pomil.algos.adversarial import warm_start_posterior

    demos, codes = _separable_demos()
    cfg = AdversarialConfig(demos="x.npz", hidden_size=16, posterior_init_iterations=40, warm_start_batch=8,
                            code_kind="continuous", progress=False)
    post = build_modules(cfg, 2, 2, num_codes=2, device="cpu")[0].posterior
    stats = warm_start_posterior(post, demos, torch.zeros_like(demos.actions), codes=codes.float().unsqueeze(1) * 2 - 1,
                                 cfg=cfg, gen=torch.Generator().manual_seed(0))
    assert "posterior/stopped_after" not in stats


def test_an_evaluation_of_a_policy_that_has_not_moved_is_not_rolled_out_again(demos_path, monkeypatch):
    import pomil.eval.circles as circles
    from pomil.algos.adversarial import make_evaluator
    from pomil.data import load_training_demos

    calls = []
    real = circles.evaluate_circles

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(circles, "evaluate_circles", counted)
    demos, env_id, env_kwargs = load_training_demos(str(demos_path))
    cfg = AdversarialConfig(demos=str(demos_path), hidden_size=16, eval_episodes=2, progress=False)
    env_info = {"id": env_id, "kwargs": env_kwargs, "observation_mask": None}
    evaluate = make_evaluator(cfg, env_info, demos)
    policy = build_modules(cfg, demos.obs_dim, demos.act_dim, num_codes=2, device="cpu")[0].policy
    first = evaluate(policy)
    assert evaluate(policy) == first and len(calls) == 1  # the same weights: the same figures, no rollouts
    with torch.no_grad():
        next(policy.parameters()).add_(0.5)
    evaluate(policy)
    assert len(calls) == 2
