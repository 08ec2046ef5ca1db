import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pomil.api import TrainedPolicy
from pomil.cli import build_parser, main
from pomil.training import load_checkpoint
from tests.inprocess import pomil


def test_cli_smoke_demos_train_evaluate_plot(tmp_path):
    demos = tmp_path / "c.npz"
    r = pomil("demos", "circles", "--episodes", 40, "--out", demos, "--seed", 3)
    assert r.returncode == 0, r.stderr
    assert "40 episodes x 33 steps" in r.stdout
    run = tmp_path / "run"
    r = pomil("train", "bc", "--demos", demos, "--out", run, "--iterations", 20, "--policy", "mlp", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert {"checkpoint.pt", "metrics.csv", "config.json", "tb"} <= {p.name for p in run.iterdir()}
    assert any((run / "tb").iterdir())
    r = pomil("evaluate", run / "checkpoint.pt", "--episodes-per-code", 10, "--json")
    assert r.returncode == 0, r.stderr
    metrics = json.loads(r.stdout)
    assert metrics["algo"] == "bc" and metrics["episodes_per_code"] == 10
    assert abs(sum(metrics["overall_mode_share"]) + metrics["overall_none_share"] - 1) < 1e-9
    r = pomil("evaluate", run)
    assert r.returncode == 0 and "NMI(code, mode)" in r.stdout
    fig = tmp_path / "fig.png"
    r = pomil("plot", run / "checkpoint.pt", "--demos", demos, "--out", fig)
    assert r.returncode == 0, r.stderr
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_config_file_sets_options_and_unknown_keys_list_the_valid_ones(tmp_path, demos_path):
    cfg = tmp_path / "bc.json"
    cfg.write_text(json.dumps({"iterations": 3, "policy": "mlp", "hidden-size": 8, "progress": False}))
    assert main(["train", "bc", "--config", str(cfg), "--demos", str(demos_path), "--out", str(tmp_path / "r")]) == 0
    saved = json.loads((tmp_path / "r" / "config.json").read_text())
    assert (saved["iterations"], saved["policy"], saved["hidden_size"]) == (3, "mlp", 8)
    cfg.write_text(json.dumps({"iterations": 3, "learning_rate": 0.1}))
    r = pomil("train", "bc", "--config", cfg, "--demos", demos_path, "--out", tmp_path / "r2")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "unknown key(s) ['learning_rate']" in r.stderr and "batch_episodes" in r.stderr and "lr" in r.stderr


@pytest.mark.parametrize("args, text", [
    (["train", "bc", "--demos", "x.npz", "--iterations", "ten"], "config key 'iterations': expected int"),
    (["train", "bc", "--out", "o"], "--demos is required"),
    (["demos", "circles", "--episodes", "3"], "multiple of the number of modes"),
    (["evaluate", "nope.pt"], "no such checkpoint"),
])
def test_bad_options_are_one_line_errors(args, text, tmp_path):
    r = pomil(*args, cwd=tmp_path)  # a subprocess of its own: tests/test_config.py
    assert r.returncode == 2 and text in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_every_option_has_help_with_its_default():
    parser = build_parser()
    sub = {a.dest: a for a in parser._actions if a.dest == "command"}["command"]

    def walk(p):
        yield p
        for a in p._actions:
            if a.__class__.__name__ == "_SubParsersAction":
                for child in a.choices.values():
                    yield from walk(child)

    for p in walk(parser):
        for action in p._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, (p.prog, action.dest)
    assert set(sub.choices) >= {"demos", "train", "evaluate", "plot", "reproduce"}


def test_train_usage_lines_show_demos_as_required():
    from pomil.learners import LEARNERS

    train = {a.dest: a for a in build_parser()._actions if a.dest == "command"}["command"].choices["train"]
    learners = {a.dest: a for a in train._actions if a.dest == "algo"}["algo"].choices
    assert set(learners) == {name for name, learner in LEARNERS.items() if learner.command}
    for name, p in learners.items():
        assert p.format_usage() == f"usage: pomil train {name} --demos FILE.npz [--config FILE.json] [options]\n"


def test_reproduce_tiny_writes_metrics_table_and_figure(tmp_path):
    out = tmp_path / "results"
    (tmp_path / "adv.json").write_text(json.dumps({"warm_start_iterations": 3, "num_envs": 8, "hidden_size": 16}))
    (tmp_path / "bc.json").write_text(json.dumps({"hidden_size": 8, "obs_delta": True}))
    args = ("reproduce", "circles", "--seeds", 2, "--bc-iterations", 5, "--episodes-per-code", 5,
            "--rows", "bc-mlp,bc-gru,gail,infogail-pomdp", "--adversarial-iterations", 2,
            "--adversarial-config", tmp_path / "adv.json", "--bc-config", tmp_path / "bc.json",
            "--out", out, "--runs", tmp_path / "runs", "--demos", tmp_path / "d.npz", "--no-progress")
    r = pomil(*args)
    assert r.returncode == 0, r.stderr
    assert "recording" in r.stdout and (tmp_path / "d.npz").exists()  # the spec's recipe, into --demos
    bc_run = json.loads((tmp_path / "runs" / "bc-gru" / "seed1" / "config.json").read_text())
    assert (bc_run["hidden_size"], bc_run["obs_delta"], bc_run["iterations"], bc_run["policy"]) == (8, True, 5, "gru")
    metrics = json.loads((out / "metrics.json").read_text())
    assert list(metrics["rows"]) == ["bc-mlp", "bc-gru", "gail", "infogail-pomdp"]
    assert [run["train_seed"] for run in metrics["rows"]["bc-gru"]["runs"]] == [0, 1]
    assert metrics["spec"]["name"] == "circles" and metrics["spec"]["overrides"]["bc"]["iterations"] == 5
    settings = metrics["rows"]["infogail-pomdp"]["config"]
    assert (settings["gradient_penalty"], settings["warm_start_iterations"], settings["iterations"]) == (10.0, 3, 2)
    assert "| bc-mlp | 2 | 0/2 |" in (out / "table.md").read_text()  # one code: never every mode
    assert (out / "figure.png").stat().st_size > 1000
    assert [p.name for p in (out / "policies").iterdir()] == ["infogail-pomdp-seed0.pt"]  # the spec keeps one
    with __import__("numpy").load(out / "rollouts.npz") as roll:
        assert {"experts/positions", "bc-mlp/positions", "infogail-pomdp/groups"} <= set(roll.files)
    # --resume: every run is finished with the same settings, so none trains again and the figures are the same
    checkpoints = {p: p.read_bytes() for p in (tmp_path / "runs").glob("*/seed*/checkpoint.pt")}
    r = pomil(*args, "--resume")
    assert r.returncode == 0, r.stderr
    assert len(checkpoints) == 8 and all(p.read_bytes() == b for p, b in checkpoints.items())
    again = json.loads((out / "metrics.json").read_text())["rows"]
    assert {k: v["summary"] for k, v in again.items()} == {k: v["summary"] for k, v in metrics["rows"].items()}


def test_reproduce_any_spec_file_with_continuous_codes(tmp_path):
    """A spec of one's own: a continuous code on circles of varying radius, scored by code against radius."""
    (tmp_path / "spec.toml").write_text("""
description = "tiny continuous codes"
seeds = 2
policies = "first"
[[rows]]
name = "igp-continuous"
learner = "infogail-pomdp"
[rows.settings]
code_kind = "continuous"
iterations = 1
warm_start_iterations = 3
num_envs = 6
hidden_size = 8
posterior_init_iterations = 2
eval_every = 0
[demos]
file = "d.npz"
record = "circles --modes one --radius-range 3,7 --episodes 20"
[evaluation]
code_values = 3
episodes_per_value = 2
""")
    r = pomil("reproduce", "spec.toml", "--no-progress", "--jobs", "1", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "runs" / "results" / "spec"  # the default places
    metrics = json.loads((out / "metrics.json").read_text())
    row = metrics["rows"]["igp-continuous"]
    assert row["kind"] == "code-radius" and len(row["runs"]) == 2 and row["config"]["code_kind"] == "continuous"
    assert row["successes"] == sum(abs(r["spearman"]) >= 0.9 for r in row["runs"])
    assert "| igp-continuous | 1 |" in (out / "table.md").read_text()
    assert (out / "figure.png").stat().st_size > 1000
    assert TrainedPolicy.load(out / "policies" / "igp-continuous-seed0.pt").code_dim == 1
    assert (tmp_path / "runs" / "spec" / "igp-continuous" / "seed1" / "result.json").exists()


@pytest.mark.parametrize("text, message", [
    ("seeds = 2\nlearners = ['bc']", "no demonstrations"),
    ("learners = ['bc']\nsed = 2\n[demos]\nfile = 'd.npz'", "unknown key(s) ['sed']"),
    ("learners = ['bc', 'bc']\n[demos]\nfile = 'd.npz'", "rows named twice: ['bc']"),
    ("learners = ['bc']\nseeds = 0\n[demos]\nfile = 'd.npz'", "key 'seeds': expected an integer >= 1, got 0"),
    ("[[rows]]\nlearner = 'gail'\nsettings = { lrr = 1 }\n[demos]\nfile = 'd.npz'", "unknown key(s) ['lrr']"),
    ("[[rows]]\nlearner = 'gail'\nsettings = { lr = -1 }\n[demos]\nfile = 'd.npz'", "config key 'lr'"),
    ("learners = ['bc'\n", "not valid TOML"),
    ("learners = ['bc']\n[demos]\nfile = 'missing.npz'", "missing.npz: demonstrations not found"),
])
def test_a_bad_spec_is_one_line_before_anything_runs(tmp_path, text, message):
    (tmp_path / "bad.toml").write_text(text)
    r = pomil("reproduce", "bad.toml", cwd=tmp_path)
    assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "bad.toml" in r.stderr or "missing.npz" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


def _with(demos_path, tmp_path, name, **changes):
    """A copy of the test demonstrations with some arrays or metadata changed."""
    from pomil.data import Demonstrations

    d = Demonstrations.load(demos_path)
    md = {**d.metadata, **changes.pop("metadata", {})}
    fields = {"observations": d.observations, "actions": d.actions, "episode_bounds": d.episode_bounds,
              "labels": d.labels, "states": d.states, **changes}
    out = tmp_path / name
    Demonstrations(**fields, metadata=md).save(out)
    return out


def test_mismatched_demonstrations_are_refused_by_train_plot_and_evaluate(demos_path, tmp_path, capsys):
    import numpy as np

    run = tmp_path / "run"
    assert main(["train", "bc", "--demos", str(demos_path), "--out", str(run), "--iterations", "2", "--policy", "mlp",
                 "--hidden-size", "8", "--no-progress"]) == 0
    capsys.readouterr()
    from pomil.data import Demonstrations

    d = Demonstrations.load(demos_path)
    wide = _with(demos_path, tmp_path, "wide.npz", states=np.concatenate([d.states, d.states[:, :1]], 1))
    history = _with(demos_path, tmp_path, "h2.npz", observations=np.concatenate([d.observations, d.observations], 1),
                    metadata={"env_kwargs": {**d.metadata["env_kwargs"], "history": 2}})
    other = _with(demos_path, tmp_path, "pendulum.npz",
                  observations=np.concatenate([d.observations, d.actions[:, :1]], 1),
                  actions=d.actions[:, :1], states=None,
                  metadata={"env_id": "Pendulum-v1", "env_kwargs": {}, "observation_mask": None})
    cases = [
        (["train", "bc", "--demos", str(wide), "--out", str(tmp_path / "no")],
         f"{wide}: field 'states': expected 2 columns (the full state of pomil/Circles-v0), got 3"),
        (["plot", str(run), "--demos", str(wide), "--out", str(tmp_path / "f.png")],
         f"{wide}: field 'states': expected 2 columns"),
        (["evaluate", str(run), "--demos", str(wide)], f"{wide}: field 'states': expected 2 columns"),
        (["plot", str(run), "--demos", str(other), "--out", str(tmp_path / "f.png")],
         f"{other}: demonstrations of Pendulum-v1, but {run} was trained on pomil/Circles-v0"),
        (["evaluate", str(run), "--demos", str(other)],
         f"{other}: demonstrations of Pendulum-v1, but {run} was trained on pomil/Circles-v0"),
        (["evaluate", str(run), "--demos", str(history)],
         f"{history}: observations 4 / actions 2 wide, but {run}'s policy takes 2 / 2"),
        (["plot", "--demos", str(other), "--out", str(tmp_path / "f.png")],
         f"{other}: plot draws circles demonstrations; these are of Pendulum-v1"),
    ]
    for argv, text in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(f"pomil: error: {text}") and err.count("\n") == 1, (argv, err)
    assert not (tmp_path / "no").exists() and not (tmp_path / "f.png").exists()
    assert main(["evaluate", str(run), "--demos", str(demos_path), "--episodes-per-code", "2"]) == 0
    assert "circles evaluation does not use it" in capsys.readouterr().err


CIRCLES = Path(__file__).resolve().parents[1] / "data" / "circles.npz"
TINY_ADVERSARIAL = ["--iterations", "1", "--num-envs", "4", "--hidden-size", "8", "--warm-start-iterations", "2",
                    "--posterior-init-iterations", "1", "--critic-batch", "4", "--eval-every", "0", "--no-progress"]


@pytest.mark.parametrize("encoder", ["lstm", "attention"])
def test_infogail_pomdp_trains_with_each_belief_encoder_and_its_policy_loads_and_acts(encoder, tmp_path):
    out = tmp_path / encoder
    assert main(["train", "infogail-pomdp", "--belief-encoder", encoder, "--attention-context", "5",
                 "--demos", str(CIRCLES), "--out", str(out), *TINY_ADVERSARIAL]) == 0
    assert json.loads((out / "config.json").read_text())["belief_encoder"] == encoder
    policy = TrainedPolicy.load(out / "checkpoint.pt")
    assert policy.policy.arch.encoder == encoder
    assert policy.policy.arch.to_dict().get("context", 5) == 5
    policy.reset(3, [0, 1, 0], seed=0)
    for _ in range(3):
        assert policy.act([[0.1, 0.2]] * 3).shape == (3, 2)
    assert main(["evaluate", str(out), "--episodes-per-code", "2"]) == 0


@pytest.mark.parametrize("learner", [["infogail-pomdp"], ["infogail-pomdp", "--belief-encoder", "attention"],
                                     ["gail"]])
def test_adversarial_learners_train_in_bfloat16_and_record_it(learner, tmp_path):
    out = tmp_path / "bf16"
    assert main(["train", *learner, "--precision", "bfloat16", "--demos", str(CIRCLES), "--out", str(out),
                 *TINY_ADVERSARIAL]) == 0
    assert json.loads((out / "config.json").read_text())["precision"] == "bfloat16"
    ckpt = load_checkpoint(out / "checkpoint.pt")
    assert all(v.dtype == torch.float32 for v in ckpt["nets"]["critic"].values())
    with pytest.raises(SystemExit) as e:  # argparse names the choices
        main(["train", "infogail-pomdp", "--precision", "float16", "--demos", str(CIRCLES),
              "--out", str(tmp_path / "no"), *TINY_ADVERSARIAL])
    assert e.value.code == 2
    assert not (tmp_path / "no").exists()


@pytest.mark.parametrize("encoder", ["lstm", "attention"])
def test_bc_trains_each_encoder_and_the_checkpoint_rebuilds_the_same_policy(encoder, tmp_path):
    out = tmp_path / encoder
    assert main(["train", "bc", "--policy", encoder, "--attention-context", "3", "--demos", str(CIRCLES),
                 "--out", str(out), "--iterations", "2", "--hidden-size", "8", "--no-progress"]) == 0
    ckpt = load_checkpoint(out / "checkpoint.pt")
    policy = TrainedPolicy.load(out / "checkpoint.pt")
    assert policy.policy.arch.encoder == encoder
    assert policy.policy.arch.context == 3 or encoder != "attention"
    for k, v in ckpt["policy"].items():
        assert torch.equal(policy.policy.state_dict()[k], v)
    policy.reset(2, seed=0)
    assert policy.act([[0.0, 0.0], [1.0, -1.0]], deterministic=True).shape == (2, 2)


def test_bc_with_the_observation_change_and_no_previous_action_round_trips(tmp_path):
    out = tmp_path / "delta"
    assert main(["train", "bc", "--policy", "gru", "--obs-delta", "--no-prev-action", "--demos", str(CIRCLES),
                 "--out", str(out), "--iterations", "2", "--hidden-size", "8", "--no-progress"]) == 0
    ckpt = load_checkpoint(out / "checkpoint.pt")
    scale = ckpt["policy"]["encoder.delta_scale"]
    assert scale.shape == (2,) and bool((scale > 1).all())  # the circles move ~0.1-0.2 a step: 1 / std > 1
    policy = TrainedPolicy.load(out / "checkpoint.pt")
    assert (policy.policy.arch.obs_delta, policy.policy.arch.prev_action) == (True, False)
    assert torch.equal(policy.policy.encoder.delta_scale, scale)
    policy.reset(2, seed=0)
    assert policy.act([[0.0, 0.0], [1.0, -1.0]], deterministic=True).shape == (2, 2)


def test_infogail_pomdp_with_the_policys_input_view_trains_resumes_and_loads(tmp_path):
    out = tmp_path / "view"
    flags = ["--policy-obs-delta", "--no-policy-prev-action", "--demos", str(CIRCLES), "--out", str(out)]
    assert main(["train", "infogail-pomdp", *flags, *TINY_ADVERSARIAL]) == 0
    written = json.loads((out / "config.json").read_text())
    assert (written["policy_obs_delta"], written["policy_prev_action"]) == (True, False)
    policy = TrainedPolicy.load(out / "checkpoint.pt")
    assert (policy.policy.arch.obs_delta, policy.policy.arch.prev_action) == (True, False)
    policy.reset(2, [0, 1], seed=0)
    assert policy.act([[0.1, 0.2]] * 2).shape == (2, 2)
    assert main(["train", "infogail-pomdp", *flags, *TINY_ADVERSARIAL, "--iterations", "2", "--resume"]) == 0
    assert load_checkpoint(out / "checkpoint.pt")["iteration"] == 2


def test_resume_reads_the_runs_own_config_and_refuses_a_changed_one(tmp_path, capsys):
    """``--resume --out R --iterations N`` needs no other flag: the run's config.json gives the rest, and
    the resumed run is the run uninterrupted; a flag given that changes the results is still refused."""
    tiny = [*TINY_ADVERSARIAL, "--seed", "3", "--demos-per-mode", "20", "--demos", str(CIRCLES)]
    whole, split = tmp_path / "whole", tmp_path / "split"
    assert main(["train", "infogail-pomdp", *tiny, "--out", str(whole), "--iterations", "2"]) == 0
    assert main(["train", "infogail-pomdp", *tiny, "--out", str(split)]) == 0
    assert main(["train", "infogail-pomdp", "--out", str(split), "--iterations", "2", "--resume"]) == 0
    a, b = load_checkpoint(whole / "checkpoint.pt"), load_checkpoint(split / "checkpoint.pt")
    assert b["iteration"] == 2 and a["config"] == {**b["config"], "out": str(whole)}
    assert all(torch.equal(a["policy"][k], b["policy"][k]) for k in a["policy"])
    capsys.readouterr()
    assert main(["train", "infogail-pomdp", "--out", str(split), "--iterations", "3", "--seed", "4", "--resume"]) == 2
    assert capsys.readouterr().err == (f"pomil: error: {split / 'checkpoint.pt'}: cannot resume with a different "
                                       "config (changed: seed)\n")
    assert main(["train", "bc", "--out", str(split), "--iterations", "3", "--resume"]) == 2
    assert capsys.readouterr().err == (f"pomil: error: {split / 'config.json'}: the run there is infogail-pomdp's, "
                                       "not bc's (resume it with pomil train infogail-pomdp --resume)\n")
    assert load_checkpoint(split / "checkpoint.pt")["iteration"] == 2


def test_cli_smoke_continuous_codes_demos_train_evaluate_plot(tmp_path):
    demos = tmp_path / "r.npz"
    r = pomil("demos", "circles", "--modes", "one", "--radius-range", "3,7", "--episodes", 24, "--out", demos)
    assert r.returncode == 0, r.stderr
    assert "radius uniform in [3, 7]" in r.stdout
    run = tmp_path / "igp"
    r = pomil("train", "infogail-pomdp", "--demos", demos, "--code-kind", "continuous", "--out", run,
              "--iterations", 1, "--num-envs", 6, "--hidden-size", 8, "--warm-start-iterations", 3,
              "--posterior-init-iterations", 2, "--critic-batch", 6, "--eval-episodes", 2, "--no-progress")
    assert r.returncode == 0, r.stderr
    saved = json.loads((run / "config.json").read_text())
    assert (saved["code_kind"], saved["code_dim"], saved["code_prior"]) == ("continuous", 1, "uniform")
    r = pomil("evaluate", run, "--episodes-per-code", 2, "--code-values", 3, "--json")
    assert r.returncode == 0, r.stderr
    m = json.loads(r.stdout)
    assert m["code_dim"] == 1 and len(m["dims"][0]["median_radius"]) == 3 and -1 <= m["spearman"] <= 1
    assert m["spearman_max"] == pytest.approx(math.sqrt(1 - 3 / 35))  # 3 tied values of 2
    assert m["dims"][0]["code_values"] == pytest.approx([-2 / 3, 0.0, 2 / 3])
    r = pomil("evaluate", run, "--episodes-per-code", 2)
    assert r.returncode == 0 and "Spearman rho(code, fitted radius)" in r.stdout, r.stderr
    r = pomil("plot", run, "--demos", demos, "--out", tmp_path / "f.png", "--episodes-per-code", 2)
    assert r.returncode == 0, r.stderr
    r = pomil("train", "infogail", "--demos", demos, "--code-kind", "continuous", "--num-codes", 3, "--out",
              tmp_path / "bad")
    assert r.returncode == 2 and "config key 'num_codes': discrete codes only" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "bad").exists()
    r = pomil("demos", "circles", "--radius-range", "7,3", "--out", tmp_path / "x.npz")
    assert r.returncode == 2 and "config key 'radius_range'" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("hidden, args, hint", [
    ("minari", ["demos", "import-minari", "pomil/x-v0", "--out", "x.npz"], "pip install 'pomil[minari]'"),
    ("minari", ["demos", "export-minari", "DEMOS", "--dataset-id", "pomil/x-v0"], "pip install 'pomil[minari]'"),
    ("ray", ["reproduce", "circles", "--seeds", "1", "--ray", "--out", "r"], "pip install 'pomil[ray]'"),
])
def test_a_missing_extra_is_a_one_line_hint(hidden, args, hint, demos_path, tmp_path, monkeypatch, capsys):
    """Without the extra (its module hidden, as if not installed): one line naming the extra to install, for a
    package user and for a source checkout, exit status 2, nothing written."""
    monkeypatch.setitem(sys.modules, hidden, None)  # `import minari` / `import ray` now raise ImportError
    monkeypatch.chdir(tmp_path)
    code = main([str(demos_path) if a == "DEMOS" else a for a in args])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert hint in err and f"pip install -e '.[{hidden}]'" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_version_is_the_packages():
    import pomil

    r = pomil_cli = subprocess.run([sys.executable, "-m", "pomil.cli", "--version"], capture_output=True, text=True,
                                   timeout=120)
    assert pomil_cli.returncode == 0 and r.stdout.strip() == f"pomil {pomil.__version__}"
    from importlib.metadata import version

    assert version("pomil") == pomil.__version__  # one source: the installed metadata read it from the package


def test_the_warm_start_shows_its_progress(demos_path, tmp_path, capsys):
    """The warm start and the posterior's warm-up each draw a bar with their loss (on stderr, as the run's own)."""
    args = ["train", "infogail-pomdp", "--demos", str(demos_path), "--out", str(tmp_path / "run"), *TINY_ADVERSARIAL]
    assert main([*args[:-1], "--warm-start-iterations", "4", "--posterior-init-iterations", "3", "--progress"]) == 0
    err = capsys.readouterr().err
    assert "warm start: 100%" in err and "4/4" in err and "nll=" in err
    assert "posterior warm start: 100%" in err and "3/3" in err and "loss=" in err
    assert main([*args, "--out", str(tmp_path / "quiet")]) == 0  # --no-progress: no bars
    assert "warm start" not in capsys.readouterr().err


def test_docs_lists_the_topics_and_prints_one(capsys):
    root = Path(__file__).resolve().parents[1]
    assert main(["docs"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in listed] == sorted(p.stem for p in (root / "docs").glob("*.md"))
    assert "method     Method and training recipe" in listed
    assert main(["docs", "method"]) == 0
    assert capsys.readouterr().out == (root / "docs" / "method.md").read_text()
    assert main(["docs", "nope"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pomil: error: no documentation topic 'nope': choose from gpu, hopper,")
    assert err.count("\n") == 1


@pytest.mark.parametrize("args", [["docs"], ["docs", "method"]])  # a short page (flushed at the end), a long one
def test_a_reader_that_leaves_ends_the_command_quietly(args):
    """``pomil docs method | head``: stdout whose reader has gone is exit status 141 (as SIGPIPE in a shell) with
    nothing on stderr, not a traceback. The pipe's read end is closed before pomil starts, so every write fails."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run([sys.executable, "-m", "pomil", *args], stdout=write_end, stderr=subprocess.PIPE,
                              text=True, timeout=120)
    finally:
        os.close(write_end)
    assert (done.returncode, done.stderr) == (141, "")
