"""Every config field is type- and range-checked when the config is built, from flags,
JSON files and Python alike: one line naming the field, the value and what is allowed."""

import dataclasses
import json
import subprocess
import sys
import typing

import pytest

from pomil.algos.adversarial import AdversarialConfig
from pomil.algos.bc import BCConfig
from pomil.algos.expert import ExpertConfig
from pomil.cli import CirclesDemosConfig, HopperDemosConfig, MergeDemosConfig, RecordDemosConfig, add_config_flags, main
from pomil.config import Interval, field_interval, from_dict, option
from pomil.errors import ConfigError
from pomil.experiment import ReproduceOptions, SweepConfig

CONFIGS = [AdversarialConfig, BCConfig, ExpertConfig, CirclesDemosConfig, HopperDemosConfig, RecordDemosConfig,
           MergeDemosConfig, SweepConfig, ReproduceOptions]


@pytest.mark.parametrize("cls", CONFIGS, ids=lambda c: c.__name__)
def test_every_numeric_field_declares_its_interval_and_defaults_lie_in_it(cls):
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        numeric = tp in (int, float) or typing.get_args(tp)[:1] in ((int,), (float,))
        if numeric:
            assert isinstance(field_interval(f), Interval), (cls.__name__, f.name)
    cls()  # the defaults pass their own checks


@pytest.mark.parametrize("values, text", [
    ({"lr": float("nan")}, "config key 'lr': expected a finite number in (0, inf), got nan"),
    ({"lr": "inf"}, "config key 'lr': expected a finite number in (0, inf), got inf"),
    ({"lr": 0}, "config key 'lr': expected a finite number in (0, inf), got 0"),
    ({"lr_critic": float("nan")}, "config key 'lr_critic': expected a finite number in (0, inf)"),
    ({"gamma": 1.5}, "config key 'gamma': expected a finite number in (0, 1], got 1.5"),
    ({"gamma": 2.0}, "config key 'gamma': expected a finite number in (0, 1], got 2.0"),
    ({"gamma": "nan"}, "config key 'gamma': expected a finite number in (0, 1], got nan"),
    ({"gae_lambda": 0}, "config key 'gae_lambda': expected a finite number in (0, 1], got 0"),
    ({"iterations": 2.5}, "config key 'iterations': expected int, got 2.5"),
    ({"iterations": "2.5"}, "config key 'iterations': expected int, got '2.5'"),
    ({"iterations": True}, "config key 'iterations': expected int, got True"),
    ({"iterations": -1}, "config key 'iterations': expected an integer in [0, inf), got -1"),
    ({"mi_weight": -1}, "config key 'mi_weight': expected a finite number in [0, inf), got -1"),
    ({"mi_weight": float("nan")}, "config key 'mi_weight': expected a finite number in [0, inf), got nan"),
    ({"log_std_init": float("nan")}, "config key 'log_std_init': expected a finite number in (-inf, inf), got nan"),
    ({"clip": -0.2}, "config key 'clip': expected a finite number in (0, inf), got -0.2"),
    ({"eval_every": -1}, "config key 'eval_every': expected an integer in [0, inf), got -1"),
    ({"num_codes": 1}, "config key 'num_codes': expected -1 (from the demonstrations), auto or >= 2, got 1"),
    ({"device": "tpu"}, "config key 'device': expected cpu, cuda, cuda:N, mps or auto, got 'tpu'"),
    ({"demos": 5}, "config key 'demos': expected str, got 5"),
    ({"progress": "maybe"}, "config key 'progress': expected bool, got 'maybe'"),
    ({"seed": -3}, "config key 'seed': expected an integer in [0, 4294967295], got -3"),
])
def test_out_of_range_values_are_refused_naming_field_value_and_interval(values, text):
    with pytest.raises(ConfigError) as err:
        from_dict(AdversarialConfig, values, source="run.json")
    assert str(err.value) == f"run.json: {text}" or str(err.value).startswith(f"run.json: {text}"), str(err.value)
    with pytest.raises(ValueError):  # the same check when a config is built in Python
        AdversarialConfig(**{k: (float(v) if k in ("lr", "gamma") and isinstance(v, str) else v)
                             for k, v in values.items()})


def test_boundaries_are_as_declared():
    assert from_dict(AdversarialConfig, {"gamma": 1.0, "gae_lambda": 1, "eval_every": 0, "mi_weight": 0}).gamma == 1.0
    assert from_dict(AdversarialConfig, {"iterations": 0}).iterations == 0  # the warm start alone
    with pytest.raises(ConfigError, match=r"'iterations': expected an integer in \[1, inf\), got 0"):
        from_dict(BCConfig, {"iterations": 0})
    assert from_dict(ExpertConfig, {"lr": 1e-9, "ent_coef": 0.0}).lr == 1e-9
    assert from_dict(MergeDemosConfig, {"episodes": 0, "proportions": [1, 0.5]}).proportions == (1.0, 0.5)
    with pytest.raises(ConfigError, match=r"'proportions': expected a finite number in \[0, inf\), got -1"):
        from_dict(MergeDemosConfig, {"proportions": "1,-1"})
    with pytest.raises(ConfigError, match=r"'cpus_per_run': expected a finite number in \(0, inf\), got 0"):
        SweepConfig(cpus_per_run=0)


def test_interval_notation():
    unit = Interval.parse("(0, 1]")
    assert 1 in unit and 0.5 in unit and 0 not in unit and 1.0001 not in unit and float("nan") not in unit
    assert float("inf") not in Interval.parse("(-inf, inf)") and -1e300 in Interval.parse("(-inf, inf)")
    with pytest.raises(ValueError, match="expected e.g."):
        Interval.parse("0..1")


@pytest.mark.parametrize("flags, text", [
    (["--lr", "inf"], "config key 'lr': expected a finite number in (0, inf), got inf"),
    (["--gamma", "nan"], "config key 'gamma': expected a finite number in (0, 1], got nan"),
    (["--device", "tpu"], "config key 'device': expected cpu, cuda, cuda:N, mps or auto, got 'tpu'"),
    (["--eval-every", "-1"], "config key 'eval_every': expected an integer in [0, inf), got -1"),
    (["--config", "bad.json"], "bad.json: config key 'lr': expected a finite number in (0, inf), got nan"),
    (["--config", "int.json"], "int.json: config key 'iterations': expected int, got 2.5"),
    # a flag over a bad key of the file: the file is still checked whole
    (["--config", "int.json", "--iterations", "1"], "int.json: config key 'iterations': expected int, got 2.5"),
    (["--config", "bad.json", "--lr", "1e-4"],
     "bad.json: config key 'lr': expected a finite number in (0, inf), got nan"),
    (["--config", "range.json", "--iterations", "3"],
     "range.json: config key 'iterations': expected an integer in [0, inf), got -4"),
    (["--config", "preset.json", "--preset", "default"],
     "preset.json: config key 'preset': expected one of ['auto', 'default', 'paper-text', 'long-warm-start', "
     "'fast-warm-start', 'deep-warm-start', 'terminating'], got 'fast'"),
])
def test_cli_refuses_bad_values_in_one_line_and_writes_nothing(flags, text, tmp_path, demos_path, monkeypatch, capsys):
    (tmp_path / "bad.json").write_text('{"lr": NaN}')
    (tmp_path / "int.json").write_text('{"iterations": 2.5}')
    (tmp_path / "range.json").write_text('{"iterations": -4}')
    (tmp_path / "preset.json").write_text('{"preset": "fast"}')
    monkeypatch.chdir(tmp_path)
    code = main(["train", "infogail-pomdp", "--demos", str(demos_path), "--out", "run", *flags])
    err = capsys.readouterr().err
    assert code == 2 and err == f"pomil: error: {text}\n", err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json", "int.json", "preset.json",
                                                          "range.json"]  # no run directory, config.json, tb/


def test_cli_subprocess_bad_value_has_no_traceback(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps({"gamma": 1.5}))
    r = subprocess.run([sys.executable, "-m", "pomil.cli", "train", "bc", "--config", "c.json", "--demos", "x.npz"],
                       capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "unknown key(s) ['gamma']" in r.stderr  # BC has no discount: unknown keys still list the valid ones
    (tmp_path / "c.json").write_text(json.dumps({"lr": -1}))
    r = subprocess.run([sys.executable, "-m", "pomil.cli", "train", "bc", "--config", "c.json", "--demos", "x.npz"],
                       capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 2
    assert r.stderr == "pomil: error: c.json: config key 'lr': expected a finite number in (0, inf), got -1.0\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.json"]


def test_help_shows_the_interval():
    from pomil.cli import build_parser

    train = build_parser()._subparsers._group_actions[0].choices["train"]
    text = train._subparsers._group_actions[0].choices["gail"].format_help()
    assert "in (0, 1]" in text and "in (0, inf)" in text


def test_every_commands_help_renders_with_percent_signs_in_field_docs():
    import argparse

    from pomil.cli import build_parser

    def parsers(parser):
        yield parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for child in action.choices.values():
                    yield from parsers(child)

    texts = [p.format_help() for p in parsers(build_parser())]
    assert len(texts) > 10

    @dataclasses.dataclass(frozen=True)
    class Percent:
        speed: float = option(1.0, "7-9% faster", within="(0, inf)")

    parser = argparse.ArgumentParser()
    add_config_flags(parser, Percent)
    assert "7-9% faster" in parser.format_help()  # a field's docs with a percent sign, printed as written


def test_a_renamed_key_is_still_read_with_a_note_and_both_names_at_once_are_refused(capsys):
    assert from_dict(ExpertConfig, {"epochs": 3}).ppo_epochs == 3
    assert "'epochs' is now called 'ppo_epochs'" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="same setting"):
        from_dict(ExpertConfig, {"epochs": 3, "ppo_epochs": 4})


def test_a_saved_config_of_an_earlier_version_reads_as_this_version_writes_it():
    from pomil.config import saved_config, to_dict

    old = {k: v for k, v in to_dict(ExpertConfig(ppo_epochs=7)).items() if k != "ppo_epochs"}
    old["epochs"] = 7
    assert saved_config(ExpertConfig, old) == to_dict(ExpertConfig(ppo_epochs=7))
    without_new_keys = {k: v for k, v in to_dict(AdversarialConfig()).items() if k not in ("vf_coef", "max_grad_norm")}
    assert saved_config(AdversarialConfig, without_new_keys) == to_dict(AdversarialConfig())
