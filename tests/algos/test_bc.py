import csv

import pytest
import torch

from pomil.algos.bc import BCConfig, train_bc
from pomil.api import TrainedPolicy
from pomil.eval.rollout import evaluate_circles
from pomil.training import load_checkpoint


def _rows(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def _cfg(demos_path, out, **kw):
    base = dict(demos=str(demos_path), out=str(out), progress=False, log_every=10)
    base.update(kw)
    return BCConfig(**base)


@pytest.mark.parametrize("policy", ["mlp", "gru"])
def test_bc_loss_falls_and_rollouts_stay_on_the_circles(policy, demos_path, tmp_path):
    ckpt = train_bc(_cfg(demos_path, tmp_path / policy, policy=policy, iterations=250, hidden_size=64))
    rows = _rows(tmp_path / policy)
    first, last = float(rows[0]["bc/nll"]), float(rows[-1]["bc/nll"])
    assert rows[0]["iteration"] == "1" and rows[-1]["iteration"] == "250"
    assert last < first - 1.0, (first, last)
    metrics, _ = evaluate_circles(TrainedPolicy.load(ckpt), episodes_per_code=100, seed=0)
    # Both modes appear; few trajectories leave the circles altogether.
    assert metrics["overall_none_share"] <= 0.2, metrics
    assert min(metrics["overall_mode_share"]) >= 0.15, metrics


def test_same_seed_same_run(demos_path, tmp_path):
    a = train_bc(_cfg(demos_path, tmp_path / "a", iterations=30, hidden_size=32, seed=7))
    b = train_bc(_cfg(demos_path, tmp_path / "b", iterations=30, hidden_size=32, seed=7))
    c = train_bc(_cfg(demos_path, tmp_path / "c", iterations=30, hidden_size=32, seed=8))
    pa, pb, pc = (load_checkpoint(p)["policy"] for p in (a, b, c))
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    assert any(not torch.equal(pa[k], pc[k]) for k in pa)
    strip = lambda rows: [{k: v for k, v in r.items() if not k.startswith("time/")} for r in rows]  # noqa: E731
    assert strip(_rows(tmp_path / "a")) == strip(_rows(tmp_path / "b"))


def test_resume_continues_the_same_run(demos_path, tmp_path):
    full = train_bc(_cfg(demos_path, tmp_path / "full", iterations=40, hidden_size=32, checkpoint_every=20))
    half = _cfg(demos_path, tmp_path / "split", iterations=20, hidden_size=32, checkpoint_every=20)
    train_bc(half)
    resumed = train_bc(_cfg(demos_path, tmp_path / "split", iterations=40, hidden_size=32, checkpoint_every=20), resume=True)
    pf, pr = load_checkpoint(full), load_checkpoint(resumed)
    assert pr["iteration"] == 40
    for k in pf["policy"]:
        assert torch.equal(pf["policy"][k], pr["policy"][k]), k
    full_rows, split_rows = _rows(tmp_path / "full"), _rows(tmp_path / "split")
    assert [r["iteration"] for r in split_rows] == [r["iteration"] for r in full_rows]
    assert [r["bc/nll"] for r in split_rows] == [r["bc/nll"] for r in full_rows]


def test_resume_refuses_a_changed_config(demos_path, tmp_path):
    from pomil.errors import PomilError

    train_bc(_cfg(demos_path, tmp_path / "r", iterations=5, hidden_size=32))
    with pytest.raises(PomilError, match="changed: lr"):
        train_bc(_cfg(demos_path, tmp_path / "r", iterations=10, hidden_size=32, lr=0.5), resume=True)
    with pytest.raises(PomilError, match="nothing to resume"):
        train_bc(_cfg(demos_path, tmp_path / "empty", iterations=5), resume=True)


def test_checkpoints_load_with_weights_only(demos_path, tmp_path):
    ckpt = train_bc(_cfg(demos_path, tmp_path / "w", iterations=3, hidden_size=16))
    payload = torch.load(ckpt, weights_only=True)
    assert payload["format"] == "pomil-checkpoint" and payload["algo"] == "bc"
    assert payload["env"]["id"] == "pomil/Circles-v0"
