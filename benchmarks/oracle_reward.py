"""The oracle check: can the adversarial learner's policy optimiser lift a Hopper Forward/Backward gait off its warm
start when it is paid the task's own reward?

Runs ``pomil train infogail-pomdp ...`` (any of its flags) with one change: PPO's step reward is each episode's task
reward instead of the imitation reward: Hopper's healthy reward minus the control cost, plus the x velocity signed by
the episode's code (+1 for the code that moves forward in the first rollout, -1 for the other), divided by the
batch's standard deviation of step rewards (no mean shift: every step of a healthy hop is paid, so falling never
pays). Critic and posterior train as usual and go unused. Everything else (warm start, BC term, PPO, budget,
evaluation, hand-over) is the learner's. If the gait rises here and not with the imitation reward, the reward is what
holds it; if it stays flat here too, the optimiser is.

The environment's reward is read here only; no learner sees it.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/oracle_reward.py --demos D --demos-per-mode 4 --seed 0 --out R

Two codes only (Hopper Forward/Backward demonstrations).
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import torch

import pomil.algos.adversarial as adversarial
from pomil.cli import main as pomil_main

_state: dict[str, Any] = {}


def _make_vec_env(*args: Any, **kwargs: Any) -> Any:
    """The training environment, paying healthy - control cost only; each step's x velocity recorded aside."""
    env = _make_vec_env.original(*args, **kwargs)
    sim = env.sim
    sim.kw = {**sim.kw, "forward_reward_weight": 0.0}
    step = sim.step

    def recorded_step(actions: np.ndarray) -> Any:
        x0 = sim.x_position
        out = step(actions)
        _state["x_velocity"].append((sim.x_position - x0) / sim.dt)
        return out

    sim.step = recorded_step
    return env


def _collect(env: Any, *args: Any, **kwargs: Any) -> Any:
    """A rollout as in training; the task reward of its steps kept for :func:`_rewards`."""
    _state["x_velocity"] = []
    c = _collect.original(env, *args, **kwargs)
    mask = c.rollout.mask.to(c.env_rewards.dtype)
    vx = torch.as_tensor(np.stack(_state["x_velocity"]), dtype=c.env_rewards.dtype) * mask
    if "sign" not in _state:  # the direction of each code, fixed by the first rollout
        if int(c.codes.max()) > 1 or c.codes.ndim != 1:
            raise SystemExit("oracle_reward: error: two discrete codes expected (Hopper Forward/Backward)")
        speed = [(vx[:, c.codes == k].sum() / mask[:, c.codes == k].sum()).item() for k in (0, 1)]
        forward = int(np.argmax(speed))
        _state["sign"] = torch.tensor([1.0 if k == forward else -1.0 for k in (0, 1)])
        print(f"oracle_reward: code {forward} moves forward in the first rollout (mean x velocity per code: "
              f"{speed[0]:.2f}, {speed[1]:.2f})", file=sys.stderr)
    _state["reward"] = c.env_rewards + _state["sign"][c.codes].to(vx.dtype) * vx
    return c


def _rewards(m: Any, roll: Any, code_idx: torch.Tensor, **kwargs: Any) -> tuple[torch.Tensor, dict[str, float]]:
    """The kept task reward, over its batch standard deviation."""
    r = _state["reward"].to(roll.mask.device)
    r = r / r[roll.mask].std().clamp_min(1e-8)
    return r.to(torch.float32), {"reward/total": r[roll.mask].mean().item()}


def main(argv: list[str] | None = None) -> int:
    _make_vec_env.original = adversarial.make_vec_env
    _collect.original = adversarial.collect
    adversarial.make_vec_env, adversarial.collect, adversarial.rewards = _make_vec_env, _collect, _rewards
    return pomil_main(["train", "infogail-pomdp", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
