"""The likelihood of the model with process noise on φ: the fit for a model that is not exact.

When the model is not exact — a real machine's friction is asymmetric, a plant has dynamics
the model leaves out — a fit that trusts the model over the whole record (the output-error MAP
:func:`~thetahat.estimation.statistical.map_fit.fit_map`) lets the model's error accumulate in x and pays for
it with a biased θ. The remedy is to say so in the model: the error enters where the
perturbation enters,

    ẋ = A x + B u + E (g(v, x, θ) + w),   y = C x + e,

with w white of intensity q (unknown, estimated from the data) and e white with covariance
R = diag(σ²). The likelihood of (θ, q) is that of the extended Kalman filter's innovations
ε_k with variances S_k (the prediction-error method):

    −log L(θ, q) = ½ Σ_k Σ_i (ε_{k,i}² / S_{k,i} + log S_{k,i}) + const.

Over a sample of length h, w adds q Q₁(h), Q₁(h) = ∫₀^h e^{Aτ} E Eᵀ e^{Aᵀτ} dτ (Van Loan's
exponential, once per distinct sample length), to the covariance of x; x is propagated by the
model's sampled-data map with its exact Jacobian (:mod:`~thetahat.estimation.statistical.plant_kernel`);
the outputs update one at a time in Joseph form. θ is fitted by Gauss–Newton on the normalised
innovations ε/√S (SciPy's trust-region least squares inside Θ's bounding box, then projected
onto Θ, the Jacobian by
differences of whole filter passes over steps sized by the passes' measured rounding noise,
updated by Broyden's rule between iterates and taken afresh where the fit stops)
and log q by a bounded one-dimensional search of −log L, alternately. The scale of q is the data's own: q₀ is the intensity whose one-sample effect on
y equals the measurement noise, C q₀ Q₁(h) Cᵀ = σ², and q is searched over q₀·10^[−6, 6] and
at 0 (the output-error model, which wins when the model is exact). At a fixed θ (the trust
report, the bound) q is searched on the record's first samples only, a short head first and a
longer one when the short one does not pin q̂ (:func:`search_process_noise`).

What it may import: :mod:`thetahat.model`, the package's errors, SciPy, and, in this room,
``common``, ``noise_level``, ``plant_kernel`` and ``stage2_set``.
"""

from __future__ import annotations

import functools
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, Callable, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm
from scipy.optimize import least_squares, minimize_scalar

from ...errors import NonFiniteError
from ...model.system import PerturbedLinearSystem
from ...model.paramset import Box, ParameterSet
from ..hold import DEFAULT_HOLD
from .common import STEP_TOL, sample_interval, theta_box
from .noise_level import mad_variance
from .stage2_set import project_theta, theta_bounds
from .plant_kernel import (ACCURACY_SAMPLES, H_RHO, ModelKernel, Propagation, choose_substeps,
                           doubling_floor, model_kernel, printed_kernels)

__all__ = ["ProcessNoiseFit", "RecordEvidence", "fit_process_noise", "process_noise_scale",
           "unit_process_noise", "record_bound", "record_evidence", "process_noise_at",
           "fisher_covariance", "Q_DECADES", "Q_SEARCH_SAMPLES", "Q_FIRST_HEAD", "ALTERNATIONS",
           "QSearch", "search_process_noise", "innovation_substeps", "difference_threads"]

FloatArray = NDArray[np.float64]

#: q is searched over q₀·10^[−Q_DECADES, Q_DECADES] (and at 0).
Q_DECADES = 6.0
#: Rounds of (fit θ at q, search q at θ) before the final fit of θ.
ALTERNATIONS = 1
#: Precision of the search of log₁₀ q (a tenth of a decade: the likelihood is flat near its
#: maximum, and θ̂ changes far less than its standard error within it).
Q_XTOL = 0.1
#: :func:`record_bound` searches q on at most this many samples (the record's first): q̂'s
#: standard error from N innovations is ≈ √(2/N) relative, 0.0024 decade at 2¹⁶ — 40 times
#: below :data:`Q_XTOL` — so a longer record only makes each of the search's ~16 filter
#: passes longer, not q̂ better (``thetahat estimate`` on a 10⁶-sample log,
#: benchmarks/bench_estimate.py: 21.6 s with the whole record searched, 8.7 s with this).
Q_SEARCH_SAMPLES = 2 ** 16
#: The search at a fixed θ (:func:`search_process_noise`) starts on the record's first
#: Q_FIRST_HEAD samples and goes on to :data:`Q_SEARCH_SAMPLES` only when they do not pin q̂:
#: when the likelihood's curvature there leaves log₁₀ q̂ a standard error above
#: :data:`Q_XTOL`. Sixteen times shorter, the first search costs a sixteenth of the long one's
#: filter passes, and a long record whose model error shows early needs no other.
Q_FIRST_HEAD = 2 ** 12
#: A search near a known q̂ (:func:`search_process_noise`'s ``near``: the same record's q̂ at
#: other sub-steps, or at a nearby θ) brackets the first head's log₁₀ q within
#: ±Q_NEAR_DECADES of it; a minimum found at the bracket's edge is searched again over the
#: whole range.
Q_NEAR_DECADES = 0.5
#: Relative tolerance of the Gauss–Newton fit of θ (steps and cost).
FIT_RTOL = 1e-6
#: SciPy's trust region can stop on its relative tolerances with more than STEP_TOL standard
#: errors still to go (EMPS's head with SciPy 1.13 and one BLAS thread: 0.047): the fit is
#: restarted from where it stopped, a fresh trust region, up to this many times within its
#: budget of filter passes.
FIT_RESTARTS = 2
#: θ is fitted with Huber's loss on the normalised innovations, quadratic within ±HUBER_C:
#: a record of an inexact model carries bursts the Gaussian w does not describe (an unmeasured
#: force pulse, a slip), which would otherwise pull θ; for innovations that are Gaussian, the
#: loss costs 0.04 % of efficiency at 3 (Huber's asymptotic efficiency, 0.9996).
HUBER_C = 3.0
#: Sample lengths equal to this relative precision share one Q₁(h).
H_RTOL = 1e-6


@dataclass(frozen=True, slots=True, eq=False)
class ProcessNoiseFit:
    """θ and the process-noise intensity q that maximise the innovations' likelihood.

    Attributes
    ----------
    theta : ndarray (p,)
    cov : ndarray (p, p)
        Inverse Gauss–Newton information of θ at q (the Laplace covariance).
    q : float
        Intensity of the white noise w added to φ (units of φ² · s); 0 when the output-error
        model (q = 0) has the larger likelihood.
    q_scale : float
        q₀, the intensity whose one-sample effect on y equals the measurement noise.
    nll : float
        −log L at the optimum (without the constant).
    x_end : ndarray (n,)
        The filtered state after the last sample.
    P_end : ndarray (n, n)
        Its covariance.
    cost : float
        Mean squared normalised innovation (≈ 1 when the noise model is right).
    n_meas : int
        Scalar measurements used.
    noise_std : ndarray (r,)
    core_cost : float
        The normalised innovations' Gaussian-core variance
        (:func:`~thetahat.estimation.statistical.noise_level.mad_variance`; ≈ 1 when the noise
        model is right but for bursts the model leaves out).
    burst_fraction : float
        Fraction of the normalised innovations beyond ±:data:`HUBER_C` (0.27 % for Gaussian ones).
    iterations : int
        Filter passes of the final fit of θ (SciPy's evaluations).
    step_se : float
        The Gauss–Newton step of Huber's loss still to go at θ, in standard errors.
    substeps : int
        The RK4 sub-steps' accuracy floor of the filter.
    """

    theta: FloatArray
    cov: FloatArray
    q: float
    q_scale: float
    nll: float
    x_end: FloatArray
    P_end: FloatArray
    cost: float
    n_meas: int
    noise_std: FloatArray
    core_cost: float = math.nan
    burst_fraction: float = math.nan
    iterations: int = 0
    step_se: float = 0.0
    substeps: int = 1

    @property
    def theta_se(self) -> FloatArray:
        """Standard errors of θ, √diag(cov)."""
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def __repr__(self) -> str:
        return (f"ProcessNoiseFit(theta={self.theta}, se={self.theta_se}, q={self.q:.3g} "
                f"(q/q0 = {self.q / self.q_scale:.3g}), cost={self.cost:.3g})")


def unit_process_noise(A: FloatArray, E: FloatArray, h: float) -> FloatArray:
    """Q₁(h) = ∫₀^h e^{Aτ} E Eᵀ e^{Aᵀτ} dτ, by Van Loan's block exponential.

    Parameters
    ----------
    A : ndarray (n, n)
    E : ndarray (n, k)
    h : float
        Sample length > 0.

    Returns
    -------
    ndarray (n, n)
        Symmetric positive semi-definite.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.likelihood import unit_process_noise
    >>> Q = unit_process_noise(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), 0.1)
    >>> bool(np.allclose(Q, [[0.1 ** 3 / 3, 0.1 ** 2 / 2], [0.1 ** 2 / 2, 0.1]]))
    True
    """
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = E @ E.T
    M[n:, n:] = A.T
    V = expm(M * h)
    Phi = V[n:, n:].T
    Q = Phi @ V[:n, n:]
    return 0.5 * (Q + Q.T)


def process_noise_scale(system: PerturbedLinearSystem, h: float, noise_std: FloatArray) -> float:
    """q₀: the intensity of w whose effect on y over one sample of length h equals σ².

    Parameters
    ----------
    system : PerturbedLinearSystem
    h : float
        A typical sample length (the median).
    noise_std : ndarray (r,)
        σ of the output noise.

    Returns
    -------
    float
        The mean over the outputs of σ_i² / (C Q₁(h) Cᵀ)_ii (outputs that w does not reach
        in one sample are left out; 1 when none is reached).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.estimation.statistical.likelihood import process_noise_scale
    >>> q0 = process_noise_scale(prop3_monotone.system(), 0.01, np.array([0.01]))
    >>> bool(290 < q0 < 310)        # ≈ σ² / (h³/3) = 1e-4 / 3.3e-7 for a double integration
    True
    """
    Q1 = unit_process_noise(system.A, system.E, h)
    c = np.einsum("ia,ab,ib->i", system.C, Q1, system.C)
    ok = c > 0
    if not np.any(ok):
        return 1.0
    return float(np.mean(np.asarray(noise_std)[ok] ** 2 / c[ok]))


# Names of the printed filter module (declared for the type checker; bound when printed).
propagate_into: Callable[..., Any]
plant_work: Callable[..., Any]
C_OUT: FloatArray


def innovations(x0: Any, P0: Any, th: Any, U: Any, Y: Any, tt: Any, Rdiag: Any, Qs: Any,
                qidx: Any, q: float, pc: Any, WT: Any, NU: Any, LS: Any, xP: Any) -> int:
    """The EKF on x with θ fixed: normalised innovations and log S per sample and output.

    x propagated by the model's ``propagate_into`` (u held as ``pc, WT`` say) with P ← Φ P Φᵀ +
    q Qs[qidx[k]], the outputs updated one at a time in Joseph form; NU (N, r) receives
    ε/√S and LS (N, r) log S (0 where y is missing); the last x and P go into xP[0], xP[1:].
    Returns −1, or the first sample at which the filter is not finite.
    """
    n = x0.shape[0]
    r = C_OUT.shape[0]
    N = tt.shape[0]
    x = x0.copy()
    P = P0.copy()
    Phi = np.empty((n, n))
    Gam = np.empty((n, 0))          # the filter needs Φ only: Γ's columns are skipped
    T = np.empty((n, n))
    PC = np.empty(n)
    K = np.empty(n)
    # Γ's width (0) as a run-time int: a literal 0 would compile plant_work a second time
    work = plant_work(n, th.shape[0], Gam.shape[1], U.shape[1], WT.shape[1])
    for k in range(N):
        if k > 0:
            # a runtime True (n ≥ 1): the EKF's and the sweep's specialisation of propagate
            propagate_into(x, x, th, U, k - 1, tt[k] - tt[k - 1], pc, WT, n > 0, Phi, Gam,
                           *work)
            for i in range(n):
                for j in range(n):
                    acc = 0.0
                    for a in range(n):
                        acc += Phi[i, a] * P[a, j]
                    T[i, j] = acc
            for i in range(n):
                for j in range(i, n):
                    acc = q * Qs[qidx[k], i, j]
                    for a in range(n):
                        acc += T[i, a] * Phi[j, a]
                    P[i, j] = acc
                    P[j, i] = acc
        for i in range(r):
            yi = Y[k, i]
            if not math.isfinite(yi):
                NU[k, i] = 0.0
                LS[k, i] = 0.0
                continue
            e = yi
            for a in range(n):
                e -= C_OUT[i, a] * x[a]
            s = Rdiag[i]
            for a in range(n):
                acc = 0.0
                for b in range(n):
                    acc += P[a, b] * C_OUT[i, b]
                PC[a] = acc
                s += C_OUT[i, a] * acc
            if not (s > 0.0 and math.isfinite(s) and math.isfinite(e)):
                return k
            NU[k, i] = e / math.sqrt(s)
            LS[k, i] = math.log(s)
            for a in range(n):
                K[a] = PC[a] / s
                x[a] += K[a] * e
            # Joseph form: P ← (I − K c) P (I − K c)ᵀ + K R Kᵀ, c = C[i]
            for a in range(n):
                for b in range(n):
                    acc = P[a, b] - K[a] * PC[b]
                    T[a, b] = acc
            for a in range(n):
                for b in range(a, n):
                    acc = T[a, b]
                    for c_ in range(n):
                        acc -= T[a, c_] * C_OUT[i, c_] * K[b]
                    acc += K[a] * Rdiag[i] * K[b]
                    P[a, b] = acc
                    P[b, a] = acc
    for a in range(n):
        xP[0, a] = x[a]
        for b in range(n):
            xP[1 + a, b] = P[a, b]
    return -1


@functools.lru_cache(maxsize=16)
def _filter_for(model: ModelKernel) -> Callable[..., int]:
    mod, (name,) = printed_kernels(
        "thetahat_innovations", "Printed by thetahat.estimation.statistical.likelihood: the "
        "innovations filter of one model; do not edit (content-addressed).", [innovations],
        {"propagate_into": model.propagate_into, "plant_work": model.plant_work,
         "C_OUT": model.C}, model.compiled)
    fn: Callable[..., int] = getattr(mod, name)
    return fn


@dataclass(frozen=True, slots=True, eq=False)
class _Problem:
    """One record and everything the filter needs but θ and q."""

    system: PerturbedLinearSystem
    t: FloatArray
    U: FloatArray
    Y: FloatArray
    x0: FloatArray
    P0: FloatArray
    Rdiag: FloatArray
    Qs: FloatArray
    qidx: NDArray[np.int64]
    prop: Propagation
    run: Callable[..., int]
    valid: NDArray[np.bool_]
    compiled: bool = False

    def filter(self, theta: FloatArray, q: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        N, r, n = self.t.shape[0], self.Y.shape[1], self.x0.shape[0]
        NU, LS, xP = np.empty((N, r)), np.empty((N, r)), np.empty((n + 1, n))
        pc, WT = self.prop.arrays()
        bad = self.run(self.x0, self.P0, np.array(theta, dtype=np.float64), self.U, self.Y,
                       self.t, self.Rdiag, self.Qs, self.qidx, float(q), pc, WT, NU, LS, xP)
        if bad >= 0:
            NU[bad:] = np.nan
        return NU, LS, xP

    def residuals(self, theta: FloatArray, q: float) -> FloatArray:
        NU = self.filter(theta, q)[0][self.valid]
        # a filter that failed part-way is a very poor θ, not an error: a large finite residual
        return np.where(np.isfinite(NU), NU, 1e6)

    def nll(self, theta: FloatArray, q: float) -> float:
        NU, LS, _ = self.filter(theta, q)
        nu, ls = NU[self.valid], LS[self.valid]
        if not np.all(np.isfinite(nu)):
            return math.inf
        return 0.5 * float(np.sum(nu * nu + ls))


def _problem(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
             x0: FloatArray, x_sd: FloatArray, noise_std: FloatArray, prop: Propagation,
             compiled: bool | None) -> _Problem:
    model = model_kernel(system, compiled=compiled)
    h = np.diff(t)
    if h.size == 0:
        h = np.array([1.0])
    # one Q₁ per distinct sample length (to H_RTOL): a uniform record needs one exponential
    key = np.round(np.log(h) / H_RTOL).astype(np.int64)
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    Qs = np.stack([unit_process_noise(system.A, system.E, float(h[i])) for i in first])
    qidx = np.concatenate([[0], inv]).astype(np.int64)
    valid = np.isfinite(Y)
    return _Problem(system=system, t=np.ascontiguousarray(t, dtype=np.float64),
                    U=np.ascontiguousarray(U), Y=np.ascontiguousarray(Y),
                    x0=np.array(x0, dtype=np.float64), P0=np.diag(np.asarray(x_sd) ** 2),
                    Rdiag=np.asarray(noise_std, dtype=np.float64) ** 2,
                    Qs=np.ascontiguousarray(Qs), qidx=qidx, prop=prop,
                    run=_filter_for(model), valid=valid, compiled=model.compiled)


def _innovation_substeps(pb: _Problem, theta: FloatArray, q: float,
                         total: int | None = None, start: int = 1,
                         limit: int | None = None) -> int:
    """The RK4 sub-steps the likelihood at (θ, q) needs: its normalised innovations accurate
    to a tenth of θ̂'s standard error.

    The rule of :func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps` applied
    to what this likelihood fits: the innovations ε/√S with the floor n and with every
    sample's sub-steps doubled, over the record's first
    :data:`~thetahat.estimation.statistical.plant_kernel.ACCURACY_SAMPLES` samples
    (:func:`~thetahat.estimation.statistical.plant_kernel.doubling_floor`). At q = 0 the
    filter is the output-error model and the rule is the free run's; with process noise the
    filter corrects x at every sample, so a discretisation error no longer accumulates over
    the record but over the filter's memory, and is measured against √S ≥ σ (EMPS: 2
    sub-steps here against the free run's 16). ``total``: the record's length when ``pb``
    holds only its head (default: ``pb``'s). ``start``: the first floor tried; ``limit``:
    the first not tried (:func:`~thetahat.estimation.statistical.plant_kernel.doubling_floor`).
    """
    N = pb.t.shape[0] if total is None else total
    K = min(pb.t.shape[0], ACCURACY_SAMPLES)
    if K < 2:
        return 1
    head = replace(pb, t=pb.t[:K], U=pb.U[:K], Y=pb.Y[:K], qidx=pb.qidx[:K],
                   valid=pb.valid[:K])

    def run(n: int, refine: int) -> FloatArray:
        prop = replace(head.prop, substeps=n * refine, h_rho=head.prop.h_rho / refine)
        NU = replace(head, prop=prop).filter(theta, q)[0]
        return np.where(head.valid, NU, 0.0)     # a missing output: no innovation to compare

    return doubling_floor(run, N, start=start, limit=limit)


def innovation_substeps(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray,
                        Y: FloatArray, *, theta: FloatArray, q: float, x_hat0: FloatArray,
                        x_sd: FloatArray, noise_std: FloatArray, hold: str = DEFAULT_HOLD,
                        h_rho: float = H_RHO, compiled: bool | None = None, start: int = 1,
                        limit: int | None = None) -> int:
    """The RK4 sub-steps' floor at which the likelihood at (θ, q) is accurate: its normalised
    innovations move θ̂ by at most a tenth of a standard error when every sample's sub-steps
    are doubled (the rule :func:`fit_process_noise` applies to itself).

    Parameters
    ----------
    system, t, U, Y, x_hat0, x_sd, noise_std, hold, h_rho, compiled
        As for :func:`record_bound`.
    theta : ndarray (p,)
    q : float
        The process-noise intensity (≥ 0; 0: the output-error model, whose rule is the free
        run's).
    start, limit : int
        The first floor tried, and the first not tried (the result is then at most
        ``limit``): :func:`~thetahat.estimation.statistical.plant_kernel.doubling_floor`.

    Returns
    -------
    int
        The floor (≥ 1).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.estimation.statistical.likelihood import innovation_substeps
    >>> d = prop3_monotone.simulate(seed=0, t_end=5.0)
    >>> n = innovation_substeps(prop3_monotone.system(), d.t, np.asarray(d.u),
    ...                         np.asarray(d.y), theta=np.array([1.2]), q=0.0,
    ...                         x_hat0=np.zeros(2), x_sd=np.full(2, 10.0),
    ...                         noise_std=np.array([0.01]), compiled=False)
    >>> n >= 1
    True
    """
    K = min(len(t), ACCURACY_SAMPLES)        # the rule reads the head: set up only that
    head = _problem(system, np.asarray(t[:K], dtype=np.float64),
                    np.asarray(U[:K], dtype=np.float64), np.asarray(Y[:K], dtype=np.float64),
                    np.asarray(x_hat0, dtype=np.float64), np.asarray(x_sd, dtype=np.float64),
                    np.asarray(noise_std, dtype=np.float64),
                    Propagation(hold=hold, h_rho=h_rho), compiled)
    return _innovation_substeps(head, np.asarray(theta, dtype=np.float64), float(q),
                                total=len(t), start=start, limit=limit)


def _propagation(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
                 theta: FloatArray, x0: FloatArray, noise_std: FloatArray, hold: str,
                 substeps: int | None, h_rho: float, compiled: bool | None) -> Propagation:
    """The hold and the sub-steps (given, or chosen at θ from x0 on the record)."""
    if substeps is None:
        substeps = choose_substeps(model_kernel(system, compiled=compiled),
                                   np.asarray(t, dtype=np.float64), np.asarray(U, np.float64),
                                   np.asarray(Y, np.float64), np.asarray(theta, np.float64),
                                   np.asarray(x0, np.float64), noise_std, hold=hold,
                                   h_rho=h_rho)
    return Propagation(hold=hold, substeps=substeps, h_rho=h_rho)


def _fit_theta(pb: _Problem, theta0: FloatArray, q: float, theta_set: ParameterSet,
               max_nfev: int) -> tuple[FloatArray, FloatArray, int, float]:
    """Least squares of θ within Θ's bounding box, then projected onto Θ (exact for a box; for
    another convex Θ the projection is in the norm of the fit's own information JᵀJ).

    SciPy's iterations take :meth:`_Differences.secant`'s Jacobian (the differences at the
    start, Broyden's update after); where SciPy stops, the differences are taken again there
    (:meth:`_Differences.jacobian`, steps from the residuals' measured rounding noise), and
    give both the step still to go and the returned J. Where that step is more than
    :data:`STEP_TOL` standard errors, the fit starts again from there with them
    (:data:`FIT_RESTARTS`, within ``max_nfev`` residual evaluations in all). Returns (θ, J weighted as
    Huber's loss weighs it, the residual evaluations, the step still to go in standard
    errors)."""
    lo, hi = theta_bounds(theta_set)
    width = hi - lo

    def interior(th: FloatArray) -> FloatArray:     # SciPy's trf starts strictly inside
        return np.clip(th, lo + 1e-9 * width, hi - 1e-9 * width)
    inner = interior(theta0)
    diff = _Differences(pb, q, lo, hi, inner)
    nfev, start = 0, inner
    for _ in range(1 + FIT_RESTARTS):
        sol = least_squares(diff.residuals, start, jac=diff.secant, bounds=(lo, hi),
                            x_scale=width, method="trf", max_nfev=max_nfev - nfev,
                            xtol=FIT_RTOL, ftol=FIT_RTOL, loss="huber", f_scale=HUBER_C)
        nfev += int(sol.nfev)
        box_theta = np.asarray(sol.x, dtype=np.float64)
        res = diff.residuals(box_theta)
        J_raw = diff.jacobian(box_theta)
        J = _huber_weighted(J_raw, res)     # the information θ's covariance comes from
        cov = _inverse_information(J)
        theta = (box_theta if isinstance(theta_set, Box)
                 else project_theta(theta_set, box_theta, cov))
        step_se = _step_to_go(pb, q, J_raw, res, box_theta, theta, cov, theta_set)
        if step_se <= STEP_TOL or nfev >= max_nfev:
            break
        start = interior(box_theta)
    return theta, J, nfev, step_se


def _huber_weighted(J: FloatArray, res: FloatArray) -> FloatArray:
    """J with its rows scaled as SciPy scales them for Huber's loss at :data:`HUBER_C`, so
    that JᵀJ is that loss's Gauss–Newton Hessian: √(ρ′ + 2ρ″ε²), 1 within ±c and 0 beyond
    (held at √(machine ε), SciPy's floor)."""
    eps = float(np.finfo(np.float64).eps)
    scale = np.where(np.abs(res) <= HUBER_C, 1.0, math.sqrt(eps))
    return J * scale[:, None]


def _huber_cost(res: FloatArray) -> float:
    """½ Σ ρ(ε) of Huber's loss at :data:`HUBER_C` (what the fit of θ minimises)."""
    a = np.abs(res)
    return float(np.sum(np.where(a <= HUBER_C, 0.5 * a * a, HUBER_C * a - 0.5 * HUBER_C ** 2)))


#: The relative rounding noise of the residuals is taken within [machine ε, NOISE_MAX]: a
#: difference step of at most √NOISE_MAX = 0.1 % of θ's scale.
NOISE_MAX = 1e-6
#: The rounding noise is measured on the record's first NOISE_SAMPLES samples (all of a
#: shorter record): a ratio of two norms, as well measured on 2¹⁶ samples as on 10⁶, and the
#: step it gives enters as √η, so that the passes at θ and along the p columns, which need
#: the step, then run at once over the whole record. On 10⁶ LuGre samples the paper's trust
#: report: three whole-record passes, two of them at once, become two at once.
NOISE_SAMPLES = 1 << 16


class _Differences:
    """The normalised innovations as a function of θ and their Jacobian by forward differences.

    A filter pass is exact only to the rounding of its long recursion: an encoder record at
    σ = 1.7e-8 m on positions of 0.2 m leaves the innovations a relative noise η ≈ 1e-7, not
    machine ε, and a difference over SciPy's default step (√ε of θ) is then wrong by 50–80 %
    in three of EMPS's four columns;
    the fit it steers stops where its trust region collapses, short of the optimum. The noise
    is measured once (the residuals at θ and at θ moved by 64 ulps, over the record's first
    :data:`NOISE_SAMPLES` samples), and each step is √η · max(|θᵢ|, 1 % of Θ's width) (the
    forward difference's balance of rounding against truncation), towards Θ's inside at its
    upper face.

    Within one Gauss–Newton fit, :meth:`secant` updates the last difference Jacobian along
    each step taken (Broyden's rank-one update, in θ scaled as the steps are) instead of
    paying p filter passes at every iterate; the fit takes the differences again where it
    stopped (:func:`_fit_theta`), so the standard errors and the test of convergence rest on
    them, not on the update. On EMPS's first 12 000 samples mle's fits took 646 filter passes
    instead of 1 029, θ̂ within 0.005 standard errors.
    """

    def __init__(self, pb: _Problem, q: float, lo: FloatArray, hi: FloatArray,
                 theta: FloatArray) -> None:
        self.pb, self.q, self.lo, self.hi = pb, q, lo, hi
        eps = float(np.finfo(np.float64).eps)
        scale = np.maximum(np.abs(theta), 1e-2 * (hi - lo))
        # η over the head (the whole of a record of at most NOISE_SAMPLES samples): its passes
        # at θ and 64 ulps away do not depend on each other, and run at once
        head = pb if pb.t.shape[0] <= NOISE_SAMPLES else _head(pb, NOISE_SAMPLES)
        r0, r1 = _at_once(head, lambda th: head.residuals(th, q),
                          [theta, np.minimum(theta + 64.0 * eps * scale, hi)])
        norm = float(np.linalg.norm(r0))
        eta = float(np.linalg.norm(r1 - r0)) / norm if norm > 0.0 else eps
        self.noise = min(max(eta, eps), NOISE_MAX) if math.isfinite(eta) else NOISE_MAX
        self.steps = math.sqrt(self.noise) * scale
        self.scale = scale
        # the residuals at θ: these when the head is the record, else the first call's
        self._last: tuple[FloatArray, FloatArray] = (
            (theta.copy(), r0) if head is pb else (np.full_like(theta, np.nan), r0))
        self._last_jacobian: tuple[FloatArray, FloatArray] | None = None
        # (θ, residuals, J) the secant updates from, and the residual evaluations then
        self._anchor: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self._evaluations = self._anchor_evaluations = 0

    # Copies go out: SciPy 1.13 (our lowest) scales the residuals and the Jacobian in place
    # for the robust loss, which would corrupt the cache.
    def residuals(self, theta: FloatArray) -> FloatArray:
        if not np.array_equal(theta, self._last[0]):
            self._last = (np.array(theta, dtype=np.float64), self.pb.residuals(theta, self.q))
            self._evaluations += 1
        return self._last[1].copy()

    def jacobian(self, theta: FloatArray) -> FloatArray:
        if self._last_jacobian is not None and np.array_equal(theta, self._last_jacobian[0]):
            return self._last_jacobian[1].copy()
        p = theta.shape[0]
        steps = [-float(self.steps[i]) if theta[i] + self.steps[i] > self.hi[i]
                 else float(self.steps[i]) for i in range(p)]
        points = [np.array(theta, dtype=np.float64) for _ in range(p)]
        for i in range(p):
            points[i][i] += steps[i]
        known = np.array_equal(theta, self._last[0])
        # the residuals at θ (unless known) and along the p columns, all at once
        passes = _at_once(self.pb, lambda th: self.pb.residuals(th, self.q),
                          points if known else [np.array(theta, dtype=np.float64), *points])
        if not known:
            self._last = (np.array(theta, dtype=np.float64), passes.pop(0))
            self._evaluations += 1
        r0 = self._last[1]
        columns = [(r - r0) / step for r, step in zip(passes, steps)]
        J = np.column_stack(columns) if columns else np.empty((r0.shape[0], 0))
        self._last_jacobian = (np.array(theta, dtype=np.float64), J)
        self._anchor = (np.array(theta, dtype=np.float64), r0, J)
        self._anchor_evaluations = self._evaluations
        return J.copy()

    def secant(self, theta: FloatArray) -> FloatArray:
        """The Jacobian at θ for SciPy's iterations: Broyden's update of the last one along
        the step to θ (one residual pass, which SciPy has just made at θ, instead of p).

        The update is J + (Δr − J Δθ) (Δz/s)ᵀ / |Δz|², Δz = Δθ/s with s the steps' scale. The
        differences are taken instead at the first call, after SciPy refused a step (it
        evaluated the residuals more than once since the last Jacobian: the model was not
        good enough there) and where the update is not finite. Without that refresh the
        update alone stalled on the Silverbox from Θ's centre (83 standard errors short after
        60 evaluations); with it, it ends where the differences do (0.001 standard errors;
        both one-off runs)."""
        if self._anchor is None:
            return self.jacobian(theta)
        th0, r_a, J0 = self._anchor
        dth = np.asarray(theta, dtype=np.float64) - th0
        dz = dth / self.scale
        dd = float(dz @ dz)
        if dd == 0.0:
            return J0.copy()
        if self._evaluations - self._anchor_evaluations > 1:     # a step was refused
            return self.jacobian(theta)
        r = self.residuals(theta)
        J = J0 + np.outer((r - r_a) - J0 @ dth, dz / self.scale / dd)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
            return self.jacobian(theta)
        self._anchor = (np.array(theta, dtype=np.float64), r, J)
        self._anchor_evaluations = self._evaluations
        return J.copy()


def _head(pb: _Problem, n: int) -> _Problem:
    """The problem of ``pb``'s first n samples (views of its arrays)."""
    return replace(pb, t=pb.t[:n], U=pb.U[:n], Y=pb.Y[:n], qidx=pb.qidx[:n],
                   valid=pb.valid[:n])


def _at_once(pb: _Problem, fn: Callable[[Any], FloatArray], items: Any) -> list[FloatArray]:
    """``[fn(i) for i in items]``, each a filter pass of ``pb``, in :func:`difference_threads`
    threads when its filter is compiled (it releases the GIL; each pass has its own arrays,
    so the results are the same numbers in any order)."""
    items = list(items)
    workers = difference_threads(len(items)) if pb.compiled else 1
    if workers > 1:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            return list(pool.map(fn, items))
    return [fn(i) for i in items]


def difference_threads(p: int) -> int:
    """Threads for the p filter passes of a forward-difference Jacobian: one per core this
    process may use, at most p (the compiled filter releases the GIL, so they run at once;
    the columns are the same numbers in any order).

    Parameters
    ----------
    p : int
        The parameters (columns).

    Returns
    -------
    int
        ≥ 1.

    Examples
    --------
    >>> 1 <= difference_threads(4) <= 4
    True
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):          # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(int(p), cores))


def _step_to_go(pb: _Problem, q: float, J: FloatArray, res: FloatArray, box_theta: FloatArray,
                theta: FloatArray, cov: FloatArray, theta_set: ParameterSet) -> float:
    """The Gauss–Newton step of Huber's loss still to go (weights min(1, c/|ε|)) from the
    box's solution ``box_theta`` (where the raw Jacobian J and the residuals are), projected
    onto Θ, measured
    from the returned θ (Π_Θ of the box's solution): a fit that ends on Θ's face has
    converged there. In standard errors of θ (its largest component).

    The step is taken only as far as it lowers the loss (tried whole, then halved twice;
    one filter pass each): a long record's gradient ΣJᵀε cancels to a part in √N at the
    optimum, where a difference Jacobian's relative error of √η already points a step of
    √(ηN) standard errors that the loss does not follow (EMPS: 1.7 sd, uphill). A step no
    fraction of which descends is 0: the fit is at its minimum to the Jacobian's precision.
    """
    if not np.all(np.isfinite(res)):
        return math.inf
    w = np.minimum(1.0, HUBER_C / np.maximum(np.abs(res), 1e-300))
    Jw = J * w[:, None]
    delta = -np.linalg.lstsq(Jw.T @ J, Jw.T @ res, rcond=None)[0]
    if not np.all(np.isfinite(delta)):
        return math.inf
    se = np.sqrt(np.maximum(np.diag(cov), 1e-300))

    def in_se(move: FloatArray) -> float:
        with np.errstate(invalid="ignore"):
            ratio = np.where(np.isfinite(se), np.abs(move) / se, 0.0)
        return float(np.max(ratio, initial=0.0))

    lo, hi = theta_bounds(theta_set)
    base = _huber_cost(res)
    for frac in (1.0, 0.5, 0.25):
        target = project_theta(theta_set, box_theta + frac * delta, cov)
        if in_se(target - theta) <= 0.0:
            return 0.0
        trial = _huber_cost(pb.residuals(np.clip(target, lo, hi), q))
        if trial < base:
            return in_se(target - theta)
    return 0.0


def _search_log_q(pb: _Problem, theta: FloatArray, q0: float,
                  bounds: tuple[float, float] = (-Q_DECADES, Q_DECADES)
                  ) -> tuple[float, float]:
    """log₁₀(q / q₀) minimising −log L at θ within ``bounds``, to :data:`Q_XTOL`, and −log L
    there."""
    def f(s: float) -> float:
        return pb.nll(theta, q0 * 10.0 ** s)

    res = minimize_scalar(f, bounds=bounds, method="bounded", options={"xatol": Q_XTOL})
    return float(res.x), float(res.fun)


def _q_or_zero(pb: _Problem, theta: FloatArray, q: float, nll_q: float | None = None) -> float:
    """q, or 0 when the output-error model (q = 0) has the larger likelihood (``nll_q``:
    −log L at q when known)."""
    at_q = pb.nll(theta, q) if nll_q is None else nll_q
    return q if at_q <= pb.nll(theta, 0.0) else 0.0


def _search_q(pb: _Problem, theta: FloatArray, q0: float, near: float | None = None) -> float:
    """q̂ at θ (:func:`_search_around`); 0 when the output-error model has the larger
    likelihood."""
    s, f = _search_around(pb, theta, q0, near)
    return _q_or_zero(pb, theta, q0 * 10.0 ** s, f)


def _log_q_sd(pb: _Problem, theta: FloatArray, q0: float, s: float) -> float:
    """The standard error of log₁₀ q̂ at ``s`` from −log L's curvature there (a central
    second difference over ±2 :data:`Q_XTOL`, its centre moved inside ±:data:`Q_DECADES`
    when ``s`` is at a bound); inf where −log L is flat or not convex (q not pinned by these
    samples)."""
    d = 2.0 * Q_XTOL
    c = min(max(s, -Q_DECADES + 2.0 * d), Q_DECADES - 2.0 * d)    # the three points in range
    f = [pb.nll(theta, q0 * 10.0 ** v) for v in (c - d, c, c + d)]
    curvature = (f[0] + f[2] - 2.0 * f[1]) / (d * d)
    if not (np.isfinite(curvature) and curvature > 0.0):
        return math.inf
    return 1.0 / math.sqrt(curvature)


class QSearch(NamedTuple):
    """The process-noise intensity a record supports at a fixed θ (:func:`search_process_noise`).

    Attributes
    ----------
    q : float
        q̂ ≥ 0 (0 when the output-error model has the larger likelihood).
    samples : int
        The record's first samples the search ended on.
    log_sd : float
        The standard error of log₁₀ q̂ on them (inf: −log L flat there; NaN: not computed,
        the search ran on the longest head at once).
    """

    q: float
    samples: int
    log_sd: float


def _search_near(pb: _Problem, theta: FloatArray, q0: float, near: float
                 ) -> tuple[float, float] | None:
    """The search of log₁₀(q / q₀) within ±:data:`Q_NEAR_DECADES` of ``near`` (> 0), and −log L
    there; None when its minimum is at an edge of the bracket that is not the range's."""
    c = min(max(math.log10(near / q0), -Q_DECADES), Q_DECADES)
    lo, hi = max(-Q_DECADES, c - Q_NEAR_DECADES), min(Q_DECADES, c + Q_NEAR_DECADES)
    s, f = _search_log_q(pb, theta, q0, (lo, hi))
    if (s - lo <= Q_XTOL and lo > -Q_DECADES) or (hi - s <= Q_XTOL and hi < Q_DECADES):
        return None
    return s, f


def _search_around(pb: _Problem, theta: FloatArray, q0: float, near: float | None
                   ) -> tuple[float, float]:
    """log₁₀(q̂ / q₀) and −log L there: within ±:data:`Q_NEAR_DECADES` of ``near`` when it is
    finite and > 0 and the minimum is inside that bracket, over the whole range otherwise."""
    found = None
    if near is not None and near > 0.0 and math.isfinite(near):
        found = _search_near(pb, theta, q0, near)
    return found if found is not None else _search_log_q(pb, theta, q0)


def _search_head(head: Callable[[int], _Problem], N: int, theta: FloatArray, q0: float,
                 first: int, near: float | None = None) -> QSearch:
    """The search of :func:`search_process_noise` on heads of the record (``head(n)``: the
    problem of its first n samples): on ``first`` samples (around ``near`` when it is > 0,
    :func:`_search_near`; over the whole range when not, or when that search ends at its
    bracket's edge), then on :data:`Q_SEARCH_SAMPLES` (or N) when q̂ is not pinned to
    :data:`Q_XTOL` — around the first head's q̂ (± 4 of its standard errors, at least one
    decade) when it has one, over the whole range when not."""
    last = min(N, Q_SEARCH_SAMPLES)
    n = min(max(int(first), 2), last)
    pb = head(n)
    s, f = _search_around(pb, theta, q0, near)
    sd = math.nan
    if n < last:
        sd = _log_q_sd(pb, theta, q0, s)
        if not sd <= Q_XTOL:
            width = max(1.0, 4.0 * sd) if math.isfinite(sd) else 2.0 * Q_DECADES
            bounds = (max(-Q_DECADES, s - width), min(Q_DECADES, s + width))
            n, pb, sd = last, head(last), math.nan
            s, f = _search_log_q(pb, theta, q0, bounds)
    return QSearch(q=_q_or_zero(pb, theta, q0 * 10.0 ** s, f), samples=n, log_sd=sd)


def _inverse_information(J: FloatArray) -> FloatArray:
    """(JᵀJ)⁺ after Jacobi scaling, by a symmetric eigendecomposition: directions the data do
    not determine get infinite variance, not a huge finite one."""
    info = J.T @ J
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    lam, V = np.linalg.eigh(info / np.outer(d, d))
    keep = lam > 1e-12 * max(float(lam[-1]), 1e-300)
    cov = ((V[:, keep] / lam[keep]) @ V[:, keep].T) / np.outer(d, d)
    if not np.all(keep):
        # the undetermined directions: infinite variance on every parameter they move
        lost = np.any(np.abs(V[:, ~keep]) > 1e-6, axis=1)
        cov[lost, lost] = np.inf
    return np.asarray(cov, dtype=np.float64)


def record_bound(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
                 *, theta: FloatArray, x_hat0: FloatArray, x_sd: FloatArray,
                 noise_std: FloatArray, hold: str = DEFAULT_HOLD, substeps: int | None = None,
                 h_rho: float = H_RHO, compiled: bool | None = None
                 ) -> tuple[float, FloatArray]:
    """At a fixed θ: the process-noise intensity q the record supports, and θ's Cramér–Rao
    covariance with it (one filter set-up for both).

    Parameters
    ----------
    system : PerturbedLinearSystem
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
    theta : ndarray (p,)
    x_hat0, x_sd : ndarray (n,)
        Prior mean and standard deviation of x(t₀).
    noise_std : ndarray (r,)
    hold : {"zoh", "foh", "bandlimited", "smooth"}
    substeps : int, optional
        Default: chosen at θ (:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`).
    h_rho : float
    compiled : bool, optional

    Returns
    -------
    q : float
        q̂ ≥ 0 maximising the likelihood at θ (0 when the output-error model has the larger),
        searched on the record's first samples (:func:`search_process_noise`).
    cov : ndarray (p, p)
        As :func:`fisher_covariance` at (θ, q̂), on the whole record.
    """
    sigma = np.asarray(noise_std, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    prop = _propagation(system, t, U, Y, th, x_hat0, sigma, hold, substeps, h_rho, compiled)
    pb = _problem(system, t, U, Y, x_hat0, x_sd, sigma, prop, compiled)
    head = _heads(system, t, U, Y, x_hat0, x_sd, sigma, prop, compiled, whole=pb)
    q = _search_head(head, t.shape[0], th, process_noise_scale(system, sample_interval(t),
                                                                sigma), Q_FIRST_HEAD).q
    return q, _covariance(pb, th, q, *theta_box(system))


def _heads(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
           x_hat0: FloatArray, x_sd: FloatArray, sigma: FloatArray, prop: Propagation,
           compiled: bool | None, whole: _Problem | None = None) -> Callable[[int], _Problem]:
    """``head(n)``: the problem of the record's first n samples (``whole`` when it covers
    them all and is given)."""
    def head(n: int) -> _Problem:
        if whole is not None and n >= t.shape[0]:
            return whole
        return _problem(system, t[:n], U[:n], Y[:n], x_hat0, x_sd, sigma, prop, compiled)
    return head


def search_process_noise(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray,
                         Y: FloatArray, *, theta: FloatArray, x_hat0: FloatArray,
                         x_sd: FloatArray, noise_std: FloatArray, hold: str = DEFAULT_HOLD,
                         substeps: int | None = None, h_rho: float = H_RHO,
                         compiled: bool | None = None, first_head: int = Q_FIRST_HEAD,
                         near: float | None = None) -> QSearch:
    """q̂ at a fixed θ by a bounded search of −log L on the record's first samples.

    The search runs on the first ``first_head`` samples; when −log L's curvature there leaves
    log₁₀ q̂ a standard error above :data:`Q_XTOL` (a tenth of a decade: q not pinned by
    them), it runs again on the first :data:`Q_SEARCH_SAMPLES` samples (or all of a shorter
    record), around the first q̂. Each search is one-dimensional in log₁₀(q / q₀) over
    ±:data:`Q_DECADES` (q₀ = :func:`process_noise_scale`), to :data:`Q_XTOL`; q̂ is 0 when
    the output-error model has the larger likelihood on the samples searched.

    Given ``near`` (a q̂ already found on this record: at other sub-steps, or at a nearby θ),
    the first search is within ±:data:`Q_NEAR_DECADES` of it (over the whole range when its
    minimum is at the bracket's edge); the long head's is as above.

    Parameters
    ----------
    system, t, U, Y, theta, x_hat0, x_sd, noise_std, hold, substeps, h_rho, compiled
        As for :func:`record_bound`.
    first_head : int
        The first search's samples (``Q_SEARCH_SAMPLES``: one search on the long head).
    near : float, optional
        A q̂ to search around (ignored unless finite and > 0).

    Returns
    -------
    QSearch
        q̂, the samples it was searched on and its standard error there.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.estimation.statistical.likelihood import search_process_noise
    >>> d = prop3_monotone.simulate(seed=0, t_end=10.0)                  # an exact model
    >>> found = search_process_noise(prop3_monotone.system(), d.t, np.asarray(d.u),
    ...                              np.asarray(d.y).reshape(-1, 1), theta=np.array([1.2]),
    ...                              x_hat0=np.zeros(2), x_sd=np.full(2, 10.0),
    ...                              noise_std=np.array([0.01]), compiled=False)
    >>> found.samples == d.t.size, bool(found.q < 1e-3)
    (True, True)
    """
    sigma = np.asarray(noise_std, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    prop = _propagation(system, t, U, Y, th, x_hat0, sigma, hold, substeps, h_rho, compiled)
    return _search_head(_heads(system, t, U, Y, x_hat0, x_sd, sigma, prop, compiled),
                        t.shape[0], th, process_noise_scale(system, sample_interval(t), sigma),
                        first_head, near)


def process_noise_at(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray,
                     Y: FloatArray, *, theta: FloatArray, x_hat0: FloatArray,
                     x_sd: FloatArray, noise_std: FloatArray, hold: str = DEFAULT_HOLD,
                     substeps: int | None = None, h_rho: float = H_RHO,
                     compiled: bool | None = None, near: float | None = None) -> float:
    """q̂ at a fixed θ: :func:`search_process_noise`'s q (0 when the output-error model has
    the larger likelihood).

    Parameters
    ----------
    system, t, U, Y, theta, x_hat0, x_sd, noise_std, hold, substeps, h_rho, compiled, near
        As for :func:`search_process_noise`.

    Returns
    -------
    float
    """
    return search_process_noise(system, t, U, Y, theta=theta, x_hat0=x_hat0, x_sd=x_sd,
                                noise_std=noise_std, hold=hold, substeps=substeps,
                                h_rho=h_rho, compiled=compiled, near=near).q


class RecordEvidence(NamedTuple):
    """What one linearisation of the innovations at a fixed θ says (:func:`record_evidence`).

    Attributes
    ----------
    q : float
        q̂ ≥ 0 at θ, as :func:`record_bound` searches it.
    cov : ndarray (p, p)
        The Cramér–Rao covariance (JᵀJ)⁺ at (θ, q̂), as :func:`record_bound` returns it.
    step : ndarray (p,)
        The Gauss–Newton step δ = −(JᵀJ)⁺ Jᵀ ν from θ (least squares of J δ = −ν): where one
        linearisation of the innovations ν puts the maximum of the likelihood, θ + δ.
    score : float
        Rao's score statistic νᵀ J (JᵀJ)⁺ Jᵀ ν = δᵀ (JᵀJ) δ: χ² with p degrees of freedom
        when θ is the true value and the model holds.
    cost : float
        The mean squared normalised innovation at θ (≈ 1 when the noise model is right).
    """

    q: float
    cov: FloatArray
    step: FloatArray
    score: float
    cost: float


def record_evidence(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
                    *, theta: FloatArray, x_hat0: FloatArray, x_sd: FloatArray,
                    noise_std: FloatArray, q: float | None = None, hold: str = DEFAULT_HOLD,
                    substeps: int | None = None, h_rho: float = H_RHO,
                    compiled: bool | None = None) -> RecordEvidence:
    """:func:`record_bound` with the score of the innovations at θ: is θ where the data put it?

    The same filter passes as :func:`record_bound` (the q search on the first
    :data:`Q_SEARCH_SAMPLES` samples, then p + 1 passes over the record for the Jacobian J of
    the normalised innovations ν): the gradient Jᵀν and the Gauss–Newton information JᵀJ of
    −log L at θ come with them, hence Rao's score test and the one-step θ + δ at no cost.

    Parameters
    ----------
    system, t, U, Y, theta, x_hat0, x_sd, noise_std, hold, substeps, h_rho, compiled
        As for :func:`record_bound` (the sub-steps, when not given, are chosen once at θ and
        serve the q search and the Jacobian alike).
    q : float, optional
        The intensity of the process noise; default: searched at θ
        (:func:`process_noise_at`).

    Returns
    -------
    RecordEvidence

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.estimation.statistical.likelihood import record_evidence
    >>> d = prop3_monotone.simulate(seed=0, t_end=10.0)          # θ = 1.2
    >>> ev = record_evidence(prop3_monotone.system(), d.t, np.asarray(d.u), np.asarray(d.y),
    ...                      theta=np.array([1.5]), x_hat0=np.zeros(2), x_sd=np.full(2, 10.0),
    ...                      noise_std=np.array([0.01]), compiled=False)
    >>> from thetahat.estimation.statistical.trust import chi2_limit
    >>> bool(ev.score > 3 * chi2_limit(1)), bool(abs(1.5 + ev.step[0] - 1.2) < 0.05)
    (True, True)
    """
    sigma = np.asarray(noise_std, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    prop = _propagation(system, t, U, Y, th, x_hat0, sigma, hold, substeps, h_rho, compiled)
    pb = _problem(system, t, U, Y, x_hat0, x_sd, sigma, prop, compiled)
    if q is None:
        q = process_noise_at(system, t, U, Y, theta=th, x_hat0=x_hat0, x_sd=x_sd,
                             noise_std=sigma, hold=hold, substeps=prop.substeps, h_rho=h_rho,
                             compiled=compiled)
    r0, J = _jacobian(pb, th, q, *theta_box(system))
    cov = _inverse_information(J)
    d = np.sqrt(np.maximum(np.einsum("ij,ij->j", J, J), 1e-300))
    step = np.linalg.lstsq(J / d, -r0, rcond=None)[0] / d     # Jacobi-scaled least squares
    fitted = J @ step
    return RecordEvidence(q=float(q), cov=cov, step=step, score=float(fitted @ fitted),
                          cost=float(np.mean(r0 * r0)) if r0.size else math.nan)


def fisher_covariance(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray,
                      Y: FloatArray, *, theta: FloatArray, q: float, x_hat0: FloatArray,
                      x_sd: FloatArray, noise_std: FloatArray, hold: str = DEFAULT_HOLD,
                      substeps: int | None = None, h_rho: float = H_RHO,
                      compiled: bool | None = None) -> FloatArray:
    """The Cramér–Rao covariance of θ on a record: the inverse Fisher information at θ.

    The Gauss–Newton information JᵀJ of the normalised innovations ε/√S of the model with
    process noise q on φ (module docstring), J by forward differences of whole filter passes
    with steps of 1e-6 of Θ's width (taken inward at Θ's faces). Parameters the record does
    not determine get an infinite variance.

    Parameters
    ----------
    system : PerturbedLinearSystem
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
    theta : ndarray (p,)
    q : float
        Process-noise intensity (0: the output-error model).
    x_hat0, x_sd : ndarray (n,)
    noise_std : ndarray (r,)
    hold : {"zoh", "foh", "bandlimited", "smooth"}
    substeps : int, optional
        Default: chosen at θ (:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`).
    h_rho : float
    compiled : bool, optional

    Returns
    -------
    ndarray (p, p)
    """
    sigma = np.asarray(noise_std, dtype=np.float64)
    prop = _propagation(system, t, U, Y, np.asarray(theta, dtype=np.float64), x_hat0, sigma,
                        hold, substeps, h_rho, compiled)
    pb = _problem(system, t, U, Y, x_hat0, x_sd, sigma, prop, compiled)
    return _covariance(pb, np.asarray(theta, dtype=np.float64), q, *theta_box(system))


def _covariance(pb: _Problem, th: FloatArray, q: float, lo: FloatArray, hi: FloatArray
                ) -> FloatArray:
    return _inverse_information(_jacobian(pb, th, q, lo, hi)[1])


def _jacobian(pb: _Problem, th: FloatArray, q: float, lo: FloatArray, hi: FloatArray
              ) -> tuple[FloatArray, FloatArray]:
    """The normalised innovations at θ and their Jacobian, by :class:`_Differences`' forward
    differences (p + 1 filter passes at once, and two over the noise's head)."""
    diff = _Differences(pb, q, lo, hi, np.asarray(th, dtype=np.float64))
    J = diff.jacobian(th)           # first: the residuals at θ are then among its passes
    return diff.residuals(th), J


def fit_process_noise(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray,
                      Y: FloatArray, *, theta0: FloatArray, x_hat0: FloatArray,
                      x_sd: FloatArray, noise_std: FloatArray, q: float | None = None,
                      max_nfev: int = 60, hold: str = DEFAULT_HOLD, substeps: int | None = None,
                      h_rho: float = H_RHO, compiled: bool | None = None,
                      min_substeps: int = 1, q_near: float | None = None,
                      at_q_near: bool = False) -> ProcessNoiseFit:
    """Maximum-likelihood θ and q of the model with process noise on φ (module docstring).

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a symbolic g and any convex Θ (fitted in its bounding box, then projected onto Θ).
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        The record (validated by the caller); NaN in Y marks missing samples.
    theta0 : ndarray (p,)
        Starting θ (projected onto Θ).
    x_hat0, x_sd : ndarray (n,)
        Prior mean and standard deviation of x(t₀).
    noise_std : ndarray (r,)
        σ of the output noise, > 0.
    q : float, optional
        The intensity; default: estimated with θ.
    max_nfev : int
        Residual evaluations per Gauss–Newton fit of θ (each iterate one pass, and p more
        where its Jacobian is taken by differences: at the start, after a refused step, at
        the end).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples (:mod:`~thetahat.estimation.hold`); U holds the samples it
        reconstructs from (:func:`~thetahat.estimation.statistical.input_hold.stage2_samples`).
    substeps : int, optional
        The RK4 sub-steps' accuracy floor; default: the innovations' own
        (the rule of :func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps` applied
        to the normalised innovations), at (θ₀, q) and again at (θ, q̂) after the search of q,
        the larger kept.
    h_rho : float
    compiled : bool, optional
    min_substeps : int
        Where the default's search starts (≥ 1; the floor is at least this): e.g. the floor
        of a fit of this record's first samples, which a longer window rarely needs less of
        (its error is allowed over more samples), so that the fits of a growing record do not
        run the smaller floors again.
    q_near : float, optional
        Where the estimate of q starts (``q`` None only): e.g. the q of a fit of this
        record's first samples. θ is fitted first at it (not at the data's scale q₀), and q
        is searched within ±:data:`Q_NEAR_DECADES` of it, over the whole range when the
        minimum is at that bracket's edge. Ignored unless finite and at least the data's
        scale q₀ (:func:`process_noise_scale`): a model error the record shows, which pins
        q; below it −log L is nearly flat in q, its minimum depends on where θ was fitted
        first, and the fit starts at q₀ and searches the whole range as without it.
    at_q_near : bool
        ``theta0`` is already the fit of θ at ``q_near`` on these samples (a fit with that q
        fixed, which a consistency test then refused): q is searched from it at once, the fit
        of θ at ``q_near`` not run again.

    Returns
    -------
    ProcessNoiseFit

    Raises
    ------
    NonFiniteError
        The filter is not finite at the fitted θ.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.estimation.statistical.likelihood import fit_process_noise
    >>> d = prop3_monotone.simulate(seed=0, t_end=10.0)
    >>> fit = fit_process_noise(prop3_monotone.system(), d.t, np.asarray(d.u), np.asarray(d.y),
    ...                         theta0=np.array([1.0]), x_hat0=np.zeros(2),
    ...                         x_sd=np.full(2, 10.0), noise_std=np.array([0.01]),
    ...                         compiled=False)
    >>> bool(abs(fit.theta[0] - 1.2) < 4 * fit.theta_se[0])
    True
    """
    theta_set = system.require_parameter_set("stage 2")
    sigma = np.asarray(noise_std, dtype=np.float64)
    chosen = substeps is None           # else the caller's, kept
    theta = project_theta(theta_set, np.asarray(theta0, dtype=np.float64))
    h_med = sample_interval(t)
    q0 = process_noise_scale(system, h_med, sigma)
    near = q_near if (q_near is not None and math.isfinite(q_near) and q_near >= q0) else None
    q_now = (near or q0) if q is None else float(q)
    pb = _problem(system, t, U, Y, x_hat0, x_sd, sigma, Propagation(hold=hold, h_rho=h_rho),
                  compiled)
    # the floor at (θ₀, q), or at (θ₀, q₀) when q is estimated: also when it starts at a
    # larger q_near, whose floor can be smaller than the one q̂ needs (the check after the
    # search keeps the larger of the two floors, never lowers it)
    floor = (_innovation_substeps(pb, theta, q0 if q is None else q_now, start=min_substeps)
             if substeps is None else substeps)
    pb = replace(pb, prop=replace(pb.prop, substeps=floor))
    if q is None:
        for i in range(ALTERNATIONS):
            if not (i == 0 and at_q_near and near is not None):
                theta = _fit_theta(pb, theta, q_now, theta_set, max_nfev)[0]
            q_now = _search_q(pb, theta, q0, near)
        if chosen:                      # again at the (θ, q̂) found: a q̂ far below q₀
            # may need more (the floors below the one taken are not run again)
            more = _innovation_substeps(pb, theta, q_now, start=pb.prop.substeps)
            if more > pb.prop.substeps:
                pb = replace(pb, prop=replace(pb.prop, substeps=more))
    theta, J, nfev, step_se = _fit_theta(pb, theta, q_now, theta_set, max_nfev)
    NU, LS, xP = pb.filter(theta, q_now)
    nu = NU[pb.valid]
    if not np.all(np.isfinite(nu)):
        raise NonFiniteError("the process-noise likelihood's filter is not finite at the "
                             f"fitted θ = {theta}; check the model and the data.")
    cov = _inverse_information(J)
    n_meas = int(nu.size)
    return ProcessNoiseFit(theta=theta, cov=cov, q=float(q_now), q_scale=q0,
                           nll=0.5 * float(np.sum(nu * nu + LS[pb.valid])),
                           x_end=xP[0].copy(), P_end=xP[1:].copy(),
                           cost=float(np.mean(nu * nu)) if n_meas else math.nan,
                           n_meas=n_meas, noise_std=sigma, core_cost=mad_variance(nu),
                           burst_fraction=float(np.mean(np.abs(nu) > HUBER_C))
                           if n_meas else math.nan, iterations=nfev, step_se=step_se,
                           substeps=pb.prop.substeps)
