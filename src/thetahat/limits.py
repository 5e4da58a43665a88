"""Limits that keep bad or hostile input from hanging the program or exhausting memory.

Every string a user gives thetahat (model files, :func:`~thetahat.model.parse.parse_perturbation`,
string entries of :func:`~thetahat.structure.scb_symbolic.scb_symbolic`) is parsed, never
evaluated, and checked against the size limits below; symbolic work that can run for ever on a
small input (SymPy ``solve`` on ``(θ + y)**1000``) runs under a time budget; large allocations
are estimated before they are made. Each limit raises a typed error that names it:
:class:`~thetahat.errors.InputLimitError`, :class:`~thetahat.errors.SymbolicTimeoutError`,
:class:`~thetahat.errors.ResourceLimitError`.

The limits are module constants; a program that needs more may raise them (for example
``thetahat.limits.SYMBOLIC_TIME_BUDGET = 120.0``) before the call.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import threading
from collections.abc import Callable
from typing import Any, TypeVar

from .errors import ResourceLimitError, SymbolicTimeoutError, UnsupportedError

__all__ = ["MAX_EXPRESSION_CHARS", "MAX_EXPRESSION_DEPTH", "MAX_EXPONENT", "MAX_POWER_NESTING",
           "MAX_SYMBOLIC_DIM", "MAX_FILE_NESTING", "SYMBOLIC_TIME_BUDGET", "MEMORY_FRACTION",
           "MAX_MODEL_FILE_BYTES", "MAX_MATRIX_ENTRY", "MAX_DATA_FILE_BYTES",
           "MAX_DATA_SAMPLES", "MAX_DECOMPRESSED_BYTES", "MAX_SIGNAL_MAGNITUDE",
           "MIN_SIGNAL_MAGNITUDE",
           "run_with_time_budget", "check_allocation", "available_memory"]

T = TypeVar("T")

#: Longest accepted formula, in characters: model files hold short formulas.
MAX_EXPRESSION_CHARS: int = 10_000
#: Deepest accepted nesting of a formula's syntax tree (parentheses, calls, operators): far
#: above hand-written formulas (the LuGre g has depth 9), far below Python's recursion limit.
MAX_EXPRESSION_DEPTH: int = 100
#: Largest |exponent| of a numeric power in a formula (``y**1000`` is refused): beyond it
#: symbolic differentiation and solving blow up and float64 overflows anyway.
MAX_EXPONENT: float = 100.0
#: Deepest accepted tower of powers (``y**y**y`` has nesting 2): towers make SymPy's
#: derivatives and solution forms grow without bound.
MAX_POWER_NESTING: int = 3
#: Largest matrix dimension accepted by the exact (symbolic) SCB.
MAX_SYMBOLIC_DIM: int = 30
#: Deepest accepted nesting of a model file's tables and lists (TOML/JSON): a model file
#: needs 3 (a table holding a matrix); deep nesting is refused before it reaches recursion.
MAX_FILE_NESTING: int = 32
#: Seconds granted to one symbolic solve (θ* from g): SymPy's ``solve`` has no cost bound.
SYMBOLIC_TIME_BUDGET: float = 30.0
#: Fraction of the available memory one allocation may take.
MEMORY_FRACTION: float = 0.5
#: Largest |entry| of a system matrix (A, B, C, E): the structure and gain computations form
#: products of up to three entries (C A E, Rosenbrock pencils), which overflow float64
#: (1.8e308) beyond 1e100; rescale the units (time, states) instead.
MAX_MATRIX_ENTRY: float = 1e100
#: Largest |value| of a sample of t, u or y, and of a step length dt, that an estimator takes:
#: the estimators square their signals (covariances, ‖y‖², g's polynomials, exp(A dt)), and
#: the square of 1e150 is 1e300, a normal float64 (the largest is 1.8e308) with little room
#: to spare; data beyond it are in the wrong unit: rescale them.
MAX_SIGNAL_MAGNITUDE: float = 1e150
#: Smallest |value| of a nonzero sample of u or y, and of a step length dt: its square, 1e-300,
#: is still a normal float64 (the smallest is 2.2e-308); a signal below it computes in
#: subnormal numbers, or as 0, and a fit of it is singular: rescale the unit.
MIN_SIGNAL_MAGNITUDE: float = 1e-150
#: Largest model file read, in bytes (checked before reading): model files hold a few small
#: matrices and short formulas (the examples have under 4 kB).
MAX_MODEL_FILE_BYTES: int = 1 << 20
#: Largest data file (CSV or Parquet) read, in bytes (checked before reading): a 10⁷-sample
#: record of t, u, y is about 0.6 GB of CSV text; split bigger logs or raise the limit.
MAX_DATA_FILE_BYTES: int = 4 << 30
#: Most samples of one record a reader takes (a Parquet file's row count is checked against it
#: from the metadata, a MAT variable from its declared dimensions, before reading): 10⁸
#: samples of t, u, y are 2.4 GB of float64, ten times the longest record the soak benchmark
#: streams.
MAX_DATA_SAMPLES: int = 100_000_000
#: Largest size a compressed element of a MAT file may declare once decompressed (checked
#: before decompressing; decompression stops there): a 10⁸-sample float64 signal is 0.8 GB.
MAX_DECOMPRESSED_BYTES: int = 1 << 30


def _child(conn: Any, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
    try:
        result = ("ok", fn(*args))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which re-raises
        result = ("error", exc)
    try:
        conn.send_bytes(pickle.dumps(result))
    except Exception as exc:  # noqa: BLE001 - an unpicklable result: report its type
        conn.send_bytes(pickle.dumps(("error", UnsupportedError(
            f"the result of the symbolic computation cannot be sent back ({exc})."))))
    finally:
        conn.close()


def _in_subprocess(fn: Callable[..., T], args: tuple[Any, ...], seconds: float,
                   what: str) -> T:
    ctx = multiprocessing.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, fn, args), daemon=True)
    proc.start()
    send.close()
    try:
        if not recv.poll(seconds):
            raise SymbolicTimeoutError(
                f"{what} did not finish within its time budget of {seconds:g} s (SymPy has "
                f"no cost bound on such work). Give the result explicitly instead, or raise "
                f"thetahat.limits.SYMBOLIC_TIME_BUDGET.", seconds=seconds)
        try:
            status, value = pickle.loads(recv.recv_bytes())
        except EOFError:
            raise SymbolicTimeoutError(f"{what} stopped without a result (the worker process "
                                       f"died, e.g. out of memory).", seconds=seconds) from None
    finally:
        recv.close()
        if proc.is_alive():
            proc.kill()
        proc.join()
    if status == "error":
        raise value
    return value


class _Alarm(Exception):
    pass


def _in_process(fn: Callable[..., T], args: tuple[Any, ...], seconds: float, what: str) -> T:
    def on_alarm(signum: int, frame: Any) -> None:
        raise _Alarm

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        return fn(*args)
    except _Alarm:
        raise SymbolicTimeoutError(
            f"{what} did not finish within its time budget of {seconds:g} s. Give the result "
            f"explicitly instead, or raise thetahat.limits.SYMBOLIC_TIME_BUDGET.",
            seconds=seconds) from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def run_with_time_budget(fn: Callable[..., T], *args: Any, seconds: float | None = None,
                         what: str = "the symbolic computation") -> T:
    """Call ``fn(*args)`` and return its result, or raise when it takes too long.

    On platforms with ``fork`` (Linux, macOS) the call runs in a forked worker process that is
    killed when the budget runs out, which stops even work stuck inside C code (big-integer
    arithmetic); the result comes back pickled, so ``fn`` must return picklable objects
    (SymPy expressions are). Inside a daemonic worker (which may not fork), the main thread
    uses a ``SIGALRM`` timer instead (it interrupts Python code only), and other threads run
    ``fn`` without a budget.

    Parameters
    ----------
    fn : callable
        A module-level function (it runs in a forked copy of this process).
    *args
        Its arguments.
    seconds : float, optional
        The budget; default :data:`SYMBOLIC_TIME_BUDGET`.
    what : str
        Names the work in the error message.

    Returns
    -------
    The value of ``fn(*args)``.

    Raises
    ------
    SymbolicTimeoutError
        The budget ran out; ``fn``'s own exceptions are re-raised unchanged.

    Examples
    --------
    >>> import sympy as sp
    >>> from thetahat.limits import run_with_time_budget
    >>> y = sp.Symbol("y")
    >>> run_with_time_budget(sp.solve, y**2 - 4, y, seconds=20.0)
    [-2, 2]
    """
    budget = SYMBOLIC_TIME_BUDGET if seconds is None else float(seconds)
    can_fork = ("fork" in multiprocessing.get_all_start_methods()
                and not multiprocessing.current_process().daemon)
    if can_fork:
        return _in_subprocess(fn, args, budget, what)
    if hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread():
        return _in_process(fn, args, budget, what)
    return fn(*args)


def available_memory() -> int:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``; else the
    physical memory), or 0 when unknown.

    Returns
    -------
    int
        Available memory in bytes; 0 when it cannot be determined (then
        :func:`check_allocation` sets no limit).
    """
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def check_allocation(nbytes: float, what: str, *, fix: str = "") -> None:
    """Raise :class:`~thetahat.errors.ResourceLimitError` before allocating ``nbytes`` when
    that exceeds :data:`MEMORY_FRACTION` of the available memory.

    Parameters
    ----------
    nbytes : float
        Estimated size of the allocation.
    what : str
        What is being allocated (for the message).
    fix : str
        What the user can do (for the message), e.g. "shorten --t-end".

    Examples
    --------
    >>> from thetahat.limits import check_allocation
    >>> check_allocation(8 * 1000, "a small array")          # fine: returns None
    >>> check_allocation(8e15, "the trajectory", fix="shorten t_end")
    Traceback (most recent call last):
    ...
    thetahat.errors.ResourceLimitError: the trajectory needs 8e+06 GB of memory ...
    """
    avail = available_memory()
    limit = MEMORY_FRACTION * avail if avail else float("inf")
    if nbytes > limit or nbytes > 2 ** 62:
        raise ResourceLimitError(
            f"{what} needs {nbytes / 1e9:.3g} GB of memory but only {limit / 1e9:.3g} GB "
            f"({MEMORY_FRACTION:.0%} of the available memory) may be used"
            + (f"; {fix}." if fix else "."),
            required=int(min(nbytes, 2 ** 62)), available=int(min(limit, 2 ** 62)))
