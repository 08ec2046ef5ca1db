"""``--resume`` after a kill -9 gives the run uninterrupted, bit for bit, for every learner.

Each case runs the command line in subprocesses on one torch thread (``tests/kill_at.py``): once straight
through, and once killed with SIGKILL at two points, each followed by ``--resume``: right after a
checkpoint inside the policy's warm-up iterations (adversarial learners), and as a later iteration's row
is logged, before its checkpoint (the run then goes on from the one before).  Every tensor and number of
the final checkpoints and every logged figure but the wall-clock ones must be equal.  The defaults run at
small sizes: the warm start, the policy's updates after its warm-up, the gradient penalty and the BC term
are all on.  The wider sweep (belief encoders, shared beliefs, continuous codes, the paper's text,
bfloat16, the number of codes chosen from the data, two threads) is marked slow.
"""

import csv
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pomil.demos import record_circles_demos
from pomil.envs.circles import make_spec

ROOT = Path(__file__).resolve().parents[1]
KILL_AT = ROOT / "tests" / "kill_at.py"
HOPPER = str(ROOT / "data" / "hopper-paper.npz")
SMALL = ["--num-envs", "8", "--hidden-size", "16", "--warm-start-iterations", "10", "--posterior-init-iterations", "5",
         "--policy-warmup-iterations", "2", "--eval-every", "0", "--checkpoint-every", "1", "--iterations", "5"]


@pytest.fixture(scope="module")
def circles40(tmp_path_factory):
    path = tmp_path_factory.mktemp("resume") / "circles40.npz"
    record_circles_demos(make_spec(), 40, seed=0).save(path)
    return str(path)


def _start(point: str, at: int, args: list[str], threads: int) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    return subprocess.Popen([sys.executable, str(KILL_AT), point, str(at), *args, "--no-progress"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _finish(proc: subprocess.Popen, point: str, at: int) -> None:
    _, err = proc.communicate(timeout=600)
    expected = 0 if point == "never" else -signal.SIGKILL
    assert proc.returncode == expected, (point, at, proc.returncode, err[-2000:])


def _pomil(point: str, at: int, args: list[str], threads: int) -> None:
    _finish(_start(point, at, args, threads), point, at)


def _flat(x, prefix: str = "") -> dict:
    if isinstance(x, dict):
        return {k: v for key, val in x.items() for k, v in _flat(val, f"{prefix}/{key}").items()}
    if isinstance(x, (list, tuple)):
        return {k: v for i, val in enumerate(x) for k, v in _flat(val, f"{prefix}/{i}").items()}
    return {prefix: x}


def _same(a, b) -> bool:
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    return a == b


def _logged(run: Path) -> list[dict[str, str]]:
    with open(run / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if not k.startswith("time/")} for row in csv.DictReader(f)]


def check_resume_is_exact(tmp_path: Path, args: list[str], kills: list[tuple[str, int]], threads: int = 1) -> dict:
    """The run of ``args`` straight through against the same run killed at each of ``kills`` and resumed;
    returns the final checkpoint."""
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    args = [*args, "--log-every", "1"]  # every iteration's row logged: a "log" kill point is always reached
    uninterrupted = _start("never", 0, [*args, "--out", str(straight)], threads)  # beside the others: one core each
    for i, (point, at) in enumerate(kills):
        _pomil(point, at, [*args, "--out", str(resumed)] + (["--resume"] if i else []), threads)
    _pomil("never", 0, [*args, "--out", str(resumed), "--resume"], threads)
    _finish(uninterrupted, "never", 0)
    a = torch.load(straight / "checkpoint.pt", weights_only=True)
    b = torch.load(resumed / "checkpoint.pt", weights_only=True)
    assert a["iteration"] == b["iteration"]
    a["config"].pop("out"), b["config"].pop("out")
    fa, fb = _flat(a), _flat(b)
    assert sorted(fa) == sorted(fb)
    differ = [k for k in fa if not _same(fa[k], fb[k])]
    assert not differ, f"{len(differ)} of {len(fa)} entries differ after the resume, e.g. {differ[:5]}"
    assert _logged(straight) == _logged(resumed)
    return a


ADVERSARIAL_KILLS = [("checkpoint", 1), ("log", 4)]  # inside the policy's 2 warm-up iterations, then after them


@pytest.mark.parametrize("learner", ["infogail-pomdp", pytest.param("infogail", marks=pytest.mark.slow),
                                     pytest.param("gail", marks=pytest.mark.slow)])  # one loop: the default suite
def test_adversarial_resume_on_circles_is_exact(learner, circles40, tmp_path):
    check_resume_is_exact(tmp_path, ["train", learner, "--demos", circles40, *SMALL], ADVERSARIAL_KILLS)


def test_adversarial_resume_on_hopper_is_exact_with_evaluation(tmp_path):
    """Hopper's episodes start from noisy states drawn by the simulator's generators: a resume must
    carry them on, not start them over.  Evaluation during training is on."""
    small = list(SMALL)
    small[small.index("--eval-every") + 1] = "2"
    small[small.index("--iterations") + 1] = "4"
    ckpt = check_resume_is_exact(tmp_path, ["train", "infogail-pomdp", "--demos", HOPPER, *small, "--num-envs", "4",
                                            "--critic-batch", "4", "--minibatches", "2", "--eval-episodes", "1"],
                                 [("checkpoint", 1), ("log", 3)])  # as ADVERSARIAL_KILLS, in 4 iterations
    assert {"env", "selection"} <= set(ckpt["carried"])  # the nearest policy so far, handed over by default


def test_bc_resume_is_exact(circles40, tmp_path):
    check_resume_is_exact(tmp_path, ["train", "bc", "--demos", circles40, "--policy", "gru", "--hidden-size", "32",
                                     "--iterations", "8", "--checkpoint-every", "2"], [("checkpoint", 2), ("log", 5)])


def test_expert_resume_is_exact(tmp_path):
    check_resume_is_exact(tmp_path, ["experts", "hopper", "--num-envs", "4", "--hidden-size", "16", "--iterations",
                                     "3", "--ppo-epochs", "2", "--minibatches", "4", "--checkpoint-every", "1"],
                          [("checkpoint", 1), ("log", 2)])


SWEEP = {
    "belief-shared": ["--belief", "shared"],
    "belief-policy": ["--belief", "policy"],
    "lstm": ["--belief-encoder", "lstm"],
    "attention": ["--belief-encoder", "attention", "--attention-context", "8"],
    "continuous-codes": ["--code-kind", "continuous", "--code-dim", "2"],
    "paper-text": ["--preset", "paper-text"],
    "bfloat16": ["--precision", "bfloat16"],
    "num-codes-auto": ["--num-codes", "auto", "--num-codes-max", "3", "--num-codes-search-iterations", "20"],
}


@pytest.mark.slow
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("variant", list(SWEEP))
def test_adversarial_resume_is_exact_across_settings(variant, threads, circles40, tmp_path):
    check_resume_is_exact(tmp_path, ["train", "infogail-pomdp", "--demos", circles40, *SMALL, *SWEEP[variant]],
                          [("checkpoint", 1), ("checkpoint", 3), ("log", 5)], threads)
