import os

import pytest
import torch

from pomil.demos import record_circles_demos
from pomil.envs.circles import make_spec

TORCH_THREADS = torch.get_num_threads()
"""Torch's own thread count in this process (one per core), which the recorded checkpoint hashes name."""

if os.environ.get("PYTEST_XDIST_WORKER"):
    # One thread per worker (scripts/test.sh runs one worker per core): two workers of two threads each on two
    # cores spend their time waiting on each other. The commands the tests start inherit it.
    torch.set_num_threads(1)
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"


@pytest.fixture
def torch_default_threads():
    """Torch's own thread count (:data:`TORCH_THREADS`) for the test, the worker's restored after it."""
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
