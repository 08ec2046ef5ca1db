"""The learning-curve figure: what each learner's lines say."""

import numpy as np
import pytest

from pomil.eval.plots import curves_figure, grid_axis, grid_figure, grid_lines


def _results():
    ref = {"expert_returns": {"forward": 100.0}, "still_returns": {"forward": 10.0}}
    curve = lambda steps, ys: {"env_steps": steps, "forward": ys}  # noqa: E731
    return {"tasks": ["forward"], "reference": ref, "setting": "paper", "learners": {
        "bc-gru": {"curves": [curve([], [])], "summary": {"forward": {"normalised_return": [0.4, 0.0]}}},
        "infogail-pomdp": {"curves": [curve([0, 10, 20], [0.5, 0.7, 0.9]),
                                      curve([0, 10, 20, 30], [0.7, 0.9, 1.0, 1.0])], "summary": {}},
        "igp-warm-start": {"curves": [curve([0], [0.6]), curve([0], [0.8])], "summary": {}},
    }}


def test_curves_mark_the_warm_start_at_zero_steps_and_draw_ablations_dashed():
    fig = curves_figure(_results())
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    full = lines["infogail-pomdp (2 seeds)"]
    np.testing.assert_allclose(full.get_xdata(), [0, 10, 20])  # the shortest seed's length
    np.testing.assert_allclose(full.get_ydata(), [0.6, 0.8, 0.95])  # mean over seeds
    assert full.get_marker() == "o" and list(full.get_markevery()) == [0] and full.get_linestyle() == "-"
    warm = lines["igp-warm-start (2 seeds)"]
    np.testing.assert_allclose(warm.get_xdata(), [0])
    assert warm.get_ydata()[0] == pytest.approx(0.7) and warm.get_linestyle() == "--" and warm.get_marker() == "o"
    bc = lines["bc-gru (final)"]
    assert bc.get_ydata()[0] == pytest.approx(0.4) and bc.get_linestyle() == ":"
    assert lines["zero actions"].get_ydata()[0] == pytest.approx(0.1)


def _grid_rows():
    row = lambda learner, n, mean: {"learner": learner, "settings": {"demos_per_mode": n, "bc_weight": 1.0},  # noqa: E731
                                    "summary": {"forward": {"normalised_return": [mean, 0.1]}}}
    return {"igp-warm-start demos_per_mode=4": row("infogail-pomdp", 4, 0.7),
            "igp-warm-start demos_per_mode=1": row("infogail-pomdp", 1, 0.3),
            "infogail-pomdp demos_per_mode=1": row("infogail-pomdp", 1, 0.4)}


def test_a_grid_over_one_number_gives_one_line_per_row_against_it(tmp_path):
    rows = _grid_rows()
    assert grid_axis(rows) == "demos_per_mode"  # bc_weight is a setting of every row, not in the names
    assert grid_lines(rows, "forward", "demos_per_mode") == {
        "igp-warm-start": ([1, 4], [0.3, 0.7], [0.1, 0.1]), "infogail-pomdp": ([1], [0.4], [0.1])}
    grid_figure(rows, ["forward"], "demos_per_mode", tmp_path / "figure.png")
    assert (tmp_path / "figure.png").read_bytes()[:4] == b"\x89PNG"
    two = {"a n=1 m=2": {"settings": {"n": 1, "m": 2}}, "a n=2 m=2": {"settings": {"n": 2, "m": 2}}}
    assert grid_axis(two) is None and grid_axis({"a": {"settings": {}}}) is None  # two keys; no grid
    assert grid_axis({"a flag=True": {"settings": {"flag": True}}}) is None  # not a number
