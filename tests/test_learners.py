"""One table of learners, read by the CLI, sweeps and reproductions."""

import pytest

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.algos.bc import BCConfig, train_bc
from pomil.cli import build_parser
from pomil.errors import PomilError
from pomil.learners import ADVERSARIAL, LEARNERS, learner
from pomil.reproduce import CirclesReproConfig


def test_each_learner_names_its_config_train_function_and_fixed_values():
    assert ADVERSARIAL == ("gail", "infogail", "infogail-pomdp")
    for name in ADVERSARIAL:
        assert (LEARNERS[name].config, LEARNERS[name].train) == (AdversarialConfig, train_adversarial)
        assert LEARNERS[name].make_config({"demos": "d.npz", "learner": "gail"}).learner == name  # the name wins
    assert (LEARNERS["bc"].config, LEARNERS["bc"].train) == (BCConfig, train_bc)
    assert LEARNERS["bc-mlp"].make_config({}).policy == "mlp"
    assert LEARNERS["bc-gru"].make_config({}).policy == "gru"


def test_the_train_command_has_one_subcommand_per_command_learner():
    parser = build_parser()
    train = next(a for a in parser._subparsers._group_actions[0].choices["train"]._actions if a.dest == "algo")
    assert sorted(train.choices) == sorted(n for n, lr in LEARNERS.items() if lr.command) == \
        ["bc", "gail", "infogail", "infogail-pomdp"]
    args = parser.parse_args(["train", "gail", "--demos", "d.npz"])
    assert args.learner == "gail"


def test_reproductions_and_lookups_take_the_tables_names_only():
    assert CirclesReproConfig(learners=tuple(LEARNERS)).learners == tuple(LEARNERS)
    with pytest.raises(ValueError, match="unknown learners"):
        CirclesReproConfig(learners=("bc", "dagger"))
    with pytest.raises(PomilError, match="must be one of"):
        learner("dagger")
