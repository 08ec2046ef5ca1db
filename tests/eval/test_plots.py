"""The learning-curve figure: what each learner's lines say."""

import numpy as np
import pytest

from pomil.eval.plots import curves_figure


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
