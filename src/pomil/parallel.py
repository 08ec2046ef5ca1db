"""Many runs at once: in local worker processes, or on Ray (optional extra: ``pip install 'pomil[ray]'``).

:func:`run_jobs` calls a module-level function once per job: one after
another in this process, in ``workers`` spawned processes on this machine
(each on one torch thread: on 2 cores two one-thread runs get through about
1.5x the work of one two-thread run), or as Ray tasks on a local Ray started
in-process or on an existing cluster given its address.  Ray does the
scheduling (each task asks for ``cpus_per_job`` CPUs, so a 2-core machine runs
two 1-CPU runs at a time) and the fault handling (a task whose worker dies is
retried once; an exception inside a run is not retried but reported).  Both
parallel ways start the costliest jobs first when their costs are given.  On a
cluster the paths a job reads and writes must be on a file system every node sees.
"""

from __future__ import annotations

import multiprocessing
import os
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from pomil.errors import PomilError


@dataclass(frozen=True)
class JobResult:
    """What one job gave: its value, or the error that stopped it (one line and the traceback)."""

    name: str
    value: Any = None
    error: str | None = None
    details: str = ""
    wall_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.error is None


def _call(fn: Callable[..., Any], args: tuple, threads: int | None) -> tuple[Any, float]:
    if threads:
        import torch

        torch.set_num_threads(threads)
    t0 = time.perf_counter()
    value = fn(*args)
    return value, time.perf_counter() - t0


def usable_cpus() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one, e.g. under taskset)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def require_ray() -> Any:
    """The ray module; a one-line PomilError naming the extra when it is not installed."""
    try:
        import ray
    except ImportError:
        raise PomilError("running on Ray is an optional extra: pip install 'pomil[ray]' (in a source checkout: "
                         "pip install -e '.[ray]')") from None
    return ray


def submission_order(costs: Sequence[float]) -> list[int]:
    """Job indices costliest first; equal costs keep their order."""
    return sorted(range(len(costs)), key=lambda i: -costs[i])


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[-1] if text else ''}"[:300]


def run_jobs(fn: Callable[..., Any], jobs: Sequence[tuple], names: Sequence[str], *, ray: bool = False,
             address: str | None = None, cpus_per_job: float = 1.0, capture_errors: bool = True,
             on_done: Callable[[JobResult, int, int], None] | None = None,
             costs: Sequence[float] | None = None, workers: int = 1) -> list[JobResult]:
    """``fn(*job)`` for every job; results in job order.

    ``ray``: run the jobs as Ray tasks (``address``: an existing cluster;
    None starts a local Ray in this process and stops it afterwards).
    ``capture_errors``: a failed job becomes a JobResult with ``error`` set
    (else the first error is raised).  ``on_done(result, finished, total)``
    is called as each job ends, in the order they end.  ``costs``: each job's
    rough relative wall time; on Ray the jobs are submitted costliest first
    (longest processing time first), so that the longest runs do not start
    last and end alone on an otherwise idle cluster.  Results do not depend on it.
    ``workers``: without Ray, how many jobs run at once, each in a spawned
    process on ``cpus_per_job`` torch threads; 1 runs them one after another in
    this process on torch's own thread count.
    """
    total = len(jobs)
    if costs is not None and len(costs) != total:
        raise ValueError(f"costs: {len(costs)} values for {total} jobs")
    results: list[JobResult | None] = [None] * total
    order = submission_order(costs) if costs is not None else range(total)

    def finish(i: int, result: JobResult) -> None:
        results[i] = result
        if on_done is not None:
            on_done(result, sum(r is not None for r in results), total)

    if ray:
        _run_ray(fn, jobs, names, address=address, cpus_per_job=cpus_per_job, capture_errors=capture_errors,
                 order=order, finish=finish)
    elif workers > 1 and total > 1:
        _run_local(fn, jobs, names, workers=min(workers, total), threads=max(1, int(cpus_per_job)),
                   capture_errors=capture_errors, order=order, finish=finish)
    else:
        for i, (job, name) in enumerate(zip(jobs, names, strict=True)):
            try:
                value, wall = _call(fn, job, None)
                finish(i, JobResult(name, value, wall_s=wall))
            except Exception as err:
                if not capture_errors:
                    raise
                finish(i, JobResult(name, error=_one_line(err), details=traceback.format_exc()))
    return results  # type: ignore[return-value]


def _run_ray(fn: Callable[..., Any], jobs: Sequence[tuple], names: Sequence[str], *, address: str | None,
             cpus_per_job: float, capture_errors: bool, order: Sequence[int],
             finish: Callable[[int, JobResult], None]) -> None:
    """The jobs as Ray tasks, submitted in ``order`` (see :func:`run_jobs`)."""
    ray_lib = require_ray()
    started = not ray_lib.is_initialized()
    if started:
        try:
            ray_lib.init(address=address or None, include_dashboard=False, logging_level="ERROR",
                         configure_logging=True, log_to_driver=True)
        except (ConnectionError, ValueError, RuntimeError) as err:
            where = f" at {address}" if address else ""
            raise PomilError(f"cannot start or reach Ray{where} ({_one_line(err)})") from None
    threads = max(1, int(cpus_per_job))
    task = ray_lib.remote(_call).options(num_cpus=cpus_per_job, max_retries=1, retry_exceptions=False)
    t_submit = time.perf_counter()
    pending = {task.remote(fn, tuple(jobs[i]), threads): i for i in order}
    try:
        while pending:
            done, _ = ray_lib.wait(list(pending), num_returns=1)
            i = pending.pop(done[0])
            try:
                value, wall = ray_lib.get(done[0])
                finish(i, JobResult(names[i], value, wall_s=wall))
            except ray_lib.exceptions.RayTaskError as err:
                cause = getattr(err, "cause", None) or err
                if not capture_errors:
                    raise cause from None
                finish(i, JobResult(names[i], error=_one_line(cause), details=str(err),
                                    wall_s=time.perf_counter() - t_submit))
            except ray_lib.exceptions.RayError as err:  # worker died twice, object lost, ...
                if not capture_errors:
                    raise PomilError(f"{names[i]}: {_one_line(err)}") from None
                finish(i, JobResult(names[i], error=_one_line(err), details=str(err)))
    finally:
        for ref in pending:
            ray_lib.cancel(ref, force=True)
        if started:
            ray_lib.shutdown()


def _run_local(fn: Callable[..., Any], jobs: Sequence[tuple], names: Sequence[str], *, workers: int, threads: int,
               capture_errors: bool, order: Sequence[int], finish: Callable[[int, JobResult], None]) -> None:
    """The jobs in ``workers`` spawned processes (spawn, not fork: torch's threads do not survive a fork), submitted
    in ``order``."""
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    t_submit = time.perf_counter()
    pending: dict[Future, int] = {pool.submit(_call, fn, tuple(jobs[i]), threads): i for i in order}
    clean = False
    try:
        while pending:
            done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
            for future in sorted(done, key=lambda f: pending[f]):
                i = pending.pop(future)
                try:
                    value, wall = future.result()
                    finish(i, JobResult(names[i], value, wall_s=wall))
                except BrokenProcessPool:  # a worker died (out of memory, killed): every unfinished job with it
                    unfinished = [names[j] for j in sorted([i, *pending.values()])]
                    raise PomilError(f"a worker process died (out of memory or killed?); {len(unfinished)} run(s) "
                                     f"unfinished: {', '.join(unfinished)}") from None
                except Exception as err:
                    if not capture_errors:
                        raise
                    finish(i, JobResult(names[i], error=_one_line(err), wall_s=time.perf_counter() - t_submit,
                                        details="".join(traceback.format_exception(err))))
        clean = True
    finally:
        if clean:
            pool.shutdown()
        else:  # an error or Ctrl-C: the runs still going are stopped, not waited for
            processes = list((getattr(pool, "_processes", None) or {}).values())  # no public handle before 3.14
            pool.shutdown(wait=False, cancel_futures=True)
            for process in processes:
                process.terminate()
