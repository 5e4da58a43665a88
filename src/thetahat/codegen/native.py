"""The paper's observer on the C derived from its formulas, built by the system's C compiler.

A model's first numba compilation of the observer kernel takes 20–60 s; the C that
:func:`~thetahat.codegen.generate.generate_c` prints from the same formulas compiles in well
under a second with ``cc -O2`` and runs as fast (the conformance tests hold the two to
rounding). :class:`NativeObserver` runs a record through that C, loaded with ctypes
(:class:`~thetahat.codegen.loader.CObserver`), wherever it can:

* a C compiler exists (``$CC`` or ``cc``; :func:`~thetahat.codegen.loader.find_compiler`) and
  ``THETAHAT_C`` is not ``0``;
* ``generate_c`` supports the observer;
* the record is sampled uniformly (the C step has one step length compiled in): every step
  within :data:`~thetahat.estimation.observer.plan.DT_RTOL` of the record's mean spacing.

Otherwise it hands the record to its fallback (the numba kernel, or the observer itself). A
nonzero status of the C run is the :class:`~thetahat.estimation.status.Status` of the same code
(the header's codes are derived from it), reported as every back end reports a failed step
(:func:`~thetahat.estimation.observer.record_run.failure`): raised with ``throw=True``, in the
result with ``throw=False``.

Built libraries are kept in :func:`~thetahat.estimation.kernels.kernel_cache.cache_dir`, each
with a manifest of its key (the generated sources, which are printed from the formulas and hold
every number of the model, the compiler, its flags, thetahat's version) and its SHA-256: a
second process loads the library without compiling, after checking it
(:mod:`~thetahat.codegen.native_cache`: a damaged or foreign entry is rebuilt, never loaded).

What lives here: :class:`NativeObserver`, :func:`load_cached` and :data:`BACKEND`. What it may
import: the generator and loader of this package, the observer's record loop and result
(:mod:`thetahat.estimation.observer.record_run`), the kernel cache and
:mod:`thetahat.estimation.drive`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import CCompilerError, FileAccessError, UnsupportedError
from ..estimation.drive import Backend
from ..estimation.kernels.kernel_cache import cache_dir
from ..estimation.observer.observer import ModifiedHighGainObserver, ObserverEstimate
from ..estimation.observer.plan import DT_RTOL
from ..estimation.observer.record_run import (PROGRESS_EVERY, ROW_BLOCK, Failure, RecordRows,
                                              failure, row_blocks)
from ..estimation.protocol import EstimateResult, check_step_length
from .generate import CCode, generate_c, supports_c
from .loader import CObserver, find_compiler
from .native_cache import cached_library

__all__ = ["BACKEND", "NativeObserver", "native_enabled", "load_cached"]


def native_enabled() -> bool:
    """Whether the C path may be used: a compiler exists and ``THETAHAT_C`` is not ``"0"``.

    Returns
    -------
    bool

    Examples
    --------
    >>> isinstance(native_enabled(), bool)
    True
    """
    return os.environ.get("THETAHAT_C", "1") != "0" and find_compiler() is not None


def load_cached(code: CCode) -> CObserver:
    """Load ``code``'s shared library from the cache, verified, building it first if needed
    (:func:`~thetahat.codegen.native_cache.cached_library`).

    Parameters
    ----------
    code : CCode
        Generated C (:func:`~thetahat.codegen.generate.generate_c`).

    Returns
    -------
    CObserver

    Raises
    ------
    CCompilerError
        No compiler, or it failed, or its library failed to load in a child process.

    Warns
    -----
    ThetahatWarning
        One line: a damaged or foreign cache entry was discarded and rebuilt, or the cache
        could not be written (the library then runs from memory).

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> code = generate_c(build_observer(loads_model(EXAMPLE_MODEL)), dt=0.01, name="prop3")
    >>> obs = load_cached(code) if native_enabled() else None
    >>> obs is None or obs.step(obs.init(), [0.0], [0.1]) == 0
    True
    """
    return CObserver(code, cached_library(code))


class NativeObserver:
    """An observer's record runs in generated C where possible, else in ``fallback``.

    Parameters
    ----------
    observer : ModifiedHighGainObserver
        The observer (one whose parts ``generate_c`` does not support runs in the fallback);
        its ``hold`` and ``progress`` are the runs'.
    fallback : callable
        Returns what runs a record the C cannot take (non-uniform steps): an object with the
        observer's ``run(t, u, y, *, state0=, throw=)``; called at most once, when first
        needed.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> obs = build_observer(loads_model(EXAMPLE_MODEL))
    >>> fast = NativeObserver(obs, lambda: obs)
    >>> t = np.arange(200) * 0.01
    >>> a = fast.run(t, np.sin(t)[:, None], np.cos(t)[:, None])
    >>> b = obs.run(t, np.sin(t)[:, None], np.cos(t)[:, None])
    >>> bool(np.allclose(a.theta_hat, b.theta_hat, rtol=1e-9, atol=1e-12))
    True
    """

    def __init__(self, observer: ModifiedHighGainObserver, fallback: Callable[[], Any]) -> None:
        self.observer = observer
        self._fallback_of = fallback
        self._fallback: Any = None
        self._loaded: dict[float, CObserver] = {}
        self._stream: tuple[float, CObserver | None] | None = None

    def init(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None,
             z0: ArrayLike | None = None,
             x_hat_refined0: ArrayLike | None = None) -> NDArray[np.float64]:
        """The observer's initial state (see its ``init``).

        Parameters
        ----------
        x_hat0, theta_hat0, z0, x_hat_refined0 : array_like, optional
            As for :meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.init`.

        Returns
        -------
        ndarray
        """
        return self.observer.init(x_hat0=x_hat0, theta_hat0=theta_hat0, z0=z0,
                                  x_hat_refined0=x_hat_refined0)

    @property
    def system(self) -> Any:
        """The observer's system."""
        return self.observer.system

    def step(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike, dt: float
             ) -> NDArray[np.float64]:
        """One step of a stream (zero-order hold, as the observer's own ``step``): in the C of
        the stream's step length, else (or when the C refuses the sample) the observer's.

        The C is built (or loaded from the cache) at the first step, for its ``dt``; later
        steps take it when their ``dt`` is within
        :data:`~thetahat.estimation.observer.plan.DT_RTOL` of that one (as :meth:`run` takes
        a record whose steps are), others the observer's own step. A sample the C refuses
        (a NaN it may not skip, a divergence) goes to the observer's step, which raises as
        it always does. One call costs microseconds where the NumPy step costs hundreds.

        Parameters
        ----------
        state, u, y, dt
            As :meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.step`.

        Returns
        -------
        ndarray
        """
        obs = self.observer
        u_, y_, _ = obs.check_samples(u, y)
        nxt = self._c_step(obs.check_state(state), u_, y_, check_step_length(dt))
        return obs.step(state, u, y, dt) if nxt is None else nxt

    def read_and_step(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike, dt: float
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                 NDArray[np.float64] | None, NDArray[np.float64]]:
        """:meth:`read_estimates` and :meth:`step` of one state and sample, checked once (the
        observer's ``read_and_step``, its step in C as :meth:`step`'s).

        Parameters
        ----------
        state, u, y, dt
            As :meth:`step`.

        Returns
        -------
        tuple
            x̂, θ̂, x̂₂ (or None) at the samples' time, and the next state.
        """
        obs = self.observer
        u_, y_, _ = obs.check_samples(u, y)
        s = obs.check_state(state)
        nxt = self._c_step(s, u_, y_, check_step_length(dt))
        if nxt is None:
            return obs.read_and_step(state, u, y, dt)
        return (*obs.layout.read(s), nxt)

    def _c_step(self, s: NDArray[np.float64], u: NDArray[np.float64], y: NDArray[np.float64],
                h: float) -> NDArray[np.float64] | None:
        """The next state of checked arrays in the stream's C, or None (no C for this h, or
        the C refused the sample: the observer's step decides)."""
        c = self._stream_c(h)
        if c is None:
            return None
        status, nxt = c.stepped(s, u if self.observer.layout.m else None, y)
        return nxt if status == 0 else None

    def steps_in_c(self, dt: float) -> bool:
        """Whether a :meth:`step` of length ``dt`` runs in C (the first call builds the C of
        the stream's step length).

        Parameters
        ----------
        dt : float

        Returns
        -------
        bool
        """
        return self._stream_c(check_step_length(dt)) is not None

    def _stream_c(self, h: float) -> CObserver | None:
        """The zoh C of the stream's first step length, if it takes a step of length h."""
        if self._stream is None:
            c: CObserver | None = None
            try:
                code = generate_c(self.observer.with_run_options(hold="zoh"), dt=h,
                                  name="thetahat_observer")
                if code.sizes["state"] == self.observer.layout.size:
                    c = load_cached(code)
            except (UnsupportedError, CCompilerError, FileAccessError, OSError):
                c = None
            self._stream = (h, c)
        d, c = self._stream
        return c if c is not None and abs(h - d) <= DT_RTOL * d else None

    def estimate(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike) -> ObserverEstimate:
        """x̂, φ̂, θ̂ (and x̂₂) of a state: the observer's ``estimate``.

        Parameters
        ----------
        state, u, y
            As :meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.estimate`.

        Returns
        -------
        ObserverEstimate
        """
        return self.observer.estimate(state, u, y)

    def read_estimates(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                  NDArray[np.float64] | None]:
        """x̂, θ̂ and x̂₂ of a state, without φ̂: the observer's ``read_estimates``.

        Parameters
        ----------
        state, u, y
            As :meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.read_estimates`.

        Returns
        -------
        tuple
        """
        return self.observer.read_estimates(state, u, y)

    def fallback(self) -> Any:
        """What runs the records the C cannot take (built on first use).

        Returns
        -------
        object
            With ``run(t, u, y, *, state0=, throw=)``.
        """
        if self._fallback is None:
            self._fallback = self._fallback_of()
        return self._fallback

    def _c(self, dt: float) -> CObserver:
        if dt not in self._loaded:
            code = generate_c(self.observer, dt=dt, name="thetahat_observer")
            self._loaded[dt] = load_cached(code)
        return self._loaded[dt]

    def run(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
            state0: ArrayLike | None = None, throw: bool = True) -> EstimateResult:
        """Run over a record: in C when its steps are uniform, else in the fallback.

        Parameters
        ----------
        t, u, y, state0, throw
            As :meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.run`
            (with the observer's ``hold`` and ``progress``).

        Returns
        -------
        EstimateResult
            As the observer's (to rounding: the C uses the mean step length); a step the C
            refuses gives the status of its code, at the same ``failed_at``.

        Raises
        ------
        NonFiniteError, UpdateLawError
            With ``throw``: a failed step, as the observer's ``run`` raises it.
        """
        obs = self.observer
        lay = obs.layout
        t_, dts, U3, Y3, ok3 = obs.check_records(t, u, y)
        N = t_.shape[0]
        c = self._uniform_c(t_, dts)
        if c is None or c.code.sizes["state"] != lay.size:
            return self.fallback().run(t, u, y, state0=state0, throw=throw)
        U = np.ascontiguousarray(U3[0] if lay.m else np.zeros((N, 1)), dtype=np.float64)
        Y = np.ascontiguousarray(Y3[0], dtype=np.float64)
        s = np.array(obs.init() if state0 is None else obs.check_state(state0),
                     dtype=np.float64)
        progress = obs.progress
        step = PROGRESS_EVERY if progress is not None else ROW_BLOCK
        out = RecordRows(lay, N)
        S = np.empty((min(step, N - 1) + 1, lay.size))      # a block's rows (scratch)
        PHI = np.empty((S.shape[0], lay.k))
        fail: Failure | None = None
        for a, b in row_blocks(N, step):
            if progress is not None:
                progress(a, N - 1)
            n = b - a + 1           # a C of another precision writes into arrays of its own
            rows, phi, status, index = c.run_rows(s, U[a:b + 1], Y[a:b + 1],
                                                  out=(S[:n], PHI[:n]))
            out.put(a, rows, phi)
            if status:
                fail = failure(status, a + index, t_, type(obs.update_law).__name__)
                if throw:
                    raise fail.error()
                break
            s = np.array(rows[-1], dtype=np.float64)
        if progress is not None and fail is None:
            progress(N - 1, N - 1)
        return out.result(t_, ok3[0], fail)

    def _uniform_c(self, t: NDArray[np.float64], dts: NDArray[np.float64]) -> CObserver | None:
        """The C of the record's one step length, or None (non-uniform steps, no C)."""
        N = t.shape[0]
        dt = float((t[-1] - t[0]) / (N - 1)) if N > 1 else 0.0
        if not (N > 1 and dt > 0.0 and float(np.max(np.abs(dts - dt))) <= DT_RTOL * dt):
            return None
        try:
            return self._c(dt)
        except (UnsupportedError, CCompilerError, FileAccessError, OSError):
            return None

    def __repr__(self) -> str:
        return f"NativeObserver(observer={self.observer!r})"


def _native_backend(observer: Any, dt: float, fallback: Callable[[], Any]
                    ) -> NativeObserver | str:
    """:data:`BACKEND`'s build: the C of the observer's formulas, or why it cannot be had."""
    if not native_enabled():
        return "no C compiler (set $CC) or THETAHAT_C=0"
    if not supports_c(observer):
        return "the C printer does not support a part of this observer"
    return NativeObserver(observer, fallback)


#: The generated C as a back end of :func:`thetahat.estimation.drive.runner` (registered under
#: the entry-point group ``thetahat.backends``): first, and for records of any length, since it
#: builds in under a second and runs as fast as numba's kernel; a record it cannot take
#: (non-uniform steps) goes to the next back end.
BACKEND = Backend(name="c", rank=10, min_samples=0, build=_native_backend)
