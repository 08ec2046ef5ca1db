"""Any Gymnasium task: the generic batched simulator, task keywords, recording and merging demonstrations."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from pomil.config import from_dict, parse_kwargs
from pomil.data import Demonstrations
from pomil.demos import merge_demos, record_hopper_demos
from pomil.envs import make_vec_env
from pomil.envs.batch import GymSim
from pomil.envs.locomotion import HOPPER_EXPERTS, hopper_kwargs, locomotion_kwargs
from pomil.envs.wrappers import parse_mask
from pomil.errors import PomilError

ROOT = Path(__file__).resolve().parents[1]


from tests.inprocess import pomil  # noqa: E402


def test_gym_sim_equals_gymnasium_and_freezes_ended_copies():
    kwargs = {"max_episode_steps": 5}
    sim = GymSim("Pendulum-v1", 3, kwargs)
    envs = [gym.make("Pendulum-v1", **kwargs) for _ in range(3)]
    obs = sim.reset(seed=11)
    np.testing.assert_array_equal(obs, np.stack([e.reset(seed=11 + i)[0] for i, e in enumerate(envs)]))
    rng = np.random.default_rng(0)
    for _ in range(5):
        act = rng.uniform(-2, 2, (3, 1))
        obs, rew, term, trunc = sim.step(act)
        for i, e in enumerate(envs):
            o, r, te, tr, _ = e.step(act[i].astype(np.float32))
            np.testing.assert_array_equal(obs[i], o)
            assert rew[i] == pytest.approx(r, abs=1e-12) and (term[i], trunc[i]) == (te, tr)
    assert sim.done.all() and trunc.all()
    with pytest.raises(RuntimeError, match="reset"):
        sim.step(np.zeros((3, 1)))
    with pytest.raises(AttributeError, match="not a MuJoCo"):
        _ = sim.x_position


def test_gym_sim_halfcheetah_position_and_vec_env_mask():
    env = make_vec_env("HalfCheetah-v5", {"max_episode_steps": 3}, 2, observation_mask=list(range(8)), seed=0)
    obs = env.reset()
    assert tuple(obs.shape) == (2, 8) and env.full_observation.shape == (2, 17)
    x0 = env.sim.x_position
    import torch

    for _ in range(3):
        obs, rew, term, trunc = env.step(torch.ones(2, 6))
    assert bool(trunc.all()) and not bool(term.any())
    assert np.all(env.sim.x_position != x0)
    env.close()


def test_non_box_spaces_are_refused():
    with pytest.raises(ValueError, match="1-D Box"):
        GymSim("CartPole-v1", 2)


def test_locomotion_task_keywords():
    assert locomotion_kwargs("HalfCheetah-v5", "backward", "paper") == {"forward_reward_weight": -1.0,
                                                                        "max_episode_steps": 128}
    assert locomotion_kwargs("Walker2d-v5", "forward", "paper") == {
        "forward_reward_weight": 1.0, "max_episode_steps": 128, "terminate_when_unhealthy": False}
    assert locomotion_kwargs("Walker2d-v5", "forward", "standard") == {"forward_reward_weight": 1.0}
    assert locomotion_kwargs("Hopper-v5", "forward", "paper") == hopper_kwargs("forward", "paper")
    assert locomotion_kwargs("Pendulum-v1", "none", "standard") == {}
    with pytest.raises(ValueError, match="forward_reward_weight"):
        locomotion_kwargs("Pendulum-v1", "backward", "paper")


def test_kwargs_and_mask_parsing():
    assert parse_kwargs(("forward_reward_weight=-1", "x=abc", "flag=true", "r=[1, 2]")) == {
        "forward_reward_weight": -1, "x": "abc", "flag": True, "r": [1, 2]}
    with pytest.raises(PomilError, match="key=value"):
        parse_kwargs(("novalue",))
    from pomil.algos.expert import ExpertConfig

    cfg = from_dict(ExpertConfig, {"env_kwargs": {"ctrl_cost_weight": 0.05}, "env_id": "HalfCheetah-v5"})
    assert cfg.env_settings() == ({"forward_reward_weight": 1.0, "max_episode_steps": 128, "ctrl_cost_weight": 0.05},
                                  None)
    assert parse_mask("") is None and parse_mask("positions-only") == "positions-only" and parse_mask("0, 2") == [0, 2]
    assert parse_mask("velocities") == "velocities"
    with pytest.raises(ValueError, match="comma-separated"):
        parse_mask("speed")


def _demos(label_name, n, env_kwargs, value, env_id="HalfCheetah-v5", mask=None):
    T = 4
    return Demonstrations(
        observations=np.full((n * T, 2), value, dtype=np.float32), actions=np.full((n * T, 1), value, dtype=np.float32),
        episode_bounds=np.arange(0, n * T + 1, T), labels=np.zeros(n, dtype=np.int64),
        metadata={"env_id": env_id, "env_kwargs": env_kwargs, "observation_mask": mask, "label_names": [label_name],
                  "tasks": {label_name: env_kwargs}, "expert_returns": {label_name: value * 10},
                  "still_returns": {label_name: 0.0}, "expert_displacement": {label_name: 1.0}})


def test_merge_in_proportions_keeps_labels_for_evaluation_only():
    fwd = _demos("forward", 10, {"forward_reward_weight": 1, "max_episode_steps": 4}, 1.0)
    bwd = _demos("backward", 6, {"forward_reward_weight": -1, "max_episode_steps": 4}, 2.0)
    m = merge_demos([fwd, bwd], seed=1)
    assert m.num_episodes == 12 and np.bincount(m.labels).tolist() == [6, 6]
    assert m.metadata["label_names"] == ["forward", "backward"]
    # every episode keeps its source's rows: label 0 <-> value 1, label 1 <-> value 2
    first_obs = m.observations[m.episode_bounds[:-1], 0]
    np.testing.assert_array_equal(first_obs, np.where(m.labels == 0, 1.0, 2.0))
    assert m.metadata["tasks"]["backward"]["forward_reward_weight"] == -1
    assert m.metadata["env_kwargs"] == fwd.metadata["env_kwargs"]
    assert m.metadata["expert_returns"] == {"forward": 10.0, "backward": 20.0}
    m2 = merge_demos([fwd, bwd], proportions=[2, 1], seed=1)
    assert np.bincount(m2.labels).tolist() == [10, 5]
    m3 = merge_demos([fwd, bwd], proportions=[1, 1], episodes=4, seed=1)
    assert np.bincount(m3.labels).tolist() == [2, 2]
    # the same task in two files keeps one label; returns are episode-weighted
    again = _demos("forward", 2, {"forward_reward_weight": 1, "max_episode_steps": 4}, 4.0)
    m4 = merge_demos([fwd, again], proportions=[5, 1], seed=0)
    assert m4.metadata["label_names"] == ["forward"] and m4.num_episodes == 12
    assert m4.metadata["expert_returns"]["forward"] == pytest.approx((10 * 10 + 40 * 2) / 12)


@pytest.mark.parametrize("other, text", [
    (_demos("b", 3, {"max_episode_steps": 9}, 1.0), "differ from"),
    (_demos("b", 3, {}, 1.0, env_id="Walker2d-v5"), "metadata.env_id"),
    (_demos("b", 3, {}, 1.0, mask=[0, 1]), "metadata.observation_mask"),
])
def test_merge_refuses_incompatible_files(other, text):
    base = _demos("a", 3, {}, 1.0)
    with pytest.raises(ValueError, match=text):
        merge_demos([base, other])
    with pytest.raises(ValueError, match="requested"):
        merge_demos([base, base], episodes=20)
    with pytest.raises(ValueError, match="proportions"):
        merge_demos([base, base], proportions=[1, -1])


def test_hopper_demos_record_plus_merge_reproduce_the_shipped_file():
    shipped = Demonstrations.load(ROOT / "data" / "hopper-paper.npz")
    demos = record_hopper_demos(HOPPER_EXPERTS["paper"], 200)
    # the file was recorded on another CPU: MuJoCo's and torch's floats differ in the last bits between CPUs
    # (measured: up to 8e-7 in the observations), so floats are compared to a tolerance and the rest exactly
    for name in ("episode_bounds", "labels"):
        np.testing.assert_array_equal(getattr(demos, name), getattr(shipped, name), err_msg=name)
    for name in ("observations", "actions", "states"):
        np.testing.assert_allclose(getattr(demos, name), getattr(shipped, name), rtol=0, atol=1e-4, err_msg=name)
    for key in ("tasks", "observation_mask", "env_kwargs"):
        assert demos.metadata[key] == shipped.metadata[key], key
    for key in ("expert_returns", "still_returns", "expert_displacement"):
        assert demos.metadata[key] == pytest.approx(shipped.metadata[key], rel=1e-4), key


def test_cli_any_task_experts_record_merge_train_evaluate(tmp_path):
    """Pendulum (not Hopper, not circles): an expert seeing cos and sin only, demos
    with the angle's cosine observed, InfoGAIL-POMDP on them, per-task evaluation."""
    r = pomil("experts", "train", "--env-id", "Pendulum-v1", "--task", "none", "--setting", "paper",
              "--observation-mask", "0,1", "--iterations", 2, "--num-envs", 4, "--out", tmp_path / "e", "--no-progress")
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "e" / "evaluation.json").read_text())
    assert report["env_id"] == "Pendulum-v1" and report["paper"]["length"] == 128
    for name, seed in (("a", 0), ("b", 1)):
        r = pomil("demos", "record", "--expert", tmp_path / "e" / "checkpoint.pt", "--episodes", 4,
                  "--observation-mask", "0", "--task", name, "--seed", seed, "--out", tmp_path / f"{name}.npz")
        assert r.returncode == 0, r.stderr
    r = pomil("demos", "merge", tmp_path / "a.npz", tmp_path / "b.npz", "--proportions", "1,1",
              "--out", tmp_path / "m.npz")
    assert r.returncode == 0 and "a 4, b 4" in r.stdout, r.stderr + r.stdout
    m = Demonstrations.load(tmp_path / "m.npz")
    assert m.obs_dim == 1 and m.metadata["observation_mask"] == [0] and m.states.shape[1] == 3
    r = pomil("train", "infogail-pomdp", "--demos", tmp_path / "m.npz", "--iterations", 2, "--num-envs", 4,
              "--warm-start-iterations", 2, "--posterior-init-iterations", 2, "--eval-every", 1, "--eval-episodes", 2,
              "--out", tmp_path / "run", "--no-progress")
    assert r.returncode == 0, r.stderr
    header = (tmp_path / "run" / "metrics.csv").read_text().splitlines()[0]
    assert "eval/a/normalised_return" in header and "eval/b/progress" in header
    r = pomil("evaluate", tmp_path / "run", "--demos", tmp_path / "m.npz", "--episodes-per-code", 2, "--json")
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert set(result["tasks"]) == {"a", "b"} and result["num_codes"] == 2


@pytest.mark.parametrize("args, text", [
    (["experts", "train", "--env-id", "NoSuchEnv-v0"], "cannot build 'NoSuchEnv-v0'"),
    (["experts", "train", "--env-id", "Pendulum-v1", "--task", "forward"], "forward_reward_weight"),
    (["experts", "train", "--env-id", "Hopper-v5", "--env-kwargs", "bogus_weight=1"], "cannot build"),
    (["experts", "train", "--env-id", "Pendulum-v1", "--task", "none", "--observation-mask", "7"], "[0, 3)"),
    (["demos", "record", "--expert", "nope.pt", "--out", "x.npz"], "no expert checkpoint"),
    (["demos", "merge", "nope.npz", "--out", "x.npz"], "no such file"),
])
def test_any_task_bad_input_is_one_line(args, text, tmp_path):
    r = pomil(*args, "--no-progress" if args[0] == "experts" else "--seed=0", cwd=tmp_path)
    assert r.returncode == 2 and text in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_training_overrides_remask_full_observations_and_replace_env_keywords(tmp_path):
    from pomil.data import load_training_demos
    from pomil.errors import DataError

    path = ROOT / "data" / "hopper-paper.npz"
    shipped = Demonstrations.load(path)
    same, env_id, kw = load_training_demos(str(path), {}, "positions-only")
    np.testing.assert_array_equal(same.observations, shipped.observations)
    demos, env_id, kw = load_training_demos(str(path), {"max_episode_steps": 64}, [0, 5, 6])
    assert env_id == "Hopper-v5" and kw["max_episode_steps"] == 64 and kw["forward_reward_weight"] == 1.0
    np.testing.assert_array_equal(demos.observations, shipped.states[:, [0, 5, 6]])
    assert demos.metadata["observation_mask"] == [0, 5, 6]
    no_states = Demonstrations(shipped.observations, shipped.actions, shipped.episode_bounds, metadata=shipped.metadata)
    no_states.save(tmp_path / "n.npz")
    with pytest.raises(DataError, match="states"):
        load_training_demos(str(tmp_path / "n.npz"), {}, [0])
    # the CLI: a policy on height + two velocities, in 16-step episodes
    r = pomil("train", "infogail-pomdp", "--demos", path, "--observation-mask", "0,5,6",
              "--env-kwargs", "max_episode_steps=16",
              "--iterations", 1, "--num-envs", 2, "--minibatches", 2, "--warm-start-iterations", 1, "--eval-every", 0,
              "--posterior-init-iterations", 1, "--out", tmp_path / "r",
              "--no-progress")
    assert r.returncode == 0, r.stderr
    from pomil.api import TrainedPolicy

    policy = TrainedPolicy.load(tmp_path / "r" / "checkpoint.pt")
    assert policy.obs_dim == 3 and policy.env["observation_mask"] == [0, 5, 6]
    assert policy.env["kwargs"]["max_episode_steps"] == 16
    r = pomil("train", "bc", "--demos", path, "--observation-mask", "speed", "--out", tmp_path / "b")
    assert r.returncode == 2 and "comma-separated integers" in r.stderr and "Traceback" not in r.stderr


def test_reproduce_tasks_and_a_sequential_sweep_on_any_task(tmp_path):
    """`pomil reproduce tasks` and `pomil sweep --no-ray` on Pendulum demonstrations merged from two recordings."""
    r = pomil("experts", "train", "--env-id", "Pendulum-v1", "--task", "none", "--iterations", 1, "--num-envs", 2,
              "--out", tmp_path / "e", "--no-progress")
    assert r.returncode == 0, r.stderr
    for name in ("up", "down"):
        r = pomil("demos", "record", "--expert", tmp_path / "e" / "checkpoint.pt", "--episodes", 2,
                  "--observation-mask", "0,1",
                  "--task", name, "--out", tmp_path / f"{name}.npz")
        assert r.returncode == 0, r.stderr
    r = pomil("demos", "merge", tmp_path / "up.npz", tmp_path / "down.npz", "--out", tmp_path / "m.npz")
    assert r.returncode == 0, r.stderr
    tiny = {"num_envs": 2, "minibatches": 2,
            "warm_start_iterations": 1, "posterior_init_iterations": 1, "hidden_size": 8, "eval_every": 1,
            "eval_episodes": 1}
    (tmp_path / "adv.json").write_text(json.dumps(tiny))
    r = pomil("reproduce", "tasks", "--demos", tmp_path / "m.npz", "--out", tmp_path / "res",
              "--rows", "infogail-pomdp",
              "--seeds", 1, "--adversarial-iterations", 1, "--episodes-per-code", 1,
              "--adversarial-config", tmp_path / "adv.json",
              "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    metrics = json.loads((tmp_path / "res" / "metrics.json").read_text())
    assert metrics["spec"]["name"] == "tasks" and metrics["env_id"] == "Pendulum-v1"
    assert list(metrics["reference"]["tasks"]) == ["up", "down"]
    # runs/ named after --out
    assert (tmp_path / "runs" / "res" / "infogail-pomdp" / "seed0" / "checkpoint.pt").exists()
    assert (tmp_path / "res" / "figure.png").exists()
    assert "| infogail-pomdp |" in (tmp_path / "res" / "table.md").read_text()
    (tmp_path / "sweep.json").write_text(json.dumps({"learner": "infogail-pomdp", "demos": str(tmp_path / "m.npz"),
                                                     "iterations": 1, **tiny}))
    r = pomil("sweep", tmp_path / "sweep.json", "--seeds", 2, "--no-ray", "--episodes-per-code", 1,
              "--out", tmp_path / "sw")
    assert r.returncode == 0, r.stderr
    data = json.loads((tmp_path / "sw" / "metrics.json").read_text())
    assert len(data["rows"]["base"]["runs"]) == 2 and set(data["rows"]["base"]["summary"]) == {"up", "down"}
    assert "up: progress" in (tmp_path / "sw" / "table.md").read_text() and (tmp_path / "sw" / "figure.png").exists()
    r = pomil("reproduce", "tasks", "--out", tmp_path / "x", cwd=tmp_path)
    assert r.returncode == 2 and "data/tasks.npz: demonstrations not found" in r.stderr and "--demos" in r.stderr


def test_speed_tasks_record_merge_and_score_behaviour_by_speed(tmp_path):
    """pomil/HopperSpeed-v0: two target speeds, recordings named by speed, merged (the target is a
    reward term), and `reproduce tasks` scores each code's episodes by their nearest expert speed."""
    for v in ("0.5", "1.5"):
        r = pomil("experts", "train", "--env-id", "pomil/HopperSpeed-v0", "--task", "none", "--env-kwargs",
                  f"target_velocity={v},max_episode_steps=24", "--iterations", 1, "--num-envs", 2,
                  "--out", tmp_path / f"e{v}", "--no-progress")
        assert r.returncode == 0, r.stderr
        r = pomil("demos", "record", "--expert", tmp_path / f"e{v}" / "checkpoint.pt", "--episodes", 2,
                  "--out", tmp_path / f"{v}.npz")
        assert r.returncode == 0, r.stderr
        d = Demonstrations.load(tmp_path / f"{v}.npz")
        assert d.metadata["label_names"] == [f"speed-{v}"] and d.obs_dim == 5  # positions only
        speed = d.metadata["expert_speed"][f"speed-{v}"]
        displacement = d.metadata["expert_displacement"][f"speed-{v}"]
        assert speed == pytest.approx(displacement / (24 * 0.008))  # 24 steps of 4 x 2 ms, never ended early
    r = pomil("demos", "merge", tmp_path / "0.5.npz", tmp_path / "1.5.npz", "--out", tmp_path / "m.npz")
    assert r.returncode == 0, r.stderr
    m = Demonstrations.load(tmp_path / "m.npz").metadata
    assert set(m["expert_speed"]) == {"speed-0.5", "speed-1.5"}
    r = pomil("reproduce", "tasks", "--demos", tmp_path / "m.npz", "--out", tmp_path / "res", "--rows", "bc-mlp",
              "--seeds", 1, "--episodes-per-code", 3, "--bc-iterations", 2, "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    run = json.loads((tmp_path / "res" / "metrics.json").read_text())["rows"]["bc-mlp"]["runs"][0]
    shares = run["behaviour"]["code0"]["shares"]
    assert sum(shares.values()) == pytest.approx(1.0) and run["behaviour"]["code0"]["purity"] == max(shares.values())
    for t in ("speed-0.5", "speed-1.5"):  # one code serves both tasks: its shares are the on-task shares
        assert run["tasks"][t]["on_task_share"] == shares[t]
        assert run["tasks"][t]["speed_error"] == pytest.approx(
            abs(run["behaviour"]["code0"]["mean_speed"] - m["expert_speed"][t]))
    assert "on-task share" in (tmp_path / "res" / "table.md").read_text()
    r = pomil("evaluate", tmp_path / "res" / "policies" / "bc-mlp-seed0.pt", "--demos", tmp_path / "m.npz",
              "--episodes-per-code", 2)
    assert r.returncode == 0 and "on-task share" in r.stdout and "purity" in r.stdout, r.stderr


def test_dart_recording_executes_noisy_actions_and_records_the_experts():
    from pomil.api import TrainedPolicy
    from pomil.demos import record_expert_demos

    path = HOPPER_EXPERTS["paper"]["forward"]
    clean = record_expert_demos(path, 3, seed=0)
    noisy = record_expert_demos(path, 3, seed=0, action_noise=0.3)
    np.testing.assert_array_equal(clean.observations[0], noisy.observations[0])  # same reset, then apart
    assert np.abs(clean.states - noisy.states).max() > 0.1
    expert = TrainedPolicy.load(path)  # an MLP on the full observation: each recorded action is its own
    expert.reset(len(noisy.states))
    np.testing.assert_allclose(noisy.actions, expert.act(noisy.states, deterministic=True), rtol=0, atol=1e-6)
    assert "DART" in noisy.metadata["source"] and "DART" not in clean.metadata["source"]
    with pytest.raises(ValueError, match="action_noise"):
        record_expert_demos(path, 1, action_noise=-0.1)


def test_the_velocities_view_is_qvel_alone_while_the_experts_see_everything():
    from pomil.api import TrainedPolicy
    from pomil.data import load_training_demos
    from pomil.demos import record_expert_demos
    from pomil.envs.wrappers import resolve_observation_mask

    qvel = list(range(5, 11))
    assert resolve_observation_mask("Hopper-v5", {}, "velocities") == qvel
    env = gym.make("Hopper-v5")
    obs, _ = env.reset(seed=3)
    np.testing.assert_array_equal(obs[qvel], env.unwrapped.data.qvel)  # a constructed state: exactly its qvel
    env.close()
    path = ROOT / "data" / "hopper-paper.npz"  # full states recorded: the paper's demonstrations re-masked
    velocities, _, _ = load_training_demos(str(path), {}, "velocities")
    np.testing.assert_array_equal(velocities.observations, Demonstrations.load(path).states[:, qvel])
    expert = HOPPER_EXPERTS["paper"]["forward"]
    demos = record_expert_demos(expert, 2, observation_mask="velocities", seed=0)
    assert demos.obs_dim == 6 and demos.metadata["observation_mask"] == qvel
    np.testing.assert_array_equal(demos.observations, demos.states[:, qvel])  # the file holds the learner's view
    policy = TrainedPolicy.load(expert)  # an MLP on the full observation: each recorded action is its own
    policy.reset(len(demos.states))
    np.testing.assert_allclose(demos.actions, policy.act(demos.states, deterministic=True), rtol=0, atol=1e-6)
