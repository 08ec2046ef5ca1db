"""The library's defaults are the measured recipe; the paper's text is a named preset."""

import dataclasses
import json
from pathlib import Path

import pytest

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.api import TrainedPolicy
from pomil.cli import main
from pomil.config import from_dict, resolved
from pomil.data import Demonstrations
from pomil.envs.circles import Circle, CirclesSpec
from pomil.errors import PomilError
from pomil.eval.circles import evaluate_circles
from pomil.experiment import load_spec, modes_success
from pomil.learners import LEARNERS

ROOT = Path(__file__).resolve().parents[1]


def test_defaults_are_the_recipe_the_reproductions_run(tmp_path):
    cfg = AdversarialConfig()
    assert (cfg.critic_optimizer, cfg.gradient_penalty, cfg.weight_clip, cfg.lr_critic) == ("adam", 10.0, 0.0, 5e-4)
    assert (cfg.warm_start_codes, cfg.warm_start_iterations, cfg.bc_weight, cfg.lr, cfg.policy_warmup_iterations) == (
        "mixture", 600, 10.0, 5e-5, 5)
    assert (cfg.warm_start_lr, cfg.warm_start_lr_decay, cfg.warm_start_lr_warmup, cfg.warm_start_log_std_lr_scale,
            cfg.warm_start_fit_log_std) == (1e-2, True, 0.2, 1.0, False)
    # the warm starts of the presets, whole (steps, peak lr, decay, rise, log std's scale, its fit)
    for name, warm_start in (("deep-warm-start", (600, 1e-2, True, 0.2, 10.0, True)),
                             ("fast-warm-start", (600, 3e-3, True, 0.0, 10.0, True)),
                             ("terminating", (2400, 3e-3, True, 0.0, 10.0, True)),
                             ("long-warm-start", (3000, 1e-3, False, 0.0, 1.0, False)),
                             ("paper-text", (300, 1e-3, False, 0.0, 1.0, False))):
        p = from_dict(AdversarialConfig, {"preset": name})
        assert (p.warm_start_iterations, p.warm_start_lr, p.warm_start_lr_decay, p.warm_start_lr_warmup,
                p.warm_start_log_std_lr_scale, p.warm_start_fit_log_std) == warm_start, name
    assert cfg.mixture_balance == "dataset"
    assert (cfg.num_envs, cfg.iterations, cfg.preset) == (256, 15, "auto")
    # the circles experiment adds only the run's own fields to the defaults (auto: the circles' default preset)
    spec = load_spec("circles")
    row = next(r for r in spec.rows if r.learner == "infogail-pomdp")
    repro = resolved(LEARNERS["infogail-pomdp"].make_config({**spec.values(row), "out": str(tmp_path), "seed": 3}))
    plain = AdversarialConfig(demos=repro.demos, out=str(tmp_path), seed=3)
    assert repro.preset == "default" and repro == resolved(plain) == dataclasses.replace(plain, preset="default")


def test_paper_text_preset_gives_the_texts_settings_and_flags_override_it():
    cfg = from_dict(AdversarialConfig, {"preset": "paper-text"})
    assert cfg.preset == "paper-text"
    assert (cfg.critic_optimizer, cfg.weight_clip, cfg.gradient_penalty) == ("rmsprop", 0.01, 0.0)
    assert cfg.lr == cfg.lr_critic == cfg.lr_posterior == 2e-4
    assert (cfg.update_mode, cfg.warm_start_codes, cfg.bc_weight, cfg.policy_warmup_iterations) == ("window", "random",
                                                                                                 0.0, 0)
    assert (cfg.gamma, cfg.gae_lambda, cfg.hidden_size) == (0.99, 0.95, 128)  # the text's, and the defaults too
    assert from_dict(AdversarialConfig, {"preset": "paper-text", "lr": 1e-3}).lr == 1e-3  # the user's values win
    assert from_dict(AdversarialConfig, {"preset": "default"}) == dataclasses.replace(AdversarialConfig(),
                                                                                         preset="default")
    with pytest.raises(PomilError,
                       match="config key 'preset': expected one of \\['auto', 'default', 'paper-text', "
                             "'long-warm-start', 'fast-warm-start', 'deep-warm-start', 'terminating'\\], got 'paper'"):
        from_dict(AdversarialConfig, {"preset": "paper"})


def test_preset_flag_is_recorded_in_config_json(demos_path, tmp_path):
    out = tmp_path / "run"
    assert main(["train", "infogail", "--preset", "paper-text", "--demos", str(demos_path), "--out", str(out),
                 "--iterations", "1",
                 "--num-envs", "4", "--hidden-size", "8", "--warm-start-iterations", "1", "--eval-every", "0",
                 "--critic-steps", "1", "--no-progress"]) == 0
    written = json.loads((out / "config.json").read_text())
    assert written["preset"] == "paper-text"
    assert written["critic_optimizer"] == "rmsprop" and written["weight_clip"] == 0.01
    assert written["warm_start_iterations"] == 1  # the flag over the preset


@pytest.fixture(scope="module")
def standard_hopper_demos(tmp_path_factory):
    """The paper's Hopper demonstrations relabelled as recorded in Hopper-v5's own setting (episodes end when the
    hopper is unhealthy): only the metadata matter to the recipe."""
    from pomil.data import Demonstrations

    demos = Demonstrations.load(ROOT / "data" / "hopper-paper.npz")
    standard = {"terminate_when_unhealthy": True, "max_episode_steps": 1000}
    md = {**demos.metadata, "env_kwargs": {**demos.metadata["env_kwargs"], **standard},
          "tasks": {k: {**v, **standard} for k, v in demos.metadata["tasks"].items()}}
    path = tmp_path_factory.mktemp("standard") / "standard.npz"
    dataclasses.replace(demos, metadata=md).save(path)
    return path


def at_start(cls, values):
    """The config a run of ``values`` trains with: built, then its preset resolved where training starts."""
    return resolved(from_dict(cls, values))


def test_auto_preset_follows_whether_the_demonstrations_episodes_end_on_failure(standard_hopper_demos, tmp_path):
    from pomil.algos.bc import BCConfig

    paper = str(ROOT / "data" / "hopper-paper.npz")
    for demos in (str(ROOT / "data" / "circles.npz"), paper, str(tmp_path / "missing.npz")):
        cfg = at_start(AdversarialConfig, {"demos": demos})
        assert cfg == dataclasses.replace(AdversarialConfig(demos=demos), preset="default")
        assert at_start(BCConfig, {"demos": demos}) == dataclasses.replace(BCConfig(demos=demos), preset="default")
    assert from_dict(AdversarialConfig, {"demos": str(standard_hopper_demos)}).preset == "auto"  # read at the start
    std = at_start(AdversarialConfig, {"demos": str(standard_hopper_demos)})
    assert std.preset == "terminating"
    assert (std.policy_obs_delta, std.policy_prev_action, std.iterations) == (True, False, 15)
    assert (std.warm_start_iterations, std.warm_start_lr, std.warm_start_lr_decay, std.warm_start_log_std_lr_scale,
            std.warm_start_fit_log_std) == (2400, 3e-3, True, 10.0, True)
    assert dataclasses.replace(std, preset="fast-warm-start", policy_obs_delta=False, policy_prev_action=True,
                               warm_start_iterations=600) == \
        at_start(AdversarialConfig, {"demos": str(standard_hopper_demos), "preset": "fast-warm-start"})
    # the user's values win, also one equal to the field's default; a named preset is taken as named
    mine = at_start(AdversarialConfig, {"demos": str(standard_hopper_demos), "policy_prev_action": True,
                                         "warm_start_iterations": 100, "iterations": 30})
    assert (mine.preset, mine.policy_obs_delta, mine.policy_prev_action, mine.warm_start_iterations,
            mine.iterations) == ("terminating", True, True, 100, 30)
    default = at_start(AdversarialConfig, {"demos": str(standard_hopper_demos), "preset": "default"})
    assert default.warm_start_lr == 1e-2
    # the run's env_kwargs decide, as they decide the environment: paper's demonstrations made to end on a fall
    ended = at_start(AdversarialConfig, {"demos": paper, "env_kwargs": ["terminate_when_unhealthy=true"]})
    assert ended.preset == "terminating"
    kept = at_start(AdversarialConfig, {"demos": str(standard_hopper_demos),
                                         "env_kwargs": ["terminate_when_unhealthy=false"]})
    assert kept.preset == "default"
    bc = at_start(BCConfig, {"demos": str(standard_hopper_demos)})
    assert (bc.preset, bc.obs_delta, bc.prev_action, bc.iterations) == ("terminating", True, False, 500)
    # built in Python: resolved when it trains, the preset's values for the fields left at their defaults
    py = resolved(AdversarialConfig(demos=str(standard_hopper_demos), warm_start_iterations=100))
    assert (py.preset, py.policy_obs_delta, py.warm_start_iterations, py.warm_start_lr) == (
        "terminating", True, 100, 3e-3)
    assert resolved(std) is std


def test_train_on_terminating_demonstrations_records_the_preset_it_ran(standard_hopper_demos, tmp_path):
    tiny = ["--iterations", "1", "--num-envs", "2", "--hidden-size", "8", "--warm-start-iterations", "1",
            "--posterior-init-iterations", "1", "--critic-batch", "2", "--warm-start-batch", "2", "--eval-every", "0",
            "--critic-steps", "1", "--no-progress"]
    assert main(["train", "infogail-pomdp", "--demos", str(standard_hopper_demos), "--out", str(tmp_path / "igp"),
                 *tiny]) == 0
    written = json.loads((tmp_path / "igp" / "config.json").read_text())
    assert (written["preset"], written["policy_obs_delta"], written["policy_prev_action"]) == ("terminating", True,
                                                                                               False)
    assert (written["warm_start_iterations"], written["warm_start_lr"]) == (1, 3e-3)  # the flag over the preset
    assert main(["train", "bc", "--demos", str(standard_hopper_demos), "--out", str(tmp_path / "bc"),
                 "--iterations", "1", "--hidden-size", "8", "--no-progress"]) == 0
    written = json.loads((tmp_path / "bc" / "config.json").read_text())
    assert (written["preset"], written["obs_delta"], written["prev_action"]) == ("terminating", True, False)
    # a resume with the same flags resolves the same preset: it continues the run
    assert main(["train", "bc", "--demos", str(standard_hopper_demos), "--out", str(tmp_path / "bc"),
                 "--iterations", "2", "--hidden-size", "8", "--no-progress", "--resume"]) == 0


def test_circle_through_origin_and_every_modes_case_records_its_set(tmp_path, monkeypatch):
    c = Circle.through_origin(210, 5.0, -1)
    assert abs(c.center[0] + 5.0 * 3 ** 0.5 / 2) < 1e-9 and abs(c.center[1] + 2.5) < 1e-9
    monkeypatch.chdir(tmp_path)
    modes = {}
    for row in load_spec("circles-modes").rows:  # each recorded the spec's way, 100 episodes per mode
        record = [*row.demos.record[:row.demos.record.index("--episodes")], "--episodes", "60"]
        assert main(["demos", *record, "--out", f"{row.name}.npz"]) == 0
        spec = CirclesSpec.from_dict(Demonstrations.load(f"{row.name}.npz").metadata["env_kwargs"])
        modes[row.name] = len(spec.circles)
    assert modes == {"two": 2, "four": 4, "three": 3, "five": 5, "six": 6}
    five = CirclesSpec.from_dict(Demonstrations.load("five.npz").metadata["env_kwargs"]).circles
    assert five[1] == Circle.through_origin(90, 6.0, 1) and five[2] == Circle.through_origin(270, 5.0, -1)
    assert main(["demos", "circles", "--circles", "90:4", "--out", "bad.npz"]) == 2
    assert main(["demos", "circles", "--circles", "45:4:1,90:4:2", "--out", "bad.npz"]) == 2
    assert not Path("bad.npz").exists()


def test_modes_success_needs_purity_coverage_and_nmi():
    share = lambda *s: {"mode_share": list(s)}  # noqa: E731
    good = {"min_purity": 0.96, "nmi": 0.93, "modes_covered": 3, "per_code": [share(1, 0, 0)] * 3}
    assert modes_success(good)
    assert not modes_success({**good, "min_purity": 0.94})
    assert not modes_success({**good, "nmi": 0.89})
    assert not modes_success({**good, "modes_covered": 2})


def test_reproduce_circles_modes_tiny(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "adv.json").write_text(json.dumps({"iterations": 1, "num_envs": 4, "hidden_size": 8,
                                                   "warm_start_iterations": 2,
                                                   "posterior_init_iterations": 1, "critic_batch": 4, "eval_every": 0}))
    out = tmp_path / "results"
    assert main(["reproduce", "circles-modes", "--seeds", "1", "--cases", "two,three", "--episodes-per-code", "3",
                 "--adversarial-config", "adv.json", "--out", str(out), "--runs", "runs", "--no-progress"]) == 0
    results = json.loads((out / "metrics.json").read_text())
    assert list(results["rows"]) == ["two", "three"] and results["rows"]["three"]["demos"] == "data/circles-three.npz"
    assert len(results["rows"]["two"]["runs"]) == 1 and "success" in results["rows"]["two"]["runs"][0]
    assert "| three | 3 |" in (out / "table.md").read_text() and "| case | modes |" in (out / "table.md").read_text()


def _default_run(demos_path, out, **overrides):
    cfg = dataclasses.replace(AdversarialConfig(demos=str(demos_path), out=str(out), progress=False, eval_every=0),
                              **overrides)
    return evaluate_circles(TrainedPolicy.load(train_adversarial(cfg)), 50, seed=1000)[0]


def test_short_default_run_separates_the_two_circles(demos_path, tmp_path):
    """The defaults with a shorter schedule (the smoke version of the slow test below)."""
    m = _default_run(demos_path, tmp_path / "short", iterations=2, num_envs=64, warm_start_iterations=400,
                     posterior_init_iterations=50)
    assert m["modes_covered"] == 2 and m["min_purity"] >= 0.9, m


@pytest.mark.slow
def test_default_flags_learn_the_two_circles(demos_path, tmp_path):
    m = _default_run(demos_path, tmp_path / "default")
    assert m["modes_covered"] == 2 and m["min_purity"] >= 0.95 and m["nmi"] >= 0.9, m


def test_long_episodes_cut_the_episode_counts_to_the_step_caps(capsys):
    from pomil.algos.adversarial import sized_for_episodes
    from pomil.algos.bc import BCConfig
    from pomil.algos.bc import sized_for_episodes as bc_sized
    from pomil.algos.warm_start import cloning_window

    cfg = AdversarialConfig()
    for short in (33, 128):  # circles and the paper's Hopper: the configured counts
        assert sized_for_episodes(cfg, short) == cfg
    assert capsys.readouterr().err == ""
    long = sized_for_episodes(cfg, 1000)  # Hopper's own episodes
    assert (long.num_envs, long.warm_start_batch, long.critic_batch) == (65, 16, 16)
    assert dataclasses.replace(long, num_envs=256, warm_start_batch=64, critic_batch=64) == cfg
    assert "1000-step episodes: num_envs 256 -> 65, warm_start_batch 64 -> 16, critic_batch 64 -> 16" in \
        capsys.readouterr().err
    tiny = AdversarialConfig(max_iteration_steps=10, max_batch_steps=10, critic_batch=1)
    assert (lambda c: (c.num_envs, c.warm_start_batch, c.critic_batch))(sized_for_episodes(tiny, 1000)) == (1, 1, 1)
    assert bc_sized(BCConfig(), 128) == BCConfig()
    assert bc_sized(BCConfig(), 1000).batch_episodes == 16
    assert bc_sized(BCConfig(batch_episodes=8), 1000).batch_episodes == 8  # under the cap: as configured
    # a recurrent policy clones episodes longer than 128 steps in 128-step windows; shorter ones and a
    # feed-forward policy's stay whole, as does everything without the dataset-wide mixture assignment
    assert [cloning_window(cfg, n, True) for n in (33, 128, 1000)] == [0, 0, 128]
    assert cloning_window(dataclasses.replace(cfg, learner="infogail"), 1000, True) == 0
    assert cloning_window(cfg, 1000, False) == cloning_window(dataclasses.replace(cfg, mixture_balance="batch"),
                                                              1000, True) == 0
    assert sized_for_episodes(cfg, 1000, window=128).warm_start_batch == 64  # 64 windows: 8,192 steps


def test_few_demonstrations_clone_three_policies_acting_as_one(capsys, demos_path, tmp_path):
    from pomil.algos.warm_start import ENSEMBLE_MEMBERS, members_for_demonstrations
    from pomil.training import load_checkpoint

    cfg = AdversarialConfig()
    assert (cfg.policy_members, ENSEMBLE_MEMBERS) == (0, 3)  # auto

    def members(c=cfg, lengths=(1000,) * 8, window=128, recurrent=True, mixture=True):
        return members_for_demonstrations(c, list(lengths), window, recurrent=recurrent, mixture=mixture).policy_members

    # four standard-Hopper episodes per mode (64 windows), one or four circle episodes per mode: an ensemble of 3
    assert members() == 3
    assert "64 128-step windows of demonstrations: policy_members auto -> 3" in capsys.readouterr().err
    assert members(lengths=[33] * 2, window=0) == members(lengths=[33] * 8, window=0) == 3
    # sets larger than one batch (11 standard-Hopper episodes per mode, the shipped sets, the suite's 200 circle
    # episodes), a feed-forward policy, random codes, restarts, no warm start or a shared belief: one policy
    capsys.readouterr()
    for lengths, window in (([1000] * 22, 128), ([128] * 400, 0), ([33] * 200, 0), ([33] * 65, 0)):
        assert members(lengths=lengths, window=window) == 1
    assert members(recurrent=False) == members(mixture=False) == 1
    for key, value in (("warm_start_restarts", 2), ("warm_start_iterations", 0), ("belief", "shared")):
        assert members(dataclasses.replace(cfg, **{key: value})) == 1, key
    assert capsys.readouterr().err == ""
    # an explicit value stays, and the resolved one is what --resume reads back
    assert members(dataclasses.replace(cfg, policy_members=1)) == 1
    assert members(dataclasses.replace(cfg, policy_members=5), lengths=[33] * 200, window=0) == 5
    # a run records it in config.json: the suite's circles (200 episodes) clone one policy, a draw of one per mode three
    small = dict(demos=str(demos_path), iterations=0, hidden_size=8, warm_start_iterations=2,
                 posterior_init_iterations=1, eval_every=0, progress=False)
    for per_mode, expected in ((0, 1), (1, 3)):
        out = tmp_path / f"n{per_mode}"
        train_adversarial(AdversarialConfig(out=str(out), demos_per_mode=per_mode, **small))
        assert json.loads((out / "config.json").read_text())["policy_members"] == expected
        assert load_checkpoint(out / "checkpoint.pt")["policy_arch"].get("members", 1) == expected


def test_few_demonstrations_cut_the_cloning_batch_to_a_quarter_of_them(capsys):
    from pomil.algos.warm_start import MIN_CLONING_BATCH, sized_for_demonstrations

    cfg = AdversarialConfig()
    assert (cfg.warm_start_batch_share, MIN_CLONING_BATCH, cfg.warm_start_batch) == (4, 8, 64)
    # four standard-Hopper episodes per mode, two modes: 64 windows of 128 steps -> 16 a step
    four = sized_for_demonstrations(cfg, [1000] * 8, 128)
    assert four.warm_start_batch == 16 and dataclasses.replace(four, warm_start_batch=64) == cfg
    assert "64 128-step windows of demonstrations: warm_start_batch 64 -> 16" in capsys.readouterr().err
    assert sized_for_demonstrations(four, [1000] * 8, 128) == four  # idempotent (as --resume applies it again)
    # the windows that hold a demonstrated step: a 130-step episode has two, a 128-step one one
    assert sized_for_demonstrations(cfg, [130] * 20 + [128] * 20, 128).warm_start_batch == 15
    assert "60 128-step windows" in capsys.readouterr().err
    # sets larger than one batch keep it: 11 (172 windows) or 25 episodes per mode, one window over a batch, and the
    # shipped sets (circles, the paper's Hopper: 400 whole episodes each) and the test suite's 200 circle episodes
    for lengths, window in (([1000] * 22, 128), ([1000] * 50, 128), ([1000] * 8 + [1], 128), ([128] * 400, 0),
                            ([33] * 200, 0), ([33] * 65, 0)):
        assert sized_for_demonstrations(cfg, lengths, window) == cfg
    assert capsys.readouterr().err == ""
    # whole episodes count one each, and the batch never falls below the floor
    assert sized_for_demonstrations(cfg, [128] * 64, 0).warm_start_batch == 16
    assert sized_for_demonstrations(dataclasses.replace(cfg, warm_start_batch=128), [128] * 100,
                                    0).warm_start_batch == 25  # the set fits in a batch of 128
    assert sized_for_demonstrations(cfg, [33] * 2, 0).warm_start_batch == 8
    assert "2 episodes of demonstrations: warm_start_batch 64 -> 8" in capsys.readouterr().err
    assert sized_for_demonstrations(dataclasses.replace(cfg, warm_start_batch=4), [33] * 2, 0).warm_start_batch == 4
    off = dataclasses.replace(cfg, warm_start_batch_share=0)  # the specs whose tables ran the whole batch
    assert sized_for_demonstrations(off, [1000] * 8, 128) == off
    assert sized_for_demonstrations(dataclasses.replace(cfg, warm_start_batch_share=2), [1000] * 8,
                                    128).warm_start_batch == 32
