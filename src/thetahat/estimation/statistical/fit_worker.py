"""Stage 2's MAP fits off the sample path: a worker process that never shares a lock with ``step``.

A streaming :meth:`~thetahat.estimation.statistical.guarded.GuardedEstimator.step` hands each scheduled
fit to an executor and picks the result up at the first ``step`` after it has finished. The
default executor is one worker *process* (``spawn`` start, shared by every stream of the
Python process, started by the first stream), not a thread: a fit's Python and numpy parts
(the Gauss–Newton loop, the noise estimate, and, on a cold worker, numba's compilation of the
fit's kernels, seconds during which a thread would hold the GIL) then never hold a lock that
``step`` needs, with or without numba. What ``step`` itself pays for a fit is copying the
window's samples at submission (O(window), a memory copy) and reading a finished
:class:`TimedFit`; the pickling and the pipe run on the executor's helper threads in short
GIL-holding spans. The worker starts and compiles at the caller's priority, then runs the fits at
the lowest (:data:`WORKER_NICE`), so that when a fit competes with the sample path for a core
the scheduler favours the sample path.

The worker rebuilds the :class:`~thetahat.estimation.statistical.map_fit.FitSchedule` from
:func:`fit_spec` (everything but its clock ``times``, which the worker does not need) once per
model and keeps it, with its compiled kernels; :func:`warm_up` compiles them before the first
fit is due. Any :class:`concurrent.futures.Executor` can replace the default (a thread pool,
a Dask client's executor); the callables submitted are the module-level :func:`run_fit` and
:func:`warm_up`, so a process-based executor can pickle them.

The ``spawn`` start method imports the caller's ``__main__`` module again in the worker, as
for every use of :mod:`multiprocessing`: a script that streams with fits must keep its
top-level work under ``if __name__ == "__main__":``.

What it may import: the standard library's process machinery, and, in this room,
``common``, ``map_fit`` and ``window`` (the fits it runs).
"""

from __future__ import annotations

import atexit
import concurrent.futures
import dataclasses
import multiprocessing
import multiprocessing.connection
import os
import pickle
import threading
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .common import theta_box
from .map_fit import FitResult, FitSchedule, fit_map, fit_record
from .window import fit_window

__all__ = ["TimedFit", "fit_spec", "run_fit", "warm_up", "default_executor",
           "discard_default_executor", "WORKER_NICE"]

FloatArray = NDArray[np.float64]

#: Niceness added to the worker process (Unix; 19, the lowest priority): the sample path wins
#: a contended core. Measured (benchmarks/bench_stream.py, a busy worker, 2 loaded cores):
#: steps over 1 ms 85–98 at +0, 36–50 at +10, 14–21 at +19 (17 and 6 without fits).
WORKER_NICE = 19

#: FitSchedules rebuilt in this (worker) process, by their spec.
_SCHEDULES: dict[bytes, FitSchedule] = {}
#: (is this the default executor's worker process, has it lowered its priority yet)
_WORKER = [False, False]

#: The shared default executor of this process (one spawned worker process).
_EXECUTOR: concurrent.futures.ProcessPoolExecutor | None = None


@dataclass(frozen=True, slots=True, eq=False)
class TimedFit:
    """A fit computed by :func:`run_fit`, with the time it took in the worker.

    Attributes
    ----------
    fit : FitResult
        With ``k0``, ``k1`` as absolute sample indices of the stream.
    seconds : float
        Wall time of the fit in the worker (s).
    cpu_seconds : float
        CPU time of the worker's thread during the fit (s).
    """

    fit: FitResult
    seconds: float
    cpu_seconds: float

    def __repr__(self) -> str:
        return f"TimedFit({self.fit!r}, seconds={self.seconds:.4g})"


def fit_spec(schedule: FitSchedule) -> bytes:
    """The part of a schedule the worker needs (all fields but ``times``), pickled.

    Parameters
    ----------
    schedule : FitSchedule

    Returns
    -------
    bytes
        The key under which the worker keeps the rebuilt schedule and its compiled kernels.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.map_fit import FitSchedule
    >>> from thetahat.estimation.statistical.fit_worker import fit_spec
    >>> spec = fit_spec(FitSchedule(system=lugre.system(), compiled=False))
    >>> isinstance(spec, bytes)
    True
    """
    fields = {f.name: getattr(schedule, f.name) for f in dataclasses.fields(schedule)
              if f.name != "times"}
    return pickle.dumps(fields, protocol=pickle.HIGHEST_PROTOCOL)


def _schedule(spec: bytes) -> FitSchedule:
    sched = _SCHEDULES.get(spec)
    if sched is None:
        sched = _SCHEDULES[spec] = FitSchedule(**pickle.loads(spec))  # noqa: S301 (our bytes)
    return sched


def run_fit(spec: bytes, t: FloatArray, U: FloatArray, Y: FloatArray, k1: int,
            previous: FitResult | None, prior0: tuple[FloatArray, FloatArray], elapsed: float,
            base: int, by_samples: bool = False,
            anchor: tuple[FloatArray, FloatArray, FloatArray] | None = None) -> TimedFit:
    """The fit of a stream's retained window (runs in the worker).

    :func:`~thetahat.estimation.statistical.map_fit.fit_record` (all the data so far; output error, else with
    process noise when that is consistent) for a schedule by sample counts, as the offline
    run fits; with an ``anchor``, :func:`~thetahat.estimation.statistical.window.fit_window`
    (the samples retained, their first summarised by the anchor's posterior: a stream with a
    ``window``); :meth:`FitSchedule.fit` (blocks with arrival cost) for one with times.

    Parameters
    ----------
    spec : bytes
        From :func:`fit_spec`.
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        The samples retained by the stream; sample i is the stream's sample ``base + i``.
    k1 : int
        The fit ends at window sample k1 − 1.
    previous : FitResult or None
        The previous fit, with indices relative to the window.
    prior0 : (ndarray, ndarray)
        The initial prior (q̄, Π⁻¹) of :meth:`FitSchedule.initial_prior`.
    elapsed : float
        Time since the start of the stream (s).
    base : int
        Absolute index of the window's first sample.
    by_samples : bool
        The stream fits on sample counts (its schedule has no ``times``; the worker's
        rebuilt schedule does not carry them).
    anchor : tuple of ndarray, optional
        (s, P, σ): the posterior N(s, P) of col(x, θ) at the retained first sample and the
        noise level, the arrival cost of a window fit.

    Returns
    -------
    TimedFit
        The fit with absolute indices k0 + base, k1 + base.
    """
    sched = _schedule(spec)
    if _WORKER[0] and not _WORKER[1]:      # never the caller's process (a thread executor)
        _WORKER[1] = True
        _lower_priority()
    w0, c0 = time.perf_counter(), time.thread_time()
    if anchor is not None:
        fit = fit_window(sched, t, U, Y, k0=0, k1=k1, s0=anchor[0], P0=anchor[1],
                         noise_std=anchor[2])
    elif by_samples:
        fit = fit_record(sched, t, U, Y, k1, previous, prior0)
    else:
        fit = sched.fit(t, U, Y, k1, previous, prior0, elapsed=elapsed)
    w1, c1 = time.perf_counter(), time.thread_time()
    fit = dataclasses.replace(fit, k0=fit.k0 + base, k1=fit.k1 + base)
    return TimedFit(fit=fit, seconds=w1 - w0, cpu_seconds=c1 - c0)


def warm_up(spec: bytes) -> float:
    """Compile the fit kernels of ``spec``'s model in this process (a 3-sample fit).

    Called on the worker when a stream starts, so that the first scheduled fit does not wait
    for numba's compilation. The arrays have the types of a real fit (C-contiguous, writable
    float64), so the specialisation compiled here is the one :func:`run_fit` uses.

    Parameters
    ----------
    spec : bytes
        From :func:`fit_spec`.

    Returns
    -------
    float
        Seconds spent (compilation included on a cold worker).
    """
    t0 = time.perf_counter()
    sched = _schedule(spec)
    sys_ = sched.system
    n, m, r, p = sys_.n, sys_.m, sys_.r, sys_.p
    q = np.zeros(n + p)
    q[n:] = theta_box(sys_)[0]
    t = np.array([0.0, 1e-3, 2e-3])
    fit_map(sys_, t, np.zeros((3, m)), np.zeros((3, r)), k0=0, k1=3, q_start=q,
            q_prior=q.copy(), prior_info=np.eye(n + p), noise_std=np.ones(r), max_iter=1,
            hold=sched.hold, substeps=1, h_rho=sched.h_rho, compiled=sched.compiled)
    return time.perf_counter() - t0


def _mark_worker() -> None:
    """Initializer of the default executor's worker process: remember it, and end the process
    when its parent ends, however abruptly (the pool's own shutdown needs a live parent)."""
    _WORKER[0] = True
    parent = multiprocessing.parent_process()
    if parent is not None:
        threading.Thread(target=_exit_with, args=(parent.sentinel,), daemon=True,
                         name="thetahat-fit-parent-watch").start()


def _exit_with(sentinel: int) -> None:
    multiprocessing.connection.wait([sentinel])
    os._exit(0)


def _lower_priority() -> None:
    """Lower this process's priority by :data:`WORKER_NICE` where the OS supports it (the
    first fit does it: the start and the compilation of a cold worker keep the caller's
    priority, so that the first fits are not delayed by a loaded machine)."""
    if hasattr(os, "nice"):
        try:
            os.nice(WORKER_NICE)
        except OSError:                         # not permitted: run at the caller's priority
            pass


def default_executor() -> concurrent.futures.Executor:
    """The shared fit executor of this process: one ``spawn``-started worker process.

    Created on first use (by the first stream that fits).

    Returns
    -------
    concurrent.futures.ProcessPoolExecutor
    """
    global _EXECUTOR
    if _EXECUTOR is None:
        _EXECUTOR = concurrent.futures.ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn"),
            initializer=_mark_worker)
        atexit.register(discard_default_executor, _EXECUTOR)
    return _EXECUTOR


def discard_default_executor(executor: concurrent.futures.Executor) -> None:
    """Forget ``executor`` if it is the shared default (after it broke: its process died, or
    at exit, while the interpreter can still collect it), so that the next
    :func:`default_executor` starts a new worker.

    Parameters
    ----------
    executor : concurrent.futures.Executor
    """
    global _EXECUTOR
    if executor is _EXECUTOR:
        _EXECUTOR = None
        executor.shutdown(wait=False, cancel_futures=True)
