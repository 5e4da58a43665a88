"""One step of observer (3) with update law (8) and the second observer of Sec. VI: the NumPy
back end of the formulas of :mod:`~thetahat.estimation.observer.formulas`.

The formulas of one sample are written once in :mod:`~thetahat.estimation.observer.formulas`;
this module runs them printed for NumPy (:func:`~thetahat.estimation.kernels.modules.numpy_binding`:
one row, or B rows on a leading axis), bound to the model's
:class:`~thetahat.model.perturbation.Perturbation` and update law: the streaming
:meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.step` and
:meth:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver.run` are the batch of one,
:func:`~thetahat.estimation.observer.batch_run.run_batch` the batch of B; the constant data come from a
:class:`~thetahat.estimation.observer.plan.StepPlan`. What is NumPy-specific lives here: the choice of
the plan per step length, the rows of a batch that miss a sample (predicted over, the NaN
policy), the per-row report of a divergence, and the readout.
"""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import NonFiniteError, UnsupportedError
from ...model.perturbation import Perturbation
from . import formulas
from .discretize import IMPLICITNESS
from .formulas import DIVERGENCE_BOUND
from .laws.inversion import invalid_theta_star_error
from ..kernels.kernel_args import (LawArrays, PlanArrays, SecondArrays, WorkArrays, dimensions,
                                   work_arrays)
from ..kernels.modules import numpy_binding
from ..kernels.printer import Program
from ..kernels.subset import External, definition
from .plan import SecondPlan, StateLayout, StepPlan
from ..status import Status, status_constants
from .laws import UpdateLaw

__all__ = ["DIVERGENCE_BOUND", "advance", "diverged", "divergence_error", "integrate",
           "observer_forcing", "program", "readout", "second_advance", "second_forcing"]

FloatArray = NDArray[np.float64]

_scratch = threading.local()


@functools.cache
def program() -> Program:
    """The observer's formulas (:data:`formulas.FORMULAS <thetahat.estimation.observer.formulas.FORMULAS>`)
    as one program, the model functions and the law's step provided by the binding.

    Returns
    -------
    Program

    Examples
    --------
    >>> sorted(program().viewed["implicit_step"])
    ['out', 's']
    """
    calls = {name: External(params, frozenset(params) & formulas.VIEWED)
             for name, params in formulas.CALLS.items()}
    return Program({name: definition(fn) for name, fn in formulas.FORMULAS.items()}, calls)


@functools.cache
def _within_bound() -> Callable[..., Any]:
    """The divergence rule on NumPy rows (:func:`formulas.within_bound`)."""
    prog = program()
    within: Callable[..., Any] = numpy_binding(
        prog, "within_bound", prog, ["within_bound"], "batch",
        lambda: {"BOUND_SQ": DIVERGENCE_BOUND ** 2})["within_bound"]
    return within


def _model_functions(pert: Perturbation) -> dict[str, Any]:
    """The model functions of the formulas, evaluated by the perturbation's NumPy methods
    (x̂ and θ̂ arrive as views of the state)."""
    def g_dx(v: FloatArray, x: FloatArray, th: FloatArray, g: FloatArray,
             Gx: FloatArray) -> None:
        g[...] = pert.g(v, x, th)
        Gx[...] = pert.dg_dx(v, x, th)

    def g_val(v: FloatArray, x: FloatArray, th: FloatArray, g: FloatArray) -> None:
        g[...] = pert.g(v, x, th)

    def dg_dy(v: FloatArray, x: FloatArray, th: FloatArray, Gy: FloatArray) -> None:
        m = pert.dims[1]
        Gy[...] = np.asarray(pert.dg_dv(v, x, th))[..., m:]

    def dg_dtheta(v: FloatArray, x: FloatArray, th: FloatArray, Gth: FloatArray) -> None:
        Gth[...] = pert.dg_dtheta(v, x, th)

    return {"g_dx": g_dx, "g_val": g_val, "dg_dy": dg_dy, "dg_dtheta": dg_dtheta}


def _law_function(law: UpdateLaw, lay: StateLayout) -> Callable[..., int]:
    """``law_step`` of the formulas: the law's :meth:`~UpdateLaw.advance` (one Γ per row)."""
    size = lay.law_size

    def law_step(LP: LawArrays, v: FloatArray, x: FloatArray, phi: FloatArray,
                 th: FloatArray, dt: float, thn: FloatArray, lsn: FloatArray) -> int:
        G = LP.Gamma_rows
        state = lsn[..., :size]
        if G is None:
            th1, ls1 = law.advance(v, x, phi, th, state, dt)
        else:
            th1, ls1 = law.advance(v, x, phi, th, state, dt, Gamma=G)
        thn[...] = th1
        lsn[..., :size] = ls1
        return 0

    return law_step


def _constants(lay: StateLayout) -> dict[str, Any]:
    """The dimensions and constants the formulas read."""
    return {**dimensions(lay.n, lay.m, lay.r, lay.k, lay.p, lay.law_size),
            "IMPLICITNESS": IMPLICITNESS, "BOUND_SQ": DIVERGENCE_BOUND ** 2,
            **status_constants()}


#: What the formulas are printed for without a law (the forcing of ``rhs``, Sec. VI alone),
#: and with one.
_ROOTS = {False: ("observer_forcing", "second_forcing", "second_step"), True: ("advance",)}


def _binding(pert: Perturbation, law: UpdateLaw | None, lay: StateLayout, row: bool
             ) -> dict[str, Any]:
    """The formulas printed for NumPy (one row, or a batch) and bound to the perturbation
    and the law (kept while in use)."""
    def names() -> dict[str, Any]:
        out: dict[str, Any] = {**_model_functions(pert), **_constants(lay)}
        if law is not None:       # the binding holds the law: its id stays unique
            out["law_step"] = _law_function(law, lay)
        return out

    prog = program()
    return numpy_binding(pert, (id(law), lay, row), prog, _ROOTS[law is not None],
                         "row" if row else "batch", names)


def _work(lay: StateLayout, lead: tuple[int, ...]) -> WorkArrays:
    """Scratch buffers of :func:`formulas.advance` for rows of shape ``lead`` (per thread)."""
    cache: dict[Any, WorkArrays] | None = getattr(_scratch, "work", None)
    if cache is None:
        cache = _scratch.work = {}
    key = (lay.n, lay.m, lay.r, lay.k, lay.p, lay.law_size, lead)
    W = cache.get(key)
    if W is None:
        W = work_arrays(dimensions(lay.n, lay.m, lay.r, lay.k, lay.p, lay.law_size), lead)
        if len(cache) > 32:
            cache.clear()
        cache[key] = W
    return W


def _shared(M: FloatArray) -> FloatArray:
    """A plan array without its batch axis when all rows share it."""
    return M[0] if M.ndim == 3 and M.shape[0] == 1 else M


#: P and P2 per (plan, correct), kept while the plan is in use.
_ARRAYS_KEPT = 64
_arrays: OrderedDict[tuple[int, bool], tuple[object, tuple[Any, ...]]] = OrderedDict()
_arrays_lock = threading.Lock()


def _cached(plan: StepPlan | SecondPlan, correct: bool, build: Callable[[], tuple[Any, ...]]
            ) -> tuple[Any, ...]:
    key = (id(plan), correct)
    hit = _arrays.get(key)
    if hit is not None and hit[0] is plan:
        return hit[1]
    arrays = build()
    with _arrays_lock:
        _arrays[key] = (plan, arrays)
        if len(_arrays) > _ARRAYS_KEPT:
            _arrays.popitem(last=False)
    return arrays


def _plan_arrays(plan: StepPlan, correct: bool) -> tuple[FloatArray, ...]:
    """P of the formulas: the plan's arrays with the φ-matrices of this step."""
    def build() -> tuple[FloatArray, ...]:
        Phi1, Phi2 = (plan.Phi1, plan.Phi2) if correct else _prediction_phis(plan)
        return PlanArrays(L=_shared(plan.L), Bv=_shared(plan.Bv), E=plan.E, C=plan.C,
                          A=plan.A, B=plan.B, K_x=_shared(plan.K_x), KxC=_shared(plan.KxC),
                          Phi1=_shared(Phi1), Phi2=_shared(Phi2))
    return _cached(plan, correct, build)


def _second_arrays(plan: SecondPlan | None, correct: bool) -> tuple[Any, ...]:
    """P2 of the formulas (empty without a second observer)."""
    if plan is None:
        return ()

    def build() -> tuple[FloatArray, ...]:
        assert plan is not None
        Phi1, Phi2 = (plan.Phi1, plan.Phi2) if correct else _prediction_phis(plan)
        return SecondArrays(A=plan.A, B=plan.B, C=plan.C, E=plan.E, K_x=_shared(plan.K_x),
                            Phi1=_shared(Phi1), Phi2=_shared(Phi2))
    return _cached(plan, correct, build)


def _prediction_phis(plan: StepPlan | SecondPlan) -> tuple[FloatArray, FloatArray]:
    """Φ₁, Φ₂ of the prediction over a missing sample (a plan built with ``predict``)."""
    if plan.Phi1_open is None or plan.Phi2_open is None:
        raise UnsupportedError("this plan has no prediction over a missing sample (built with "
                               "predict=False, as for nan_policy='raise'); build the observer "
                               "with nan_policy='skip' to step over missing samples.")
    return plan.Phi1_open, plan.Phi2_open


def observer_forcing(plan: StepPlan, pert: Perturbation, xz: FloatArray, th: FloatArray,
                     u: FloatArray, y: FloatArray, correct: bool
                     ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Forcing F of (3a)–(3b) on (x̂, z) without the θ̂ term; returns (F, φ̂, ∂g/∂x, v).

    :func:`formulas.observer_forcing <thetahat.estimation.observer.formulas.observer_forcing>` on
    NumPy arrays (for the continuous-time :meth:`rhs
    <thetahat.estimation.observer.observer.ModifiedHighGainObserver.rhs>`).

    Parameters
    ----------
    plan : StepPlan
    pert : Perturbation
        g and its Jacobians.
    xz : ndarray, shape (..., n + k)
    th : ndarray, shape (..., p)
    u : ndarray, shape (..., m)
    y : ndarray, shape (..., r)
    correct : bool

    Returns
    -------
    F : ndarray, shape (..., n + k)
    phi_hat : ndarray, shape (..., k)
        φ̂ = g(v, x̂, θ̂) + z (3c).
    Gx : ndarray, shape (..., k, n)
    v : ndarray, shape (..., m + r)
    """
    lay = plan.layout
    n, k = lay.n, lay.k
    s = np.concatenate((xz, th), axis=-1)
    lead = s.shape[:-1]
    env = _binding(pert, None, lay, lead == ())
    v, g = np.empty(lead + (lay.m + lay.r,)), np.empty(lead + (k,))
    Gx, F = np.empty(lead + (k, n)), np.empty(lead + (n + k,))
    env["observer_forcing"](_plan_arrays(plan, True), s, u, y, correct, v, g, Gx, F,
                            np.empty(lead + (lay.r,)),
                            np.empty(lead + (n,)))
    return F, g + xz[..., n:], Gx, v


def second_forcing(plan: SecondPlan, pert: Perturbation, x2: FloatArray, u: FloatArray,
                   y: FloatArray, th: FloatArray, correct: bool
                   ) -> tuple[FloatArray, FloatArray]:
    """F = A x̂₂ + B u + E g(v̄, x̂₂, θ̂) + K_x2 (y − C x̂₂) (Sec. VI); returns (F, v̄).

    :func:`formulas.second_forcing <thetahat.estimation.observer.formulas.second_forcing>` on NumPy
    arrays.

    Parameters
    ----------
    plan : SecondPlan
    pert : Perturbation
    x2 : ndarray, shape (..., n)
    u : ndarray, shape (..., m)
    y : ndarray, shape (..., r)
    th : ndarray, shape (..., p)
        θ̂ at the start of the step.
    correct : bool

    Returns
    -------
    F : ndarray, shape (..., n)
    v_bar : ndarray, shape (..., m + r)
    """
    lay = _second_layout(pert)
    s = _second_state(lay, x2, th)
    lead = s.shape[:-1]
    env = _binding(pert, None, lay, lead == ())
    v2, F2 = np.empty(lead + (lay.m + lay.r,)), np.empty(lead + (lay.n,))
    env["second_forcing"](_second_arrays(plan, True), s, u, y, correct, plan.g_on_estimates,
                          v2, np.empty(lead + (lay.k,)), np.empty(lead + (lay.k, lay.n)), F2,
                          np.empty(lead + (lay.r,)))
    return F2, v2


def _second_layout(pert: Perturbation) -> StateLayout:
    n, m, r, p, k = pert.dims
    return StateLayout(n=n, m=m, r=r, k=k, p=p, second=True, law_size=0)


def _second_state(lay: StateLayout, x2: FloatArray, th: FloatArray) -> FloatArray:
    """A state row col(0, 0, θ̂, x̂₂) for the second observer's formulas alone."""
    lead = np.broadcast_shapes(x2.shape[:-1], th.shape[:-1])
    s = np.zeros(lead + (lay.size,))
    s[..., lay.theta] = th
    s[..., lay.x2] = x2
    return s


def second_advance(plan: SecondPlan, pert: Perturbation, x2: FloatArray, u0: FloatArray,
                   y0: FloatArray, th: FloatArray, dt: float, correct: bool,
                   u1: FloatArray | None = None, y1: FloatArray | None = None) -> FloatArray:
    """One step of the second observer alone (ZOH, or FOH to ``u1``, ``y1``); shape (..., n).

    The second observer's part of :func:`formulas.advance
    <thetahat.estimation.observer.formulas.advance>`.

    Parameters
    ----------
    plan : SecondPlan
    pert : Perturbation
    x2 : ndarray, shape (..., n)
    u0, y0 : ndarray, shapes (..., m), (..., r)
        Samples at the start of the step.
    th : ndarray, shape (..., p)
    dt : float
    correct : bool
        False: the sample is missing (prediction).
    u1, y1 : ndarray, optional
        Samples at the end of the step (first-order hold).

    Returns
    -------
    ndarray, shape (..., n)
    """
    lay = _second_layout(pert)
    s = _second_state(lay, x2, th)
    lead = s.shape[:-1]
    env = _binding(pert, None, lay, lead == ())
    out = np.empty_like(s)
    env["second_step"](_second_arrays(plan, correct), s, u0, y0, u1,
                       y0 if y1 is None else y1, dt, correct, u1 is not None,
                       plan.g_on_estimates, out, _work(lay, lead))
    return out[..., lay.x2]


def advance(plan: StepPlan, pert: Perturbation, law: UpdateLaw, s: FloatArray, u0: FloatArray,
            y0: FloatArray, dt: float, correct: bool, u1: FloatArray | None = None,
            y1: FloatArray | None = None) -> FloatArray:
    """One step of the whole estimator for B rows: :func:`formulas.advance
    <thetahat.estimation.observer.formulas.advance>` on NumPy arrays; shape (B, size).

    Rows whose φ̂ is not finite come back as NaN (the caller reports the divergence).

    Parameters
    ----------
    plan : StepPlan
        Plan of the B rows for this step length.
    pert : Perturbation
    law : UpdateLaw
        Shared by the rows; Γ per row comes from ``plan.Gamma``.
    s : ndarray, shape (B, size) or (size,)
    u0, y0 : ndarray, shapes (B, m), (B, r)
        Samples at the start of the step (y0 finite when ``correct``).
    dt : float
        This step's length (the plan's φ-matrices are for ``plan.dt``, equal to 12 digits).
    correct : bool
        False: the samples of every row are missing (prediction over the step).
    u1, y1 : ndarray, optional
        Samples at the end of the step: first-order hold (``y1`` ignored when not correct).

    Returns
    -------
    ndarray, shape (B, size) or (size,)

    Raises
    ------
    UpdateLawError
        θ* invalid where the weight is positive (``on_invalid='raise'``).
    """
    lay = plan.layout
    env = _binding(pert, law, lay, s.ndim == 1)
    W = _work(lay, s.shape[:-1])
    out = np.empty_like(s)
    G = plan.Gamma if plan.Gamma is not None and plan.Gamma.shape[0] > 1 else None
    second = plan.second is not None
    foh = u1 is not None
    status = env["advance"](
        _plan_arrays(plan, correct), _second_arrays(plan.second, correct),
        LawArrays(Gamma_rows=G), s, u0, y0,
        u1, y0 if (y1 is None or not correct) else y1, dt, correct, foh, second,
        plan.second is not None and plan.second.g_on_estimates, out, W)
    if status == Status.OK:
        return out
    if status == Status.THETA_STAR:   # the law's own check raises first; kept for safety
        raise invalid_theta_star_error(type(law).__name__, None)
    # DIVERGED (φ̂ not finite) or SINGULAR (an implicit step): those rows become NaN, which
    # the callers report as the divergence of that step (divergence_error)
    if s.ndim == 1:
        return np.full_like(s, np.nan)
    if status == Status.SINGULAR:     # which rows: each row on its own
        out = np.empty_like(s)
        for i in range(s.shape[0]):
            out[i] = advance(plan.rows(np.array([i])), pert, law, s[i:i + 1], u0[i:i + 1],
                             y0[i:i + 1], dt, correct, None if u1 is None else u1[i:i + 1],
                             None if y1 is None else y1[i:i + 1])[0]
        return out
    finite = np.isfinite(W.phi).all(axis=-1)
    out = np.full_like(s, np.nan)
    good = np.flatnonzero(finite)
    if good.size:
        out[good] = advance(plan.rows(good), pert, law, s[good], u0[good], y0[good], dt,
                            correct, None if u1 is None else u1[good],
                            None if y1 is None else y1[good])
    return out


def diverged(s: FloatArray) -> NDArray[np.bool_]:
    """Rows of ``s`` (shape (B, size)) that have diverged: norm > DIVERGENCE_BOUND, or NaN/inf.

    Parameters
    ----------
    s : ndarray, shape (B, size) or (size,)

    Returns
    -------
    ndarray of bool, shape (B,) or () (a 0-d array for one state)

    Examples
    --------
    >>> import numpy as np
    >>> diverged(np.array([[1.0, 2.0], [1e101, 0.0], [np.nan, 0.0]])).tolist()
    [False, True, True]
    """
    with np.errstate(over="ignore", invalid="ignore"):
        within = _within_bound()
        if s.ndim == 1:
            return np.array(not within(s, s.shape[-1]))
        if within(s.reshape(-1), s.size):          # every row is fine: one dot product decides
            return np.zeros(s.shape[0], dtype=bool)
        return ~within(s, s.shape[-1])


def divergence_error(where: str) -> NonFiniteError:
    """The error every back end raises when a step diverges (``where`` says which step).

    Parameters
    ----------
    where : str
        E.g. ``"in the step from t[12] = 0.012"``.

    Returns
    -------
    NonFiniteError
    """
    return NonFiniteError(f"the observer state diverged (NaN, inf, a norm above "
                          f"{DIVERGENCE_BOUND:g}, or a singular implicit step) {where}: the "
                          "gains are too high for this dt (decrease dt or increase ε), or the "
                          "update law / data scaling is off.")


def integrate(plan_for: Callable[[float], StepPlan], pert: Perturbation, law: UpdateLaw,
              s0: FloatArray, t: FloatArray, dts: FloatArray, U: FloatArray, Y: FloatArray,
              ok: NDArray[np.bool_], foh: bool) -> FloatArray:
    """The states of B rows over a shared time grid; shape (B, N, size).

    Parameters
    ----------
    plan_for : callable
        ``plan_for(dt)`` -> the StepPlan of the B rows for that step length.
    pert, law
        As for :func:`advance`.
    s0 : ndarray, shape (B, size)
    t : ndarray, shape (N,)
    dts : ndarray, shape (N - 1,)
    U : ndarray, shape (B, N, m)
    Y : ndarray, shape (B, N, r)
    ok : ndarray of bool, shape (B, N)
        Samples whose y is present (the others are predicted over).
    foh : bool
        First-order hold.

    Returns
    -------
    ndarray, shape (B, N, size)

    Raises
    ------
    NonFiniteError
        A row diverged (:func:`diverged`); the message names the step (and the row when B > 1).
    """
    B, N = U.shape[:2]
    S = np.empty((B, N, s0.shape[1]))
    S[:, 0] = s = s0
    every = np.asarray(ok.all(axis=0), dtype=np.bool_)
    plans: dict[float, StepPlan] = {}
    if B == 1:                        # the batch of one runs on (size,) vectors
        _integrate_one(plan_for, plans, pert, law, S[0], t, dts, U[0], Y[0], ok[0], foh)
        return S
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for i in range(N - 1):
            dt = float(dts[i])
            plan = plans.get(dt)
            if plan is None:
                plan = plans[dt] = plan_for(dt)
            u1 = U[:, i + 1] if foh else None
            y1 = (Y[:, i + 1] if every[i + 1] else np.where(ok[:, i + 1, None], Y[:, i + 1],
                                                             Y[:, i])) if foh else None
            if every[i]:
                s = advance(plan, pert, law, s, U[:, i], Y[:, i], dt, True, u1, y1)
            else:
                nxt = np.empty_like(s)
                for flag in (True, False):
                    rows = np.flatnonzero(ok[:, i] == flag)
                    if rows.size:
                        nxt[rows] = advance(
                            plan.rows(rows), pert, law, s[rows], U[rows, i], Y[rows, i], dt,
                            flag, None if u1 is None else u1[rows],
                            None if y1 is None else y1[rows])
                s = nxt
            bad = diverged(s)
            if bad.any():
                raise divergence_error(f"of run {int(np.argmax(bad))} in the step from "
                                       f"t[{i}] = {t[i]!r}")
            S[:, i + 1] = s
    return S


def _integrate_one(plan_for: Callable[[float], StepPlan], plans: dict[float, StepPlan],
                   pert: Perturbation, law: UpdateLaw, S: FloatArray, t: FloatArray,
                   dts: FloatArray, U: FloatArray, Y: FloatArray, ok: NDArray[np.bool_],
                   foh: bool) -> None:
    """:func:`integrate` for one row, into S (N, size) whose row 0 holds the initial state."""
    s = S[0]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for i in range(S.shape[0] - 1):
            dt = float(dts[i])
            plan = plans.get(dt)
            if plan is None:
                plan = plans[dt] = plan_for(dt)
            if foh:
                s = advance(plan, pert, law, s, U[i], Y[i], dt, bool(ok[i]), U[i + 1],
                            Y[i + 1] if ok[i + 1] else Y[i])
            else:
                s = advance(plan, pert, law, s, U[i], Y[i], dt, bool(ok[i]))
            if diverged(s):
                raise divergence_error(f"in the step from t[{i}] = {t[i]!r}")
            S[i + 1] = s


def readout(pert: Perturbation, C: FloatArray, S: FloatArray, U: FloatArray, Y: FloatArray,
            ok: NDArray[np.bool_], lay: StateLayout
            ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """(x̂, φ̂ = g(v, x̂, θ̂) + z, θ̂, x̂₂ or None) of states S (..., N, size); y ← C x̂ if missing.

    Parameters
    ----------
    pert : Perturbation
    C : ndarray, shape (r, n)
    S : ndarray, shape (..., N, size)
    U : ndarray, shape (..., N, m)
    Y : ndarray, shape (..., N, r)
    ok : ndarray of bool, shape (..., N)
    lay : StateLayout

    Returns
    -------
    X : ndarray, shape (..., N, n)
    PHI : ndarray, shape (..., N, k)
    TH : ndarray, shape (..., N, p)
    X2 : ndarray, shape (..., N, n), or None
    """
    X, Z, TH = S[..., lay.x], S[..., lay.z], S[..., lay.theta]
    Yv = np.where(ok[..., None], Y, X @ C.T)
    V = np.concatenate((U, Yv), axis=-1)
    PHI = np.asarray(pert.g(V, X, TH), dtype=np.float64) + Z
    X2 = S[..., lay.x2] if lay.second else None
    return X, PHI, TH, X2
