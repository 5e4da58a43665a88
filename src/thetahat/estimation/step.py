"""One step of observer (3) with update law (8) and the second observer of Sec. VI, written once.

Every function here works on B rows at once (a leading batch axis): the streaming
:meth:`~thetahat.estimation.observer.ModifiedHighGainObserver.step` and
:meth:`~thetahat.estimation.observer.ModifiedHighGainObserver.run` are the batch of one,
:func:`~thetahat.estimation.batch_run.run_batch` the batch of B; the constant data come from a
:class:`~thetahat.estimation.plan.StepPlan`. The pieces of one sample:

* the forcing F of (3a)–(3b) on (x̂, z) (:func:`observer_forcing`) and the state-dependent part
  N of its Jacobian (:func:`observer_jacobian`), for a measured or a missing sample;
* the update law's :meth:`~thetahat.estimation.update_laws.UpdateLaw.advance` (θ̂, law state),
  and z corrected by −∂g/∂θ Δθ̂, the discrete form of the first term of (3b);
* the second observer (:func:`second_forcing`), driven by θ̂ at the start of the step;
* the exponential, linearly implicit step of :mod:`~thetahat.estimation.discretize`
  (:func:`~thetahat.estimation.discretize.batched_step`), ZOH or FOH;
* the NaN policy (a missing sample is a prediction: y ← C x̂, θ̂ frozen, z constant) and the
  divergence rule (:data:`DIVERGENCE_BOUND`, :func:`diverged`), which every back end applies in
  the same way.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..errors import NonFiniteError, UnsupportedError
from ..model.perturbation import Perturbation
from .discretize import batched_step
from .plan import SecondPlan, StateLayout, StepPlan
from .update_laws import UpdateLaw

__all__ = ["DIVERGENCE_BOUND", "advance", "diverged", "divergence_error", "integrate",
           "observer_forcing", "observer_jacobian", "readout", "second_advance",
           "second_forcing", "second_jacobian"]

FloatArray = NDArray[np.float64]

#: A row of the state has diverged when its Euclidean norm exceeds this (or is not finite).
#: No observer quantity of a sensibly scaled problem comes near it, and its square (1e200)
#: stays finite, so one dot product per step decides. The same rule in every back end makes
#: them report a divergence at the same sample (the old paths disagreed: NonFiniteError in
#: ``run`` while ``run_batch`` returned values near 1e84 at ε = 0.001).
DIVERGENCE_BOUND = 1e100


def _mv(M: FloatArray, x: FloatArray) -> FloatArray:
    """Plan matrix times vectors: M (B|1, a, b), x (b,) or (B, b) -> (a,) or (B, a)."""
    if M.shape[0] == 1:
        return x @ M[0].T
    return np.matmul(M, x[..., None])[..., 0]


def _gmv(G: FloatArray, w: FloatArray) -> FloatArray:
    """Jacobian times vectors: G (k, n) or (B, k, n), w (n,) or (B, n)."""
    if w.ndim == 1:
        return G @ w
    return np.matmul(G, w[..., None])[..., 0]


def _shared(M: FloatArray) -> FloatArray:
    """A plan matrix without its batch axis when the rows share it."""
    return M[0] if M.shape[0] == 1 else M


def observer_forcing(plan: StepPlan, pert: Perturbation, xz: FloatArray, th: FloatArray,
                     u: FloatArray, y: FloatArray, correct: bool
                     ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Forcing F of (3a)–(3b) on (x̂, z) without the θ̂ term; returns (F, φ̂, ∂g/∂x, v).

    Measured sample: F = L col(x̂, z) + [[B, K_x], [0, K_φ]] v + col(E g, −∂g/∂x K_x ỹ).
    Missing sample (``correct=False``): v = col(u, C x̂) and F = col(A x̂ + B u + E φ̂, 0).

    Parameters
    ----------
    plan : StepPlan
    pert : Perturbation
        g and its Jacobians.
    xz : ndarray, shape (B, n + k)
    th : ndarray, shape (B, p)
    u : ndarray, shape (B, m)
    y : ndarray, shape (B, r)
    correct : bool

    Returns
    -------
    F : ndarray, shape (B, n + k)
    phi_hat : ndarray, shape (B, k)
        φ̂ = g(v, x̂, θ̂) + z (3c).
    Gx : ndarray, shape (B, k, n)
    v : ndarray, shape (B, m + r)
    """
    n = plan.layout.n
    x, z = xz[..., :n], xz[..., n:]
    if correct:
        v = np.concatenate((u, y), axis=-1)
    else:
        v = np.concatenate((u, x @ plan.C.T), axis=-1)
    g = np.asarray(pert.g(v, x, th), dtype=np.float64)
    Gx = np.asarray(pert.dg_dx(v, x, th), dtype=np.float64)
    if correct:
        F = _mv(plan.L, xz) + _mv(plan.Bv, v)
        F[..., :n] += g @ plan.E.T
        F[..., n:] -= _gmv(Gx, _mv(plan.K_x, y - x @ plan.C.T))
    else:
        F = np.zeros(xz.shape)
        F[..., :n] = x @ plan.A.T + u @ plan.B.T + (g + z) @ plan.E.T
    return F, g + z, Gx, v


def observer_jacobian(plan: StepPlan, pert: Perturbation, Gx: FloatArray, v: FloatArray,
                      x: FloatArray, th: FloatArray, correct: bool) -> FloatArray:
    """N = [[E ∂g/∂x, 0], [∂g/∂x K_x C, 0]] (measured) or [[E(∂g/∂x + ∂g/∂y C), 0], [0, 0]].

    The linearisation ∂d/∂(x̂, φ̂) of the paper's d without the terms proportional to ỹ and
    θ̂̇ (see :class:`~thetahat.estimation.observer.ModifiedHighGainObserver`, Notes).

    Parameters
    ----------
    plan : StepPlan
    pert : Perturbation
    Gx : ndarray, shape (B, k, n)
    v : ndarray, shape (B, m + r)
    x : ndarray, shape (B, n)
    th : ndarray, shape (B, p)
    correct : bool

    Returns
    -------
    ndarray, shape (B, n + k, n + k)
    """
    lay = plan.layout
    n, q = lay.n, lay.n + lay.k
    N = np.zeros(x.shape[:-1] + (q, q))
    if correct:
        N[..., :n, :n] = plan.E @ Gx
        N[..., n:, :n] = Gx @ _shared(plan.KxC)
    else:
        Gv = np.asarray(pert.dg_dv(v, x, th), dtype=np.float64)
        N[..., :n, :n] = plan.E @ (Gx + Gv[..., lay.m:] @ plan.C)
    return N


def second_forcing(plan: SecondPlan, pert: Perturbation, x2: FloatArray, u: FloatArray,
                   y: FloatArray, th: FloatArray, correct: bool
                   ) -> tuple[FloatArray, FloatArray]:
    """F = A x̂₂ + B u + E g(v̄, x̂₂, θ̂) + K_x2 (y − C x̂₂) (Sec. VI); returns (F, v̄).

    v̄ = col(u, C x̂₂) with ``g_on_estimates`` or for a missing sample (no injection then),
    else col(u, y).

    Parameters
    ----------
    plan : SecondPlan
    pert : Perturbation
    x2 : ndarray, shape (B, n)
    u : ndarray, shape (B, m)
    y : ndarray, shape (B, r)
    th : ndarray, shape (B, p)
        θ̂ at the start of the step.
    correct : bool

    Returns
    -------
    F : ndarray, shape (B, n)
    v_bar : ndarray, shape (B, m + r)
    """
    y_hat = x2 @ plan.C.T
    v = np.concatenate((u, y_hat if plan.g_on_estimates or not correct else y), axis=-1)
    g = np.asarray(pert.g(v, x2, th), dtype=np.float64)
    F = x2 @ plan.A.T + u @ plan.B.T + g @ plan.E.T
    if correct:
        F = F + _mv(plan.K_x, y - y_hat)
    return F, v


def second_jacobian(plan: SecondPlan, pert: Perturbation, v: FloatArray, x2: FloatArray,
                    th: FloatArray, correct: bool) -> FloatArray:
    """N = E ∂g/∂x, plus E ∂g/∂y C where g sees C x̂₂ (the exact Jacobian of F in x̂₂).

    Parameters
    ----------
    plan : SecondPlan
    pert : Perturbation
    v : ndarray, shape (B, m + r)
        v̄ of :func:`second_forcing`.
    x2 : ndarray, shape (B, n)
    th : ndarray, shape (B, p)
    correct : bool

    Returns
    -------
    ndarray, shape (B, n, n)
    """
    Jg = np.asarray(pert.dg_dx(v, x2, th), dtype=np.float64)
    if plan.g_on_estimates or not correct:
        m = plan.B.shape[1]
        Jg = Jg + np.asarray(pert.dg_dv(v, x2, th), dtype=np.float64)[..., m:] @ plan.C
    return plan.E @ Jg


def _prediction_phis(plan: StepPlan | SecondPlan) -> tuple[FloatArray, FloatArray]:
    """Φ₁, Φ₂ of the prediction over a missing sample (a plan built with ``predict``)."""
    if plan.Phi1_open is None or plan.Phi2_open is None:
        raise UnsupportedError("this plan has no prediction over a missing sample (built with "
                               "predict=False, as for nan_policy='raise'); build the observer "
                               "with nan_policy='skip' to step over missing samples.")
    return plan.Phi1_open, plan.Phi2_open


def second_advance(plan: SecondPlan, pert: Perturbation, x2: FloatArray, u0: FloatArray,
                   y0: FloatArray, th: FloatArray, dt: float, correct: bool,
                   u1: FloatArray | None = None, y1: FloatArray | None = None) -> FloatArray:
    """One step of the second observer (ZOH, or FOH to ``u1``, ``y1``); shape (B, n).

    Parameters
    ----------
    plan : SecondPlan
    pert : Perturbation
    x2 : ndarray, shape (B, n)
    u0, y0 : ndarray, shapes (B, m), (B, r)
        Samples at the start of the step.
    th : ndarray, shape (B, p)
    dt : float
    correct : bool
        False: the sample is missing (prediction).
    u1, y1 : ndarray, optional
        Samples at the end of the step (first-order hold).

    Returns
    -------
    ndarray, shape (B, n)
    """
    F, v = second_forcing(plan, pert, x2, u0, y0, th, correct)
    N = second_jacobian(plan, pert, v, x2, th, correct)
    F_dot = None
    if u1 is not None:
        F1 = second_forcing(plan, pert, x2, u1, y0 if y1 is None else y1, th, correct)[0]
        F_dot = (F1 - F) / dt
    if correct:
        return batched_step(x2, F, N, plan.Phi1, plan.Phi2, F_dot)
    return batched_step(x2, F, N, *_prediction_phis(plan), F_dot)


def advance(plan: StepPlan, pert: Perturbation, law: UpdateLaw, s: FloatArray, u0: FloatArray,
            y0: FloatArray, dt: float, correct: bool, u1: FloatArray | None = None,
            y1: FloatArray | None = None) -> FloatArray:
    """One step of the whole estimator for B rows: (3a)–(3c), (8), Sec. VI; shape (B, size).

    Rows whose φ̂ is not finite come back as NaN (the caller reports the divergence).

    Parameters
    ----------
    plan : StepPlan
        Plan of the B rows for this step length.
    pert : Perturbation
    law : UpdateLaw
        Shared by the rows; Γ per row comes from ``plan.Gamma``.
    s : ndarray, shape (B, size)
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
    ndarray, shape (B, size)
    """
    lay = plan.layout
    n, k = lay.n, lay.k
    q = n + k
    xz, x, th = s[..., :q], s[..., :n], s[..., lay.theta]
    F, phi, Gx, v = observer_forcing(plan, pert, xz, th, u0, y0, correct)
    finite = True if math.isfinite(float(phi.sum())) else np.isfinite(phi).all(axis=-1)
    if not np.all(finite):            # g overflowed at a finite state: report the divergence
        if s.ndim == 1:
            return np.full_like(s, np.nan)
        out = np.full_like(s, np.nan)
        good = np.flatnonzero(finite)
        out[good] = advance(plan.rows(good), pert, law, s[good], u0[good], y0[good], dt,
                            correct, None if u1 is None else u1[good],
                            None if y1 is None else y1[good])
        return out
    th_next, ls_next = th, s[..., lay.law]
    z_theta = None
    if correct:
        if s.ndim == 1:
            th1, ls1 = law.advance(v, x, phi, th, ls_next, dt)
            th_next = np.asarray(th1, dtype=np.float64).reshape(lay.p)
            ls_next = np.asarray(ls1, dtype=np.float64).reshape(lay.law_size)
            d_th = th_next - th
            if d_th.any():            # skip ∂g/∂θ while θ̂ rests (held, l = 0, ...)
                z_theta = -(np.asarray(pert.dg_dtheta(v, x, th), dtype=np.float64) @ d_th) / dt
                F[n:] += z_theta
        else:
            G = plan.Gamma if plan.Gamma is not None and plan.Gamma.shape[0] > 1 else None
            th_next, ls_next = law.advance(v, x, phi, th, ls_next, dt, Gamma=G)
            d_th = th_next - th
            moving = np.flatnonzero(np.any(d_th != 0, axis=1))
            if moving.size:           # skip ∂g/∂θ for the rows whose θ̂ rests
                z_theta = np.zeros((s.shape[0], k))
                Gth = np.asarray(pert.dg_dtheta(v[moving], x[moving], th[moving]),
                                 dtype=np.float64)
                z_theta[moving] = -_gmv(Gth, d_th[moving]) / dt
                F[:, n:] += z_theta
    N = observer_jacobian(plan, pert, Gx, v, x, th, correct)
    F_dot = None
    if u1 is not None:
        F1 = observer_forcing(plan, pert, xz, th, u1, y1 if (correct and y1 is not None)
                              else y0, correct)[0]
        if z_theta is not None:
            F1[..., n:] += z_theta
        F_dot = (F1 - F) / dt
    if correct:
        xz_next = batched_step(xz, F, N, plan.Phi1, plan.Phi2, F_dot)
    else:
        xz_next = batched_step(xz, F, N, *_prediction_phis(plan), F_dot)
    parts = [xz_next, th_next]
    if plan.second is not None:
        parts.append(second_advance(plan.second, pert, s[..., lay.x2], u0, y0, th, dt,
                                    correct, u1, y1 if correct else None))
    if lay.law_size:
        parts.append(ls_next)
    return np.concatenate(parts, axis=-1)


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
        total = float(np.vdot(s, s))
        if s.ndim == 1:
            return np.array(not total <= DIVERGENCE_BOUND ** 2)
        if total <= DIVERGENCE_BOUND ** 2:     # every row is fine (one dot product decides)
            return np.zeros(s.shape[0], dtype=bool)
        sq = np.einsum("ij,ij->i", s, s)
    return ~(sq <= DIVERGENCE_BOUND ** 2)


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
    return NonFiniteError(f"the observer state diverged (NaN, inf or a norm above "
                          f"{DIVERGENCE_BOUND:g}) {where}: the gains are too high for this dt "
                          "(decrease dt or increase ε), or the update law / data scaling is "
                          "off.")


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
