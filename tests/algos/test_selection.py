import csv
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
