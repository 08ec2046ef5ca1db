"""Experiment specs: the shipped ones and the committed results they made, grids, summaries, tables."""

import json
from pathlib import Path

import pytest

from pomil.errors import PomilError
from pomil.experiment import load_spec, results_table, select_rows, spec_from_dict, spec_names, summarise

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = (ROOT / "results").is_dir()  # the repository's; an unpacked sdist has none
NO_RESULTS = "the committed results/ are the repository's: the sdist does not carry them"


@pytest.mark.parametrize("name", spec_names())
def test_every_shipped_spec_loads_and_its_committed_results_name_it(name):
    spec = load_spec(name)
    assert spec.rows and spec.description
    if not spec.results:
        return
    if not COMMITTED:
        pytest.skip(NO_RESULTS)
    metrics = json.loads((ROOT / spec.results / "metrics.json").read_text())
    assert metrics["spec"]["name"] == name and metrics["spec"]["source"] == f"src/pomil/experiments/{name}.toml"
    assert list(metrics["rows"]) == [r.name for r in spec.rows]
    assert [r["learner"] for r in metrics["rows"].values()] == [r.learner for r in spec.rows]
    for row in metrics["rows"].values():  # the recorded summary is the one its runs give
        assert len(row["runs"]) == metrics["spec"]["seeds"] and row["successes"] == sum(r["success"]
                                                                                         for r in row["runs"])
    kept = sorted(p.name for p in (ROOT / spec.results).glob("policies/*.pt"))
    expected = sorted(f"{r.name}-seed{s}.pt" for r in spec.rows for s in range(metrics["spec"]["seeds"])
                      if spec.keeps_policy(r.name, s))
    assert kept == expected


@pytest.mark.skipif(not COMMITTED, reason=NO_RESULTS)
def test_every_results_directory_is_made_by_a_spec_the_readme_lists():
    made = {load_spec(n).results for n in spec_names()}
    readme = (ROOT / "README.md").read_text()
    for d in sorted((ROOT / "results").iterdir()):
        assert f"results/{d.name}" in made, d
        assert f"`{d.name}`" in readme, d.name


def test_a_grid_makes_one_row_per_combination_with_its_settings():
    spec = spec_from_dict({"rows": [{"name": "a", "learner": "gail"}, {"name": "b", "learner": "infogail"}],
                           "demos": {"file": "d.npz", "record": "circles --episodes 4"},
                           "grid": {"lr": [1e-4, 2e-4], "mi_weight": [0.0]}}, "g", "g.toml")
    assert [r.name for r in spec.rows] == ["a lr=0.0001 mi_weight=0.0", "a lr=0.0002 mi_weight=0.0",
                                           "b lr=0.0001 mi_weight=0.0", "b lr=0.0002 mi_weight=0.0"]
    assert spec.rows[1].settings == {"lr": 2e-4, "mi_weight": 0.0} and spec.rows[0].demos.record[-1] == "4"
    with pytest.raises(PomilError, match="grid key 'lr': expected a non-empty list"):
        spec_from_dict({"learners": ["gail"], "demos": {"file": "d.npz"}, "grid": {"lr": 1e-4}}, "g", "g.toml")


def test_settings_of_a_kind_go_under_a_rows_own_and_the_command_lines_over_both():
    spec = spec_from_dict({"rows": [{"learner": "gail", "settings": {"lr": 3e-4}}, {"learner": "bc-mlp"}],
                           "demos": {"file": "d.npz"},
                           "settings": {"adversarial": {"lr": 1e-4, "mi_weight": 1.0}, "bc": {"hidden_size": 8}}},
                          "s", "s.toml")
    gail, bc = spec.rows
    assert spec.values(gail)["lr"] == 3e-4 and spec.values(gail)["mi_weight"] == 1.0
    assert spec.values(bc) == {"hidden_size": 8, "demos": str(Path("d.npz").resolve())}
    over = type(spec)(**{**spec.__dict__, "overrides": {"adversarial": {"lr": 5e-4}}})
    assert over.values(gail)["lr"] == 5e-4 and over.values(gail)["demos"] == str(Path("d.npz").resolve())


def _circles_run(seed, purity, nmi, covered=2):
    return {"train_seed": seed, "mean_purity": purity, "min_purity": purity, "modes_covered": covered, "nmi": nmi,
            "overall_none_share": 1 - purity, "per_code": [{"mode_share": [purity, 0.0]}] * 2,
            "overall_mode_share": [purity, 0.0],
            "success": purity >= 0.95 and nmi >= 0.9 and covered == 2}


def test_summary_success_counts_and_table_come_from_the_runs():
    data = {"spec": {"description": "", "episodes_per_code": 10, "row_label": "case"}, "failed": [],
            "rows": {"x": {"learner": "infogail-pomdp", "kind": "circles", "wall_s": [10.0, 30.0],
                           "runs": [_circles_run(0, 1.0, 1.0), _circles_run(1, 0.5, 0.2, covered=1)]}}}
    row = summarise(data)["rows"]["x"]
    assert row["successes"] == 1
    assert row["summary"]["min_purity"] == [0.75, 0.25] and row["summary"]["nmi"] == [0.6, 0.4]
    table = results_table(data)
    assert "| case | modes |" in table
    # coverage from the modes' shares; episode purity and switching were not measured
    assert ("| x | 2 | 1/2 | 0.75 ± 0.25 | 0.75 ± 0.25 | 1.5 ± 0.5 | 0.60 ± 0.40 | 0.25 ± 0.25 | 0.00 ± 0.00 | - | - "
            "| 20 |") in table
    assert "mean ± std over 2 seed(s) (0, 1); 10 stochastic rollouts per code" in table
    # free-sampling figures, "-" for a row measured before them
    data["rows"]["y"] = {"learner": "diffusion", "kind": "circles", "wall_s": [5.0, 7.0],
                         "runs": [{**_circles_run(s, 0.5, 0.0, covered=1), "coverage": c, "episode_purity": p,
                                   "switch_share": w} for s, c, p, w in ((0, 1.0, 0.9, 0.0), (1, 0.8, 0.7, 0.1))]}
    table = results_table(summarise(data))
    assert "| none share | coverage | episode purity | switching | wall s / seed |" in table
    assert "| 0.25 ± 0.25 | 0.00 ± 0.00 | - | - | 20 |" in table  # coverage from the modes' shares
    assert "| 0.50 ± 0.00 | 0.90 ± 0.10 | 0.80 ± 0.10 | 0.05 ± 0.05 | 6 |" in table


def test_rows_are_chosen_by_name_and_a_rows_name_chooses_its_grid_rows():
    spec = load_spec("hopper-few-demos")
    assert [r.name for r in select_rows(spec, ("igp-warm-start",))] == [
        f"igp-warm-start demos_per_mode={n}" for n in (1, 4, 11, 25)]
    assert [r.name for r in select_rows(spec, ("infogail-pomdp demos_per_mode=4",))] == [
        "infogail-pomdp demos_per_mode=4"]
    assert len(select_rows(spec, ())) == 28
    assert len(select_rows(load_spec("hopper-paper-few-demos"), ())) == 15  # 5 learners x N in {1, 4, 11}
    with pytest.raises(PomilError, match=r"--rows: no rows \['igp'\] in .*hopper-few-demos.toml"):
        select_rows(spec, ("igp",))
