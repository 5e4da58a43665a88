"""Sampled checks of the conditions of Propositions 2–4 (Sec. IV).

* :func:`check_monotonicity` samples the matrix inequality (13)/(14),
  M(v, x, θ₁) ∂g/∂θ(v, x, θ₂) + (…)ᵀ >= 2P (or 2S(v, x)), over boxes of (v, x) and pairs
  θ₁, θ₂ ∈ Θ.
* :func:`excitation_report` measures persistency of excitation on a trajectory: the minimum
  over windows of length T of ∫ l dt (Proposition 2) and of λ_min(∫ S dt) (Proposition 4).

Sampling can find a violation but never prove the condition; the reports say where the worst
case was found so that it can be inspected.

* :func:`law_conditions_on_record` samples the diagonal of (14) and the excitation along a
  run of the observer, with the run's own (v, x̂, θ̂): did the law's conditions hold where it
  ran? (The trust report's check of the paper's method.)

What lives here: those checks, :func:`check_theta_star` (θ* on a record, before estimation)
and their reports. What it may import: the model, θ* of :mod:`.laws` and the package's
helpers; never an observer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any, final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_matrix, as_vector, check_finite, positive_scalar
from ...errors import DimensionError, ThetahatError, UpdateLawError
from ...model.paramset import Box, ParameterSet
from ...model.perturbation import EVAL_BLOCK, Perturbation
from ...model.state_set import (ASSUMPTION_2_REMEDY, GROWTH_DECADES, GROWTH_LIMIT,
                                 lipschitz_growth, state_scale)
from .laws.theta_star import ThetaStar

FloatArray = NDArray[np.float64]

__all__ = ["MonotonicityReport", "ExcitationReport", "LawConditionReport", "check_monotonicity",
           "excitation_report", "check_theta_star", "law_conditions_on_record"]

#: Eigenvalues of the sampled symmetric matrices above -EIG_ATOL count as >= 0 in the (14) check:
#: eigvalsh of an exactly PSD matrix returns about -1e-16 times its norm; 1e-12 leaves room for
#: moderately scaled g.
EIG_ATOL = 1e-12
#: A window that ends at the last sample up to rounding (relative to the time span) counts.
WINDOW_RTOL = 1e-12
#: Integration is done in chunks of this many samples to bound memory for long trajectories.
CHUNK = 4096


@final
@dataclass(frozen=True, slots=True, eq=False)
class MonotonicityReport:
    """Result of :func:`check_monotonicity`.

    Attributes
    ----------
    worst_eigenvalue : float
        Smallest eigenvalue found of M(v, x, θ₁)∂g/∂θ(v, x, θ₂) + (…)ᵀ (minus 2S(v, x) when S
        was given).
    v, x, theta1, theta2 : ndarray
        Where it was found.
    n_samples : int
    with_S : bool
        Whether S was subtracted, i.e. whether (14) rather than (13) was checked.
    """

    worst_eigenvalue: float
    v: FloatArray
    x: FloatArray
    theta1: FloatArray
    theta2: FloatArray
    n_samples: int
    with_S: bool

    @property
    def holds(self) -> bool:
        """(13): worst > 0 (P = worst/2 · I works on the samples); (14): worst >= -EIG_ATOL."""
        if self.with_S:
            return self.worst_eigenvalue >= -EIG_ATOL
        return self.worst_eigenvalue > 0

    @property
    def P_bound(self) -> float:
        """λ_min(P) of the largest P = cI consistent with (13) on the samples (worst/2)."""
        return 0.5 * self.worst_eigenvalue

    def __repr__(self) -> str:
        cond = "(14)" if self.with_S else "(13)"
        verdict = "holds" if self.holds else "VIOLATED"
        return (f"MonotonicityReport({cond} {verdict} on {self.n_samples} samples: worst "
                f"eigenvalue {self.worst_eigenvalue:.4g} at v={np.round(self.v, 4).tolist()}, "
                f"x={np.round(self.x, 4).tolist()}, theta1={np.round(self.theta1, 4).tolist()}, "
                f"theta2={np.round(self.theta2, 4).tolist()})")


def _check_sampling(perturbation: Perturbation, v_box: Box, x_box: Box,
                    parameter_set: ParameterSet) -> None:
    """The sampling boxes of :func:`check_monotonicity` fit the perturbation."""
    if not isinstance(perturbation, Perturbation):
        raise DimensionError(f"perturbation must be a thetahat Perturbation; got "
                             f"{type(perturbation).__name__}.")
    n, m, r, p, _ = perturbation.dims
    for name, box, size in (("v_box", v_box, m + r), ("x_box", x_box, n)):
        if not isinstance(box, Box) or box.dim != size:
            raise DimensionError(f"{name} must be a Box of dimension {size}; got {box!r}.")
    if not isinstance(parameter_set, ParameterSet) or parameter_set.dim != p:
        raise DimensionError(f"parameter_set must be a ParameterSet of dimension {p}; got "
                             f"{parameter_set!r}.")


def check_monotonicity(perturbation: Perturbation,
                       M: Callable[[FloatArray, FloatArray, FloatArray], Any] | None = None, *,
                       v_box: Box, x_box: Box, parameter_set: ParameterSet,
                       n_samples: int = 2000, seed: int = 0,
                       S: Callable[[FloatArray, FloatArray], Any] | None = None
                       ) -> MonotonicityReport:
    """Sampled check of condition (13) (Proposition 3) or (14) (Proposition 4).

    Parameters
    ----------
    perturbation : Perturbation
        g and ∂g/∂θ.
    M : callable, optional
        ``M(v, x, theta)``, shape (..., p, k); default (∂g/∂θ)ᵀ, as in
        :class:`~thetahat.estimation.observer.laws.GradientInversion`.
    v_box : Box
        Box of v = col(u, y) values (dimension m + r), standing in for V.
    x_box : Box
        Box of states (dimension n), standing in for X.
    parameter_set : ParameterSet
        Θ; θ₁ and θ₂ are drawn independently from ``parameter_set.sample``.
    n_samples : int, optional
        Number of random (v, x, θ₁, θ₂).
    seed : int, optional
        Seed of the random generator (the check is reproducible).
    S : callable, optional
        ``S(v, x)``, shape (..., p, p): check (14), i.e. the matrix minus 2S(v, x), instead of
        (13).

    Returns
    -------
    MonotonicityReport
        The smallest eigenvalue found and where; ``.holds`` gives the verdict.

    Examples
    --------
    g = θ + θ³/3 has ∂g/∂θ = 1 + θ² >= 1, so with M = 1 the matrix is 2(1 + θ₂²) >= 2:

    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.model.perturbation import Perturbation
    >>> from thetahat.estimation.observer.checks import check_monotonicity
    >>> class Cubic(Perturbation):
    ...     dims = (1, 0, 1, 1, 1)
    ...     def g(self, v, x, th): return th + th**3 / 3
    ...     def dg_dv(self, v, x, th): raise NotImplementedError
    ...     def dg_dx(self, v, x, th): raise NotImplementedError
    ...     def dg_dtheta(self, v, x, th): return (1 + th**2)[..., None]
    >>> rep = check_monotonicity(Cubic(), lambda v, x, th: np.ones(th.shape[:-1] + (1, 1)),
    ...                          v_box=Box([-1.0], [1.0]), x_box=Box([-1.0], [1.0]),
    ...                          parameter_set=Box([-2.0], [2.0]), n_samples=500)
    >>> rep.holds, rep.worst_eigenvalue >= 2.0
    (True, True)
    """
    _check_sampling(perturbation, v_box, x_box, parameter_set)
    _, _, _, p, k = perturbation.dims
    N = int(positive_scalar("n_samples", n_samples))
    rng = np.random.default_rng(seed)
    v = v_box.sample(rng, N)
    x = x_box.sample(rng, N)
    th1 = parameter_set.sample(rng, N)
    th2 = parameter_set.sample(rng, N)
    J2 = np.broadcast_to(np.asarray(perturbation.dg_dtheta(v, x, th2), dtype=np.float64),
                         (N, k, p))
    if M is None:
        M1 = np.swapaxes(np.broadcast_to(perturbation.dg_dtheta(v, x, th1), (N, k, p)), -1, -2)
    else:
        M1 = np.broadcast_to(np.asarray(M(v, x, th1), dtype=np.float64), (N, p, k))
    G = M1 @ J2
    sym = G + np.swapaxes(G, -1, -2)
    if S is not None:
        sym = sym - 2.0 * np.broadcast_to(np.asarray(S(v, x), dtype=np.float64), (N, p, p))
    check_finite("M ∂g/∂θ on the samples", sym)
    eig = np.linalg.eigvalsh(0.5 * (sym + np.swapaxes(sym, -1, -2)))[:, 0]
    i = int(np.argmin(eig))
    return MonotonicityReport(float(eig[i]), v[i].copy(), x[i].copy(), th1[i].copy(),
                              th2[i].copy(), N, S is not None)


@final
@dataclass(frozen=True, slots=True, eq=False)
class ExcitationReport:
    """Result of :func:`excitation_report`.

    Attributes
    ----------
    window : float
        T, the window length.
    n_windows : int
        Number of windows [t_i, t_i + T] inside the data (one per sample time t_i).
    sigma_l, t_l : float or None
        min over windows of ∫ l dt (Proposition 2's σ) and the window start where it occurs.
    sigma_S, t_S : float or None
        min over windows of λ_min(∫ S dt) (Proposition 4's σ) and where it occurs.
    """

    window: float
    n_windows: int
    sigma_l: float | None
    t_l: float | None
    sigma_S: float | None
    t_S: float | None

    @property
    def is_exciting(self) -> bool:
        """Whether every σ that was computed is > 0 on this trajectory."""
        sig = [s for s in (self.sigma_l, self.sigma_S) if s is not None]
        return all(s > 0 for s in sig)

    def __repr__(self) -> str:
        parts = [f"window={self.window:g}", f"n_windows={self.n_windows}"]
        if self.sigma_l is not None:
            parts.append(f"sigma_l={self.sigma_l:.4g} (at t={self.t_l:g})")
        if self.sigma_S is not None:
            parts.append(f"sigma_S={self.sigma_S:.4g} (at t={self.t_S:g})")
        return "ExcitationReport(" + ", ".join(parts) + ")"


def _window_integrals(t: FloatArray, f: FloatArray, window: float) -> tuple[FloatArray,
                                                                             FloatArray]:
    """∫_{t_i}^{t_i + T} f dt (trapezoid) for every t_i with t_i + T <= t_end; (starts, vals)."""
    flat = f.reshape(len(t), -1)
    cum = np.zeros_like(flat)
    cum[1:] = np.cumsum(0.5 * (flat[1:] + flat[:-1]) * np.diff(t)[:, None], axis=0)
    starts = t[t + window <= t[-1] + WINDOW_RTOL * (t[-1] - t[0])]
    end = starts + window
    vals = np.stack([np.interp(end, t, cum[:, j]) for j in range(flat.shape[1])], axis=-1)
    vals -= cum[: len(starts)]
    return starts, vals.reshape((len(starts),) + f.shape[1:])


def excitation_report(t: ArrayLike, l: ArrayLike | None = None,  # noqa: E741
                      S: ArrayLike | None = None, *, window: float) -> ExcitationReport:
    """Persistency of excitation of l (Proposition 2) and S (Proposition 4) on a trajectory.

    Parameters
    ----------
    t : array_like, shape (N,)
        Strictly increasing sample times.
    l : array_like, shape (N,), optional
        The excitation weight l(v(t), x(t), φ(t)) along the trajectory.
    S : array_like, shape (N, p, p), optional
        S(v(t), x(t)) along the trajectory (symmetric positive semidefinite).
    window : float
        T > 0, the window length; the trajectory must span at least T.

    Returns
    -------
    ExcitationReport
        min over windows [t_i, t_i + T] of ∫ l dt and of λ_min(∫ S dt), integrated with the
        trapezoid rule (the window end is interpolated in the cumulative integral).

    Raises
    ------
    DimensionError
        Shapes disagree, t is not strictly increasing, or the trajectory is shorter than T.
    NonFiniteError
        NaN or inf in the data.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.observer.checks import excitation_report
    >>> t = np.linspace(0.0, 20.0, 2001)
    >>> rep = excitation_report(t, l=(np.sin(t) > 0).astype(float), window=2 * np.pi)
    >>> round(rep.sigma_l, 1)  # half of every period
    3.1
    """
    t_ = as_vector("t", t)
    T = positive_scalar("window", window)
    if t_.size < 2 or np.any(np.diff(t_) <= 0):
        raise DimensionError("t must hold at least two strictly increasing sample times.")
    if t_[-1] - t_[0] < T:
        raise DimensionError(f"the trajectory spans {t_[-1] - t_[0]:g}, shorter than the "
                             f"window T = {T:g}; simulate longer or use a shorter window.")
    if l is None and S is None:
        raise DimensionError("give l (Proposition 2), S (Proposition 4), or both.")
    sigma_l = t_l = sigma_S = t_S = None
    n_windows = 0
    if l is not None:
        l_ = as_vector("l", l, t_.size)
        starts, vals = _window_integrals(t_, l_, T)
        i = int(np.argmin(vals))
        sigma_l, t_l, n_windows = float(vals[i]), float(starts[i]), len(starts)
    if S is not None:
        S_ = np.asarray(S, dtype=np.float64)
        if S_.ndim != 3 or S_.shape[0] != t_.size or S_.shape[1] != S_.shape[2]:
            raise DimensionError(f"S must have shape ({t_.size}, p, p); got {S_.shape}.")
        check_finite("S", S_)
        starts, vals = _window_integrals(t_, S_, T)
        lam = np.concatenate([np.linalg.eigvalsh(0.5 * (c + np.swapaxes(c, -1, -2)))[:, 0]
                              for c in np.array_split(vals, max(1, len(vals) // CHUNK))])
        i = int(np.argmin(lam))
        sigma_S, t_S, n_windows = float(lam[i]), float(starts[i]), len(starts)
    return ExcitationReport(T, n_windows, sigma_l, t_l, sigma_S, t_S)


#: θ* recovers θ at a data point when |θ*(v, x, g(v, x, θ)) − θ| <= THETA_STAR_RTOL·(1 + |θ|):
#: far above the rounding of a closed-form inverse (~1e-12 relative), far below a branch error.
THETA_STAR_RTOL = 1e-6
#: Points of Θ at which θ* is checked along the data (the first is Θ's interior point).
THETA_STAR_POINTS = 3
#: Points listed in the error message.
THETA_STAR_SHOW = 5


def _record(name: str, a: Any, N: int, width: int) -> FloatArray:
    """A sampled record (N, width), (N,) allowed for width 1; NaN allowed (dropouts)."""
    arr = np.asarray(a)
    if arr.ndim == 1 and width == 1:
        arr = arr.reshape(-1, 1)
    return as_matrix(name, arr, (N, width), finite=False)


def _times(t: FloatArray, idx: Any) -> str:
    idx = np.asarray(idx, dtype=int)
    shown = ", ".join(f"{float(t[i]):.6g}" for i in idx[:THETA_STAR_SHOW])
    more = f" and {idx.size - THETA_STAR_SHOW} more" if idx.size > THETA_STAR_SHOW else ""
    return f"t = [{shown}]{more}"


def check_theta_star(theta_star: Callable[..., Any], perturbation: Perturbation,
                     parameter_set: ParameterSet, C: ArrayLike, t: ArrayLike,
                     u: ArrayLike | None, y: ArrayLike, *, seed: int = 0) -> None:
    """Check θ*(v, x, φ) where it will be used, on a data record, before estimation starts.

    Along the data, with x a state consistent with y (x = C⁺ y plus one fixed random offset
    in ker C) and θ at ``THETA_STAR_POINTS`` points of Θ, φ = g(v, x, θ) must give back
    θ* = θ wherever ∂g/∂θ ≠ 0 (Proposition 1 needs θ* to invert g on the range the estimator
    visits). Refused: points where θ* is NaN
    or inf (a singularity or a branch cut on the data), points where θ* returns another θ
    (a branch that misses Θ), and a denominator of θ* that
    changes sign between two samples (a pole crossed by the data, e.g. θ* = log(φ + 1)/y
    for g = exp(θ y) − 1 when y crosses 0); the last check needs θ* as a
    :class:`~thetahat.estimation.observer.laws.theta_star.ThetaStar` (derived by SymPy or read from a file).

    Parameters
    ----------
    theta_star : callable
        θ*(v, x, φ) → (..., p), as held by an inversion law's ``theta_star``.
    perturbation : Perturbation
    parameter_set : ParameterSet
    C : array_like, shape (r, n)
    t : array_like, shape (N,)
    u : array_like, shape (N, m), or None when m = 0
    y : array_like, shape (N, r)
        Rows with NaN (dropouts) are ignored.
    seed : int
        Seed of the points of Θ beyond the interior point.

    Raises
    ------
    UpdateLawError
        θ* fails on the data; the message gives the times and what to do.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.observer.laws import algebraic_from_perturbation
    >>> from thetahat.estimation.observer.checks import check_theta_star
    >>> g = parse_perturbation("exp(theta*y) - 1", u=[], y=["y"], x=["x"], theta=["theta"])
    >>> Theta = Box([0.5], [2.0])
    >>> law = algebraic_from_perturbation(g, Gamma=1.0, parameter_set=Theta)
    >>> t = np.linspace(0.0, 1.0, 101)
    >>> check_theta_star(law.theta_star, g, Theta, [[1.0]], t, None, 1.0 + t)  # y > 0: fine
    >>> check_theta_star(law.theta_star, g, Theta, [[1.0]], t, None, np.cos(4 * t))
    Traceback (most recent call last):
    ...
    thetahat.errors.UpdateLawError: theta_star is singular on the data: its denominator ... at t = [0.39], ...
    """
    n, m, r, _, _ = perturbation.dims
    t_ = as_vector("t", t)
    C_ = as_matrix("C", C, (r, n))
    Y = _record("y", y, t_.size, r)
    U = np.zeros((t_.size, 0)) if u is None else _record("u", u, t_.size, m)
    keep = np.isfinite(Y).all(axis=1) & np.isfinite(U).all(axis=1)
    if not keep.all():
        t_, U, Y = t_[keep], U[keep], Y[keep]
    if t_.size == 0:
        return
    rng = np.random.default_rng(seed)
    # x consistent with y: the least-norm part C⁺y plus one fixed offset in ker C (the part
    # of x the data do not show; fixed, so that θ*'s denominators vary with the data only)
    _, sv, Vh = np.linalg.svd(C_)
    null = Vh[int(np.sum(sv > 1e-12 * max(1.0, float(sv[0]) if sv.size else 1.0))):]
    Cp, offset = np.linalg.pinv(C_).T, rng.standard_normal(null.shape[0]) @ null
    thetas = np.vstack([np.asarray(parameter_set.interior_point, dtype=np.float64)[None, :],
                        parameter_set.sample(rng, THETA_STAR_POINTS - 1)])

    def blocks() -> Iterator[tuple[slice, FloatArray, FloatArray]]:
        """(rows, v, x) a block of EVAL_BLOCK samples at a time: a long record's arrays stay
        a block long."""
        for a in range(0, t_.size, EVAL_BLOCK):
            rows = slice(a, a + EVAL_BLOCK)
            yield rows, np.concatenate((U[rows], Y[rows]), axis=1), Y[rows] @ Cp + offset

    fix = ("Give theta_star explicitly with a form valid on the data, restrict Θ, or use the "
           "gradient law (Propositions 3–4).")
    for th in thetas:
        _check_inverse(theta_star, perturbation, blocks, th, t_, fix)
    _check_poles(theta_star, blocks, perturbation, thetas[0], t_, fix)


def _check_inverse(theta_star: Callable[..., Any], perturbation: Perturbation,
                   blocks: Callable[[], Iterator[tuple[slice, FloatArray, FloatArray]]],
                   th: FloatArray, t: FloatArray, fix: str) -> None:
    """θ*(v, x, g(v, x, θ)) = θ at every sample where ∂g/∂θ ≠ 0, for one θ ∈ Θ."""
    p = th.size
    bad, wrong = np.zeros(t.size, dtype=bool), np.zeros(t.size, dtype=bool)
    first: FloatArray | None = None           # θ* at the first sample where it misses θ
    for rows, V, X in blocks():
        N = V.shape[0]
        with np.errstate(all="ignore"):
            phi = np.asarray(perturbation.g(V, X, np.broadcast_to(th, (N, p))),
                             dtype=np.float64)
            est = np.asarray(theta_star(V, X, phi), dtype=np.float64).reshape(N, p)
            J = np.asarray(perturbation.dg_dtheta(V, X, np.broadcast_to(th, (N, p))),
                           dtype=np.float64).reshape(N, -1)
        # only where φ determines θ (∂g/∂θ ≠ 0): elsewhere no θ* can recover θ
        usable = np.isfinite(phi).all(axis=1) & (np.abs(J) > 0).any(axis=1)
        bad[rows] = usable & ~np.isfinite(est).all(axis=1)
        wrong[rows] = usable & (np.max(np.abs(est - th), axis=1) > THETA_STAR_RTOL * (
            1.0 + np.max(np.abs(th))))
        if first is None and wrong[rows].any():
            first = est[int(np.argmax(wrong[rows]))]
    if bad.any():
        raise UpdateLawError(
            f"theta_star is NaN or inf on the data at {_times(t, np.flatnonzero(bad))} "
            f"(θ = {np.round(th, 6).tolist()}): a singularity or branch cut of θ* lies on "
            f"the range of the data. {fix}")
    if first is not None:
        i = int(np.argmax(wrong))
        raise UpdateLawError(
            f"theta_star does not invert g on the data at {_times(t, np.flatnonzero(wrong))}"
            f": at t = {float(t[i]):.6g} it returns {np.round(first, 6).tolist()} for θ = "
            f"{np.round(th, 6).tolist()} ∈ Θ (a branch that misses Θ). {fix}")


def _check_poles(theta_star: Any,
                 blocks: Callable[[], Iterator[tuple[slice, FloatArray, FloatArray]]],
                 perturbation: Perturbation, th: FloatArray, t: FloatArray, fix: str) -> None:
    """Sign changes of the denominators of a symbolic θ* between consecutive samples."""
    if not isinstance(theta_star, ThetaStar) or t.size < 2:
        return
    solution, arguments = theta_star.expr, theta_star.arguments
    import sympy as sp

    dens = [(expr, den) for expr in solution
            if not (den := sp.denom(sp.together(expr))).is_number]
    if not dens:
        return
    fns = [sp.lambdify(list(arguments), den, "numpy") for _, den in dens]
    D = np.empty((len(dens), t.size))          # each denominator along the data
    for rows, V, X in blocks():                 # g once a block for every denominator
        with np.errstate(all="ignore"):
            phi = np.asarray(perturbation.g(V, X, np.broadcast_to(th, (V.shape[0], th.size))),
                             dtype=np.float64)
            for d, fn in zip(D, fns):
                d[rows] = np.asarray(fn(*V.T, *X.T, *phi.T), dtype=np.float64)
    for (expr, den), d in zip(dens, D):
        nz = np.flatnonzero(np.isfinite(d) & (d != 0))     # a sign change between these
        cross = nz[:-1][np.sign(d[nz[:-1]]) != np.sign(d[nz[1:]])]
        if cross.size:
            raise UpdateLawError(
                f"theta_star is singular on the data: its denominator {den} (θ* = {expr}) "
                f"vanishes between samples at {_times(t, cross)}, where θ* has a pole and "
                f"the estimate would be driven by noise. {fix}")


#: Points of Θ drawn as θ₂ of (14) at every sample of :func:`law_conditions_on_record` (with
#: θ₂ = θ̂ at the sample itself and at the run's end).
RECORD_THETAS = 8
#: Samples of the run at which :func:`law_conditions_on_record` evaluates (evenly spaced; the
#: check costs O(RECORD_SAMPLES · RECORD_THETAS), whatever the record's length).
RECORD_SAMPLES = 4096
#: A parameter fails (14) when its diagonal entry is negative on more than this fraction of
#: the samples (a few samples at a zero crossing of a smoothed sign are rounding, not a
#: failure of the law).
CONDITION_FRACTION = 0.02
#: A signal "drives" the sign of ∂g/∂θᵢ when the two signs agree (or disagree) on at least this
#: fraction of the samples where both are non-zero.
SIGN_AGREEMENT = 0.95
#: The excitation of Props. 2–4 is checked over windows of this fraction of the record.
EXCITATION_WINDOW = 0.25
#: A window whose scaled information λ_min(∫ S dt) is below this fraction of the window's
#: length has no excitation in some direction (the scaled S has mean trace p per unit time).
EXCITATION_RTOL = 1e-4


@final
@dataclass(frozen=True, slots=True, eq=False)
class LawConditionReport:
    """The update law's conditions sampled along a run (:func:`law_conditions_on_record`).

    Attributes
    ----------
    names : tuple of str
        The parameters' names.
    proposition : str
        ``"(14)"`` for the gradient and least-squares laws (Props. 3–4), ``"l"`` for the
        intermittent inversion (Prop. 2), ``""`` when the law has no condition to sample.
    fail_fraction : ndarray (p,)
        Per parameter, the fraction of the samples at which the diagonal entry
        2 Mᵢ(v, x̂, θ̂) ∂g/∂θᵢ(v, x̂, θ₂) of (14) is negative for some θ₂ drawn from Θ (or θ̂
        at the run's end): there no S ≥ 0 satisfies (14).
    at_estimate : ndarray (p,)
        The same with θ₂ = θ̂ at the sample (a sign of Mᵢ ∂g/∂θᵢ that changes along the record
        itself, not only across Θ).
    sign_with : tuple of str
        Per parameter, the signal whose sign ∂g/∂θᵢ(v, x̂, θ̂) follows ('' if none does).
    witness : ndarray (p, p)
        Per parameter, a θ₂ ∈ Θ at which its entry was negative (NaN rows where none was).
    excitation : ExcitationReport or None
        Persistency of excitation along the run: of the Jacobi-scaled (∂g/∂θ)ᵀ∂g/∂θ at θ̂
        (Props. 3–4) or of l (Prop. 2), over windows of :data:`EXCITATION_WINDOW` of the record.
    n_samples : int
    x_growth : float
        Assumption 2's global Lipschitz condition in x, probed at the run's middle sample:
        the growth of ‖∂g/∂x‖ from the run's states to 100 times their scale
        (:func:`~thetahat.model.state_set.lipschitz_growth`; NaN when not probed).
    """

    names: tuple[str, ...]
    proposition: str
    fail_fraction: FloatArray
    at_estimate: FloatArray
    sign_with: tuple[str, ...]
    witness: FloatArray
    excitation: ExcitationReport | None
    n_samples: int
    x_growth: float = math.nan

    @property
    def lipschitz(self) -> bool:
        """Whether g looked Lipschitz in x beyond the run's states (Assumption 2; True when
        not probed)."""
        return not self.x_growth > GROWTH_LIMIT

    @property
    def failing(self) -> tuple[str, ...]:
        """Parameters whose (14) entry fails on more than :data:`CONDITION_FRACTION`."""
        return tuple(n for n, f in zip(self.names, self.fail_fraction)
                     if f > CONDITION_FRACTION)

    @property
    def exciting(self) -> bool:
        """Every window of the record carries excitation in every direction."""
        ex = self.excitation
        if ex is None:
            return True
        sig = ex.sigma_S if ex.sigma_S is not None else ex.sigma_l
        return sig is None or sig > EXCITATION_RTOL * ex.window

    @property
    def warnings(self) -> tuple[str, ...]:
        """One sentence per failed condition, with what to do."""
        out = []
        for i, name in enumerate(self.names):
            f = self.fail_fraction[i]
            if not f > CONDITION_FRACTION:
                continue
            follows = (f" (its sign follows {self.sign_with[i]})"
                       if self.sign_with[i] and self.sign_with[i] != "the data" else "")
            if self.at_estimate[i] > CONDITION_FRACTION:
                why = (f"M·∂g/∂{name} is negative at θ̂ itself on "
                       f"{100 * self.at_estimate[i]:.0f} % of the samples{follows}")
            elif np.all(np.isfinite(self.witness[i])):
                shown = ", ".join(f"{n} = {v:.3g}" for n, v in zip(self.names, self.witness[i]))
                why = (f"∂g/∂{name}{follows} has opposite signs at θ̂ and at points of Θ "
                       f"such as ({shown})")
            else:
                why = f"M·∂g/∂{name} changes sign between θ̂ and the run's final θ̂{follows}"
            out.append(f"the update law's condition (14) (Props. 3–4) fails for {name} on "
                       f"{100 * f:.0f} % of the samples of this run: {why}; the "
                       "paper's convergence guarantee does not hold here (restrict Θ to where "
                       f"∂g/∂{name} keeps its sign, or use method guarded or mle)")
        if not self.lipschitz:
            growth = ("is not finite" if math.isinf(self.x_growth)
                      else f"grows {self.x_growth:.3g}-fold")
            out.append(f"Assumption 2 fails: g is Lipschitz in x only on bounded sets (‖∂g/∂x‖ "
                       f"{growth} from this run's states to {10 ** GROWTH_DECADES} times their "
                       "scale), so the paper's global guarantee does not hold: an x̂ driven "
                       f"off by a wrong θ̂ or start meets a g its gains cannot dominate "
                       f"({ASSUMPTION_2_REMEDY}; or use method guarded or mle)")
        ex = self.excitation
        if ex is not None and not self.exciting:
            where = float((ex.t_S if ex.sigma_S is not None else ex.t_l) or 0.0)
            what = ("λ_min of the scaled information (∂g/∂θ)ᵀ∂g/∂θ" if ex.sigma_S is not None
                    else "the excitation weight l (Prop. 2)")
            out.append(f"the excitation the update law needs (Props. 2–4) is missing over "
                       f"[{where:.6g}, {where + ex.window:.6g}]: {what} integrates to almost "
                       "nothing there (other excitation, or a record whose input moves every "
                       "parameter throughout)")
        return tuple(out)

    def __repr__(self) -> str:
        return (f"LawConditionReport({self.proposition or 'no condition'}: failing="
                f"{list(self.failing)}, exciting={self.exciting}, n_samples={self.n_samples})")


def _sign_driver(J_i: FloatArray, signals: FloatArray, labels: tuple[str, ...]) -> str:
    """The signal whose sign ∂g/∂θᵢ follows on ≥ SIGN_AGREEMENT of the samples, or ''."""
    s = np.sign(J_i)
    if not (np.any(s > 0) and np.any(s < 0)):
        return ""
    for j, label in enumerate(labels):
        z = np.sign(signals[:, j])
        both = (s != 0) & (z != 0)
        if both.sum() < 10:
            continue
        agree = float(np.mean(s[both] == z[both]))
        if max(agree, 1.0 - agree) >= SIGN_AGREEMENT:
            return label
    return "the data"


def law_conditions_on_record(perturbation: Perturbation, t: ArrayLike, v: ArrayLike,
                             x_hat: ArrayLike, theta_hat: ArrayLike,
                             parameter_set: ParameterSet, *, law: object,
                             names: tuple[str, ...] | None = None,
                             signal_names: tuple[str, ...] | None = None,
                             seed: int = 0) -> LawConditionReport:
    """The conditions of Props. 2–4 along a run of the observer: where did they hold?

    At :data:`RECORD_SAMPLES` samples of the run (evenly spaced), with the run's own
    (v, x̂, θ̂): for the gradient law (Props. 3–4, M = ``law.M`` or (∂g/∂θ)ᵀ) and the
    least-squares law (M = (∂g/∂θ)ᵀ on the filtered regressor; its condition is read on the
    unfiltered one), the diagonal entries 2 Mᵢ(v, x̂, θ̂) ∂g/∂θᵢ(v, x̂, θ₂) of (14) for θ₂ = θ̂
    at the sample, θ̂ at the run's end and :data:`RECORD_THETAS` points of Θ — a negative one
    means no S ≥ 0 satisfies (14) there (the proofs of Props. 3–4 take θ₂ between θ̂ and θ);
    and the persistency of excitation of the Jacobi-scaled (∂g/∂θ)ᵀ∂g/∂θ at θ̂ over windows of
    :data:`EXCITATION_WINDOW` of the record. For the intermittent inversion (Prop. 2): the
    excitation of its weight l(v, x̂, φ̂ = g(v, x̂, θ̂)). Cost: O(RECORD_SAMPLES · RECORD_THETAS)
    evaluations of ∂g/∂θ, whatever N.

    Parameters
    ----------
    perturbation : Perturbation
    t : array_like (N,)
    v : array_like (N, m + r)
        col(u, y) of the run (rows with NaN are left out).
    x_hat, theta_hat : array_like (N, n), (N, p)
        The run's estimates.
    parameter_set : ParameterSet
        Θ.
    law : UpdateLaw
        The run's law (its ``M``, or ``l`` for Prop. 2, is read).
    names : tuple of str, optional
        The parameters' names.
    signal_names : tuple of str, optional
        Names of the columns of v followed by those of x̂ (to say what a sign follows).
    seed : int
        Seed of the points of Θ.

    Returns
    -------
    LawConditionReport

    Examples
    --------
    g = θ tanh(v/0.01) with Θ = [−1, 1]: ∂g/∂θ = tanh(v/0.01) changes sign across Θ? No —
    it does not depend on θ, so (14) holds with S = (∂g/∂θ)²:

    >>> import numpy as np
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.observer.laws import GradientInversion
    >>> from thetahat.estimation.observer.checks import law_conditions_on_record
    >>> g = parse_perturbation("th*tanh(y/0.01)", u=[], y=["y"], x=["x"], theta=["th"])
    >>> law = GradientInversion(g, Gamma=1.0, parameter_set=Box([-1.0], [1.0]))
    >>> t = np.linspace(0.0, 10.0, 1001)
    >>> rep = law_conditions_on_record(g, t, np.sin(t)[:, None], np.zeros((1001, 1)),
    ...                                np.full((1001, 1), 0.5), Box([-1.0], [1.0]), law=law)
    >>> rep.failing, rep.exciting
    ((), True)
    """
    n, m, r, p, k = perturbation.dims
    t_ = as_vector("t", t)
    N = t_.size
    V = _record("v", v, N, m + r)
    X = _record("x_hat", x_hat, N, n)
    TH = _record("theta_hat", theta_hat, N, p)
    names_ = tuple(names) if names is not None else tuple(f"theta{i + 1}" for i in range(p))
    labels = (tuple(signal_names) if signal_names is not None
              else tuple(f"v{i + 1}" for i in range(m + r)) + tuple(f"x{i + 1}"
                                                                   for i in range(n)))
    ok = np.isfinite(V).all(axis=1) & np.isfinite(X).all(axis=1) & np.isfinite(TH).all(axis=1)
    idx_all = np.flatnonzero(ok)
    empty = LawConditionReport(names_, "", np.zeros(p), np.zeros(p), ("",) * p,
                               np.full((p, p), np.nan), None, 0)
    if idx_all.size < 2:
        return empty
    mid = int(idx_all[idx_all.size // 2])
    try:
        growth = lipschitz_growth(perturbation, V[mid], X[mid], TH[mid], state_scale(X[ok]))
    except ThetahatError:           # a g that cannot be probed: the check is skipped
        growth = math.nan
    empty = replace(empty, x_growth=growth)
    weight = getattr(law, "l", None)
    is_inversion = hasattr(law, "theta_star")
    if is_inversion:
        if weight is None:
            return empty
        with np.errstate(all="ignore"):
            phi = np.asarray(perturbation.g(V[ok], X[ok], TH[ok]), dtype=np.float64)
            lw = np.broadcast_to(np.asarray(weight(V[ok], X[ok], phi), dtype=np.float64),
                                 (idx_all.size,))
        ex = _excitation(t_[ok], np.nan_to_num(lw), None)
        return LawConditionReport(names_, "l", np.zeros(p), np.zeros(p), ("",) * p,
                                  np.full((p, p), np.nan), ex, int(idx_all.size), growth)
    idx = idx_all[np.unique(np.linspace(0, idx_all.size - 1, min(RECORD_SAMPLES, idx_all.size))
                            .astype(np.int64))]
    Vs, Xs, T1 = V[idx], X[idx], TH[idx]
    S = idx.size
    M_fn = getattr(law, "M", None)
    with np.errstate(all="ignore"):
        J1 = np.broadcast_to(np.asarray(perturbation.dg_dtheta(Vs, Xs, T1), dtype=np.float64),
                             (S, k, p))
        M1 = (np.swapaxes(J1, -1, -2) if M_fn is None
              else np.broadcast_to(np.asarray(M_fn(Vs, Xs, T1), dtype=np.float64), (S, p, k)))
        rng = np.random.default_rng(seed)
        thetas = np.vstack([TH[idx_all[-1]][None, :], parameter_set.sample(rng, RECORD_THETAS)])
        at_est = np.einsum("spk,skp->sp", M1, J1) < 0
        fails = at_est.copy()
        witness = np.full((p, p), np.nan)
        for th2 in thetas:
            J2 = np.broadcast_to(np.asarray(perturbation.dg_dtheta(
                Vs, Xs, np.broadcast_to(th2, (S, p))), dtype=np.float64), (S, k, p))
            neg = np.einsum("spk,skp->sp", M1, J2) < 0
            for i in np.flatnonzero(np.isnan(witness[:, 0]) & (neg.mean(axis=0)
                                                               > CONDITION_FRACTION)):
                witness[i] = th2
            fails |= neg
    sign_with = tuple(_sign_driver(J1[:, :, i].sum(axis=1), np.concatenate([Vs, Xs], axis=1),
                                   labels) if fails[:, i].mean() > CONDITION_FRACTION else ""
                      for i in range(p))
    Jn = np.nan_to_num(J1)
    info = np.einsum("ski,skj->sij", Jn, Jn)
    d = np.sqrt(np.maximum(np.mean(np.diagonal(info, axis1=1, axis2=2), axis=0), 1e-300))
    ex = _excitation(t_[idx], None, info / np.outer(d, d))
    return LawConditionReport(names_, "(14)", fails.mean(axis=0), at_est.mean(axis=0),
                              sign_with, witness, ex, int(S), growth)


def _excitation(t: FloatArray, l: FloatArray | None,  # noqa: E741
                S: FloatArray | None) -> ExcitationReport | None:
    """:func:`excitation_report` over windows of EXCITATION_WINDOW of the span (None when
    the run is too short to have one)."""
    span = float(t[-1] - t[0])
    if not span > 0 or t.size < 4:
        return None
    return excitation_report(t, l=l, S=S, window=EXCITATION_WINDOW * span)
