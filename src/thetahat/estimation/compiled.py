"""A compiled fast path for the observer: one numba kernel per symbolic model (optional extra).

:func:`compile_observer` turns a :class:`~thetahat.estimation.observer.ModifiedHighGainObserver`
whose parts are all symbolic or structured into a :class:`CompiledObserver` whose ``step`` and
``run`` execute the observer's step (eqs. (3), (8) and the second observer of Sec. VI) as
machine code. Supported:

* g: a :class:`~thetahat.model.perturbation.SymbolicPerturbation` (g, ∂g/∂x, ∂g/∂θ and ∂g/∂v
  are printed to scalar Python code with SymPy's common-subexpression elimination);
* Θ: a :class:`~thetahat.model.paramset.Box`, with a diagonal Γ (the Γ⁻¹-weighted projection
  onto a box is then a clip);
* update laws: :class:`~thetahat.estimation.update_laws.ConstantLaw`,
  :class:`~thetahat.estimation.update_laws.IntermittentInversion` (l ≡ 1, as built by
  :func:`~thetahat.estimation.update_laws.AlgebraicInversion`, or the weight of
  :func:`~thetahat.estimation.update_laws.smooth_ramp`) whose θ* is a
  :class:`~thetahat.estimation.theta_star.ThetaStar` (from ``from_perturbation`` or
  ``ThetaStar.from_expr``), and
  :class:`~thetahat.estimation.update_laws.GradientInversion` with the default M = (∂g/∂θ)ᵀ;
  none of them with a ``saturation``;
* an attached :class:`~thetahat.estimation.redesign.SecondObserver`;
* a fixed step dt and the zero-order hold (Φ₁ is computed once).

Everything else raises :class:`~thetahat.errors.UnsupportedError` (a NotImplementedError) naming the part; use the Python observer.

The kernel is not a transcription: :mod:`~thetahat.estimation.scalar_backend` emits the
step's formulas (:mod:`~thetahat.estimation.formulas`,
:mod:`~thetahat.estimation.law_formulas`) as written, with the scalar primitives of one row
(:mod:`~thetahat.estimation.scalar_primitives`) and g, its Jacobians and θ* printed from their
SymPy expressions; this module checks the observer's parts, lays its
:class:`~thetahat.estimation.plan.StepPlan` out for the kernel (:func:`kernel_arrays`) and
calls it. The module is written to a cache directory (``$THETAHAT_CACHE_DIR``, default
``~/.cache/thetahat``, else a temporary directory) under a name that hashes its content, and
compiled with ``numba.njit(cache=True)``: the first compilation of a model and law formula
costs 20–40 s, later processes load the machine code from disk. The gains, ε, Γ, Θ, the
ramp, ``on_invalid``, the second observer and dt are data, not code: observers that differ
only in them share one kernel.

numba is the optional extra ``speed``; without it this module imports, and
:func:`compile_observer` raises :class:`ImportError`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from types import ModuleType
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from .._validate import as_vector, positive_scalar
from ..errors import DimensionError, MissingExtraError, UnsupportedError
from ..model.paramset import Box
from ..model.perturbation import SymbolicPerturbation
from .kernel_cache import load_module
from .observer import ModifiedHighGainObserver
from .protocol import EstimateResult, ObserverDiagnostics
from .results import ObserverEstimate
from .formulas import WORK
from .plan import StateLayout, StepPlan
from .scalar_backend import LAWS, kernel_source
from .step import DIVERGENCE_BOUND, divergence_error
from .theta_star import ThetaStar
from .update_laws import (ConstantLaw, GradientInversion, IntermittentInversion, SmoothRamp,
                          invalid_theta_star_error)

__all__ = ["CompiledObserver", "KernelParts", "compile_observer", "kernel_arrays", "kernel_parts",
           "kernel_work"]

FloatArray = NDArray[np.float64]

#: The samples given to ``CompiledObserver.run`` must be spaced by dt to this relative accuracy.
#: A uniform grid ``np.arange(N) * dt`` has spacings off by up to ~1e-12 relative (rounding);
#: the kernel uses Φ₁(dt) for every step, and each step's own spacing in the update law and
#: the ∂g/∂θ term, as the Python ``run`` does. 1e-9 changes Φ₁ by far less than the 1e-9
#: agreement promised between the two paths.
DT_RTOL = 1e-9

_SUPPORTED = ("supported: a SymbolicPerturbation g, a Box Θ with diagonal Γ, ConstantLaw, "
              "IntermittentInversion (l ≡ 1, i.e. AlgebraicInversion, or a smooth_ramp weight) "
              "with a ThetaStar θ*, GradientInversion with the default M, no saturation, no law "
              "state, an optional SecondObserver, fixed dt and zero-order hold")


def _require_numba() -> Any:
    try:
        import numba
    except ImportError as exc:  # pragma: no cover - exercised only without numba
        raise MissingExtraError("compile_observer needs numba, the optional extra 'speed': "
                          "pip install 'thetahat[speed]'. Without it, use the observer's own "
                          "run/step, or thetahat.estimation.batch_run.run_batch for many "
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
    box : Box
        Θ.
    theta_star : ThetaStar or None
        θ* of the inversion laws.
    ramp : tuple of float or None
        (low, high) of the smooth ramp l (code 2).
    freeze : bool
        The inversion law's ``on_invalid == "freeze"``.
    """

    code: int
    perturbation: SymbolicPerturbation
    box: Box
    theta_star: ThetaStar | None = None
    ramp: tuple[float, float] | None = None
    freeze: bool = False


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
    >>> from thetahat.estimation.compiled import kernel_parts
    >>> kernel_parts(lugre.observer(1.0)).code      # the intermittent law with a smooth ramp
    2
    """
    pert = observer.system.perturbation
    if not isinstance(pert, SymbolicPerturbation):
        raise _unsupported(f"a {type(pert).__name__} g (it must be a SymbolicPerturbation)")
    law = observer.update_law
    if law.state_size:
        raise _unsupported("an update law with a state")
    box = law.parameter_set
    if not isinstance(box, Box):
        raise _unsupported(f"Θ = {type(box).__name__} (it must be a Box)")
    if getattr(law, "saturation", None) is not None:
        raise _unsupported("an update law with saturation")
    if isinstance(law, ConstantLaw):
        return KernelParts(code=0, perturbation=pert, box=box)
    _diagonal_gain(law)
    if isinstance(law, GradientInversion):
        if law.M is not None:
            raise _unsupported("GradientInversion with a user M")
        if not (law.perturbation is pert or law.perturbation == pert):
            raise _unsupported("GradientInversion with a g other than the observer's")
        return KernelParts(code=3, perturbation=pert, box=box)
    if not isinstance(law, IntermittentInversion):
        raise _unsupported(f"the update law {type(law).__name__}")
    code, ramp = 1, None
    if isinstance(law.l, SmoothRamp):
        code, ramp = 2, (float(law.l.low), float(law.l.high))
    elif law.l is not None:
        raise _unsupported("an excitation weight l other than smooth_ramp(low, high)")
    ts = law.theta_star
    if isinstance(ts, ThetaStar):
        return KernelParts(code=code, perturbation=pert, box=box, theta_star=ts, ramp=ramp,
                           freeze=law.on_invalid == "freeze")
    raise UnsupportedError(
        f"compile_observer: the θ* of {type(law).__name__} is a Python callable "
        f"({type(ts).__name__}), which cannot be compiled; build the law with a ThetaStar "
        "(thetahat.estimation.theta_star.ThetaStar.from_expr(expr, perturbation=g, phi=[...]) "
        "or from_perturbation), which carries θ*'s SymPy form.")


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
    """A :class:`ModifiedHighGainObserver` compiled for one step length (zero-order hold).

    ``step`` and ``run`` compute what the observer's own ``step`` and ``run(hold="zoh")``
    compute, in machine code. Build it with :func:`compile_observer`, which documents the
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
        The fixed step length (s).
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
    _args: tuple[tuple[Any, ...], ...]

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
                               None if ts is None else ts.arguments, LAWS[parts.code])
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
        if status >= 2:
            raise invalid_theta_star_error(type(self.observer.update_law).__name__, status - 1)
        raise divergence_error(where)

    def step(self, state: Any, u: Any, y: Any, dt: float | None = None) -> FloatArray:
        """Advance the state by ``dt`` holding the samples (as the observer's ``step``).

        Parameters
        ----------
        state : array_like, shape (state_size,)
        u : array_like, shape (m,)
            Current input sample (``None`` when m = 0).
        y : array_like, shape (r,)
            Current output sample (finite: the compiled path does not skip missing samples).
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
            NaN or inf in the state, u or y, or the step diverged.
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
        # the record of one step (the samples held): the same compiled loop as run's, so a
        # kernel has one entry point to compile
        U, Y = np.stack((u_, u_)), np.stack((y_, y_))
        S, PHI = np.empty((2, lay.size)), np.empty((2, lay.k))
        status, _ = self._kernel.kernel_run(s, U, Y, np.array([self.dt]), *self._args[:3],
                                            *self._args[3], *_scratch(lay), S, PHI)
        out = S[1]
        if status == 0 and float(out @ out) <= DIVERGENCE_BOUND ** 2:
            return out
        # something is wrong: find out what, with the observer's own checks and messages
        obs.check_state(state)
        if not obs.check_samples(u, y)[2]:
            raise _no_prediction()
        self._raise(int(status) or 1, "in this step")

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

    def run(self, t: Any, u: Any, y: Any, *, state0: Any = None) -> EstimateResult:
        """Run over sampled records spaced by ``dt`` (the loop runs in machine code).

        Parameters
        ----------
        t : array_like, shape (N,)
            Sampling instants spaced by ``dt`` (to a relative ``DT_RTOL`` = 1e-9).
        u : array_like, shape (N, m) or (N,) when m = 1
            Input samples (``None`` when m = 0).
        y : array_like, shape (N, r) or (N,) when r = 1
            Output samples, finite.
        state0 : array_like, shape (state_size,), optional
            Initial state; default ``init()``.

        Returns
        -------
        EstimateResult
            As :meth:`ModifiedHighGainObserver.run` with ``hold="zoh"`` (agreement to rounding;
            see :func:`compile_observer`).

        Raises
        ------
        DimensionError
            Wrong shapes, or t not spaced by dt.
        NonFiniteError
            NaN or inf in t, u or y, or the state diverged.
        UpdateLawError
            θ* invalid where l > 0 and ``on_invalid='raise'``.
        """
        obs = self.observer
        lay = obs.layout
        t_, dts, U3, Y3, ok = obs.check_records(t, u, y)
        N = t_.shape[0]
        if N > 1 and not np.all(np.abs(dts - self.dt) <= DT_RTOL * self.dt):
            raise DimensionError(f"the compiled observer steps dt = {self.dt!r}; t has spacings "
                                 f"in [{float(dts.min())!r}, {float(dts.max())!r}]. Resample, "
                                 "or compile again with compile_observer(observer, dt=...).")
        if not ok.all():
            raise _no_prediction()
        U, Y, dts = (_kernel_array(a) for a in (U3[0], Y3[0], dts))
        s0 = _kernel_array(obs.init() if state0 is None else obs.check_state(state0))
        S = np.empty((N, lay.size))
        PHI = np.empty((N, lay.k))
        status, index = self._kernel.kernel_run(s0, U, Y, dts, *self._args[:3], *self._args[3],
                                                *_scratch(lay), S, PHI)
        if status:
            i = int(index)
            self._raise(int(status), f"in the step from t[{i}] = {t_[i]!r}")
        def frozen(a: NDArray[Any]) -> NDArray[Any]:
            out = np.array(a, copy=True)
            out.setflags(write=False)
            return out

        return EstimateResult(t=frozen(t_), x_hat=frozen(S[:, lay.x]), phi_hat=frozen(PHI),
                              theta_hat=frozen(S[:, lay.theta]),
                              skipped=frozen(np.zeros(N, dtype=bool)),
                              diagnostics=ObserverDiagnostics(
                                  x_hat_refined=frozen(S[:, lay.x2]) if lay.second else None))

    def __repr__(self) -> str:
        return (f"CompiledObserver(dt={self.dt!r}, observer={self.observer!r}, "
                f"kernel={self._kernel.__name__})")


_threads = threading.local()


def _scratch(lay: StateLayout) -> tuple[tuple[FloatArray, ...], tuple[FloatArray, ...]]:
    """:func:`kernel_work` of this thread (scratch only: nothing is carried between calls)."""
    cache: dict[StateLayout, Any] | None = getattr(_threads, "work", None)
    if cache is None:
        cache = _threads.work = {}
    hit = cache.get(lay)
    if hit is None:
        hit = cache[lay] = kernel_work(lay)
    return hit


def _no_prediction() -> UnsupportedError:
    return UnsupportedError("y contains NaN (nan_policy='skip'); the compiled observer does "
                               "not predict over missing samples: use the observer's own "
                               "step/run or run_batch.")


def kernel_arrays(parts: KernelParts, plan: StepPlan) -> tuple[tuple[Any, ...], ...]:
    """(P, P2, LP, flags): the plan's arrays for one row, the second observer's, the law's,
    and (a second observer is attached, its g sees C x̂₂): what the kernel takes.

    See :mod:`~thetahat.estimation.formulas` for P and P2 and
    :mod:`~thetahat.estimation.law_formulas` for the law's LP (with the box Θ and the ramp at
    :data:`~thetahat.estimation.scalar_backend.LAW_BOX`). Writable, C-contiguous copies:
    numba compiles one specialisation per array type.

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

    P = tuple(own(a) for a in (plan.L[0], plan.Bv[0], plan.E, plan.C, plan.A, plan.B,
                               plan.K_x[0], plan.KxC[0], plan.Phi1[0], plan.Phi2[0]))
    sec = plan.second
    if sec is None:                  # never read: flags[0] (a second observer) is False
        P2 = tuple(np.zeros(shape) for shape in ((n, n), (n, m), (r, n), (n, k), (n, r),
                                                (n, n), (n, n)))
    else:
        P2 = tuple(own(a) for a in (sec.A, sec.B, sec.C, sec.E, sec.K_x[0], sec.Phi1[0],
                                    sec.Phi2[0]))
    box = (own(parts.box.lower), own(parts.box.upper))
    G = own(np.eye(p) if plan.Gamma is None else plan.Gamma[0])
    LP: tuple[FloatArray, ...]
    if parts.code == 0:
        LP = box
    elif parts.code == 3:
        LP = (G, np.zeros(k), np.zeros((k, p)), np.zeros((p, k)), np.zeros((p, k)),
              np.zeros(p), np.zeros((p, p)), *(np.zeros((p + 1, p + 1)) for _ in range(4)),
              *box)
    else:                            # a diagonal Γ: Λ its diagonal, V = I
        low, high = parts.ramp if parts.ramp is not None else (0.0, 1.0)
        LP = (own(np.diagonal(G)), np.eye(p), np.eye(p), np.zeros(p), np.zeros(p), *box,
              np.array([low, high, parts.ramp is not None, parts.freeze], dtype=np.float64))
    return P, P2, LP, (sec is not None, sec is not None and sec.g_on_estimates)


def kernel_work(lay: StateLayout) -> tuple[tuple[FloatArray, ...], tuple[FloatArray, ...]]:
    """Scratch of the kernel: the formulas' work buffers and the rows (s, s⁺, u, y).

    Parameters
    ----------
    lay : StateLayout

    Returns
    -------
    W : tuple of ndarray
        :data:`~thetahat.estimation.formulas.WORK`.
    rows : tuple of ndarray
        (s, s⁺, u, y) of one sample.
    """
    dims = {"NX": lay.n, "NY": lay.r, "NK": lay.k, "NP": lay.p, "NV": lay.m + lay.r,
            "NQ": lay.n + lay.k, "LS1": max(lay.law_size, 1)}
    W = tuple(np.zeros(tuple(dims[d] for d in shape)) for _, shape in WORK)
    return W, (np.zeros(lay.size), np.zeros(lay.size), np.zeros(max(lay.m, 1)),
               np.zeros(lay.r))


def compile_observer(observer: ModifiedHighGainObserver, *, dt: float) -> CompiledObserver:
    """Compile an observer's step for a fixed ``dt`` with numba (the optional extra ``speed``).

    Parameters
    ----------
    observer : ModifiedHighGainObserver
        Observer (3) with update law (8) and optionally a second observer (Sec. VI); its parts
        must be of the supported kinds (see the module docstring). A law with a θ* needs a
        :class:`~thetahat.estimation.theta_star.ThetaStar` (it carries the SymPy form).
    dt : float
        The step length (s) > 0; ``run`` checks that its t is spaced by it.

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
    The kernel is the step's formulas (:mod:`~thetahat.estimation.formulas`) compiled for one
    row, reading the observer's :class:`~thetahat.estimation.plan.StepPlan` for ``dt``; it
    differs from the Python path only in the summation order of the small matrix products, a
    pivoted elimination in place of LAPACK's, a Taylor ``expm`` in place of SciPy's, and
    scalar code for g, its Jacobians and θ* (printed from the same SymPy expressions the
    Python path lambdifies). It applies the same divergence rule
    (:data:`~thetahat.estimation.formulas.DIVERGENCE_BOUND`) and raises the same errors.
    Measured on a shared 2-core machine: ≈ 0.2 µs per sample inside ``run``, a few µs per
    call of ``step`` from Python (validation and dispatch dominate). The first compilation of
    a model takes 20–40 s; later ones load from the cache.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.compiled import compile_observer
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
