"""The adversarial learner's phases, each on one fixed batch without a training run."""

import contextlib
from dataclasses import replace

import pytest
import torch

from pomil.algos.adversarial import (
    AdversarialConfig,
    AdversarialRun,
    BatchSampler,
    absorbing_bootstrap,
    build_modules,
    build_optimizers,
    update_critic,
    update_policy,
    update_posterior,
    with_rewards,
)
from pomil.algos.warm_start import FAST_WARM_START, clone_demonstrations
from pomil.envs import executed_actions_fn, make_vec_env
from pomil.nn.policy import shift_actions
from pomil.rl.collect import Collected, collect
from pomil.rl.gae import gae
from pomil.rl.ppo import masked_mean


def make_run(demos, **kw):
    cfg = AdversarialConfig(**{**dict(demos="d.npz", hidden_size=16, num_envs=8, critic_batch=4, critic_steps=2,
                                      minibatches=2, ppo_epochs=1, bc_weight=0.0, policy_warmup_iterations=1), **kw})
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    env_id, kwargs = demos.metadata["env_id"], demos.metadata["env_kwargs"]
    execute = executed_actions_fn(env_id, kwargs)
    m, _ = build_modules(cfg, demos.obs_dim, demos.act_dim, num_codes=2, device="cpu")
    expert = demos.padded("cpu")
    expert = replace(expert, actions=execute(expert.actions))
    sampler = BatchSampler(cfg.update_mode, cfg.window_length)
    run = AdversarialRun(cfg, m, build_optimizers(cfg, m), gen, torch.Generator().manual_seed(1), sampler, expert,
                         shift_actions(expert.actions),
                         execute, num_codes=2)
    collected = collect(make_vec_env(env_id, kwargs, cfg.num_envs), m.policy, m.value, num_codes=2, execute=execute,
                        generator=gen, device="cpu")
    return run, collected


def params(net):
    return [p.detach().clone() for p in net.parameters()]


def changed(before, net):
    return any(not torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))


def test_collect_returns_a_named_rollout(demos):
    _, c = make_run(demos)
    assert isinstance(c, Collected)
    assert c.rollout.num_envs == 8 and c.next_values.shape == c.env_rewards.shape == (33, 8)
    assert c.codes.shape == (8,) and set(c.codes.tolist()) <= {0, 1}


@pytest.mark.parametrize("mode", ["sequence", "window"])
def test_the_sampler_cuts_whole_episodes_or_windows(demos, mode):
    run, c = make_run(demos, update_mode=mode, window_length=5)
    e = run.sampler.expert(run.expert, run.expert.actions, run.expert_prev, 4, run.gen)
    assert e[0].shape == ((33 if mode == "sequence" else 5), 4, 2) and bool(e[3][0].all())  # starts at the first step
    p = run.sampler.policy(c.rollout, 4, run.gen)
    assert p.num_envs == 4 and p.num_steps == (33 if mode == "sequence" else 5)
    code_steps = c.codes.unsqueeze(0).expand(33, -1)
    (codes, batch), = run.sampler.posterior(c.rollout, code_steps, run.gen)
    assert batch.num_envs == (8 if mode == "sequence" else 33 * 8 // 5) and codes.shape == batch.mask.shape
    assert len(list(run.sampler.minibatches(c.rollout, 2, run.gen))) == 2


def test_the_critic_phase_moves_only_the_critic(demos):
    run, c = make_run(demos)
    critic, policy = params(run.m.critic), params(run.m.policy)
    s = update_critic(run, c.rollout)
    assert set(s) == {"critic/wasserstein", "critic/gradient_penalty", "critic/loss"}
    assert changed(critic, run.m.critic) and not changed(policy, run.m.policy)


def test_the_posterior_phase_moves_only_the_posterior_and_is_empty_without_codes(demos):
    run, c = make_run(demos)
    before = params(run.m.posterior)
    s = update_posterior(run, c.rollout, c.codes)
    assert 0.0 <= s["posterior/accuracy"] <= 1.0 and changed(before, run.m.posterior)
    assert update_posterior(replace(run, m=replace(run.m, posterior=None)), c.rollout, c.codes) == {}


def test_rewards_standardise_the_critic_term_and_add_the_weighted_log_posterior(demos):
    run, c = make_run(demos, mi_weight=0.0)
    roll, s = with_rewards(run, c.rollout, c.codes, next_values=c.next_values)
    mask = roll.mask
    assert masked_mean(roll.rewards, mask).item() == pytest.approx(0.0, abs=1e-5)
    assert masked_mean(roll.rewards ** 2, mask).sqrt().item() == pytest.approx(1.0, abs=1e-4)
    weighted, s2 = with_rewards(replace(run, cfg=replace(run.cfg, mi_weight=2.0)), c.rollout, c.codes,
                                next_values=c.next_values)
    assert s2["reward/total"] == pytest.approx(s["reward/total"] + 2.0 * s2["reward/log_posterior"], abs=1e-5)
    assert roll.advantages.shape == roll.returns.shape == (33, 8)


def fall_or_stay_batch():
    """Two episodes of constant reward -1 and zero values: env 0 falls (terminates) at step 1, env 1 stays up to
    the time limit at step 3 (truncated, bootstrapped with value 0)."""
    r = torch.tensor([[-1.0, -1.0], [-1.0, -1.0], [0.0, -1.0], [0.0, -1.0]])
    mask = torch.tensor([[True, True], [True, True], [False, True], [False, True]])
    terminated = torch.zeros(4, 2, dtype=torch.bool)
    terminated[1, 0] = True
    truncated = torch.zeros(4, 2, dtype=torch.bool)
    truncated[3, 1] = True
    return r, mask, terminated, truncated


def test_a_return_that_ends_at_termination_pays_for_falling_when_rewards_are_negative():
    r, mask, term, trunc = fall_or_stay_batch()
    _, ret = gae(r, torch.zeros(4, 2), torch.zeros(4, 2), terminated=term, truncated=trunc, gamma=0.5, lam=1.0)
    assert ret[0].tolist() == pytest.approx([-1.5, -1.875])  # falling: -1 - 0.5; staying: -1 - .5 - .25 - .125


def test_the_absorbing_state_takes_the_lowest_reward_so_falling_never_pays():
    r, mask, term, trunc = fall_or_stay_batch()
    r[3, 1] = -3.0  # the batch's lowest step reward, on the step that stays up last
    nv, v_abs = absorbing_bootstrap(r, mask, term, next_values=torch.zeros(4, 2), gamma=0.5)
    assert v_abs == pytest.approx(-6.0)  # -3 / (1 - 0.5)
    assert nv[1, 0].item() == pytest.approx(-6.0) and nv.sum().item() == pytest.approx(-6.0)  # only where it fell
    _, ret = gae(r, torch.zeros(4, 2), nv, terminated=torch.zeros_like(term), truncated=term | trunc, gamma=0.5,
                 lam=1.0)
    falls, stays = -1 - 0.5 - 0.25 * 6.0, -1 - 0.5 - 0.25 - 0.125 * 3  # -3.0 < -2.125
    assert ret[0].tolist() == pytest.approx([falls, stays])
    assert absorbing_bootstrap(r, mask, torch.zeros_like(term), next_values=torch.zeros(4, 2), gamma=0.5)[1] == 0.0


def test_absorbing_termination_leaves_batches_without_terminations_unchanged(demos):
    run, c = make_run(demos, termination="absorbing")
    assert not c.rollout.terminated.any()
    a, _ = with_rewards(run, c.rollout, c.codes, next_values=c.next_values)
    e, _ = with_rewards(replace(run, cfg=replace(run.cfg, termination="end")), c.rollout, c.codes,
                        next_values=c.next_values)
    assert torch.equal(a.returns, e.returns) and torch.equal(a.advantages, e.advantages)


@pytest.mark.parametrize("mode", ["sequence", "window"])
def test_the_policy_phase_waits_out_the_warm_up_then_moves_the_policy(demos, mode):
    run, c = make_run(demos, update_mode=mode)
    roll, _ = with_rewards(run, c.rollout, c.codes, next_values=c.next_values)
    policy, value = params(run.m.policy), params(run.m.value)
    s = update_policy(run, roll, it=1)  # policy_warmup_iterations = 1
    assert not changed(policy, run.m.policy) and changed(value, run.m.value)
    assert {"ppo/policy_loss", "ppo/value_loss", "ppo/approx_kl"} <= set(s)
    update_policy(run, roll, it=2)
    assert changed(policy, run.m.policy)


def test_bfloat16_updates_round_the_networks_passes_but_keep_outputs_losses_and_weights_float32(demos):
    run32, c32 = make_run(demos, critic_steps=2, bc_weight=1.0)
    run16, c16 = make_run(demos, critic_steps=2, bc_weight=1.0, precision="bfloat16")
    roll = c32.rollout
    critic = lambda run: run.m.critic.unroll(roll.observations, roll.prev_actions,  # noqa: E731
                                             run.m.critic.initial_state(roll.num_envs), roll.starts,
                                             extra=roll.executed_actions)[0]
    f32 = critic(run32)
    with run16.precision():
        f16 = critic(run16)
        dist, _ = run16.m.policy.unroll(roll.observations, roll.prev_actions, roll.h0_policy, roll.starts,
                                        codes=roll.codes)
    assert f16.dtype == dist.mean.dtype == torch.float32
    gap = (f16 - f32).abs().max().item()
    assert 0 < gap < 0.02 * f32.abs().max().item() + 1e-3  # rounded to bfloat16 inside, near float32's
    s32 = update_critic(run32, roll)
    s16 = update_critic(run16, roll)  # the phases enter the precision's context themselves, once a step
    with run16.precision():
        after16 = critic(run16)
    update_posterior(run16, roll, c32.codes)
    roll16, _ = with_rewards(run16, roll, c32.codes, next_values=c32.next_values)
    p16 = update_policy(run16, roll16, it=2)
    moved32, moved16 = critic(run32) - f32, after16 - f16
    assert torch.corrcoef(torch.stack([moved16.flatten(), moved32.flatten()]))[0, 1] > 0.8  # moved alike
    assert s16["critic/loss"] != s32["critic/loss"]
    assert s16["critic/loss"] == pytest.approx(s32["critic/loss"], rel=0.05, abs=0.05)  # the second step's
    assert p16["ppo/approx_kl"] < 1e-2  # the bfloat16 policy's log-probs near the float32 rollout's
    for net in (run16.m.policy, run16.m.value, run16.m.critic, run16.m.posterior):
        assert all(p.dtype == torch.float32 and bool(p.isfinite().all()) for p in net.parameters())


def test_a_bfloat16_warm_start_fits_the_demonstrations_as_the_float32_one(demos):
    """Every step computes with the weights of that step (autocast's weight cache is per step):
    with one context around the whole warm start, its NLL after 5 steps was 3.8 against 1.06.
    Also inside an enclosing autocast, which would otherwise keep the cache for its own length."""
    nll = {}
    for precision, enclosing in (("float32", False), ("bfloat16", False), ("bfloat16", True)):
        run, _ = make_run(demos, precision=precision, **{**FAST_WARM_START, "warm_start_iterations": 20})
        with torch.autocast("cpu", enabled=False) if enclosing else contextlib.nullcontext():
            stats = clone_demonstrations(run.m.policy, run.expert, run.expert_prev, num_codes=2, mixture=True,
                                         cfg=run.cfg,
                                         gen=torch.Generator().manual_seed(0))
        nll[precision, enclosing] = stats["bc/nll"]
    assert nll["bfloat16", False] != nll["float32", False]
    for enclosing in (False, True):
        assert nll["bfloat16", enclosing] == pytest.approx(nll["float32", False], abs=0.05)


def test_no_function_in_the_package_is_longer_than_a_screen():
    import ast
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "src" / "pomil"
    functions = [(p, n) for p in src.rglob("*.py") for n in ast.walk(ast.parse(p.read_text()))
                 if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    assert len(functions) > 300  # the whole package was read
    long = [f"{p.relative_to(src)}:{n.name} ({n.end_lineno - n.lineno + 1} lines)" for p, n in functions
            if n.end_lineno - n.lineno + 1 > 60]
    assert long == []


def test_functions_of_five_or_more_parameters_take_at_most_three_positionally():
    """Module-level functions of the package: the parameters after the third are keyword-only where a function
    has five or more, so that a call names what it passes (``collect(env, policy, value, num_codes=K, ...)``)."""
    import ast
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "src" / "pomil"
    functions = [(p, n) for p in src.rglob("*.py") for n in ast.parse(p.read_text()).body
                 if isinstance(n, ast.FunctionDef)]
    assert len(functions) > 200  # the whole package was read
    wide = [f"{p.relative_to(src)}:{n.name}" for p, n in functions
            if len(n.args.posonlyargs + n.args.args) + len(n.args.kwonlyargs) >= 5
            and len(n.args.posonlyargs + n.args.args) > 3]
    assert wide == []
