import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Set before torch loads OpenMP: a test on two torch threads (the checkpoint hashes) beside the other worker
    # has three threads on two cores; OpenMP's threads then sleep at a barrier instead of spinning (same floats;
    # the hash test 71 s -> 32 s beside a busy core)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest  # noqa: E402
import torch  # noqa: E402

from pomil.demos import record_circles_demos  # noqa: E402
from pomil.envs.circles import make_spec  # noqa: E402

TORCH_THREADS = torch.get_num_threads()
"""Torch's own thread count in this process (one per core), which the recorded checkpoint hashes name."""
CORES = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
"""The cores this process may run on before a test worker is pinned to one of them."""

if os.environ.get("PYTEST_XDIST_WORKER"):
    # One thread per worker (scripts/test.sh runs one worker per core): two workers of two threads each on two
    # cores spend their time waiting on each other. The commands the tests start inherit it.
    torch.set_num_threads(1)
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
    if hasattr(os, "sched_setaffinity"):
        # and one core each, inherited by the processes they start: a reproduction then runs its jobs one after
        # another in the worker (pomil.parallel.usable_cpus) instead of spawning a process per core beside the
        # other worker, and the simulator steps its environments on one thread
        index = int(os.environ["PYTEST_XDIST_WORKER"].removeprefix("gw") or 0)
        os.sched_setaffinity(0, {CORES[index % len(CORES)]})


@pytest.fixture
def all_cores():
    """Every core for the test and the processes it starts (a test worker is pinned to one), the pin restored after."""
    pinned = os.sched_getaffinity(0) if CORES else None
    if CORES:
        os.sched_setaffinity(0, CORES)
    yield
    if CORES:
        os.sched_setaffinity(0, pinned)


@pytest.fixture
def torch_default_threads(all_cores):
    """Torch's own thread count (:data:`TORCH_THREADS`) for the test, the worker's restored after it; on every core,
    where OpenMP's waiting threads do not spin against each other."""
    before = torch.get_num_threads()
    torch.set_num_threads(TORCH_THREADS)
    yield TORCH_THREADS
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def spec():
    return make_spec()


@pytest.fixture(scope="session")
def demos(spec):
    return record_circles_demos(spec, 200, seed=0)


@pytest.fixture(scope="session")
def demos_path(demos, tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "circles.npz"
    demos.save(path)
    return path
