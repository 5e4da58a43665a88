"""A compiled fast path for the observer: one numba kernel per symbolic model (optional extra).

:func:`compile_observer` turns a :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`
whose parts are all symbolic or structured into a :class:`CompiledObserver` whose ``step`` and
``run`` execute the observer's step (eqs. (3), (8) and the second observer of Sec. VI) as
machine code. Supported:

* g: a :class:`~thetahat.model.perturbation.SymbolicPerturbation` (g, ∂g/∂x, ∂g/∂θ and ∂g/∂v
  are printed to scalar Python code with SymPy's common-subexpression elimination);
* Θ: a :class:`~thetahat.model.paramset.Box` with a diagonal Γ (the Γ⁻¹-weighted projection
  onto a box is then a clip), or a :class:`~thetahat.model.paramset.Ball` or
  :class:`~thetahat.model.paramset.Ellipsoid` with any Γ (the Γ⁻¹-weighted projection of
  :func:`~thetahat.estimation.kernels.set_projection.project_into`; Θ's centre and shape are
  data, so one kernel serves every ball and ellipsoid of a model);
* update laws: :class:`~thetahat.estimation.observer.laws.ConstantLaw`,
  :class:`~thetahat.estimation.observer.laws.IntermittentInversion` (l ≡ 1, as built by
  :func:`~thetahat.estimation.observer.laws.AlgebraicInversion`, or the weight of
  :func:`~thetahat.estimation.observer.laws.smooth_ramp`) whose θ* has a SymPy form (a
  :class:`~thetahat.estimation.observer.laws.theta_star.ThetaStar` from ``from_perturbation`` or
  ``ThetaStar.from_expr``, or a model file's ``theta_star``), and
  :class:`~thetahat.estimation.observer.laws.GradientInversion` with the default M = (∂g/∂θ)ᵀ,
  and :class:`~thetahat.estimation.observer.laws.FilteredLeastSquares` on a Box Θ (its state
  col(w, w_b, a, R) in the kernel's state row; its projection in R's metric by
  :func:`~thetahat.estimation.kernels.set_projection.project_box_metric`);
  none of them with a ``saturation``;
* an attached :class:`~thetahat.estimation.observer.redesign.SecondObserver`;
* any sampling the Python ``run`` takes: irregular steps (the φ-matrices of each distinct step
  length, from the observer's cached plans), missing samples under ``nan_policy="skip"``
  (the prediction's φ-matrices), the zero- and first-order holds.

Everything else raises :class:`~thetahat.errors.UnsupportedError` (a NotImplementedError)
naming the part; use the Python observer.

The kernel is not a transcription: :mod:`~thetahat.estimation.observer.kernel_source` prints the
step's formulas (:mod:`~thetahat.estimation.observer.formulas`,
:mod:`~thetahat.estimation.observer.laws.formulas`) as scalar loops of one row
(:class:`~thetahat.estimation.kernels.printer.Program`), with the scalar functions of
:mod:`~thetahat.estimation.kernels.scalar_primitives` and g, its Jacobians and θ* printed from their
SymPy expressions; :mod:`~thetahat.estimation.observer.kernel_data` checks the observer's parts
and lays its :class:`~thetahat.estimation.observer.plan.StepPlan` out for the kernel, and this
module calls it. The module is written to a cache directory (``$THETAHAT_CACHE_DIR``, default
``~/.cache/thetahat``, else a temporary directory) under a name that hashes its content, and
compiled with ``numba.njit(cache=True)``: the first compilation of a model and law formula
costs 20–40 s, later processes load the machine code from disk. The gains, ε, Γ, Θ, the
ramp, ``on_invalid``, the second observer and the step lengths are data, not code: observers
that differ only in them share one kernel. :func:`~thetahat.estimation.drive.runner` chooses
between the compiled and the Python observer for a record (an observer built with
``compiled=None`` or ``True`` asks it).

numba is the optional extra ``speed``; without it this module imports, and
:func:`compile_observer` raises :class:`ImportError`.

What lives here: :class:`CompiledObserver`, :func:`compile_observer` and :data:`BACKEND` (the
kernel as a back end of :mod:`thetahat.estimation.drive`). What it may import: the observer,
its plan, record loop and kernel data (:mod:`.kernel_data`), the printed kernel
(:mod:`.kernel_source`), the kernel cache and the bottom of :mod:`thetahat.estimation`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_vector, positive_scalar
from ...errors import DimensionError, MissingExtraError, UnsupportedError
from ..drive import COMPILE_MIN_SAMPLES, Backend
from ..kernels.kernel_args import LawArrays, PlanArrays, SecondArrays, WorkArrays
from ..kernels.kernel_cache import load_module
from ..protocol import EstimateResult, check_step_length
from ..records import check_magnitude
from ..status import Status
from .formulas import DIVERGENCE_BOUND
from .kernel_data import (KernelParts, kernel_arrays, kernel_parts, kernel_work, phi_table,
                          unsupported)
from .kernel_source import LAWS, kernel_source
from .laws.theta_star import ThetaStar
from .observer import ModifiedHighGainObserver, ObserverEstimate
from .plan import DT_RTOL, StateLayout, StepPlan
from .record_run import (PROGRESS_EVERY, ROW_BLOCK, Failure, RecordRows, failure, row_blocks,
                         step_error)

__all__ = ["BACKEND", "CompiledObserver", "compile_observer"]

FloatArray = NDArray[np.float64]

def _require_numba() -> Any:
    try:
        import numba
    except ImportError as exc:  # pragma: no cover - exercised only without numba
        raise MissingExtraError("compile_observer needs numba, the optional extra 'speed': "
                          "pip install 'thetahat[speed]'. Without it, use the observer's own "
                          "run/step, or thetahat.estimation.observer.batch_run.run_batch for many "
                          "runs.") from exc
    return numba


def _load(source: str) -> ModuleType:
    """Import the generated module (written once under its content hash, then cached)."""
    _require_numba()
    return load_module(source, "thetahat_kernel")


def _as_input(name: str, a: Any, size: int) -> FloatArray:
    """A writable, contiguous float64 vector of length ``size`` (no copy if ``a`` is one).

    numba compiles one specialisation per array type, and read-only or strided arrays are
    other types: normalising them keeps the kernel at one compilation.
    """
    if (type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (size,)
            and a.flags.c_contiguous and a.flags.writeable):
        return a
    return np.array(as_vector(name, a, size, finite=False), dtype=np.float64, order="C")


def _kernel_array(a: FloatArray) -> FloatArray:
    """``a`` as a writable C-contiguous array (see :func:`_as_input`)."""
    if a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64, order="C")


@dataclass(frozen=True, slots=True, eq=False)
class CompiledObserver:
    """A :class:`ModifiedHighGainObserver` compiled (numba).

    ``step`` and ``run`` compute what the observer's own ``step`` and ``run`` compute, in
    machine code; ``step`` advances by ``dt``, ``run`` by each step of its record, with the
    observer's ``hold`` and ``progress``. Build it with :func:`compile_observer`, which
    documents the parameters ``observer`` and ``dt``.

    Parameters
    ----------
    observer, dt
        As in :func:`compile_observer`.

    Attributes
    ----------
    observer : ModifiedHighGainObserver
        The observer it was compiled from (gains, law, second observer).
    dt : float
        The step length (s) of ``step``.
    theta_star : ThetaStar or None
        The θ* compiled into the kernel, the update law's own (None for laws without θ*).
    plan : StepPlan
        The observer's plan for ``dt``, whose matrices the kernel reads.
    """

    observer: ModifiedHighGainObserver
    dt: float
    theta_star: ThetaStar | None
    plan: StepPlan
    _kernel: ModuleType
    _args: tuple[PlanArrays, SecondArrays, LawArrays, tuple[bool, bool]]
    _step_tables: dict[bool, tuple[NDArray[np.int64], tuple[FloatArray, ...]]]

    def __init__(self, observer: ModifiedHighGainObserver, *, dt: float) -> None:
        _require_numba()
        if not isinstance(observer, ModifiedHighGainObserver):
            raise unsupported(f"a {type(observer).__name__} (it must be a "
                              "ModifiedHighGainObserver)")
        h = positive_scalar("dt", dt)
        parts = kernel_parts(observer)
        ts = parts.theta_star
        plan = observer.plan(h)
        source = kernel_source(parts.perturbation, None if ts is None else ts.expr,
                               None if ts is None else ts.arguments, LAWS[parts.code],
                               M=parts.M, ellipsoid=parts.ellipsoid,
                               law_size=parts.law_size)
        for name, value in (("observer", observer), ("dt", h), ("theta_star", ts),
                            ("plan", plan), ("_kernel", _load(source)),
                            ("_args", kernel_arrays(parts, plan)),
                            ("_step_tables", {})):
            object.__setattr__(self, name, value)

    @property
    def state_size(self) -> int:
        """Length of the state vector (as :attr:`ModifiedHighGainObserver.state_size`)."""
        return self.observer.state_size

    def init(self, *, x_hat0: ArrayLike | None = None, theta_hat0: ArrayLike | None = None,
             z0: ArrayLike | None = None,
             x_hat_refined0: ArrayLike | None = None) -> FloatArray:
        """Initial state; see :meth:`ModifiedHighGainObserver.init` (same parameters).

        Parameters
        ----------
        x_hat0, theta_hat0, z0, x_hat_refined0
            As for :meth:`ModifiedHighGainObserver.init`.

        Returns
        -------
        ndarray, shape (state_size,)
        """
        return self.observer.init(x_hat0=x_hat0, theta_hat0=theta_hat0, z0=z0,
                                  x_hat_refined0=x_hat_refined0)

    def step(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike, dt: float
             ) -> FloatArray:
        """Advance the state by ``dt`` holding the samples (as the observer's ``step``).

        Parameters
        ----------
        state : array_like, shape (state_size,)
        u : array_like, shape (m,)
            Current input sample (``None`` when m = 0).
        y : array_like, shape (r,)
            Current output sample; NaN marks a missing sample under ``nan_policy="skip"``
            (the observers predict over it).
        dt : float
            Time to the next sample: the compiled step length :attr:`dt` (to a relative
            :data:`~thetahat.estimation.observer.plan.DT_RTOL`).

        Returns
        -------
        ndarray, shape (state_size,)

        Raises
        ------
        DimensionError
            Wrong shapes, or ``dt`` other than the compiled step length.
        NonFiniteError
            NaN or inf in the state or u, NaN in y under ``nan_policy="raise"``, or the step
            diverged.
        UpdateLawError
            θ* invalid where l > 0 and ``on_invalid='raise'``.
        """
        if not abs(check_step_length(dt) - self.dt) <= DT_RTOL * self.dt:
            raise DimensionError(f"the compiled observer steps dt = {self.dt!r}; got dt = "
                                 f"{dt!r}. Compile again with compile_observer(observer, "
                                 "dt=...), or use the observer's own step.")
        obs = self.observer
        lay = obs.layout
        if not (type(state) is np.ndarray and state.shape == (lay.size,)):
            state = obs.check_state(state)          # the protocol's check and message
        s = _as_input("state", state, lay.size)
        u_ = _as_input("u", np.empty(0) if u is None else u, lay.m)
        y_ = _as_input("y", y, lay.r)
        check_magnitude("u", u_)
        check_magnitude("y", y_)
        present = bool(np.isfinite(y_).all())
        if not present:
            obs.check_samples(u, y)              # raises under nan_policy="raise"
        # the record of one step (the samples held): the same compiled loop as run's, so a
        # kernel has one entry point to compile
        ok = np.array([present, True])
        S, PHI = np.empty((2, lay.size)), np.empty((2, lay.k))
        # the φ-matrices of a step of dt, with the sample present or not: two tables, made
        # once (read only: each call loads them into its own buffers)
        table = self._step_tables.get(present)
        if table is None:
            table = self._step_tables[present] = phi_table(obs, np.array([self.dt]), ok[:1])
        status, _ = self._call(s, np.stack((u_, u_)), np.stack((y_, y_)),
                               np.array([self.dt]), ok, False, S, PHI, table)
        out = S[1]
        if status == 0 and float(out @ out) <= DIVERGENCE_BOUND ** 2:
            return out
        # something is wrong: find out what, with the observer's own checks and messages
        obs.check_state(state)
        obs.check_samples(u, y)
        raise step_error(int(status) or Status.DIVERGED, type(obs.update_law).__name__)

    def estimate(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike) -> ObserverEstimate:
        """x̂, φ̂, θ̂ (and x̂₂) of a state; see :meth:`ModifiedHighGainObserver.estimate`.

        Parameters
        ----------
        state : array_like, shape (state_size,)
        u : array_like, shape (m,)
        y : array_like, shape (r,)

        Returns
        -------
        ObserverEstimate
        """
        return self.observer.estimate(state, u, y)

    def read_estimates(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike
                       ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """x̂, θ̂ and x̂₂ of a state, without φ̂.

        Parameters
        ----------
        state, u, y
            As :meth:`ModifiedHighGainObserver.read_estimates`.

        Returns
        -------
        tuple
        """
        return self.observer.read_estimates(state, u, y)

    def read_and_step(self, state: ArrayLike, u: ArrayLike | None, y: ArrayLike, dt: float
                      ) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray]:
        """:meth:`read_estimates` and :meth:`step` of one state and sample (the observer's
        ``read_and_step``, the step compiled).

        Parameters
        ----------
        state, u, y, dt
            As :meth:`step`.

        Returns
        -------
        tuple
            x̂, θ̂, x̂₂ (or None) at the samples' time, and the next state.
        """
        return (*self.observer.read_estimates(state, u, y), self.step(state, u, y, dt))

    def _call(self, s0: FloatArray, U: FloatArray, Y: FloatArray, dts: FloatArray,
              ok: NDArray[np.bool_], foh: bool, S: FloatArray, PHI: FloatArray,
              table: tuple[NDArray[np.int64], tuple[FloatArray, ...]] | None = None
              ) -> tuple[int, int]:
        """The kernel over one piece of a record (the φ-matrices of its step lengths:
        ``table``, else :func:`phi_table` of ``dts``)."""
        plan_of, PH = phi_table(self.observer, dts, ok[:-1]) if table is None else table
        P, P2, LP, flags = self._args
        W, rows, (Q1, Q2, R1, R2) = _scratch(self.observer.layout)
        # the φ-matrices are loaded into this thread's buffers: the shared arrays stay read
        P, P2 = P._replace(Phi1=Q1, Phi2=Q2), P2._replace(Phi1=R1, Phi2=R2)
        if LP.Phi1 is not None:      # the least-squares law's filter: the step's Φ₁ of the same L
            LP = LP._replace(Phi1=Q1)
        status, index = self._kernel.kernel_run(s0, U, Y, dts, ok, plan_of, PH, P, P2, LP,
                                                *flags, foh, W, rows, S, PHI)
        return int(status), int(index)

    def run(self, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
            state0: ArrayLike | None = None, throw: bool = True) -> EstimateResult:
        """Run over sampled records (the loop runs in machine code), with the observer's hold.

        The samples may be spaced irregularly: each step uses the φ-matrices of its own length
        (one :class:`~thetahat.estimation.observer.plan.StepPlan` per distinct length, as the Python
        path), and missing samples (NaN in y under ``nan_policy="skip"``) are predicted over.
        The observer's ``progress`` is called every ``PROGRESS_EVERY`` samples and at the end.

        Parameters
        ----------
        t : array_like, shape (N,)
            Strictly increasing sampling instants.
        u : array_like, shape (N, m) or (N,) when m = 1
            Input samples (``None`` when m = 0).
        y : array_like, shape (N, r) or (N,) when r = 1
            Output samples; NaN marks a missing sample under ``nan_policy="skip"``.
        state0 : array_like, shape (state_size,), optional
            Initial state; default ``init()``.
        throw : bool, default True
            A failed step raises (True) or stops the run with its status in the result
            (False), as :meth:`ModifiedHighGainObserver.run`.

        Returns
        -------
        EstimateResult
            As :meth:`ModifiedHighGainObserver.run` (agreement to rounding; see
            :func:`compile_observer`), the same status and ``failed_at`` when a step fails.

        Raises
        ------
        DimensionError
            Wrong shapes.
        NonFiniteError
            NaN or inf in t or u, NaN in y under ``nan_policy="raise"``, or (``throw``) the
            state diverged.
        UpdateLawError
            With ``throw``: θ* invalid where l > 0 and ``on_invalid='raise'``.
        """
        obs = self.observer
        lay = obs.layout
        t_, dts, U3, Y3, ok3 = obs.check_records(t, u, y)
        N = t_.shape[0]
        U, Y, dts = (_kernel_array(a) for a in (U3[0], Y3[0], dts))
        ok = np.ascontiguousarray(ok3[0], dtype=np.bool_)
        s = _kernel_array(obs.init() if state0 is None else obs.check_state(state0))
        progress = obs.progress
        step = PROGRESS_EVERY if progress is not None else ROW_BLOCK
        out = RecordRows(lay, N)
        S = np.empty((min(step, N - 1) + 1, lay.size))      # a block's rows (scratch)
        PHI = np.empty((S.shape[0], lay.k))
        fail: Failure | None = None
        for a, b in row_blocks(N, step):
            if progress is not None:
                progress(a, N - 1)
            rows = b - a + 1
            status, index = self._call(s.copy(), U[a:b + 1], Y[a:b + 1], dts[a:b],
                                       ok[a:b + 1], obs.hold == "foh", S[:rows], PHI[:rows])
            out.put(a, S[:rows], PHI[:rows])
            if status:
                fail = failure(status, a + index, t_, type(obs.update_law).__name__)
                if throw:
                    raise fail.error()
                break
            s = S[rows - 1]
        if progress is not None and fail is None:
            progress(N - 1, N - 1)
        return out.result(t_, ok, fail)

    def __repr__(self) -> str:
        return (f"CompiledObserver(dt={self.dt!r}, observer={self.observer!r}, "
                f"kernel={self._kernel.__name__})")


_threads = threading.local()


def _scratch(lay: StateLayout) -> tuple[WorkArrays, tuple[FloatArray, ...],
                                        tuple[FloatArray, ...]]:
    """:func:`kernel_work` of this thread and its buffers of the φ-matrices (Φ₁, Φ₂ and the
    second observer's) of the current step (scratch only: nothing is carried between
    calls)."""
    cache: dict[StateLayout, Any] | None = getattr(_threads, "work", None)
    if cache is None:
        cache = _threads.work = {}
    hit = cache.get(lay)
    if hit is None:
        q, n = lay.n + lay.k, lay.n
        hit = cache[lay] = (*kernel_work(lay), tuple(np.zeros((d, d)) for d in (q, q, n, n)))
    return hit


def _numba_backend(observer: ModifiedHighGainObserver, dt: float,
                   fallback: Callable[[], Any]) -> CompiledObserver | str:
    """:data:`BACKEND`'s build: the numba kernel of ``observer``, or why it cannot be had."""
    try:
        return compile_observer(observer, dt=dt)
    except MissingExtraError:
        return ("numba is not installed (pip install 'thetahat[speed]' for the compiled "
                "kernel)")
    except UnsupportedError as exc:
        return str(exc).split(" (supported:")[0].removeprefix("compile_observer: ")


#: The numba kernel as a back end of :func:`thetahat.estimation.drive.runner` (registered under
#: the entry-point group ``thetahat.backends``); the C back end comes first when it can run.
BACKEND = Backend(name="numba", rank=20, min_samples=COMPILE_MIN_SAMPLES, build=_numba_backend)


def compile_observer(observer: ModifiedHighGainObserver, *, dt: float) -> CompiledObserver:
    """Compile an observer's step for a fixed ``dt`` with numba (the optional extra ``speed``).

    Parameters
    ----------
    observer : ModifiedHighGainObserver
        Observer (3) with update law (8) and optionally a second observer (Sec. VI); its parts
        must be of the supported kinds (see the module docstring). A law with a θ* needs its
        SymPy form: a :class:`~thetahat.estimation.observer.laws.theta_star.ThetaStar`, or a model file's.
    dt : float
        The step length (s) > 0 of ``step``; ``run`` steps by its record's own spacing.

    Returns
    -------
    CompiledObserver

    Raises
    ------
    ImportError
        numba is missing: ``pip install 'thetahat[speed]'``.
    NotImplementedError
        A part of the observer is not supported by the compiled path (the message names it).

    Notes
    -----
    The kernel is the step's formulas (:mod:`~thetahat.estimation.observer.formulas`) compiled for one
    row, reading the observer's :class:`~thetahat.estimation.observer.plan.StepPlan` for ``dt``; it
    differs from the Python path only in the summation order of the small matrix products, a
    pivoted elimination in place of LAPACK's, a Taylor ``expm`` in place of SciPy's, and
    scalar code for g, its Jacobians and θ* (printed from the same SymPy expressions the
    Python path lambdifies). It applies the same divergence rule
    (:data:`~thetahat.estimation.observer.formulas.DIVERGENCE_BOUND`) and raises the same errors.
    Measured on a shared 2-core machine: ≈ 0.2 µs per sample inside ``run``, a few µs per
    call of ``step`` from Python (validation and dispatch dominate). The first compilation of
    a model takes 20–40 s; later ones load from the cache.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.observer.compiled import compile_observer
    >>> data = lugre.simulate(seed=0, t_end=0.5)
    >>> obs = lugre.observer()
    >>> try:
    ...     fast = compile_observer(obs, dt=1e-3)
    ... except ImportError:                  # numba missing: pip install 'thetahat[speed]'
    ...     fast = None
    >>> res = obs.run(data.t, data.u, data.y)
    >>> res_fast = res if fast is None else fast.run(data.t, data.u, data.y)
    >>> bool(np.allclose(res_fast.theta_hat, res.theta_hat, rtol=1e-9, atol=0))
    True
    """
    return CompiledObserver(observer, dt=dt)
