"""Shipped Hopper demonstrations and experts; CLI smoke runs on Hopper."""

from pathlib import Path

import numpy as np
import torch

from pomil.api import TrainedPolicy
from pomil.cli import main
from pomil.data import Demonstrations, check_demos_env
from pomil.envs import executed_actions_fn, make_vec_env
from pomil.envs.locomotion import HOPPER_EXPERTS, HOPPER_ID, SHIPPED_EXPERTS, hopper_kwargs
from pomil.eval.tasks import reference_of, rollout_locomotion
from pomil.nn import heads
from pomil.nn.policy import GaussianPolicy, PolicyArch
from pomil.rl.collect import collect

ROOT = Path(__file__).resolve().parents[1]
DEMOS = ROOT / "data" / "hopper-paper.npz"
EXPERTS = HOPPER_EXPERTS["paper"]


def test_shipped_demonstrations_load_and_validate():
    demos = Demonstrations.load(DEMOS)
    env_id, kwargs = check_demos_env(demos, str(DEMOS))
    assert env_id == HOPPER_ID and kwargs == hopper_kwargs("forward", "paper")
    assert demos.num_episodes == 400 and (demos.episode_lengths == 128).all()
    assert np.bincount(demos.labels).tolist() == [200, 200]
    assert demos.obs_dim == 5 and demos.states.shape[1] == 11
    np.testing.assert_array_equal(demos.observations, demos.states[:, :5])  # qpos[1:], no velocities
    ref = reference_of(demos.metadata)
    assert ref["tasks"]["backward"]["forward_reward_weight"] == -1.0
    for task in ("forward", "backward"):  # experts well above standing still
        assert ref["expert_returns"][task] > ref["still_returns"][task] + 100
        assert ref["expert_displacement"][task] > 1.0


def test_the_shipped_experts_are_package_data():
    """Found inside the package wherever it is installed (not through the current folder), and named by the
    package data the wheel takes."""
    import tomllib

    import pomil

    assert Path(pomil.__file__).parent / "experts" == SHIPPED_EXPERTS
    paths = [Path(p) for setting in HOPPER_EXPERTS.values() for p in setting.values()]
    assert len(paths) == 4 and all(p.is_file() and p.parent == SHIPPED_EXPERTS for p in paths)
    package_data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "experts/*" in package_data["pomil"]


def test_shipped_experts_reproduce_their_recorded_returns():
    demos = Demonstrations.load(DEMOS)
    for task, path in EXPERTS.items():
        expert = TrainedPolicy.load(path)
        roll = rollout_locomotion(expert, hopper_kwargs(task, "paper"), 16, seed=99)
        recorded = demos.metadata["expert_returns"][task]
        assert abs(roll["returns"].mean() - recorded) < 0.1 * recorded, (task, roll["returns"].mean(), recorded)


def test_collect_masks_steps_after_termination():
    env = make_vec_env(HOPPER_ID, hopper_kwargs("forward", "standard"), 4, seed=0)
    policy = GaussianPolicy(PolicyArch(11, 3, "mlp", 16, 0, 1.0))  # wide noise: falls within a few dozen steps
    value = heads.value(11, 3, 0, encoder="mlp", hidden_size=16)
    roll, _, _, rewards = collect(env, policy, value, num_codes=0, execute=executed_actions_fn(HOPPER_ID, {}),
                                  generator=torch.Generator().manual_seed(0),
                                  device=torch.device("cpu"))
    lengths = roll.mask.sum(0)
    assert roll.num_steps == int(lengths.max()) < 1000
    for i, n in enumerate(lengths.tolist()):
        assert roll.mask[:n, i].all() and not roll.mask[n:, i].any()
        assert bool(roll.terminated[n - 1, i]) and roll.terminated[:, i].sum() == 1
        assert (rewards[n:, i] == 0).all()


def test_cli_expert_and_infogail_pomdp_smoke(tmp_path, capsys):
    out = tmp_path / "expert"
    assert main(["experts", "hopper", "--task", "backward", "--iterations", "2", "--num-envs", "8", "--ppo-epochs", "2",
                 "--minibatches", "4", "--out", str(out), "--no-progress"]) == 0
    assert (out / "checkpoint.pt").exists() and (out / "evaluation.json").exists()
    run = tmp_path / "ip"
    assert main(["train", "infogail-pomdp", "--demos", str(DEMOS), "--out", str(run), "--iterations", "2",
                 "--num-envs", "8",
                 "--warm-start-iterations", "2", "--posterior-init-iterations", "2", "--eval-every", "1",
                 "--eval-episodes", "2", "--critic-batch", "8", "--no-progress"]) == 0
    header = (run / "metrics.csv").read_text().splitlines()[0]
    assert "eval/forward/normalised_return" in header and "eval/backward/progress" in header
    capsys.readouterr()
    assert main(["evaluate", str(run / "checkpoint.pt"), "--demos", str(DEMOS), "--episodes-per-code", "2"]) == 0
    printed = capsys.readouterr()
    assert "forward" in printed.out and "displacement ratio" in printed.out
    assert "evaluate (episodes): 100%" in printed.err and "8/8" in printed.err  # 2 codes x 2 episodes x 2 tasks
    assert "step 128" in printed.err  # the paper setting's episodes all end at its last step
    assert main(["evaluate", str(run / "checkpoint.pt"), "--demos", str(DEMOS), "--episodes-per-code", "2",
                 "--no-progress"]) == 0
    assert capsys.readouterr().err == ""
    assert main(["evaluate", str(run / "checkpoint.pt")]) == 2  # a Hopper policy needs --demos


def test_reproduce_hopper_smoke_with_override(tmp_path):
    import json

    override = tmp_path / "adv.json"
    override.write_text(json.dumps({"num_envs": 8, "critic_batch": 8, "warm_start_iterations": 2,
                                    "posterior_init_iterations": 2,
                                    "eval_every": 1, "eval_episodes": 2}))
    out = tmp_path / "results"
    assert main(["reproduce", "hopper", "--seeds", "1", "--rows", "bc-mlp,infogail-pomdp", "--bc-iterations", "2",
                 "--adversarial-iterations", "1", "--adversarial-config", str(override), "--episodes-per-code", "2",
                 "--demos", str(DEMOS), "--out", str(out), "--runs", str(tmp_path / "runs"), "--no-progress"]) == 0
    results = json.loads((out / "metrics.json").read_text())
    ip = results["rows"]["infogail-pomdp"]
    assert ip["config"]["num_envs"] == 8  # the user's file, not only the recipe
    assert ip["runs"][0]["curve"]["env_steps"] == [0.0, 8 * 128.0]  # after the warm start, then after iteration 1
    assert ip["config"]["warm_start_codes"] == "mixture"  # the Hopper recipe under the user's file
    assert set(ip["runs"][0]["tasks"]) == {"forward", "backward"} and results["setting"] == "paper"
    assert (out / "table.md").exists() and (out / "figure.png").exists()
    assert sorted(p.name for p in (out / "policies").iterdir()) == ["bc-mlp-seed0.pt", "infogail-pomdp-seed0.pt"]


def test_standard_setting_records_from_the_shipped_standard_experts(tmp_path, capsys):
    """The paper-setting experts fall soon after step 128; the standard setting has experts of its own
    (the hopper-standard spec's recipe, with fewer episodes)."""
    from pomil.experiment import DemosSource, load_spec

    record = load_spec("hopper-standard").rows[0].demos.record
    assert record == ("hopper", "--setting", "standard")
    path = DemosSource(str(tmp_path / "std.npz"), (*record, "--episodes", "2")).ensure(progress=False)
    assert "record (episodes)" not in capsys.readouterr().err  # reproduce --no-progress: no recording bar either
    demos = Demonstrations.load(path)
    assert demos.metadata["setting"] == "standard" and demos.num_episodes == 4
    assert demos.metadata["expert_returns"]["forward"] > 1500 and demos.metadata["expert_returns"]["backward"] > 1500
    assert demos.episode_lengths.max() > 128
    assert "N(0, 0.1^2) action noise (DART)" in demos.metadata["merged_from"][0]["source"]  # the setting's noise


def test_cli_demos_hopper_records_with_the_settings_action_noise_and_experts(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # from any folder: the shipped experts come from the package
    std = ["--episodes", "1"]  # the standard setting's own shipped experts, without naming them
    cases = {"paper": (["--episodes", "1"], "no"), "standard": (std, "0.1"),
             "standard-clean": ([*std, "--action-noise", "0"], "no")}
    for name, (extra, noise) in cases.items():
        out = tmp_path / f"{name}.npz"
        assert main(["demos", "hopper", "--setting", name.split("-")[0], "--out", str(out), *extra]) == 0
        assert "record (episodes): 100%" in capsys.readouterr().err  # 2 of 2 recorded
        md = Demonstrations.load(out).metadata
        if name.startswith("standard"):  # the paper's experts fall soon after step 128
            assert md["expert_returns"]["forward"] > 1500 and md["expert_returns"]["backward"] > 1500
        sources = [m["source"] for m in md["merged_from"]]
        assert all(("DART" in src) == (noise != "no") for src in sources), sources
        if noise != "no":
            assert all(f"N(0, {noise}^2) action noise (DART)" in src for src in sources)
    capsys.readouterr()
    assert main(["demos", "hopper", "--setting", "standard", "--out", str(tmp_path / "bad.npz"), *std,
                 "--action-noise", "-0.5"]) == 2
    assert "--action-noise must be -1 (the setting's) or >= 0, got -0.5" in capsys.readouterr().err
    assert not (tmp_path / "bad.npz").exists()


def test_demos_and_reproduce_take_experts_from_a_folder(tmp_path, capsys):
    """--experts DIR: the package's file names or `pomil experts hopper`'s run directories; a folder without
    them, or a spec that records no Hopper demonstrations, is one line and nothing written."""
    import shutil

    shipped, runs = tmp_path / "shipped", tmp_path / "runs"
    shipped.mkdir()
    for task, path in HOPPER_EXPERTS["paper"].items():
        shutil.copy(path, shipped / Path(path).name)
        (runs / f"expert-hopper-{task}-paper").mkdir(parents=True)
        shutil.copy(path, runs / f"expert-hopper-{task}-paper" / "checkpoint.pt")
    recorded = {}
    for folder in (shipped, runs):
        out = tmp_path / f"{folder.name}.npz"
        assert main(["demos", "hopper", "--experts", str(folder), "--episodes", "1", "--out", str(out)]) == 0
        recorded[folder.name] = Demonstrations.load(out)
    assert np.array_equal(recorded["shipped"].observations, recorded["runs"].observations)
    capsys.readouterr()
    missing = tmp_path / "missing.npz"
    assert main(["reproduce", "hopper", "--experts", str(tmp_path / "none"), "--demos", str(missing), "--rows",
                 "bc-mlp", "--seeds", "1", "--out", str(tmp_path / "r"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"--experts {tmp_path / 'none'}: no forward expert of the paper setting there (expected " \
           "hopper-forward.pt or expert-hopper-forward-paper/checkpoint.pt" in err, err
    assert not missing.exists()
    assert main(["reproduce", "circles", "--experts", str(shipped), "--out", str(tmp_path / "c")]) == 2
    assert capsys.readouterr().err.count("\n") == 1 and not (tmp_path / "c").exists()


def test_reproduce_hopper_first_seed_and_merge_join_seeds(tmp_path, capsys):
    """`--first-seed` runs later seeds; `pomil reproduce merge` joins them with the earlier ones into one
    table of all seeds (runs in seed order, policies, summaries recomputed), and refuses other settings."""
    import json

    import numpy as np

    def run(first: int, out: str, iterations: str = "2") -> None:
        assert main(["reproduce", "hopper", "--seeds", "1", "--first-seed", str(first), "--rows", "bc-mlp",
                     "--bc-iterations", iterations, "--episodes-per-code", "2", "--demos", str(DEMOS),
                     "--out", str(tmp_path / out), "--runs", str(tmp_path / "runs" / out), "--no-progress"]) == 0

    run(0, "a")
    run(1, "b")
    b = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert [r["train_seed"] for r in b["rows"]["bc-mlp"]["runs"]] == [1]
    assert (tmp_path / "b" / "policies" / "bc-mlp-seed1.pt").exists()
    assert b["rows"]["bc-mlp"]["config"]["iterations"] == 2
    assert main(["reproduce", "merge", str(tmp_path / "b"), str(tmp_path / "a"), "--out", str(tmp_path / "ab")]) == 0
    ab = json.loads((tmp_path / "ab" / "metrics.json").read_text())
    a = json.loads((tmp_path / "a" / "metrics.json").read_text())
    runs = ab["rows"]["bc-mlp"]["runs"]
    assert ab["spec"]["seeds"] == 2 and [r["train_seed"] for r in runs] == [0, 1]
    assert runs[0] == a["rows"]["bc-mlp"]["runs"][0] and runs[1] == b["rows"]["bc-mlp"]["runs"][0]
    values = [r["tasks"]["forward"]["progress"] for r in runs]
    assert ab["rows"]["bc-mlp"]["summary"]["forward"]["progress"] == [float(np.mean(values)),
                                                                         float(np.std(values))]
    assert sorted(p.name for p in (tmp_path / "ab" / "policies").iterdir()) == ["bc-mlp-seed0.pt", "bc-mlp-seed1.pt"]
    assert "mean ± std over 2 seed(s)" in (tmp_path / "ab" / "table.md").read_text()
    assert (tmp_path / "ab" / "figure.png").exists()
    # a seed twice, or other settings: one line, nothing written
    assert main(["reproduce", "merge", str(tmp_path / "ab"), str(tmp_path / "a"), "--out", str(tmp_path / "x")]) == 2
    run(2, "c", iterations="3")
    assert main(["reproduce", "merge", str(tmp_path / "a"), str(tmp_path / "c"), "--out", str(tmp_path / "y")]) == 2
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    # results committed without policies, recorded before a setting existed: --no-policies joins their metrics,
    # and a setting that only one side records is named and not compared
    import shutil

    shutil.copytree(tmp_path / "a", tmp_path / "old")
    shutil.rmtree(tmp_path / "old" / "policies")
    old = json.loads((tmp_path / "old" / "metrics.json").read_text())
    del old["rows"]["bc-mlp"]["config"]["lr"]
    (tmp_path / "old" / "metrics.json").write_text(json.dumps(old))
    capsys.readouterr()
    assert main(["reproduce", "merge", str(tmp_path / "old"), str(tmp_path / "b"), "--out", str(tmp_path / "z")]) == 2
    assert "bc-mlp-seed0.pt: missing" in capsys.readouterr().err and not (tmp_path / "z").exists()
    assert main(["reproduce", "merge", str(tmp_path / "old"), str(tmp_path / "b"), "--out", str(tmp_path / "z"),
                 "--no-policies"]) == 0
    assert "row bc-mlp: settings lr recorded by only one of" in capsys.readouterr().err
    z = json.loads((tmp_path / "z" / "metrics.json").read_text())
    assert z["spec"]["seeds"] == 2 and z["policies_merged"] is False and not (tmp_path / "z" / "policies").exists()
    assert z["rows"]["bc-mlp"]["runs"] == ab["rows"]["bc-mlp"]["runs"]
    # the same experts recorded again where floats differ: reference returns 0.5% apart merge with a note and
    # both references kept; 5% apart (other experts or tasks) are refused
    for name, factor in (("near", 1.005), ("far", 1.05)):
        shutil.copytree(tmp_path / "b", tmp_path / name)
        moved = json.loads((tmp_path / name / "metrics.json").read_text())
        moved["reference"]["expert_returns"] = {t: v * factor for t, v in moved["reference"]["expert_returns"].items()}
        (tmp_path / name / "metrics.json").write_text(json.dumps(moved))
    capsys.readouterr()
    assert main(["reproduce", "merge", str(tmp_path / "a"), str(tmp_path / "near"), "--out", str(tmp_path / "n")]) == 0
    assert "reference.expert_returns differs from" in capsys.readouterr().err
    n = json.loads((tmp_path / "n" / "metrics.json").read_text())
    assert [m["reference"]["expert_returns"] for m in n["merged_from"]] == [
        a["reference"]["expert_returns"], {t: v * 1.005 for t, v in b["reference"]["expert_returns"].items()}]
    assert main(["reproduce", "merge", str(tmp_path / "a"), str(tmp_path / "far"), "--out", str(tmp_path / "f")]) == 2
    assert "reference.expert_returns differs" in capsys.readouterr().err and not (tmp_path / "f").exists()
    # other rows of the spec on the same seeds join as rows of their own; unequal seed counts are refused
    assert main(["reproduce", "hopper", "--seeds", "2", "--rows", "bc-gru", "--bc-iterations", "2",
                 "--episodes-per-code", "2", "--demos", str(DEMOS), "--out", str(tmp_path / "g"),
                 "--runs", str(tmp_path / "runs" / "g"), "--no-progress"]) == 0
    assert main(["reproduce", "merge", str(tmp_path / "ab"), str(tmp_path / "g"), "--out", str(tmp_path / "rows")]) == 0
    rows = json.loads((tmp_path / "rows" / "metrics.json").read_text())
    g = json.loads((tmp_path / "g" / "metrics.json").read_text())
    assert list(rows["rows"]) == ["bc-mlp", "bc-gru"] and list(rows["spec"]["rows"]) == ["bc-mlp", "bc-gru"]
    assert rows["rows"]["bc-gru"]["runs"] == g["rows"]["bc-gru"]["runs"]
    assert rows["rows"]["bc-mlp"]["runs"] == ab["rows"]["bc-mlp"]["runs"]
    assert "| bc-gru | 0/2 |" in (tmp_path / "rows" / "table.md").read_text()
    assert main(["reproduce", "merge", str(tmp_path / "a"), str(tmp_path / "g"), "--out", str(tmp_path / "r1")]) == 2
    assert "different numbers of seeds" in capsys.readouterr().err and not (tmp_path / "r1").exists()


def test_demo_episodes_default_to_the_settings(tmp_path, monkeypatch, capsys):
    """-1 (the default) records what the committed results were measured on: paper 200, standard 100 per task."""
    import pomil.demos

    asked = []

    def record(experts, episodes, setting, *args, **kwargs):
        asked.append((setting, episodes))
        raise ValueError("stop here")

    monkeypatch.setattr(pomil.demos, "record_hopper_demos", record)
    for setting in ("paper", "standard"):
        assert main(["demos", "hopper", "--setting", setting, "--out", str(tmp_path / f"c-{setting}.npz")]) == 2
    assert asked == [("paper", 200), ("standard", 100)]
    capsys.readouterr()
    assert main(["demos", "hopper", "--episodes", "0", "--out", str(tmp_path / "z.npz")]) == 2
    assert "--episodes must be -1 (the setting's) or >= 1, got 0" in capsys.readouterr().err
