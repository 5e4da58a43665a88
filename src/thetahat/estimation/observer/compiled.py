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
  :class:`~thetahat.estimation.observer.laws.GradientInversion` with the default M = (∂g/∂θ)ᵀ;
  none of them with a ``saturation``;
* an attached :class:`~thetahat.estimation.observer.redesign.SecondObserver`;
* any sampling the Python ``run`` takes: irregular steps (the φ-matrices of each distinct step
  length, from the observer's cached plans), missing samples under ``nan_policy="skip"``
  (the prediction's φ-matrices), the zero- and first-order holds.

Everything else raises :class:`~thetahat.errors.UnsupportedError` (a NotImplementedError)
naming the part; use the Python observer.

The kernel is not a transcription: :mod:`~thetahat.estimation.observer.kernel_source` emits the
step's formulas (:mod:`~thetahat.estimation.observer.formulas`,
:mod:`~thetahat.estimation.observer.laws.formulas`) as written, with the scalar primitives of one row
(:mod:`~thetahat.estimation.kernels.scalar_primitives`) and g, its Jacobians and θ* printed from their
SymPy expressions; this module checks the observer's parts, lays its
:class:`~thetahat.estimation.observer.plan.StepPlan` out for the kernel (:func:`kernel_arrays`) and
calls it. The module is written to a cache directory (``$THETAHAT_CACHE_DIR``, default
``~/.cache/thetahat``, else a temporary directory) under a name that hashes its content, and
compiled with ``numba.njit(cache=True)``: the first compilation of a model and law formula
costs 20–40 s, later processes load the machine code from disk. The gains, ε, Γ, Θ, the
ramp, ``on_invalid``, the second observer and the step lengths are data, not code: observers
that differ only in them share one kernel. :func:`runner` chooses between the compiled and
the Python observer for a record (``run_estimator`` uses it).

numba is the optional extra ``speed``; without it this module imports, and
:func:`compile_observer` raises :class:`ImportError`.
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from ..._validate import as_vector, positive_scalar
from ...errors import (DimensionError, MissingExtraError, OptionError, ThetahatWarning,
                      UnsupportedError)
from ...model.paramset import Ball, Box, Ellipsoid
from ...model.perturbation import SymbolicPerturbation
from ..kernels.kernel_cache import load_module
from .observer import HOLDS, PROGRESS_EVERY, ModifiedHighGainObserver
from ..drive import COMPILE_MIN_SAMPLES, Backend
from ..protocol import EstimateResult, ObserverDiagnostics
from ..results import ObserverEstimate
from .formulas import WORK
from ..kernels.kernel_args import LawArrays, PlanArrays, SecondArrays
from .plan import StateLayout, StepPlan
from .kernel_source import LAWS, kernel_source
from ..kernels.set_projection import ellipsoid_data
from ..status import Status
from .step import DIVERGENCE_BOUND, divergence_error
from .laws.inversion import gain_eigen
from .laws.theta_star import ThetaStar, as_theta_star
from .laws import (ConstantLaw, GradientInversion, IntermittentInversion, SmoothRamp,
                          invalid_theta_star_error)

__all__ = ["CompiledObserver", "KernelParts", "compile_observer", "kernel_arrays", "kernel_parts",
           "kernel_work", "phi_table", "states_result", "BACKEND"]

FloatArray = NDArray[np.float64]

#: Relative tolerance of ``step``'s ``dt`` against the compiled step length.
DT_RTOL = 1e-9

_SUPPORTED = ("supported: a SymbolicPerturbation g, a Box Θ with diagonal Γ or a Ball or "
              "Ellipsoid Θ, ConstantLaw, "
              "IntermittentInversion (l ≡ 1, i.e. AlgebraicInversion, or a smooth_ramp weight) "
              "with a symbolic θ*, GradientInversion with the default M, no saturation, no law "
              "state, an optional SecondObserver")


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


# --------------------------------------------------------------------------- support checks
def _unsupported(what: str) -> UnsupportedError:
    return UnsupportedError(f"compile_observer: {what} is not supported by the compiled path "
                               f"({_SUPPORTED}); use the Python observer (run/step) or "
                               "run_batch.")


def _diagonal_gain(law: Any) -> FloatArray:
    G = np.asarray(law.Gamma, dtype=np.float64)
    if not np.array_equal(G, np.diag(np.diag(G))):
        raise _unsupported("a non-diagonal Γ (its Γ⁻¹-weighted projection onto a box is a "
                           "least-squares problem)")
    return G


@dataclass(frozen=True, slots=True)
class KernelParts:
    """What the kernel takes from an observer, checked (see :func:`kernel_parts`).

    Attributes
    ----------
    code : int
        0 ConstantLaw, 1 IntermittentInversion with l ≡ 1, 2 with a smooth ramp, 3 gradient.
    perturbation : SymbolicPerturbation
        g, printed into the kernel.
    theta_set : Box, Ball or Ellipsoid
        Θ.
    theta_star : ThetaStar or None
        θ* of the inversion laws.
    ramp : tuple of float or None
        (low, high) of the smooth ramp l (code 2).
    freeze : bool
        The inversion law's ``on_invalid == "freeze"``.
    M : sympy.Matrix or None
        A user's M of the gradient law (code 3), in g's symbols (its ``sympy_form``).
    """

    code: int
    perturbation: SymbolicPerturbation
    theta_set: Box | Ball | Ellipsoid
    theta_star: ThetaStar | None = None
    ramp: tuple[float, float] | None = None
    freeze: bool = False
    M: Any = None

    @property
    def ellipsoid(self) -> bool:
        """Θ is a ball or an ellipsoid (``kernel_source(..., ellipsoid=True)``), not a box."""
        return not isinstance(self.theta_set, Box)


def kernel_parts(observer: ModifiedHighGainObserver) -> KernelParts:
    """Check that the kernel supports the observer's parts, and collect them.

    Parameters
    ----------
    observer : ModifiedHighGainObserver

    Returns
    -------
    KernelParts

    Raises
    ------
    UnsupportedError
        A part the kernel does not support (the message names it).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.observer.compiled import kernel_parts
    >>> kernel_parts(lugre.observer(1.0)).code      # the intermittent law with a smooth ramp
    2
    """
    pert = observer.system.perturbation
    if not isinstance(pert, SymbolicPerturbation):
        raise _unsupported(f"a {type(pert).__name__} g (it must be a SymbolicPerturbation)")
    law = observer.update_law
    if law.state_size:
        raise _unsupported("an update law with a state")
    theta_set = law.parameter_set
    if not isinstance(theta_set, Box | Ball | Ellipsoid):
        raise _unsupported(f"Θ = {type(theta_set).__name__} (it must be a Box, Ball or "
                           "Ellipsoid)")
    if getattr(law, "saturation", None) is not None:
        raise _unsupported("an update law with saturation")
    if isinstance(law, ConstantLaw):
        return KernelParts(code=0, perturbation=pert, theta_set=theta_set)
    if isinstance(theta_set, Box):
        _diagonal_gain(law)
    if isinstance(law, GradientInversion):
        if not (law.perturbation is pert or law.perturbation == pert):
            raise _unsupported("GradientInversion with a g other than the observer's")
        M = None
        if law.M is not None:
            form = getattr(law.M, "sympy_form", None)
            if form is None:
                raise _unsupported(f"GradientInversion with a user M that is a Python callable "
                                   f"({type(law.M).__name__}) without sympy_form(g), its "
                                   "SymPy matrix in g's symbols")
            M = form(pert)
        return KernelParts(code=3, perturbation=pert, theta_set=theta_set, M=M)
    if not isinstance(law, IntermittentInversion):
        raise _unsupported(f"the update law {type(law).__name__}")
    code, ramp = 1, None
    if isinstance(law.l, SmoothRamp):
        code, ramp = 2, (float(law.l.low), float(law.l.high))
    elif law.l is not None:
        raise _unsupported("an excitation weight l other than smooth_ramp(low, high)")
    ts = as_theta_star(law.theta_star, pert)
    if ts is not None:
        return KernelParts(code=code, perturbation=pert, theta_set=theta_set, theta_star=ts,
                           ramp=ramp, freeze=law.on_invalid == "freeze")
    raise UnsupportedError(
        f"compile_observer: the θ* of {type(law).__name__} is a Python callable "
        f"({type(law.theta_star).__name__}), which cannot be compiled; build the law with a "
        "ThetaStar (thetahat.estimation.observer.laws.theta_star.ThetaStar.from_expr(expr, perturbation=g, "
        "phi=[...]) or from_perturbation), or give theta_star in the model file: both carry "
        "θ*'s SymPy form.")


# --------------------------------------------------------------------------- public API
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
    machine code; ``step`` advances by ``dt``, ``run`` by each step of its record. Build it with :func:`compile_observer`, which documents the
    parameters ``observer`` and ``dt``.

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

    def __init__(self, observer: ModifiedHighGainObserver, *, dt: float) -> None:
        _require_numba()
        if not isinstance(observer, ModifiedHighGainObserver):
            raise _unsupported(f"a {type(observer).__name__} (it must be a "
                               "ModifiedHighGainObserver)")
        h = positive_scalar("dt", dt)
        parts = kernel_parts(observer)
        ts = parts.theta_star
        plan = observer.plan(h)
        source = kernel_source(parts.perturbation, None if ts is None else ts.expr,
                               None if ts is None else ts.arguments, LAWS[parts.code],
                               M=parts.M, ellipsoid=parts.ellipsoid)
        for name, value in (("observer", observer), ("dt", h), ("theta_star", ts),
                            ("plan", plan), ("_kernel", _load(source)),
                            ("_args", kernel_arrays(parts, plan))):
            object.__setattr__(self, name, value)

    @property
    def state_size(self) -> int:
        """Length of the state vector (as :attr:`ModifiedHighGainObserver.state_size`)."""
        return self.observer.state_size

    def init(self, x_hat0: Any = None, theta_hat0: Any = None, z0: Any = None, *,
             x_hat_refined0: Any = None) -> FloatArray:
        """Initial state; see :meth:`ModifiedHighGainObserver.init` (same parameters).

        Parameters
        ----------
        x_hat0, theta_hat0, z0, x_hat_refined0
            As for :meth:`ModifiedHighGainObserver.init`.

        Returns
        -------
        ndarray, shape (state_size,)
        """
        return self.observer.init(x_hat0, theta_hat0, z0, x_hat_refined0=x_hat_refined0)

    def _raise(self, status: int, where: str) -> NoReturn:
        """The API's one failure behaviour for a step's status (:mod:`.status`)."""
        if status == Status.THETA_STAR:
            raise invalid_theta_star_error(type(self.observer.update_law).__name__, 1)
        raise divergence_error(where)        # DIVERGED or SINGULAR

    def step(self, state: Any, u: Any, y: Any, dt: float | None = None) -> FloatArray:
        """Advance the state by ``dt`` holding the samples (as the observer's ``step``).

        Parameters
        ----------
        state : array_like, shape (state_size,)
        u : array_like, shape (m,)
            Current input sample (``None`` when m = 0).
        y : array_like, shape (r,)
            Current output sample; NaN marks a missing sample under ``nan_policy="skip"``
            (the observers predict over it).
        dt : float, optional
            Time to the next sample: the compiled step length :attr:`dt` (to a relative
            ``DT_RTOL``); default :attr:`dt`. Part of the estimator protocol's signature.

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
        if dt is not None and not abs(float(dt) - self.dt) <= DT_RTOL * self.dt:
            raise DimensionError(f"the compiled observer steps dt = {self.dt!r}; got dt = "
                                 f"{dt!r}. Compile again with compile_observer(observer, "
                                 "dt=...), or use the observer's own step.")
        obs = self.observer
        lay = obs.layout
        s = _as_input("state", state, lay.size)
        u_ = _as_input("u", np.empty(0) if u is None else u, lay.m)
        y_ = _as_input("y", y, lay.r)
        present = bool(np.isfinite(y_).all())
        if not present:
            obs.check_samples(u, y)              # raises under nan_policy="raise"
        # the record of one step (the samples held): the same compiled loop as run's, so a
        # kernel has one entry point to compile
        ok = np.array([present, True])
        S, PHI = np.empty((2, lay.size)), np.empty((2, lay.k))
        status, _ = self._call(s, np.stack((u_, u_)), np.stack((y_, y_)),
                               np.array([self.dt]), ok, False, S, PHI)
        out = S[1]
        if status == 0 and float(out @ out) <= DIVERGENCE_BOUND ** 2:
            return out
        # something is wrong: find out what, with the observer's own checks and messages
        obs.check_state(state)
        obs.check_samples(u, y)
        self._raise(int(status) or Status.DIVERGED, "in this step")

    def estimate(self, state: Any, u: Any, y: Any) -> ObserverEstimate:
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

    def _call(self, s0: FloatArray, U: FloatArray, Y: FloatArray, dts: FloatArray,
              ok: NDArray[np.bool_], foh: bool, S: FloatArray, PHI: FloatArray
              ) -> tuple[int, int]:
        """The kernel over one piece of a record (the φ-matrices of its step lengths)."""
        plan_of, PH = phi_table(self.observer, dts, ok[:-1])
        P, P2, LP, flags = self._args
        W, rows, (Q1, Q2, R1, R2) = _scratch(self.observer.layout)
        # the φ-matrices are loaded into this thread's buffers: the shared arrays stay read
        P, P2 = P._replace(Phi1=Q1, Phi2=Q2), P2._replace(Phi1=R1, Phi2=R2)
        status, index = self._kernel.kernel_run(s0, U, Y, dts, ok, plan_of, PH, P, P2, LP,
                                                *flags, foh, W, rows, S, PHI)
        return int(status), int(index)

    def run(self, t: Any, u: Any, y: Any, *, state0: Any = None, hold: str = "zoh",
            progress: Callable[[int, int], None] | None = None) -> EstimateResult:
        """Run over sampled records (the loop runs in machine code).

        The samples may be spaced irregularly: each step uses the φ-matrices of its own length
        (one :class:`~thetahat.estimation.observer.plan.StepPlan` per distinct length, as the Python
        path), and missing samples (NaN in y under ``nan_policy="skip"``) are predicted over.

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
        hold : {"zoh", "foh"}
            Sample hold, as :meth:`ModifiedHighGainObserver.run`.
        progress : callable, optional
            ``progress(done, total)``, called every ``PROGRESS_EVERY`` samples and at the end.

        Returns
        -------
        EstimateResult
            As :meth:`ModifiedHighGainObserver.run` (agreement to rounding; see
            :func:`compile_observer`).

        Raises
        ------
        DimensionError
            Wrong shapes.
        OptionError
            Unknown ``hold``.
        NonFiniteError
            NaN or inf in t or u, NaN in y under ``nan_policy="raise"``, or the state
            diverged.
        UpdateLawError
            θ* invalid where l > 0 and ``on_invalid='raise'``.
        """
        if hold not in HOLDS:
            raise OptionError(f"hold must be one of {HOLDS}; got {hold!r}.")
        obs = self.observer
        lay = obs.layout
        t_, dts, U3, Y3, ok3 = obs.check_records(t, u, y)
        N = t_.shape[0]
        U, Y, dts = (_kernel_array(a) for a in (U3[0], Y3[0], dts))
        ok = np.ascontiguousarray(ok3[0], dtype=np.bool_)
        S = np.empty((N, lay.size))
        PHI = np.empty((N, lay.k))
        S[0] = _kernel_array(obs.init() if state0 is None else obs.check_state(state0))
        step = PROGRESS_EVERY if progress is not None else max(N - 1, 1)
        for a in range(0, max(N - 1, 1), step):
            if progress is not None:
                progress(a, N - 1)
            b = min(a + step, N - 1)
            status, index = self._call(S[a].copy(), U[a:b + 1], Y[a:b + 1], dts[a:b],
                                       ok[a:b + 1], hold == "foh", S[a:b + 1], PHI[a:b + 1])
            if status:
                i = a + index
                self._raise(status, f"in the step from t[{i}] = {t_[i]!r}")
        if progress is not None:
            progress(N - 1, N - 1)

        return states_result(lay, t_, S, PHI, ok)

    def __repr__(self) -> str:
        return (f"CompiledObserver(dt={self.dt!r}, observer={self.observer!r}, "
                f"kernel={self._kernel.__name__})")


def states_result(lay: StateLayout, t: FloatArray, S: FloatArray, PHI: FloatArray,
                  present: NDArray[np.bool_]) -> EstimateResult:
    """The record's EstimateResult from its state rows (read-only copies).

    Parameters
    ----------
    lay : StateLayout
    t : ndarray, shape (N,)
    S : ndarray, shape (N, state_size)
        The state at each sample.
    PHI : ndarray, shape (N, k)
        φ̂ at each sample.
    present : ndarray of bool, shape (N,)
        Whether each output sample was present (False: skipped).

    Returns
    -------
    EstimateResult

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> lay = lugre.observer().layout
    >>> res = states_result(lay, np.arange(3.0), np.zeros((3, lay.size)), np.zeros((3, lay.k)),
    ...                     np.array([True, False, True]))
    >>> res.theta_hat.shape, res.skipped.tolist(), res.theta_hat.flags.writeable
    ((3, 1), [False, True, False], False)
    """
    def frozen(a: NDArray[Any]) -> NDArray[Any]:
        out = np.array(a, copy=True)
        out.setflags(write=False)
        return out

    return EstimateResult(t=frozen(t), x_hat=frozen(S[:, lay.x]), phi_hat=frozen(PHI),
                          theta_hat=frozen(S[:, lay.theta]), skipped=frozen(~present),
                          diagnostics=ObserverDiagnostics(
                              x_hat_refined=frozen(S[:, lay.x2]) if lay.second else None))


_threads = threading.local()


def _scratch(lay: StateLayout) -> tuple[tuple[FloatArray, ...], tuple[FloatArray, ...],
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


def phi_table(observer: ModifiedHighGainObserver, dts: FloatArray, present: NDArray[np.bool_]
              ) -> tuple[NDArray[np.int64], tuple[FloatArray, ...]]:
    """The φ-matrices of a record's steps: which table entry each step uses, and the table.

    One entry per distinct (step length, sample present): Φ₁, Φ₂ of the observer's
    :meth:`~ModifiedHighGainObserver.plan` for that length — the corrected ones, or the
    prediction's over a missing sample — and the second observer's (zeros without one).

    Parameters
    ----------
    observer : ModifiedHighGainObserver
    dts : ndarray, shape (N - 1,)
        Step lengths.
    present : ndarray of bool, shape (N - 1,)
        Whether the sample at the start of each step is present.

    Returns
    -------
    plan_of : ndarray of int64, shape (N - 1,)
    table : tuple of ndarray
        (Φ₁, Φ₂, Φ₁ of the second observer, Φ₂ of the second observer), shapes (J, ·, ·).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> plan_of, table = phi_table(lugre.observer(), np.array([1e-3, 2e-3, 1e-3]),
    ...                            np.ones(3, dtype=bool))
    >>> plan_of.tolist(), table[0].shape
    ([0, 1, 0], (2, 3, 3))
    """
    lay = observer.layout
    keys = np.where(present, dts, -dts)          # a missing sample: its own entry
    uniq, inverse = np.unique(keys, return_inverse=True)
    q, n = lay.n + lay.k, lay.n
    table = tuple(np.zeros((uniq.size, d, d)) for d in (q, q, n, n))
    for j, key in enumerate(uniq.tolist()):
        plan = observer.plan(abs(key))
        sec = plan.second
        mats: tuple[FloatArray | None, ...]
        if key > 0:
            mats = (plan.Phi1, plan.Phi2, None if sec is None else sec.Phi1,
                    None if sec is None else sec.Phi2)
        else:
            mats = (plan.Phi1_open, plan.Phi2_open, None if sec is None else sec.Phi1_open,
                    None if sec is None else sec.Phi2_open)
        for dest, M in zip(table, mats):
            if M is not None:
                dest[j] = M[0]
    return np.ascontiguousarray(inverse.reshape(-1), dtype=np.int64), table


def kernel_arrays(parts: KernelParts, plan: StepPlan
                  ) -> tuple[PlanArrays, SecondArrays, LawArrays, tuple[bool, bool]]:
    """(P, P2, LP, flags): the plan's arrays for one row, the second observer's, the law's,
    and (a second observer is attached, its g sees C x̂₂): what the kernel takes.

    The named tuples of :mod:`~thetahat.estimation.kernels.kernel_args` (the fields every binding
    uses; see :mod:`~thetahat.estimation.observer.formulas` and
    :mod:`~thetahat.estimation.observer.laws.formulas`). Writable, C-contiguous copies: numba compiles
    one specialisation per array type.

    Parameters
    ----------
    parts : KernelParts
    plan : StepPlan
        For one row.

    Returns
    -------
    tuple
    """
    lay = plan.layout
    n, m, r, k, p = lay.n, lay.m, lay.r, lay.k, lay.p

    def own(a: Any) -> FloatArray:
        return np.array(a, dtype=np.float64, order="C", copy=True)

    P = PlanArrays(L=own(plan.L[0]), Bv=own(plan.Bv[0]), E=own(plan.E), C=own(plan.C),
                   A=own(plan.A), B=own(plan.B), K_x=own(plan.K_x[0]), KxC=own(plan.KxC[0]),
                   Phi1=own(plan.Phi1[0]), Phi2=own(plan.Phi2[0]))
    sec = plan.second
    if sec is None:                  # never read: flags[0] (a second observer) is False
        P2 = SecondArrays(*(np.zeros(shape) for shape in ((n, n), (n, m), (r, n), (n, k),
                                                          (n, r), (n, n), (n, n))))
    else:
        P2 = SecondArrays(A=own(sec.A), B=own(sec.B), C=own(sec.C), E=own(sec.E),
                          K_x=own(sec.K_x[0]), Phi1=own(sec.Phi1[0]), Phi2=own(sec.Phi2[0]))
    ps = parts.theta_set
    G = own(np.eye(p) if plan.Gamma is None else plan.Gamma[0])
    if isinstance(ps, Box):
        box: dict[str, Any] = {"lower": own(ps.lower), "upper": own(ps.upper)}
    else:                            # the metric Γ (ConstantLaw: Euclidean), Θ's c and Q
        box = {"lower": own(ps.center), "upper": own(ps.center), "ell": ellipsoid_data(ps),
               "pw": np.zeros((p + 2, p + 1)), "Gamma": np.eye(p) if parts.code == 0 else G}
    if parts.code == 0:
        LP = LawArrays(**box)
    elif parts.code == 3:
        LP = LawArrays(g=np.zeros(k), J=np.zeros((k, p)), Mt=np.zeros((p, k)),
                       GM=np.zeros((p, k)), f=np.zeros(p), K=np.zeros((p, p)),
                       Z=np.zeros((p + 1, p + 1)), Ex=np.zeros((p + 1, p + 1)),
                       T=np.zeros((p + 1, p + 1)), U=np.zeros((p + 1, p + 1)),
                       **{"Gamma": G, **box})
    else:                            # Γ = V diag(Λ) Vᵀ (a diagonal Γ: V = I exactly)
        low, high = parts.ramp if parts.ramp is not None else (0.0, 1.0)
        lam, V, VT = (own(a) for a in gain_eigen(G))
        LP = LawArrays(lam=lam, V=V, VT=VT, ts=np.zeros(p),
                       err=np.zeros(p), opts=np.array([low, high, parts.ramp is not None,
                                                       parts.freeze], dtype=np.float64), **box)
    return P, P2, LP, (sec is not None, sec is not None and sec.g_on_estimates)


def kernel_work(lay: StateLayout) -> tuple[tuple[FloatArray, ...], tuple[FloatArray, ...]]:
    """Scratch of the kernel: the formulas' work buffers and the rows (s, s⁺, u, y).

    Parameters
    ----------
    lay : StateLayout

    Returns
    -------
    W : tuple of ndarray
        :data:`~thetahat.estimation.observer.formulas.WORK`.
    rows : tuple of ndarray
        (s, s⁺, u, y, u₁, y₁) of one sample (u₁, y₁: the end of a first-order-hold step).
    """
    dims = {"NX": lay.n, "NY": lay.r, "NK": lay.k, "NP": lay.p, "NV": lay.m + lay.r,
            "NQ": lay.n + lay.k, "LS1": max(lay.law_size, 1)}
    W = tuple(np.zeros(tuple(dims[d] for d in shape)) for _, shape in WORK)
    return W, (np.zeros(lay.size), np.zeros(lay.size), np.zeros(max(lay.m, 1)),
               np.zeros(lay.r), np.zeros(max(lay.m, 1)), np.zeros(lay.r))


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
