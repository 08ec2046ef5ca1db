"""Per-task scores and code-to-task matching on constructed cases."""

import numpy as np
import pytest

from pomil.eval.tasks import match_codes, reference_of, speed_behaviour, task_scores

REFERENCE = {
    "tasks": {"forward": {"forward_reward_weight": 1.0}, "backward": {"forward_reward_weight": -1.0}},
    "expert_returns": {"forward": 300.0, "backward": 200.0},
    "still_returns": {"forward": 100.0, "backward": 150.0},
    "expert_displacement": {"forward": 2.0, "backward": 1.0},
}


def test_task_scores_numbers():
    s = task_scores(200.0, 1.5, REFERENCE, "forward")
    assert s["normalised_return"] == pytest.approx(200 / 300)
    assert s["progress"] == pytest.approx((200 - 100) / (300 - 100))
    assert s["displacement_ratio"] == pytest.approx(0.75)
    b = task_scores(150.0, -0.5, REFERENCE, "backward")  # standing still on the backward task
    assert b["normalised_return"] == pytest.approx(0.75) and b["progress"] == pytest.approx(0.0)
    assert b["displacement_ratio"] == pytest.approx(0.5)  # moved 0.5 backward, expert 1.0


def test_match_codes_one_to_one_beats_greedy():
    # greedy would give both tasks code 0; the best one-to-one total is code 1 -> task 0, code 0 -> task 1
    score = np.array([[0.9, 0.8], [0.85, 0.1]])
    assert match_codes(score) == [1, 0]
    assert match_codes(np.array([[0.2, 0.9], [0.8, 0.1], [0.5, 0.5]])) == [1, 0]


def test_match_codes_with_fewer_codes_than_tasks_takes_each_tasks_best():
    assert match_codes(np.array([[0.3, -1.0]])) == [0, 0]


def test_speed_behaviour_shares_purity_and_nearest_target():
    expert_speed = {"slow": 0.5, "mid": 1.0, "fast": 1.5}
    speeds = np.array([0.4, 0.7, 0.76, 1.2, 1.3, 2.0, 0.0, 1.24])
    codes = np.array([0, 0, 0, 1, 1, 1, 0, 1])
    b = speed_behaviour(speeds, codes, expert_speed, 2)
    # code 0: 0.4, 0.7 -> slow; 0.76 -> mid; 0.0 -> slow;  code 1: 1.2, 1.24 -> mid; 1.3, 2.0 -> fast
    assert b["code0"]["shares"] == {"slow": 0.75, "mid": 0.25, "fast": 0.0}
    assert b["code1"]["shares"] == {"slow": 0.0, "mid": 0.5, "fast": 0.5}
    assert b["code0"]["purity"] == 0.75 and b["code1"]["purity"] == 0.5
    assert b["code0"]["mean_speed"] == pytest.approx(1.86 / 4)
    assert b["code1"]["speed_std"] == pytest.approx(np.std([1.2, 1.3, 2.0, 1.24]))


def test_reference_keeps_expert_speeds_only_when_every_task_has_one():
    md = {**REFERENCE, "expert_speed": {"forward": 1.8, "backward": -2.1}}
    assert reference_of(md)["expert_speed"] == {"forward": 1.8, "backward": -2.1}
    assert "expert_speed" not in reference_of({**REFERENCE, "expert_speed": {"forward": 1.8}})
    assert "expert_speed" not in reference_of(REFERENCE)


def test_rates_are_assigned_to_the_nearest_task_or_to_standing():
    from pomil.eval.tasks import free_sampling, task_of_rates

    ref = {**REFERENCE, "tasks": {"forward": {"forward_reward_weight": 1.0, "max_episode_steps": 100},
                                  "backward": {"forward_reward_weight": -1.0, "max_episode_steps": 100}}}
    # expert rates: forward +0.02 per step, backward -0.01, standing 0
    assert task_of_rates(np.array([0.03, 0.012, 0.011, 0.009, -0.004, -0.006, -0.5]), ref).tolist() == \
        [0, 0, 0, -1, -1, 1, 1]
    assert task_of_rates(np.array([0.009, 0.006, -0.004]), ref, standing=False).tolist() == [0, 0, 1]
    # a forward episode that starts slowly (its first third nearer standing) is still pure; a standing one never
    roll = {"displacement": np.array([2.0, -1.0, 0.0, 2.0, 1.5]), "length": np.array([100] * 5),
            "segment_rates": np.array([[0.02] * 3, [-0.01] * 3, [0.0] * 3, [0.02, -0.01, 0.02], [0.006, 0.02, 0.02]])}
    free = free_sampling(roll, ref)
    assert free["mode_share"] == {"forward": 0.6, "backward": 0.2} and free["still_share"] == 0.2
    p = np.array([3 / 4, 1 / 4])
    assert free["coverage"] == pytest.approx(-(p * np.log(p)).sum() / np.log(2))
    assert (free["episode_purity"], free["switch_share"]) == (0.6, 0.2)
