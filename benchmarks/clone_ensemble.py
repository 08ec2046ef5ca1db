"""Several warm starts of one draw acting as one policy: at each step the members' mean actions are averaged.

The probe behind ``--policy-members`` (an ensemble trained within one run): here each member is a separate run's
checkpoint trained on the same demonstrations (e.g. ``pomil train infogail-pomdp --iterations 0`` from several seeds on
one draw). The members' codes are aligned without the environment's reward, as ``--policy-members`` renames them: each
member assigns every demonstration episode its most likely code (the mixture's balanced assignment), and each member's
codes are permuted to agree most with the first member's (``pomil.algos.warm_start.code_renaming``). Every member keeps
its own recurrent state and sees the averaged action as its previous one. The ensemble is scored as ``pomil evaluate
--json`` scores one policy (deterministic episodes, each task's matched code), with the alignment added to the JSON.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/clone_ensemble.py --demos D --demos-per-mode 4 --seed S \\
        --eval-seed 1000+S R1 R2 R3
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

import numpy as np
import torch

from pomil import TrainedPolicy
from pomil.algos.warm_start import code_renaming, most_likely_codes
from pomil.data import load_training_demos
from pomil.envs import executed_actions_fn
from pomil.errors import PomilError
from pomil.eval.tasks import evaluate_tasks, reference_of
from pomil.nn.policy import GaussianPolicy, shift_actions


class Ensemble:
    """``members`` acting as one policy for :func:`evaluate_tasks`: ensemble code c is member i's code
    ``codes[i][c]``; the action is the members' mean action, averaged."""

    def __init__(self, members: list[TrainedPolicy], codes: list[list[int]]) -> None:
        self.members, self.codes = members, [np.asarray(c) for c in codes]
        self.env, self.num_codes, self.code_dim = members[0].env, members[0].num_codes, 0

    def reset(self, num_envs: int, codes: np.ndarray | None = None, seed: int | None = None) -> None:
        for member, own in zip(self.members, self.codes, strict=True):
            member.reset(num_envs, None if codes is None else own[np.asarray(codes)], seed=seed)

    def act(self, observations: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        action = torch.stack([torch.as_tensor(m.act(observations, True)) for m in self.members]).mean(0)
        for m in self.members:  # each member's a_{t-1} is the action carried out, not its own
            m._prev = m._executed(action)
        return action


def align(assignments: list[np.ndarray], num_codes: int) -> list[list[int]]:
    """Per member, the permutation p (ensemble code c -> the member's code p[c]) under which its assignment of the
    episodes agrees most with the first member's (the first member's own: the identity)."""
    first, out = torch.as_tensor(assignments[0]), []
    for a in assignments:
        renaming = code_renaming(first, torch.as_tensor(a), num_codes).tolist()  # member code j -> ensemble code
        out.append(sorted(range(num_codes), key=lambda j: renaming[j]))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="+", help="the members: runs' checkpoint.pt files (or run directories)")
    ap.add_argument("--demos", required=True, help="the demonstrations .npz the members were trained on")
    ap.add_argument("--demos-per-mode", type=int, default=0, help="the members' --demos-per-mode (0: all)")
    ap.add_argument("--seed", type=int, default=0, help="the seed that drew the members' demonstrations")
    ap.add_argument("--eval-seed", type=int, default=0, help="the evaluation's seed (pomil evaluate --seed)")
    ap.add_argument("--episodes-per-code", type=int, default=50)
    args = ap.parse_args(argv)
    try:
        if args.episodes_per_code < 1:
            raise PomilError(f"--episodes-per-code: expected a positive number, got {args.episodes_per_code}")
        members = [TrainedPolicy.load(p if str(p).endswith(".pt") else f"{p}/checkpoint.pt")
                   for p in args.checkpoints]
        if any(not isinstance(m.policy, GaussianPolicy) for m in members):
            raise PomilError("every member must be a Gaussian policy (not a diffusion policy)")
        first = members[0]
        for path, m in zip(args.checkpoints, members, strict=True):
            if (m.env.get("id"), m.num_codes, m.obs_dim, m.act_dim) != (first.env.get("id"), first.num_codes,
                                                                          first.obs_dim, first.act_dim):
                raise PomilError(f"{path}: its environment, codes or dimensions differ from "
                                 f"{args.checkpoints[0]}'s")
        demos, env_id, env_kwargs = load_training_demos(args.demos, per_mode_episodes=args.demos_per_mode,
                                                        seed=args.seed)
        if "tasks" not in demos.metadata:
            raise PomilError(f"{args.demos}: metadata has no tasks to score the ensemble on")
        expert = demos.padded("cpu")
        expert = replace(expert, actions=executed_actions_fn(env_id, env_kwargs)(expert.actions))
        prev = shift_actions(expert.actions)
        k = max(first.num_codes, 1)
        codes = (align([most_likely_codes(m.policy, expert, prev).numpy() for m in members], k) if first.num_codes > 1
                 else [list(range(k))] * len(members))
        scores = evaluate_tasks(Ensemble(members, codes), reference_of(demos.metadata), args.episodes_per_code,
                                seed=args.eval_seed)
    except PomilError as err:
        print(f"clone_ensemble: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps({**scores, "members": args.checkpoints, "member_codes": codes}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
