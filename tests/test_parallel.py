"""run_jobs without Ray: jobs in spawned worker processes on one torch thread each, costliest first."""

import os

import pytest

from pomil import parallel
from pomil.errors import PomilError
from pomil.parallel import run_jobs, submission_order


def _probe(i: int) -> tuple[int, int, int]:
    import torch

    return i, os.getpid(), torch.get_num_threads()


def _fail_on_two(i: int) -> int:
    if i == 2:
        raise PomilError(f"job {i}: bad input")
    return i


def test_submission_order_is_costliest_first_and_ties_keep_their_order():
    assert submission_order([0.05, 1.0, 0.4, 1.0, 0.15]) == [1, 3, 2, 4, 0]
    assert submission_order([]) == []
    with pytest.raises(ValueError, match="2 values for 3 jobs"):
        run_jobs(_probe, [(0,), (1,), (2,)], ["a", "b", "c"], costs=[1.0, 2.0])


def test_local_workers_run_the_jobs_in_other_processes_on_one_thread_costliest_first(monkeypatch):
    """The pool takes the jobs in the order they are submitted (its queue is first in, first out), so the
    scheduling decision is that order: checked as submitted, not by when each process happened to start."""
    submitted = []

    class RecordingPool(parallel.ProcessPoolExecutor):
        def submit(self, fn, /, *args, **kwargs):
            submitted.append(args[1][0])  # _call(fn, job, threads): the job's index
            return super().submit(fn, *args, **kwargs)

    monkeypatch.setattr(parallel, "ProcessPoolExecutor", RecordingPool)
    costs = [0.05, 1.0, 0.4, 0.55, 0.15]
    seen = []
    results = run_jobs(_probe, [(i,) for i in range(5)], [f"job {i}" for i in range(5)], workers=2, costs=costs,
                       on_done=lambda r, n, total: seen.append((r.name, n, total)))
    assert submitted == [1, 3, 2, 4, 0]  # the two costliest first, the cheapest last
    assert [r.value[0] for r in results] == [0, 1, 2, 3, 4]  # job order, whatever order they ran in
    assert [r.name for r in results] == [f"job {i}" for i in range(5)] and all(r.ok for r in results)
    pids = {r.value[1] for r in results}
    assert os.getpid() not in pids and len(pids) <= 2
    assert {r.value[2] for r in results} == {1}  # one torch thread per worker (cpus_per_job 1)
    assert all(r.wall_s >= 0 for r in results)
    assert sorted(n for _, n, _ in seen) == [1, 2, 3, 4, 5] and {t for _, _, t in seen} == {5}


def test_local_workers_report_a_failed_job_or_raise_its_error():
    results = run_jobs(_fail_on_two, [(i,) for i in range(4)], list("abcd"), workers=2)
    assert [r.ok for r in results] == [True, True, False, True]
    assert results[2].error == "PomilError: job 2: bad input" and "Traceback" in results[2].details
    assert [r.value for r in results if r.ok] == [0, 1, 3]
    with pytest.raises(PomilError, match="job 2: bad input"):
        run_jobs(_fail_on_two, [(i,) for i in range(4)], list("abcd"), workers=2, capture_errors=False)


def _die(i: int) -> int:
    if i == 1:
        os._exit(3)  # a worker killed (out of memory, a signal): no exception to send back
    return i


def test_a_worker_that_dies_stops_the_jobs_with_one_line():
    with pytest.raises(PomilError, match=r"^a worker process died .*unfinished: .*\bb\b"):
        run_jobs(_die, [(i,) for i in range(3)], list("abc"), workers=2)


def test_one_worker_runs_in_this_process():
    results = run_jobs(_probe, [(0,), (1,)], ["a", "b"], workers=1)
    assert [r.value[1] for r in results] == [os.getpid()] * 2
