"""One table of learners, read by the CLI, sweeps and reproductions."""

import pytest

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.algos.bc import BCConfig, train_bc
from pomil.cli import build_parser
from pomil.config import to_dict
from pomil.errors import PomilError
from pomil.learners import ABLATIONS, ADVERSARIAL, LEARNERS, learner


def test_each_learner_names_its_config_train_function_and_fixed_values():
    assert ADVERSARIAL[:3] == ("gail", "infogail", "infogail-pomdp") and ADVERSARIAL[3:] == ABLATIONS
    for name in ADVERSARIAL:
        assert (LEARNERS[name].config, LEARNERS[name].train) == (AdversarialConfig, train_adversarial)
        kind = "infogail-pomdp" if name in ABLATIONS else name
        assert LEARNERS[name].make_config({"demos": "d.npz", "learner": "gail"}).learner == kind  # the name wins
    assert (LEARNERS["bc"].config, LEARNERS["bc"].train) == (BCConfig, train_bc)
    assert LEARNERS["bc-mlp"].make_config({}).policy == "mlp"
    assert LEARNERS["bc-gru"].make_config({}).policy == "gru"


def test_each_ablation_is_the_full_method_less_one_part():
    full = to_dict(LEARNERS["infogail-pomdp"].make_config({"demos": "d.npz"}))
    taken_away = {"igp-warm-start": {"iterations": 0}, "igp-no-mi": {"mi_weight": 0.0},
                  "igp-shared-belief": {"belief": "shared"}, "igp-policy-belief": {"belief": "policy"},
                  "igp-no-bc": {"bc_weight": 0.0}}
    assert set(ABLATIONS) == set(taken_away)
    for name, part in taken_away.items():
        ablated = to_dict(LEARNERS[name].make_config({"demos": "d.npz", "iterations": 7}))
        assert {k: v for k, v in ablated.items() if full[k] != v} == (part if name == "igp-warm-start" else
                                                                      {**part, "iterations": 7})


def test_the_train_command_has_one_subcommand_per_command_learner():
    parser = build_parser()
    train = next(a for a in parser._subparsers._group_actions[0].choices["train"]._actions if a.dest == "algo")
    assert sorted(train.choices) == sorted(n for n, lr in LEARNERS.items() if lr.command) == \
        ["bc", "diffusion", "diffusion-codes", "gail", "infogail", "infogail-pomdp"]
    args = parser.parse_args(["train", "gail", "--demos", "d.npz"])
    assert args.learner == "gail"


def test_experiments_and_lookups_take_the_tables_names_only():
    from pomil.experiment import spec_from_dict

    demos = {"file": "d.npz"}
    assert [r.learner for r in spec_from_dict({"learners": list(LEARNERS), "demos": demos}, "x", "x.toml").rows] \
        == list(LEARNERS)
    with pytest.raises(PomilError, match=r"x.toml: rows\[0\]: key 'learner': expected one of .*got 'dagger'"):
        spec_from_dict({"rows": [{"learner": "dagger"}], "demos": demos}, "x", "x.toml")
    with pytest.raises(PomilError, match="must be one of"):
        learner("dagger")
