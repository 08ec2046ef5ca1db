"""The benchmark scripts' own input checks (their timings are measured, never asserted)."""

import argparse
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def hopper_speed(*args):
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / "hopper_speed.py"), *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def test_hopper_speed_rejects_bad_variants_before_timing_anything():
    r = hopper_speed("--variants", "[1]")
    assert r.returncode == 1
    assert r.stdout == ""  # nothing timed: the simulator's row would be the first line
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("--variants: expected a JSON object") and "(got [1])" in lines[0]


@pytest.mark.parametrize("variants, says", [
    ("{not json", "Expecting property name"),
    ('{"x": {"gradient_penaltyy": 0}}', "unknown key(s) ['gradient_penaltyy']"),
    ('{"x": {"gradient_penalty": -1}}', "'gradient_penalty': expected a finite number in [0, inf), got -1.0"),
])
def test_hopper_speed_variants_errors_are_one_line(variants, says, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    hs = importlib.import_module("hopper_speed")
    args = argparse.Namespace(variants=variants, demos="data/hopper-paper.npz", iterations=1, device="cpu")
    with pytest.raises(SystemExit) as err:
        hs.training_configs(args, [8], [(1, "float32", "gru")])
    lines = str(err.value).splitlines()
    assert len(lines) == 1 and lines[0].startswith("--variants: expected a JSON object") and says in lines[0]


def test_copycat_fits_the_previous_action(monkeypatch, tmp_path, capsys):
    import numpy as np

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    cc = importlib.import_module("copycat")
    prev = np.random.default_rng(0).normal(size=(200, 2))
    assert cc.r_squared(prev, 2 * prev + 1) == pytest.approx(1.0)
    noise = np.random.default_rng(1).normal(size=(200, 2))
    assert abs(cc.r_squared(prev, noise)) < 0.05
    from pomil.data import Demonstrations

    demos = Demonstrations.load(ROOT / "data" / "hopper-paper.npz")
    p, c = cc.demo_pairs(demos)
    assert len(p) == len(c) == demos.num_steps - demos.num_episodes
    assert np.array_equal(p[0], demos.actions[0]) and np.array_equal(c[0], demos.actions[1])
    assert cc.main(["--demos", str(ROOT / "data" / "circles.npz"), "x.pt"]) == 2  # circles: no tasks
    assert "metadata has no tasks" in capsys.readouterr().err


def test_reward_check_ranks_a_runs_own_episodes(monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    rc = importlib.import_module("reward_check")
    ckpt = str(ROOT / "tests" / "fixtures" / "checkpoints_v1" / "infogail-pomdp.pt")  # circles, 33-step episodes
    rows = rc.episode_table(ckpt, None, episodes=12, seed=3)
    assert [r["code"] for r in rows] == [0, 1] and {r["task"] for r in rows} == {"own"}
    assert sum(r["episodes"] for r in rows) == 12
    assert all(r["length"] == 33 for r in rows)  # the circles never end early ...
    assert all(r["rho_length"] == 0 for r in rows)  # ... so the length ranks nothing
    assert all(-1 <= r["rho_return"] <= 1 for r in rows)
    assert all(r["return"] < 0 for r in rows)  # the circles pay minus the distance to the nearest circle
    assert rc.episode_table(ckpt, None, episodes=12, seed=3) == rows  # same seed, same numbers
    assert rc.main([str(ROOT / "tests" / "fixtures" / "checkpoints_v1" / "bc.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not an adversarial run's checkpoint" in err[0]
    assert rc.main([ckpt, "--episodes", "0"]) == 2
    assert capsys.readouterr().err == "reward_check: error: --episodes: expected a positive number of episodes, got 0\n"


def test_oracle_reward_pays_each_code_its_tasks_own_reward(monkeypatch):
    import numpy as np
    import torch

    from pomil.envs import make_vec_env
    from pomil.envs.locomotion import hopper_kwargs
    from pomil.rl.collect import Collected

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    orc = importlib.import_module("oracle_reward")
    monkeypatch.setattr(orc, "_state", {"x_velocity": []})
    monkeypatch.setattr(orc._make_vec_env, "original", make_vec_env, raising=False)
    kw = {"forward": hopper_kwargs("forward", "standard"), "backward": hopper_kwargs("backward", "standard")}
    paid = orc._make_vec_env("Hopper-v5", kw["forward"], 4, seed=5)
    own = {task: make_vec_env("Hopper-v5", k, 4, seed=5) for task, k in kw.items()}
    for env in (paid, *own.values()):
        env.reset()
    actions = torch.randn(6, 4, 3, generator=torch.Generator().manual_seed(0)).clamp(-1, 1)
    steps = [(paid.step(a)[1], {task: env.step(a)[1] for task, env in own.items()}) for a in actions]
    env_rewards = torch.stack([r for r, _ in steps]).to(torch.float32)
    codes = torch.tensor([1, 0, 1, 0])  # code 1 moves forward: paid the forward reward
    mask = torch.ones(6, 4, dtype=torch.bool)
    recorded = list(orc._state["x_velocity"])
    vx = torch.as_tensor(np.stack(recorded), dtype=torch.float32)

    def rollout(env, *args, **kwargs):  # the steps above, as collect would return them
        orc._state["x_velocity"].extend(recorded)
        return Collected(type("R", (), {"mask": mask})(), None, codes, env_rewards)
    monkeypatch.setattr(orc._collect, "original", rollout, raising=False)
    monkeypatch.setitem(orc._state, "sign", torch.tensor([-1.0, 1.0]))
    orc._collect(paid)
    expect = torch.stack([torch.where(codes == 1, o["forward"], o["backward"]) for _, o in steps]).to(torch.float32)
    assert torch.allclose(orc._state["reward"], expect, atol=1e-5)
    assert float(vx.abs().max()) > 0.01  # the hopper moved: the signed term is tested, not zero
    r, _ = orc._rewards(None, type("R", (), {"mask": mask})(), codes)
    assert torch.allclose(r * expect.std(), expect, atol=1e-4)  # scaled, never shifted: falling never pays

    def moving(env, *args, **kwargs):  # code 0 moves backward, code 1 forward
        orc._state["x_velocity"].extend([np.array([-1.0, 2.0, -1.0, 2.0])] * 6)
        return Collected(type("R", (), {"mask": mask})(), None, torch.tensor([0, 1, 0, 1]), torch.ones(6, 4))
    monkeypatch.setattr(orc._collect, "original", moving)
    monkeypatch.delitem(orc._state, "sign")
    orc._collect(paid)
    assert orc._state["sign"].tolist() == [-1.0, 1.0] and orc._state["reward"][0].tolist() == [2.0, 3.0, 2.0, 3.0]


def test_demo_draws_rebuilds_each_episodes_return(monkeypatch, capsys):
    import numpy as np

    from pomil.data import Demonstrations

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    dd = importlib.import_module("demo_draws")
    # one 3-step episode: x velocity 2 then 3 then 3 (the last step reads its own), one step unhealthy (z 0.5)
    states = np.zeros((3, 11), np.float32)
    states[:, 0] = [1.2, 1.2, 0.5]
    states[:, 5] = [9.0, 2.0, 3.0]
    actions = np.full((3, 3), 0.5, np.float32)
    task = {"forward_reward_weight": -1.0, "ctrl_cost_weight": 0.01, "terminate_when_unhealthy": False}
    md = {"env_id": "Hopper-v5", "tasks": {"back": task}, "label_names": ["back"], "expert_returns": {"back": 1.0}}
    one = Demonstrations(states, actions, np.array([0, 3]), np.zeros(1, np.int64), states, md)
    ctrl = 0.01 * 3 * 0.25
    assert dd.episode_returns(one) == pytest.approx([(1 - 2 - ctrl) + (0 - 3 - ctrl) + (0 - 3 - ctrl)])
    ends = Demonstrations(states, actions, np.array([0, 3]), np.zeros(1, np.int64), states,
                          {**md, "tasks": {"back": {**task, "terminate_when_unhealthy": True}}})
    assert dd.episode_returns(ends) == pytest.approx([3 - 8 - 3 * ctrl])  # paid alive on every step it took
    # the shipped paper-setting file: the rebuilt mean return is the recorded one's within 1% for both tasks
    paper = Demonstrations.load(ROOT / "data" / "hopper-paper.npz")
    rebuilt, labels = dd.episode_returns(paper), np.asarray(paper.labels)
    for m, t in enumerate(paper.metadata["label_names"]):
        assert rebuilt[labels == m].mean() == pytest.approx(paper.metadata["expert_returns"][t], rel=0.01)
    assert dd.main([str(ROOT / "data" / "hopper-paper.npz"), "--demos-per-mode", "2", "--seeds", "0", "1"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert len(table) == 5 and table[3].startswith("| 0 | 128, 128; 0; ") and table[4].startswith("| 1 | ")
    assert dd.main([str(ROOT / "data" / "circles.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "expected Hopper-v5 demonstrations" in err[0] and "pomil/Circles-v0" in err[0]
    assert dd.main([str(ROOT / "data" / "hopper-paper.npz"), "--demos-per-mode", "500"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("demo_draws: error: ") and "500 per mode" in err  # nothing printed before
    with pytest.raises(SystemExit):
        dd.main([str(ROOT / "data" / "hopper-paper.npz"), "--demos-per-mode", "0"])
    assert "--demos-per-mode: expected a positive number of episodes, got 0" in capsys.readouterr().err


def test_clone_ensemble_averages_its_members_and_aligns_their_codes(monkeypatch, tmp_path, capsys):
    import json

    import numpy as np
    import torch

    from pomil import TrainedPolicy
    from pomil.cli import main as pomil

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    ce = importlib.import_module("clone_ensemble")
    # codes named the other way round are found from the episodes' assignments alone
    assert ce.align([np.array([0, 0, 1, 1]), np.array([1, 1, 0, 0]), np.array([0, 1, 1, 1])], 2) == [
        [0, 1], [1, 0], [0, 1]]
    ckpt = ROOT / "tests" / "fixtures" / "checkpoints_v1" / "infogail-pomdp.pt"  # circles, 2 codes
    alone = TrainedPolicy.load(ckpt)
    obs = torch.randn(4, alone.obs_dim, generator=torch.Generator().manual_seed(0))
    codes = np.array([0, 1, 0, 1])
    same = ce.Ensemble([TrainedPolicy.load(ckpt), TrainedPolicy.load(ckpt)], [[0, 1], [0, 1]])
    same.reset(4, codes, seed=0)
    alone.reset(4, codes, seed=0)
    for _ in range(3):  # two copies of one policy act as the policy alone, step after step
        assert torch.allclose(same.act(obs), torch.as_tensor(alone.act(obs, True)), atol=1e-6)
    crossed = ce.Ensemble([TrainedPolicy.load(ckpt), TrainedPolicy.load(ckpt)], [[0, 1], [1, 0]])
    crossed.reset(4, codes, seed=0)
    alone.reset(4, np.array([0, 0, 0, 0]), seed=0)
    first = torch.as_tensor(alone.act(obs, True))
    alone.reset(4, np.array([1, 1, 1, 1]), seed=0)
    assert torch.allclose(crossed.act(obs), (first + torch.as_tensor(alone.act(obs, True))) / 2, atol=1e-6)

    # end to end on a tiny Hopper clone: two copies of it score as pomil evaluate scores it alone
    from pomil.data import Demonstrations, per_mode

    demos, run = str(tmp_path / "draw.npz"), str(tmp_path / "run")
    per_mode(Demonstrations.load(ROOT / "data" / "hopper-paper.npz"), 2, 0, "paper").save(demos)
    assert pomil(["train", "infogail-pomdp", "--demos", demos, "--iterations", "0", "--warm-start-iterations", "2",
                  "--posterior-init-iterations", "2", "--eval-every", "0", "--hidden-size", "8", "--no-progress",
                  "--out", run]) == 0
    capsys.readouterr()
    assert pomil(["evaluate", run, "--demos", demos, "--episodes-per-code", "2", "--seed", "3", "--json"]) == 0
    own = json.loads(capsys.readouterr().out)
    assert ce.main(["--demos", demos, "--episodes-per-code", "2", "--eval-seed", "3", run, run]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["members"] == [run, run] and scores["member_codes"] == [[0, 1], [0, 1]]
    for task in ("forward", "backward"):
        assert scores["tasks"][task]["code"] == own["tasks"][task]["code"]
        assert scores["tasks"][task]["return"] == pytest.approx(own["tasks"][task]["return"], rel=1e-4)
    assert ce.main(["--demos", str(ROOT / "data" / "circles.npz"), str(ckpt)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("clone_ensemble: error: ") and "no tasks" in err[0]
