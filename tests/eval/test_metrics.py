import math

import numpy as np
import pytest

from pomil.eval.metrics import mode_metrics, mutual_information, normalized_mutual_info


def test_nmi_extremes():
    a = np.array([0, 0, 1, 1])
    assert normalized_mutual_info(a, a) == pytest.approx(1.0)
    assert normalized_mutual_info(a, 1 - a) == pytest.approx(1.0)
    assert normalized_mutual_info(a, np.array([0, 1, 0, 1])) == pytest.approx(0.0)
    assert normalized_mutual_info(np.zeros(4), a) == 0.0


def test_mutual_information_hand_computed():
    # joint: (0,0) 1/2, (1,0) 1/4, (1,1) 1/4 -> MI = H(b) - H(b|a) = H(3/4,1/4) - 1/2 * 1 bit(in nats)
    a, b = np.array([0, 0, 1, 1]), np.array([0, 0, 0, 1])
    hb = -(0.75 * math.log(0.75) + 0.25 * math.log(0.25))
    assert mutual_information(a, b) == pytest.approx(hb - 0.5 * math.log(2))
    ha = math.log(2)
    assert normalized_mutual_info(a, b) == pytest.approx((hb - 0.5 * math.log(2)) / (0.5 * (ha + hb)))


def test_mode_metrics_on_a_constructed_case():
    codes = np.array([0] * 10 + [1] * 10)
    modes = np.array([1] * 9 + [-1] + [0] * 6 + [1] * 4)
    m = mode_metrics(codes, modes, 2, 2)
    assert m["per_code"][0]["mode_share"] == [0.0, 0.9] and m["per_code"][0]["none_share"] == pytest.approx(0.1)
    assert m["per_code"][0]["majority_mode"] == 1 and m["per_code"][1]["majority_mode"] == 0
    assert m["per_code"][1]["purity"] == pytest.approx(0.6)
    assert m["modes_covered"] == 2
    assert m["mean_purity"] == pytest.approx(0.75) and m["min_purity"] == pytest.approx(0.6)
    assert m["overall_mode_share"] == [0.3, 0.65] and m["overall_none_share"] == pytest.approx(0.05)


def test_codes_on_the_same_mode_cover_one():
    m = mode_metrics(np.array([0, 0, 1, 1]), np.array([1, 1, 1, 1]), 2, 2)
    assert m["modes_covered"] == 1 and m["nmi"] == 0.0


def test_spearman_exact_values_with_and_without_ties():
    from pomil.eval.metrics import average_ranks, spearman

    assert spearman([1, 2, 3, 4], [10, 20, 30, 400]) == pytest.approx(1.0)
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    # ranks x: 0 1 2 3, y: 1 0 3 2 -> centred products 1.5*0.5 + 0.5*1.5 + 0.5*1.5 + 1.5*0.5 -> rho = 0.6
    assert spearman([1, 2, 3, 4], [2, 1, 4, 3]) == pytest.approx(0.6)
    assert average_ranks(np.array([5.0, 1.0, 5.0, np.inf])).tolist() == [1.5, 0.0, 1.5, 3.0]
    # ties: x = (0, 0, 1, 1) ranks (0.5, 0.5, 2.5, 2.5); y ranks (0, 1, 2, 3): rho = 4 / sqrt(4 * 5)
    assert spearman([0, 0, 1, 1], [1, 2, 3, 4]) == pytest.approx(4 / math.sqrt(20))
    assert spearman([1, 1, 1], [1, 2, 3]) == 0.0
    # 9 tied values of 20 against untied ranks: the largest rho possible, sqrt(1 - (20^2 - 1) / (180^2 - 1))
    assert spearman(np.repeat(np.arange(9), 20), np.arange(180)) == pytest.approx(math.sqrt(1 - 399 / 32399))
    with pytest.raises(ValueError, match="spearman"):
        spearman([1, 2], [1, np.nan])


def test_coverage_is_the_modes_entropy_over_log_m():
    from pomil.eval.metrics import coverage

    assert coverage(np.array([0, 1, 0, 1]), 2) == pytest.approx(1.0)
    assert coverage(np.array([0, 0, 0, -1]), 2) == 0.0  # one mode (the "none" episode is not a mode)
    p = np.array([0.75, 0.25])
    assert coverage(np.array([0, 0, 0, 1, -1]), 2) == pytest.approx(-(p * np.log(p)).sum() / math.log(2))
    assert coverage(np.array([0, 1, 2, 2]), 3) == pytest.approx(1.5 * math.log(2) / math.log(3))
    assert coverage(np.array([-1, -1]), 2) == 0.0 and coverage(np.array([0, 0]), 1) == 0.0
    from pomil.eval.metrics import shares_coverage

    assert shares_coverage([0.6, 0.2]) == pytest.approx(coverage(np.array([0, 0, 0, 1, -1]), 2))


def test_episode_purity_and_switching():
    from pomil.eval.metrics import episode_purity

    seg = np.array([[0, 0, 0], [1, 1, 1], [0, 1, 1], [0, -1, 0], [-1, -1, -1]])
    assert episode_purity(seg) == {"episode_purity": 0.4, "switch_share": 0.2}
    with pytest.raises(ValueError, match="segment_modes"):
        episode_purity(np.array([0, 1]))
