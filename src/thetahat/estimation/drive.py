"""The back ends the paper's observer runs on, and the one place that chooses among them.

A *back end* is a way of running the observer's step (3), (8) over a record. The observer
itself (NumPy) always runs; faster ones are registered here by the packages that provide them,
so this module never imports them:

* ``"c"`` — the C printed from the step's formulas, built by the system's C compiler
  (:mod:`thetahat.codegen.native`);
* ``"numba"`` — the numba kernel printed from the same formulas
  (:mod:`thetahat.estimation.observer.compiled`, the optional extra ``speed``).

Each registers a :class:`Backend` under the entry-point group :data:`ENTRY_POINT_GROUP`
(``pyproject.toml``), which :func:`backends` reads once; a third package can add its own the
same way. :func:`runner` picks the fastest one that can take an observer and a record — by
:attr:`Backend.rank`, falling back down the list when one declines (no compiler, numba
missing, a part it does not support) — and says in one :class:`~thetahat.errors.ThetahatWarning`
why a record it was asked to compile runs in Python. An observer built with ``compiled=None``
or ``True`` asks it on every ``run``
(:class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`); every back end
reads the observer's ``hold`` and ``progress`` and reports a failed step with the same
:class:`~thetahat.estimation.status.Status`.

What it may import: the package's errors only (it is the bottom of the estimation layers).
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

import numpy as np

from ..errors import ThetahatWarning

__all__ = ["Backend", "COMPILE_MIN_SAMPLES", "ENTRY_POINT_GROUP", "backends", "register",
           "runner"]

#: The entry-point group under which packages register their back ends.
ENTRY_POINT_GROUP = "thetahat.backends"

#: The ``min_samples`` of a back end whose first build is slow (numba's kernel): below it a
#: model's first compilation (20–40 s; later processes load it from the cache in < 1 s) costs
#: more than it saves, the Python step running ≈ 3 000 samples/s.
COMPILE_MIN_SAMPLES = 20_000

#: ``build(observer, dt, fallback)`` returns the runner, or a string saying why it declines;
#: ``fallback()`` builds the next back end down the list (for records the runner cannot take).
Build = Callable[[Any, float, Callable[[], Any]], Any]


@dataclass(frozen=True, slots=True)
class Backend:
    """A registered way of running the observer over a record.

    Attributes
    ----------
    name : str
        Short name (``"c"``, ``"numba"``).
    rank : int
        Order of preference: lower runs first.
    min_samples : int
        By default (``compiled=None``) a record shorter than this does not take this back end:
        its first build costs more than it saves (numba's first compilation of a model takes
        tens of seconds; the C builds in under one).
    build : callable
        ``build(observer, dt, fallback)`` → an object with the observer's ``init``, ``step``,
        ``estimate`` and ``run(t, u, y, *, state0, throw)`` (the hold and the progress
        callback are the observer's), or a ``str`` that says why this back end cannot take
        the observer (it is then skipped). ``observer`` runs in NumPy (``compiled=False``);
        ``dt`` is the record's first step; ``fallback()`` builds the next back end down the
        list.
    """

    name: str
    rank: int
    min_samples: int
    build: Build

    def __repr__(self) -> str:
        return f"Backend(name={self.name!r}, rank={self.rank}, min_samples={self.min_samples})"


_REGISTRY: dict[str, Backend] = {}
_LOADED = False
_LOCK = threading.Lock()


def register(backend: Backend) -> None:
    """Add (or replace, by name) a back end.

    Parameters
    ----------
    backend : Backend

    Examples
    --------
    >>> def build(observer, dt, fallback):
    ...     return "a demonstration back end takes nothing"
    >>> register(Backend(name="demo", rank=99, min_samples=0, build=build))
    >>> "demo" in [b.name for b in backends()]
    True
    >>> unregister("demo")
    """
    with _LOCK:
        _REGISTRY[backend.name] = backend


def unregister(name: str) -> None:
    """Remove the back end ``name`` (no error when absent).

    Parameters
    ----------
    name : str
    """
    with _LOCK:
        _REGISTRY.pop(name, None)


def backends() -> tuple[Backend, ...]:
    """The registered back ends, fastest first (the entry points are read on the first call).

    Returns
    -------
    tuple of Backend

    Examples
    --------
    >>> [b.name for b in backends()][:2]      # with numba and a C compiler installed
    ['c', 'numba']
    """
    global _LOADED
    with _LOCK:
        if not _LOADED:
            _LOADED = True
            for ep in entry_points(group=ENTRY_POINT_GROUP):
                try:
                    backend = ep.load()
                except ImportError:         # its package is absent: not a back end here
                    continue
                if isinstance(backend, Backend):
                    _REGISTRY.setdefault(backend.name, backend)
        return tuple(sorted(_REGISTRY.values(), key=lambda b: b.rank))


def _first_step(t: Any) -> float | None:
    """The record's first step (1.0 when it has none), or None when t is not numbers."""
    try:
        t_ = np.asarray(t, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    steps = np.diff(t_[:2])
    return float(steps[0]) if steps.size and np.isfinite(steps[0]) and steps[0] > 0 else 1.0


def runner(observer: Any, t: Any, *, compiled: bool | None = None,
           samples: int | None = None) -> Any:
    """What runs ``observer`` over the record ``t``: the fastest back end that takes it.

    Every back end has the observer's ``run(t, u, y, *, state0, throw)`` and gives the same
    results to rounding, and the same status when a step fails (the conformance tests). ``compiled`` True: the fastest registered
    back end that takes the observer; None (the default): the same among the back ends whose
    :attr:`Backend.min_samples` the work reaches; False: the observer itself. When every
    candidate declines, the observer runs in Python with a one-line
    :class:`~thetahat.errors.ThetahatWarning` that says why (only when compiling was asked for
    or the record is long enough for every back end).

    Parameters
    ----------
    observer : ModifiedHighGainObserver
        One that runs in NumPy (``compiled=False``): the back ends fall back to it.
    t : array_like, shape (N,)
        The record's sampling instants.
    compiled : bool, optional
        True: compile whenever possible; False: never; None: where it pays.
    samples : int, optional
        The work in samples that decides "where it pays" (default N; a fleet passes the
        samples of all its records on this time grid).

    Returns
    -------
    object
        The observer, or a back end's runner standing in for it.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> obs = lugre.observer()
    >>> runner(obs, np.arange(100) * 1e-3, compiled=False) is obs
    True
    """
    dt = _first_step(t)
    if dt is None or compiled is False:     # not numbers: the observer's run says what is wrong
        return observer
    every = backends()
    if compiled is None:
        work = np.asarray(t).size if samples is None else int(samples)
        chosen = tuple(b for b in every if b.min_samples <= work)
        loud = len(chosen) == len(every)
        return _chain(observer, dt, chosen, [], loud)
    return _chain(observer, dt, every, [], True)


def _fallback(observer: Any, dt: float, rest: tuple[Backend, ...], notes: list[str],
              loud: bool) -> Callable[[], Any]:
    """What a back end calls for a record it cannot take: the chain of the ones after it."""
    return lambda: _chain(observer, dt, rest, notes, loud)


def _chain(observer: Any, dt: float, rest: tuple[Backend, ...], notes: list[str],
           loud: bool) -> Any:
    """The first back end of ``rest`` that takes the observer, each with the next as its
    fallback; the observer itself (with a note when ``loud``) when none does."""
    for i, backend in enumerate(rest):
        got = backend.build(observer, dt, _fallback(observer, dt, rest[i + 1:], notes, loud))
        if not isinstance(got, str):
            return got
        notes.append(got)
    if loud:
        warnings.warn("the observer runs in Python: " + (
            notes[-1] if notes else "no compiled back end is installed (pip install "
            "'thetahat[speed]' for numba's, or install a C compiler)") + ".", ThetahatWarning,
            stacklevel=3)
    return observer
