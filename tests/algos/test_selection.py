import csv
import math
from dataclasses import replace

import pytest
import torch

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.algos.selection import PolicySelection
from pomil.api import TrainedPolicy
from pomil.data import Demonstrations
from pomil.envs import executed_actions_fn
from pomil.nn.policy import shift_actions
from pomil.training import load_checkpoint


def _cfg(demos_path, out, **kw):
    base = dict(demos=str(demos_path), out=str(out), iterations=4, num_envs=8, hidden_size=16, critic_steps=1,
                critic_batch=8, ppo_epochs=1, minibatches=2, eval_every=1, eval_episodes=2, progress=False, log_every=1,
                warm_start_iterations=20, posterior_init_iterations=5, policy_warmup_iterations=1, lr=3e-3,
                bc_weight=0.0)
    base.update(kw)
    return AdversarialConfig(**base)


def _selected_rows(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return [(int(r["iteration"]), float(r["select/distance"]), int(float(r["select/iteration"])),
                 float(r["select/best_distance"])) for r in csv.DictReader(f) if r.get("select/distance")]


@pytest.fixture(scope="module")
def nearest_and_last(demos_path, tmp_path_factory):
    root = tmp_path_factory.mktemp("selection")
    nearest = load_checkpoint(train_adversarial(_cfg(demos_path, root / "nearest", hand_over="nearest")))
    last = load_checkpoint(train_adversarial(_cfg(demos_path, root / "last", hand_over="last")))
    return root, nearest, last


def test_the_selection_leaves_the_training_unchanged(nearest_and_last):
    _, nearest, last = nearest_and_last
    for net, weights in last["nets"].items():
        for k, v in weights.items():
            assert torch.equal(v, nearest["nets"][net][k]), (net, k)
    assert all(torch.equal(v, last["nets"]["policy"][k]) for k, v in last["policy"].items())
    assert "selection" not in last.get("carried", {})


def test_the_checkpoint_hands_over_the_nearest_policy_measured(nearest_and_last):
    root, nearest, _ = nearest_and_last
    rows = _selected_rows(root / "nearest")
    assert [r[0] for r in rows] == [0, 1, 2, 3, 4]  # the warm start, then every evaluation
    distances = [r[1] for r in rows]
    best = min(range(len(rows)), key=lambda i: distances[i])
    assert rows[-1][2] == rows[best][0] and rows[-1][3] == distances[best]
    kept = nearest["carried"]["selection"]
    assert int(kept["iteration"]) == rows[best][0] and float(kept["distance"]) == pytest.approx(distances[best])
    assert all(torch.equal(v, kept["policy"][k]) for k, v in nearest["policy"].items())
    moved = any(not torch.equal(v, nearest["nets"]["policy"][k]) for k, v in nearest["policy"].items())
    assert moved == (rows[best][0] != 4)


def test_measuring_the_handed_over_policy_again_gives_its_recorded_distance(nearest_and_last, demos_path):
    root, nearest, _ = nearest_and_last
    demos = Demonstrations.load(demos_path).padded("cpu")
    expert = replace(demos, actions=executed_actions_fn("pomil/Circles-v0", {})(demos.actions))
    selection = PolicySelection(expert, shift_actions(expert.actions), env_info=nearest["env"],
                                learner="infogail-pomdp")
    policy = TrainedPolicy.load(root / "nearest" / "checkpoint.pt").policy
    stats = selection(policy, 7)
    assert stats["select/distance"] == pytest.approx(float(nearest["carried"]["selection"]["distance"]), rel=1e-6)
    assert stats["select/iteration"] == 7.0  # the first measure is the nearest so far
    again = PolicySelection(expert, shift_actions(expert.actions), env_info=nearest["env"], learner="infogail-pomdp")
    again.load_state_dict(selection.state_dict())
    assert again.best["iteration"] == 7 and again.best["distance"] == selection.best["distance"]


def test_a_damaged_selection_state_is_refused(demos_path):
    demos = Demonstrations.load(demos_path).padded("cpu")
    selection = PolicySelection(demos, shift_actions(demos.actions), env_info={"id": "pomil/Circles-v0"},
                                learner="infogail-pomdp")
    with pytest.raises(ValueError, match="selection"):
        selection.load_state_dict({"iteration": torch.tensor(1)})
    with pytest.raises(ValueError, match="damaged"):
        selection.load_state_dict({"iteration": torch.tensor([1, 2]), "distance": torch.tensor(0.1), "policy": {}})
    selection.load_state_dict({})
    assert selection.policy_state() is None


def _first_row(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return next(csv.DictReader(f))


def test_restarts_hand_on_the_nearest_warm_start_and_the_first_is_the_runs_own(demos_path, tmp_path):
    plain = train_adversarial(_cfg(demos_path, tmp_path / "plain", iterations=0))
    restarted = train_adversarial(_cfg(demos_path, tmp_path / "three", iterations=0, warm_start_restarts=3))
    row = _first_row(tmp_path / "three")
    distances = [float(row[f"init/restart_{r}_distance"]) for r in range(3)]
    assert "init/restart" not in _first_row(tmp_path / "plain")
    assert distances[0] == pytest.approx(float(_first_row(tmp_path / "plain")["select/distance"]))
    assert len(set(distances)) == 3  # three initialisations, three policies
    chosen = int(float(row["init/restart"]))
    assert chosen == min(range(3), key=lambda r: distances[r])
    assert float(row["select/distance"]) == pytest.approx(distances[chosen])  # the hand-over measures the chosen one
    ckpt, own = load_checkpoint(restarted), load_checkpoint(plain)
    same = all(torch.equal(v, own["nets"]["policy"][k]) for k, v in ckpt["nets"]["policy"].items())
    assert same == (chosen == 0)
    for net in ("critic", "value"):  # not restarted: the run's own
        assert all(torch.equal(v, own["nets"][net][k]) for k, v in ckpt["nets"][net].items())


@pytest.mark.parametrize("nearest", [0, 1])
def test_restarts_leave_the_runs_random_numbers_as_they_were(demos_path, tmp_path, monkeypatch, nearest):
    """Whichever restart is chosen, the adversarial phase after it draws the run's own random numbers: with the
    first chosen the run is the plain run's, bit for bit; with another, only what grew from its policy differs."""
    import pomil.algos.adversarial as adversarial

    class Ranked(PolicySelection):  # restart `nearest` is the nearest, whatever its rollouts measure
        def __call__(self, policy, iteration):
            stats = super().__call__(policy, iteration)
            if iteration == nearest:
                self.best = {**self.best, "iteration": iteration, "distance": -math.inf,
                             "policy": {k: v.detach().clone() for k, v in policy.state_dict().items()}}
            return stats

    plain = load_checkpoint(train_adversarial(_cfg(demos_path, tmp_path / "plain", iterations=2, hand_over="last")))
    monkeypatch.setattr(adversarial, "PolicySelection", Ranked)
    cfg = _cfg(demos_path, tmp_path / "two", iterations=2, hand_over="last", warm_start_restarts=2)
    ckpt = load_checkpoint(train_adversarial(cfg))
    assert int(float(_first_row(tmp_path / "two")["init/restart"])) == nearest
    equal = [all(torch.equal(v, plain["nets"][net][k]) for k, v in ckpt["nets"][net].items()) for net in plain["nets"]]
    assert all(equal) == (nearest == 0)


def test_restarts_with_continuous_codes_keep_the_chosen_episode_codes(demos_path, tmp_path, monkeypatch):
    import pomil.algos.adversarial as adversarial

    kept = []

    class Ranked(PolicySelection):  # the second restart is the nearest; its episode codes are remembered
        def __call__(self, policy, iteration):
            stats = super().__call__(policy, iteration)
            if iteration == 1:
                self.best = {**self.best, "iteration": 1, "distance": -math.inf,
                             "policy": {k: v.detach().clone() for k, v in policy.state_dict().items()}}
            return stats

    original = adversarial.bc_warm_start

    def recorded(mods, *args, episode_codes=None, **kwargs):
        stats = original(mods, *args, episode_codes=episode_codes, **kwargs)
        kept.append(episode_codes.codes.detach().clone())
        return stats

    monkeypatch.setattr(adversarial, "PolicySelection", Ranked)
    monkeypatch.setattr(adversarial, "bc_warm_start", recorded)
    ckpt = load_checkpoint(train_adversarial(_cfg(demos_path, tmp_path / "c", iterations=0, code_kind="continuous",
                                                  warm_start_restarts=2)))
    assert len(kept) == 2 and not torch.equal(kept[0], kept[1])
    assert torch.equal(ckpt["nets"]["episode_codes"]["codes"], kept[1])
