"""Many runs at once on Ray (optional extra: ``pip install -e '.[ray]'``).

:func:`run_jobs` calls a module-level function once per job, either one after
another in this process or as Ray tasks: on a local Ray started in-process,
or on an existing cluster given its address.  Ray does the scheduling (each
task asks for ``cpus_per_job`` CPUs, so a 2-core machine runs two 1-CPU
runs at a time) and the fault handling (a task whose worker dies is retried
once; an exception inside a run is not retried but reported).  On a cluster
the paths a job reads and writes must be on a file system every node sees.
"""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Sequence

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


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[-1] if text else ''}"[:300]


def run_jobs(fn: Callable[..., Any], jobs: Sequence[tuple], names: Sequence[str], ray: bool = False,
             address: str | None = None, cpus_per_job: float = 1.0, capture_errors: bool = True,
             on_done: Callable[[JobResult, int, int], None] | None = None) -> list[JobResult]:
    """``fn(*job)`` for every job; results in job order.

    ``ray``: run the jobs as Ray tasks (``address``: an existing cluster;
    None starts a local Ray in this process and stops it afterwards).
    ``capture_errors``: a failed job becomes a JobResult with ``error`` set
    (else the first error is raised).  ``on_done(result, finished, total)``
    is called as each job ends, in the order they end.
    """
    total = len(jobs)
    results: list[JobResult | None] = [None] * total

    def finish(i: int, result: JobResult) -> None:
        results[i] = result
        if on_done is not None:
            on_done(result, sum(r is not None for r in results), total)

    if not ray:
        for i, (job, name) in enumerate(zip(jobs, names)):
            try:
                value, wall = _call(fn, job, None)
                finish(i, JobResult(name, value, wall_s=wall))
            except Exception as err:
                if not capture_errors:
                    raise
                finish(i, JobResult(name, error=_one_line(err), details=traceback.format_exc()))
        return results  # type: ignore[return-value]

    try:
        import ray as ray_lib
    except ImportError:
        raise PomilError("running on Ray is an optional extra: pip install -e '.[ray]' (or pip install ray)") from None
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
    pending = {task.remote(fn, tuple(job), threads): i for i, job in enumerate(jobs)}
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
    return results  # type: ignore[return-value]
