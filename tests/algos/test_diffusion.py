"""The diffusion peers: schedule, loss, sampling, receding horizon, checkpoints, a short circles run."""

import csv
import math

import pytest
import torch

pytest.importorskip("diffusers")

from pomil.algos.diffusion import DiffusionConfig, Places, denoising_loss, ema_decay, lr_factor, train_diffusion  # noqa: E402
from pomil.api import TrainedPolicy  # noqa: E402
from pomil.errors import PomilError  # noqa: E402
from pomil.eval.circles import evaluate_circles  # noqa: E402
from pomil.learners import LEARNERS  # noqa: E402
from pomil.nn.diffusion import DiffusionArch, DiffusionPolicy, DiffusionState, noise_schedulers  # noqa: E402
from pomil.training import load_checkpoint  # noqa: E402


def _rows(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if not k.startswith("time/")} for r in csv.DictReader(f)]


def _cfg(demos_path, out, **kw):
    return DiffusionConfig(**{"demos": str(demos_path), "out": str(out), "progress": False, "log_every": 10,
                              "hidden_size": 64, "layers": 1, "batch_size": 64, **kw})


def test_forward_process_is_the_cosine_schedule():
    """x_k = sqrt(abar_k) x_0 + sqrt(1 - abar_k) eps, abar_k = f(k + 1) / f(0), f(t) = cos^2((t/T + s)/(1 + s) pi/2)."""
    arch = DiffusionArch(2, 2, train_timesteps=100)
    ddpm, ddim = noise_schedulers(arch)
    f = lambda t: math.cos((t / 100 + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    clean, noise = torch.tensor([[0.5, -1.0]]), torch.tensor([[1.0, 2.0]])
    for k in (0, 10, 50, 98):
        abar = f(k + 1) / f(0)
        want = math.sqrt(abar) * clean + math.sqrt(1 - abar) * noise
        assert torch.allclose(ddpm.add_noise(clean, noise, torch.tensor([k])), want, atol=1e-6), k
    assert ddim.timesteps.tolist() == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]


def test_denoising_loss_is_the_noise_error():
    """A denoiser that answers zeros scores the noise's mean square; one that answers the noise scores 0."""
    arch = DiffusionArch(obs_dim=1, act_dim=1, obs_horizon=1, action_horizon=2, execute_horizon=1, hidden_size=8,
                         layers=1, train_timesteps=10)
    ddpm, _ = noise_schedulers(arch)
    policy = DiffusionPolicy(arch)
    windows, actions = torch.zeros(3, 1, 1), torch.tensor([[[0.5], [-0.5]], [[0.0], [1.0]], [[1.0], [1.0]]])
    drawn = torch.Generator().manual_seed(3)
    noise = torch.randn(actions.shape, generator=drawn)
    steps = torch.randint(0, 10, (3,), generator=drawn)

    policy.forward = lambda noisy, k, cond: torch.zeros_like(noisy)
    loss, stats = denoising_loss(policy, ddpm, windows, actions=actions, codes=None,
                                   generator=torch.Generator().manual_seed(3))
    assert loss.item() == pytest.approx(noise.pow(2).mean().item(), rel=1e-6) and stats["diffusion/loss"] == loss.item()

    abar = ddpm.alphas_cumprod[steps].view(-1, 1, 1)
    clean = policy.scale(actions, "act")
    policy.forward = lambda noisy, k, cond: (noisy - abar.sqrt() * clean) / (1 - abar).sqrt()
    loss, _ = denoising_loss(policy, ddpm, windows, actions=actions, codes=None,
                                   generator=torch.Generator().manual_seed(3))
    assert loss.item() < 1e-10


def test_places_repeat_the_first_observation_and_the_last_action():
    mask = torch.tensor([[1, 1], [1, 1], [1, 1], [0, 1]])  # episodes of 3 and 4 steps, time-major
    places = Places.of(mask, obs_horizon=2, action_horizon=3)
    got = {(int(t), int(e)): (o.tolist(), a.tolist()) for t, e, o, a in
           zip(places.obs_steps[:, -1], places.episodes, places.obs_steps, places.act_steps, strict=True)}
    assert got == {(0, 0): ([0, 0], [0, 1, 2]), (0, 1): ([0, 0], [0, 1, 2]), (1, 0): ([0, 1], [1, 2, 2]),
                   (1, 1): ([0, 1], [1, 2, 3]), (2, 0): ([1, 2], [2, 2, 2]), (2, 1): ([1, 2], [2, 3, 3]),
                   (3, 1): ([2, 3], [3, 3, 3])}


def test_scaling_maps_the_demonstrations_range_to_plus_minus_one():
    policy = DiffusionPolicy(DiffusionArch(2, 1, hidden_size=8, layers=1))
    policy.fit_ranges(torch.tensor([[0.0, 5.0], [2.0, 5.0]]), torch.tensor([[-3.0], [1.0]]))
    assert policy.scale(torch.tensor([[0.0, 5.0], [2.0, 5.0]]), "obs").tolist() == [[-1.0, 0.0], [1.0, 0.0]]
    assert policy.unscale(torch.tensor([[-1.0], [0.0], [1.0]]), "act").tolist() == [[-3.0], [-1.0], [1.0]]


def test_sampling_is_deterministic_given_a_seed():
    policy = DiffusionPolicy(DiffusionArch(3, 2, hidden_size=16, layers=1, action_horizon=4, execute_horizon=2))
    cond = torch.randn(5, policy.cond_dim, generator=torch.Generator().manual_seed(0))
    a = policy.sample(cond, torch.Generator().manual_seed(1))
    b = policy.sample(cond, torch.Generator().manual_seed(1))
    c = policy.sample(cond, torch.Generator().manual_seed(2))
    assert a.shape == (5, 4, 2) and torch.equal(a, b) and not torch.equal(a, c)


def test_the_window_and_the_plan_at_starts_and_resets():
    """A new plan at an episode's start and every execute_horizon steps; the window starts as the first
    observation repeated; an episode reset mid-plan replans alone."""
    policy = DiffusionPolicy(DiffusionArch(1, 1, obs_horizon=2, action_horizon=3, execute_horizon=2, hidden_size=8,
                                           layers=1))
    calls = []

    def sample(cond, generator):  # plan: the window's newest observation x 10 + the action's place
        calls.append(cond.shape[0])  # the scaling's default range [-1, 1] leaves observations as they are
        return cond[:, 1:2, None] * 10 + torch.arange(3.0)[None, :, None]

    policy.sample = sample
    state = policy.initial_state(2)
    actions, windows = [], []
    for t, (obs, start) in enumerate([([1.0, 2.0], [1, 1]), ([3.0, 4.0], [0, 0]), ([5.0, 6.0], [0, 1]),
                                      ([7.0, 8.0], [0, 0])]):
        a, state = policy.act(torch.tensor(obs)[:, None], state, torch.tensor(start), None, None)
        actions.append(a.flatten().tolist())
        windows.append(state.window.flatten(1).tolist())
        assert isinstance(state, DiffusionState), t
    assert windows[0] == [[1.0, 1.0], [2.0, 2.0]] and windows[1] == [[1.0, 3.0], [2.0, 4.0]]
    assert windows[2] == [[3.0, 5.0], [6.0, 6.0]]  # episode 1 starts again: its window is its new observation
    assert actions == [[10.0, 20.0], [11.0, 21.0], [50.0, 60.0], [51.0, 61.0]]
    assert calls == [2, 2]  # both at the start; both again at t = 2 (episode 0: plan used up; episode 1: reset)


def test_trained_policy_acts_through_its_receding_horizon(demos_path, tmp_path):
    ckpt = train_diffusion(_cfg(demos_path, tmp_path / "d", iterations=5, action_horizon=4, execute_horizon=2))
    tp = TrainedPolicy.load(ckpt)
    assert (tp.num_codes, tp.obs_dim, tp.act_dim, tp.algo) == (0, 2, 2, "diffusion")
    runs = []
    for _ in range(2):
        tp.reset(3, seed=4)
        runs.append([tp.act(torch.zeros(3, 2).numpy() + t, deterministic=True) for t in range(5)])
    assert all((a == b).all() for a, b in zip(*runs, strict=True))  # the seed decides the draw
    small = tmp_path / "policy.pt"
    tp.save(small)
    again = TrainedPolicy.load(small)
    again.reset(3, seed=4)
    assert (again.act(torch.zeros(3, 2).numpy(), deterministic=True) == runs[0][0]).all()


def test_a_damaged_diffusion_checkpoint_is_a_one_line_error(demos_path, tmp_path):
    from pomil.training import save_checkpoint

    ckpt = load_checkpoint(train_diffusion(_cfg(demos_path, tmp_path / "d", iterations=2)))
    for arch, says in (({**ckpt["policy_arch"], "hidden_size": "wide"}, "hidden_size is 'wide'"),
                       ({**ckpt["policy_arch"], "execute_horizon": 99}, "execute_horizon must be in"),
                       ({**ckpt["policy_arch"], "hidden_size": 8}, r"loading state_dict for DiffusionPolicy")):
        save_checkpoint(tmp_path / "bad.pt", {**ckpt, "policy_arch": arch})
        with pytest.raises(PomilError, match=f"bad.pt: checkpoint has no usable policy .*{says}"):
            TrainedPolicy.load(tmp_path / "bad.pt")


def test_same_seed_same_run_and_resume_is_exact(demos_path, tmp_path):
    full = train_diffusion(_cfg(demos_path, tmp_path / "full", iterations=40, checkpoint_every=20))
    again = train_diffusion(_cfg(demos_path, tmp_path / "again", iterations=40, checkpoint_every=20))
    train_diffusion(_cfg(demos_path, tmp_path / "split", iterations=20, checkpoint_every=20))
    resumed = train_diffusion(_cfg(demos_path, tmp_path / "split", iterations=40, checkpoint_every=20), resume=True)
    pf, pa, pr = (load_checkpoint(p) for p in (full, again, resumed))
    assert pr["iteration"] == 40 and set(pf["nets"]) == {"policy", "ema"}
    def flat(ckpt):  # the handed-over policy and every network's weights
        return {**{f"policy.{k}": v for k, v in ckpt["policy"].items()},
                **{f"nets.{n}.{k}": v for n, sd in ckpt["nets"].items() for k, v in sd.items()}}

    for other in (pa, pr):
        a, b = flat(pf), flat(other)
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert _rows(tmp_path / "full") == _rows(tmp_path / "split") == _rows(tmp_path / "again")
    for k, v in pf["policy"].items():  # the policy handed over is the average, not the last weights
        assert torch.equal(v, pf["nets"]["ema"][k])
    assert any(not torch.equal(v, pf["nets"]["policy"][k]) for k, v in pf["policy"].items())


def test_the_run_length_follows_the_demonstrations(demos_path, tmp_path):
    """iterations auto: 75 passes over the demonstrations' steps, at least 4000 (two circles: 4000; the paper's
    Hopper: 15,000); a count given is kept; config.json records the count run."""
    import json

    from pomil.algos.diffusion import sized_for_steps

    cfg = DiffusionConfig()
    assert [sized_for_steps(cfg, n).iterations for n in (13_200, 51_200, 8_000)] == [4000, 15_000, 4000]
    assert sized_for_steps(DiffusionConfig(iterations=7), 51_200).iterations == 7
    assert sized_for_steps(DiffusionConfig(epochs=1.0, min_iterations=3), 600).iterations == 3
    train_diffusion(_cfg(demos_path, tmp_path / "d", epochs=0.5, min_iterations=2))  # 200 episodes x 33 steps
    assert json.loads((tmp_path / "d" / "config.json").read_text())["iterations"] == math.ceil(0.5 * 6600 / 64)


def test_schedules():
    cfg = DiffusionConfig(iterations=1000, lr_warmup=100)
    assert lr_factor(cfg, 50) == 0.5 and lr_factor(cfg, 100) == 1.0 and lr_factor(cfg, 1000) == pytest.approx(0.0)
    assert lr_factor(cfg, 550) == pytest.approx(0.5)
    assert ema_decay(0.75, 0) == 0.0 and ema_decay(0.75, 15) == pytest.approx(1 - 16 ** -0.75)
    assert ema_decay(0.75, 10**9) == 0.9999


def test_bad_settings_are_one_line_errors(demos_path, tmp_path):
    with pytest.raises(PomilError, match="'execute_horizon': expected at most action_horizon"):
        _cfg(demos_path, tmp_path, action_horizon=4, execute_horizon=5)
    with pytest.raises(PomilError, match="'codes_from': only with conditioning codes"):
        _cfg(demos_path, tmp_path, codes_from="x.pt")
    bc = tmp_path / "bc"
    from pomil.algos.bc import BCConfig, train_bc

    train_bc(BCConfig(demos=str(demos_path), out=str(bc), iterations=2, hidden_size=8, progress=False))
    with pytest.raises(PomilError, match="codes_from must be a run with discrete latent codes"):
        train_diffusion(_cfg(demos_path, tmp_path / "c", conditioning="codes", codes_from=str(bc / "checkpoint.pt"),
                             iterations=2))
    assert LEARNERS["diffusion-codes"].make_config({}).conditioning == "codes"


def test_the_default_denoiser_learns_the_circles_noise(demos_path, tmp_path):
    """200 gradient steps of the default denoiser: the noise error of the last logged batch is under 40% of the
    first step's (measured on an AMD EPYC: 1.17 -> 0.29; it starts near 1, the noise's own variance).  Whether its
    samples cover both circles is the slow test below."""
    train_diffusion(DiffusionConfig(demos=str(demos_path), out=str(tmp_path / "d"), progress=False, iterations=200,
                                    log_every=25))
    rows = _rows(tmp_path / "d")
    assert [int(r["iteration"]) for r in rows] == [1, 25, 50, 75, 100, 125, 150, 175, 200]
    first, last = float(rows[0]["diffusion/loss"]), float(rows[-1]["diffusion/loss"])
    assert 0.7 < first < 1.5 and last < 0.4 * first, (first, last)


@pytest.mark.slow
@pytest.mark.parametrize("size", ["small", "default"])
def test_a_short_circles_run_covers_both_circles(size, demos_path, tmp_path):
    """Free samples of an unconditional policy: each circle at least 30% of 200 episodes (measured on an Intel Xeon
    and an AMD EPYC, 2000 steps: 0.455 and 0.365, the rest off the circles)."""
    settings = {"iterations": 2000} if size == "small" else {}
    ckpt = train_diffusion(DiffusionConfig(demos=str(demos_path), out=str(tmp_path / "d"), progress=False, **settings))
    metrics, _ = evaluate_circles(TrainedPolicy.load(ckpt), episodes_per_code=200, seed=0)
    assert min(metrics["overall_mode_share"]) >= 0.3, metrics["overall_mode_share"]


def test_codes_come_from_the_mixture_warm_start(demos_path, tmp_path, monkeypatch):
    """diffusion-codes: each episode's code is its most likely one under InfoGAIL-POMDP's warm start (run into
    OUT/warm-start, reused on --resume, or given as codes_from); the run records their shares and agreement with
    the labels; the policy takes a code per episode."""
    import dataclasses

    import pomil.algos.adversarial as adversarial
    from pomil.algos.diffusion import episode_codes
    from pomil.data import Demonstrations

    runs = []
    train = adversarial.train_adversarial

    def short(cfg, resume=False):  # the default warm start, shortened for the test
        runs.append(cfg.out)
        return train(dataclasses.replace(cfg, warm_start_iterations=30, posterior_init_iterations=5), resume)

    monkeypatch.setattr(adversarial, "train_adversarial", short)
    cfg = _cfg(demos_path, tmp_path / "dc", conditioning="codes", iterations=4, checkpoint_every=2)
    ckpt = train_diffusion(cfg)
    assert runs == [str(tmp_path / "dc" / "warm-start")]
    record = load_checkpoint(ckpt)["record"]
    demos = Demonstrations.load(demos_path)
    codes, k = episode_codes(tmp_path / "dc" / "warm-start" / "checkpoint.pt", demos, env_id="pomil/Circles-v0",
                             env_kwargs=demos.metadata["env_kwargs"], device=torch.device("cpu"))
    assert k == 2 and record["code_shares"] == [round(float((codes == c).float().mean()), 4) for c in range(2)]
    assert 0.0 <= record["codes_nmi_with_labels"] <= 1.0
    tp = TrainedPolicy.load(ckpt)
    assert tp.num_codes == 2 and tp.algo == "diffusion-codes"
    tp.reset(4, codes=[0, 1, 0, 1], seed=0)
    assert tp.act(torch.zeros(4, 2).numpy()).shape == (4, 2)
    train_diffusion(dataclasses.replace(cfg, iterations=6), resume=True)  # the warm start is not run again
    assert len(runs) == 1
    given = train_diffusion(dataclasses.replace(cfg, out=str(tmp_path / "given"),
                                                codes_from=str(tmp_path / "dc" / "warm-start" / "checkpoint.pt")))
    assert len(runs) == 1 and load_checkpoint(given)["record"]["code_shares"] == record["code_shares"]


def test_without_the_extra_a_run_says_which_to_install_and_writes_nothing(demos_path, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "diffusers", None)  # an import of it fails
    with pytest.raises(PomilError, match=r"need the optional extra diffusers: pip install 'pomil\[diffusion\]'"):
        train_diffusion(_cfg(demos_path, tmp_path / "d", iterations=2))
    assert not (tmp_path / "d").exists()
