"""Many observer runs at once: observer (3) with update law (8), vectorised over a batch axis.

:func:`run_batch` advances B independent copies of a
:class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver` over B records that share one
time grid — B noise seeds of a Monte-Carlo study, or B observers that differ only in their
gains (an ε sweep) or their adaptation gain Γ. Each step is the step of
:meth:`ModifiedHighGainObserver.run <thetahat.estimation.observer.observer.ModifiedHighGainObserver.run>`
(the exponential, linearly implicit step of :mod:`thetahat.estimation.observer.discretize`, the update
law's ``step``, z corrected by −∂g/∂θ Δθ̂, ZOH or FOH), written once for arrays with a leading
batch axis: g, its Jacobians and the update laws already evaluate whole batches, the matrix
products become batched ``matmul`` and the small linear solves one batched ``solve``. The
Python overhead of a step is paid once for all B runs. A run whose step fails stops there (its
status in :class:`BatchObserverResult`); the others go on.

The step is :func:`thetahat.estimation.observer.step.advance` — the same function
:class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver` runs as the batch of
one — over the observers' :class:`~thetahat.estimation.observer.plan.StepPlan` stacked along the
batch axis, eqs. (3a)–(3c) and (8). Γ per row reaches the update law through its public
``advance(..., Gamma=)``. Runs whose sample is missing (``nan_policy="skip"``) are advanced
separately for that step.

**Throughput** (DC motor of Sec. VIII with the second observer, 1 kHz, shared 2-core machine):
about 4·10³ observer steps per second for B = 1 (a loop of ``run``: 5.5·10³), 7·10⁴ for B = 20
and 3·10⁵ for B = 100, i.e. 50× a loop of ``run`` and 3700× a loop of
``scipy.integrate.solve_ivp(observer.rhs, method="LSODA")`` with a piecewise-constant input (80
steps per second). The compiled kernel of :mod:`thetahat.estimation.observer.compiled` runs one
observer at about 3·10⁶ steps per second. ``benchmarks/bench_step.py`` measures the per-step
cost of every path.

What lives here: :func:`run_batch`, its result :class:`BatchObserverResult` and the check
that the observers of a batch differ only in their gains. What it may import: the observer
(:mod:`.observer`), its plan, step and record loop (:mod:`.record_run`) and laws, and the
bottom of :mod:`thetahat.estimation`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import check_finite, readonly
from ...errors import DimensionError, IndexOutOfRangeError
from ..protocol import EstimateResult, ObserverDiagnostics
from ..status import Status
from .laws import ConstantLaw, UpdateLaw
from .observer import ModifiedHighGainObserver
from .plan import StepPlan, dt_key, stack_plans
from .record_run import Failure, integrate_record, integrate_records
from .step import readout

__all__ = ["BatchObserverResult", "run_batch"]

FloatArray = NDArray[np.float64]

#: Fields of the update laws that may differ between the observers of one batch (fields whose
#: name starts with "_" are derived from the public ones and are not compared).
GAIN_FIELDS = frozenset({"Gamma"})


@dataclass(frozen=True, slots=True, eq=False)
class BatchObserverResult:
    """Estimates of B observer runs over one time grid, returned by :func:`run_batch`.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sampling instants (shared).
    x_hat : ndarray, shape (B, N, n)
        State estimates x̂ of (3a).
    phi_hat : ndarray, shape (B, N, k)
        Perturbation estimates φ̂ = g(v, x̂, θ̂) + z of (3c).
    theta_hat : ndarray, shape (B, N, p)
        Parameter estimates θ̂ of (8).
    x_hat_refined : ndarray, shape (B, N, n), or None
        x̂₂ of the second observer of Sec. VI (None when none is attached).
    skipped : ndarray of bool, shape (B, N)
        Samples whose y held NaN (``nan_policy="skip"``).
    status : tuple of Status
        How each run ended (``OK``, or why it stopped: only with ``throw=False``).
    message : tuple of str
        Where, why and the fix, per run ("" when OK).
    failed_at : tuple of (int or None)
        The first row each run could not compute (None when OK); its rows from there on
        are NaN.

    Notes
    -----
    ``result[i]`` is the :class:`~thetahat.estimation.protocol.EstimateResult` of run i, the
    same object ``observers[i].run`` returns (up to rounding); ``len(result)`` is B.
    """

    t: FloatArray
    x_hat: FloatArray
    phi_hat: FloatArray
    theta_hat: FloatArray
    x_hat_refined: FloatArray | None
    skipped: NDArray[np.bool_]
    status: tuple[Status, ...] = ()
    message: tuple[str, ...] = ()
    failed_at: tuple[int | None, ...] = ()

    def __len__(self) -> int:
        return int(self.x_hat.shape[0])

    @property
    def ok(self) -> bool:
        """Every run processed every sample."""
        return all(s == Status.OK for s in self.status)

    def __getitem__(self, i: int) -> EstimateResult:
        """The result of run ``i`` as an :class:`~thetahat.estimation.protocol.EstimateResult`."""
        B = len(self)
        if not isinstance(i, (int, np.integer)) or not -B <= i < B:
            raise IndexOutOfRangeError(f"run index must be an integer in [-{B}, {B}); got {i!r}.")
        failed = bool(self.status) and self.status[i] != Status.OK
        return EstimateResult(
            t=self.t, x_hat=self.x_hat[i], phi_hat=self.phi_hat[i], theta_hat=self.theta_hat[i],
            skipped=self.skipped[i], diagnostics=ObserverDiagnostics(
                x_hat_refined=None if self.x_hat_refined is None else self.x_hat_refined[i]),
            status=self.status[i] if failed else Status.OK,
            message=self.message[i] if failed else "",
            failed_at=self.failed_at[i] if failed else None)

    def __repr__(self) -> str:
        B, N = self.x_hat.shape[:2]
        span = f"[{self.t[0]:.6g}, {self.t[-1]:.6g}]" if N else "[]"
        refined = "None" if self.x_hat_refined is None else f"{self.x_hat_refined.shape}"
        stopped = sum(s != Status.OK for s in self.status)
        return (f"BatchObserverResult(B={B}, N={N}, t={span}, x_hat={self.x_hat.shape}, "
                f"phi_hat={self.phi_hat.shape}, theta_hat={self.theta_hat.shape}, "
                f"x_hat_refined={refined}, skipped={int(self.skipped.sum())}"
                + (f", stopped={stopped}" if stopped else "") + ")")


# --------------------------------------------------------------------------- compatibility
def _equivalent(a: Any, b: Any) -> bool:
    """Structural equality of model parts (arrays by value, eq=False dataclasses by field)."""
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
                and a.shape == b.shape and bool(np.array_equal(a, b)))
    if type(a) is not type(b):
        return False
    if dataclasses.is_dataclass(a) and type(a).__eq__ is object.__eq__:
        return all(_equivalent(getattr(a, f.name), getattr(b, f.name))
                   for f in dataclasses.fields(a))
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 - anything that cannot compare is not equivalent
        return False


def _law_fields_equal(a: UpdateLaw, b: UpdateLaw) -> bool:
    """Same law up to Γ (and, for a ConstantLaw, the held value, which only sets ``init``)."""
    if type(a) is not type(b):
        return False
    ignore = GAIN_FIELDS | ({"theta"} if isinstance(a, ConstantLaw) else set())
    if not dataclasses.is_dataclass(a):
        return a is b
    return all(_equivalent(getattr(a, f.name), getattr(b, f.name))
               for f in dataclasses.fields(a)
               if f.name not in ignore and not f.name.startswith("_"))


def _check_compatible(observers: list[ModifiedHighGainObserver]) -> None:
    ref = observers[0]
    for i, obs in enumerate(observers[1:], start=1):
        what = None
        s0, s1 = ref.system, obs.system
        if not all(_equivalent(getattr(s0, a), getattr(s1, a)) for a in "ABCE"):
            what = "the system matrices (A, B, C, E)"
        elif not _equivalent(s0.perturbation, s1.perturbation):
            what = "the perturbation g"
        elif not _law_fields_equal(ref.update_law, obs.update_law):
            what = (f"the update law ({type(ref.update_law).__name__} vs "
                    f"{type(obs.update_law).__name__}; only Γ may differ)")
        elif (ref.second is None) != (obs.second is None):
            what = "whether a second observer is attached"
        elif (ref.second is not None and obs.second is not None
              and ref.second.g_on_estimates != obs.second.g_on_estimates):
            what = "the second observer's g_on_estimates"
        elif ref.nan_policy != obs.nan_policy:
            what = "nan_policy"
        elif ref.hold != obs.hold:
            what = "hold"
        if what is not None:
            raise DimensionError(f"run_batch: observers[{i}] differs from observers[0] in "
                                 f"{what}; a batch may differ only in the gains K_x, K_φ (ε), "
                                 f"Γ and the second observer's K_x. Run the others separately.")


class _Plans:
    """The stacked plan of the B observers per step length (computed once per dt)."""

    def __init__(self, observers: list[ModifiedHighGainObserver]) -> None:
        self.observers = observers
        self.cache: dict[float, StepPlan] = {}

    def __call__(self, dt: float) -> StepPlan:
        key = dt_key(dt)
        plan = self.cache.get(key)
        if plan is None:
            plan = stack_plans([o.plan(key) for o in self.observers])
            self.cache[key] = plan
        return plan


# --------------------------------------------------------------------------- public API
def _as_observers(observers: Any) -> list[ModifiedHighGainObserver]:
    if isinstance(observers, ModifiedHighGainObserver):
        return [observers]
    if isinstance(observers, Sequence) and not isinstance(observers, (str, bytes)):
        obs = list(observers)
        if obs and all(isinstance(o, ModifiedHighGainObserver) for o in obs):
            return obs
    raise DimensionError("run_batch: observers must be a ModifiedHighGainObserver or a "
                         f"non-empty sequence of them; got {type(observers).__name__}.")


def _initial(observers: list[ModifiedHighGainObserver], state0: Any, B: int,
             size: int) -> FloatArray:
    if state0 is None:
        if len(observers) == 1:
            return np.tile(observers[0].init(), (B, 1))
        return np.stack([o.init() for o in observers])
    s0 = np.asarray(state0, dtype=np.float64)
    if s0.ndim == 1:
        s0 = np.tile(s0, (B, 1))
    if s0.shape != (B, size):
        raise DimensionError(f"run_batch: state0 must have shape ({size},) or ({B}, {size}); "
                             f"got {np.shape(state0)}.")
    check_finite("state0", s0)
    return s0.copy()


def run_batch(observers: ModifiedHighGainObserver | Sequence[ModifiedHighGainObserver],
              t: ArrayLike, U: ArrayLike | None, Y: ArrayLike, *,
              state0: ArrayLike | None = None, throw: bool = True) -> BatchObserverResult:
    """Run B observers over B sampled records at once (vectorised over a batch axis).

    Parameters
    ----------
    observers : ModifiedHighGainObserver or sequence of B of them
        One observer (used for every record) or B observers that differ only in their gains
        K_x, K_φ (e.g. different ε), in Γ of the update law and in the second observer's
        gain; everything else (system, g, θ*, l, Θ, ``nan_policy``, ``hold``) must agree.
        Their ``hold`` is the batch's; their ``compiled`` and ``progress`` are not read.
    t : array_like, shape (N,)
        Shared sampling instants, strictly increasing.
    U : array_like, shape (B, N, m), or (B, N) when m = 1
        Input records (``None`` when m = 0).
    Y : array_like, shape (B, N, r), or (B, N) when r = 1
        Output records; NaN handled per the observers' ``nan_policy``.
    state0 : array_like, shape (state_size,) or (B, state_size), optional
        Initial states; default each observer's ``init()``.
    throw : bool, default True
        A run whose step fails: True raises its error (the earliest failed step, the lowest
        run of that step); False stops that run only, and the result says which, where and
        why (``status``, ``message``, ``failed_at``; its rows from there NaN).

    Returns
    -------
    BatchObserverResult
        ``result[i]`` agrees with ``observers[i].run(t, U[i], Y[i], ...)`` to rounding
        (measured 5e-16 relative on the DC motor of Sec. VIII over 20 s).

    Raises
    ------
    DimensionError
        Shapes disagree, ``t`` is not strictly increasing, or the observers differ in more
        than their gains.
    NonFiniteError
        NaN or inf in t or U; inf in Y; NaN in Y under ``nan_policy="raise"``; with
        ``throw``, a run diverged.
    UpdateLawError
        With ``throw``: θ* invalid where the weight is positive (``on_invalid='raise'``).

    Notes
    -----
    The step and the throughput: see the module docstring. A run that diverges fails with the
    same status, at the same sample, as its ``run``.

    Examples
    --------
    Three noise seeds of the paper's DC motor, one observer:

    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> runs = [lugre.simulate(seed=s, t_end=0.5) for s in range(3)]
    >>> obs = lugre.observer()
    >>> res = run_batch(obs, runs[0].t, [r.u for r in runs], [r.y for r in runs])
    >>> one = obs.run(runs[1].t, runs[1].u, runs[1].y)
    >>> res.theta_hat.shape, bool(np.allclose(res[1].x_hat, one.x_hat, rtol=1e-10, atol=1e-12))
    ((3, 501, 1), True)
    """
    obs = _as_observers(observers)
    _check_compatible(obs)
    ref = obs[0]
    t_, dts, Ub, Yb, ok = ref.check_records(t, U, Y, batch=len(obs) if len(obs) > 1 else -1)
    B = Yb.shape[0]
    s0 = _initial(obs, state0, B, ref.state_size)
    pert = ref.system.require_perturbation("run_batch")
    S, fails = _states(obs, pert, s0, t_, dts, Ub, Yb, ok, throw)
    X, PHI, TH, X2 = _readout(pert, ref, S, Ub, Yb, ok, fails)
    return BatchObserverResult(
        t=readonly(t_), x_hat=readonly(X), phi_hat=readonly(PHI), theta_hat=readonly(TH),
        x_hat_refined=None if X2 is None else readonly(X2), skipped=readonly(~ok, dtype=None),
        status=tuple(Status.OK if f is None else f.status for f in fails),
        message=tuple("" if f is None else f.message for f in fails),
        failed_at=tuple(None if f is None else f.failed_at for f in fails))


def _states(obs: list[ModifiedHighGainObserver], pert: Any, s0: FloatArray, t: FloatArray,
            dts: FloatArray, U: FloatArray, Y: FloatArray, ok: NDArray[np.bool_], throw: bool
            ) -> tuple[FloatArray, list[Failure | None]]:
    """The states (B, N, size) of the runs and how each ended."""
    ref = obs[0]
    foh = ref.hold == "foh"
    if s0.shape[0] > 1:
        return integrate_records(_Plans(obs), pert, ref.update_law, s0, t, dts, U, Y, ok, foh,
                                 throw=throw)
    S = np.full((1, t.size, s0.shape[1]), np.nan)     # the batch of one runs on (size,)
    S[0, 0] = s0[0]                                   # vectors, as run does
    fail = integrate_record(_Plans(obs), pert, ref.update_law, S[0], t, dts, U[0], Y[0], ok[0],
                            foh)
    if fail is not None and throw:
        raise fail.error()
    return S, [fail]


def _readout(pert: Any, ref: ModifiedHighGainObserver, S: FloatArray, U: FloatArray,
             Y: FloatArray, ok: NDArray[np.bool_], fails: list[Failure | None]
             ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """x̂, φ̂, θ̂, x̂₂ of every run; a stopped run's rows from its ``failed_at`` on are NaN."""
    if all(f is None for f in fails):
        return readout(pert, ref.system.C, S, U, Y, ok, ref.layout)
    lay = ref.layout
    PHI = np.full(S.shape[:2] + (lay.k,), np.nan)
    for b, f in enumerate(fails):
        rows = S.shape[1] if f is None else f.failed_at
        PHI[b, :rows] = readout(pert, ref.system.C, S[b, :rows], U[b, :rows], Y[b, :rows],
                                ok[b, :rows], lay)[1]
    return S[..., lay.x], PHI, S[..., lay.theta], S[..., lay.x2] if lay.second else None
