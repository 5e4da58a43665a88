"""Worker processes for the benchmarks' independent runs (seeds, cases, grid points).

The machine's cores run separate records side by side; every record still runs all its
estimators in one process, one after the other, so their per-step times stay comparable.
``pool(jobs)`` forks its workers (Linux): they inherit the estimators the parent has built and
numba-compiled, so no worker compiles again (stage 2's kernels are generated at run time and
not cached on disk, ≈ 20 s per process). ``jobs = 1`` runs everything in this process.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
from typing import Any, Callable

__all__ = ["pool", "default_jobs"]


def default_jobs() -> int:
    """The number of cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class _InProcess(concurrent.futures.Executor):
    """An executor that runs each call at submit, in this process (``jobs = 1``)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any
               ) -> concurrent.futures.Future:
        fut: concurrent.futures.Future = concurrent.futures.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller by result()
            fut.set_exception(exc)
        return fut


def pool(jobs: int) -> concurrent.futures.Executor:
    """``jobs`` forked worker processes, or this process alone when ``jobs <= 1``."""
    if jobs <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return _InProcess()
    return concurrent.futures.ProcessPoolExecutor(
        max_workers=jobs, mp_context=multiprocessing.get_context("fork"))
