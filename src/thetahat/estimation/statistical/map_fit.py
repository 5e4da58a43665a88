"""The MAP fits of stage 2: (x(t₀), θ) fitted by Gauss–Newton, on a schedule of information.

On a window of samples k₀ … k₁ the fit (:func:`fit_map`) minimises over q = col(x(t_{k₀}), θ)

    J(q) = Σ_k ‖y_k − C x_k(q)‖²_{R⁻¹} + (q − q̄)ᵀ Π⁻¹ (q − q̄),

x_k(q) from the sampled-data map of :mod:`~thetahat.estimation.statistical.plant_kernel`, with the
sensitivities ψ_k = C ∂x_k/∂q chained through the same map's exact Jacobians (Φ, Γ):
(Σ ψᵀR⁻¹ψ + Π⁻¹) Δ = Σ ψᵀR⁻¹ r − Π⁻¹(q − q̄), solved after Jacobi scaling by a symmetric
eigendecomposition (directions the data and the prior do not determine are left alone); the
step is halved until J decreases; θ is projected onto Θ after each step (projected
Gauss–Newton: the projection of :mod:`~thetahat.estimation.statistical.stage2_set` in the norm weighted
by the inverse of the step's marginal covariance of θ, ((M⁻¹)_θθ)⁻¹ — a clip for a box, the
exact weighted projection for a ball or ellipsoid,
:meth:`~thetahat.model.paramset.ConvexSet.nearest` for a general convex set; each trial point is feasible and J decreases, so the iteration is a
descent method on Θ); the iteration stops when |Δθ| falls below :data:`STEP_TOL` standard
errors or after ``max_iter`` iterations.

When the output-error fit is not consistent with the noise (a model that is not exact),
:func:`fit_record` tries the likelihood with process noise on φ
(:mod:`~thetahat.estimation.statistical.likelihood`); :func:`fit_as_prior` turns a fit into
the joint EKF's state at its last sample (the arrival cost of the samples that follow).

:class:`FitSchedule` holds the fits' settings. By default (``times`` None) it fits on the
information schedule (:func:`information_schedule`: counts of samples, never seconds), all the
data so far each time — offline and streaming alike; refitting at √2-fold sample counts costs
at most √2/(√2 − 1) ≈ 3.4 fits of the whole record, O(1) per sample amortised, while the stream
keeps its samples (O(N) memory). A caller who must bound the memory gives ``times`` (seconds,
e.g. :func:`doubling_schedule`) and a finite ``full_window``: fits at those times refit all data
while the elapsed time is at most ``full_window``; later ones use the block since the previous
fit with the previous fit's θ and its marginal covariance as the prior on θ — the arrival
cost, which summarises the older data — and a wide prior on x at the block's start centred at
the previous fit's end state. (Dropping the older data's information on x is conservative
only for models that forget x(t₀) quickly: the caller's choice of times and window says how
quickly.) The estimator that runs these fits over a record or a stream is
:class:`~thetahat.estimation.statistical.mle.MapEstimator`; the guarded estimator re-anchors
its stage 2 with them.

What it may import: :mod:`thetahat.model`, the package's errors, and, in this room,
``common``, ``noise_level``, ``plant_kernel``, ``stage2_set`` and ``likelihood`` (the fit with
process noise, imported where it is used: it brings SciPy's optimisers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...errors import DimensionError, NonFiniteError
from ...model.paramset import ParameterSet
from ...model.system import PerturbedLinearSystem
from .common import STEP_TOL, resolve_noise_std, sample_interval, theta_prior_sd, x_prior_sd
from .noise_level import MAD_VARIANCE_SD, MIN_SAMPLES
from .plant_kernel import H_RHO, Propagation, choose_substeps, model_kernel
from .sweep import sweep_kernel
from ..hold import DEFAULT_HOLD, check_hold
from .stage2_set import project_theta

if TYPE_CHECKING:
    from .likelihood import ProcessNoiseFit

__all__ = ["FitResult", "FitSchedule", "INFO_GROWTH", "MAX_BURST_FRACTION", "MAX_HALVINGS",
           "Q_SEARCH_GROWTH", "REJECT_SE_GROWTH", "REJECT_STEP_SE", "STEP_TOL", "doubling_schedule",
           "first_fit_samples", "fit_as_prior", "fit_map", "fit_record", "information_schedule",
           "solve_scaled", "why_not_applied"]

FloatArray = NDArray[np.float64]

#: Halvings of the Gauss–Newton step before the fit gives up improving.
MAX_HALVINGS = 10
#: A fit whose standard error of a parameter is more than this many times the previous
#: applied fit's is not applied: two orders of magnitude (more data never does that; the
#: cylinder's fit at sample 125 749 that was applied had 1e4).
REJECT_SE_GROWTH = 100.0
#: A fit that stopped with more than this many of its standard errors still to go (its
#: ``step_se``) did not converge and is not applied: its θ is further from the optimum of its
#: own data than that optimum is from the truth.
REJECT_STEP_SE = 1.0
#: A fit with process noise is consistent with at most this fraction of its normalised
#: innovations in bursts (beyond Huber's ±3; 0.27 % for Gaussian ones): a model error that
#: comes and goes (an unmeasured force pulse, a slip) is what the Huber loss of that fit is
#: for, while a wrong model, or a fit stuck far from its optimum, misses on most samples.
MAX_BURST_FRACTION = 0.05
#: :func:`fit_record` searches q anew once the window has grown this many times since q's last
#: search (q̂'s relative standard error, ∝ 1/√samples, has halved), besides on the first fit
#: with process noise and on the final one: a q searched on a short early window must not
#: decide the fits of a long record (EMPS from sample 9000 on: the q of the first fit that
#: needed one, on 34 samples, is 705× the whole record's; benchmarks/bench_emps.py --fits).
Q_SEARCH_GROWTH = 4.0


@dataclass(frozen=True, slots=True, eq=False)
class FitResult:
    """One MAP fit on samples k0 … k1 − 1.

    Attributes
    ----------
    k0, k1 : int
        The window (sample indices, k1 exclusive).
    x_start, x_end : ndarray (n,)
        Fitted x at the first and the last sample of the window.
    theta : ndarray (p,)
    cov : ndarray (n + p, n + p)
        Inverse of the Gauss–Newton information of (x_start, θ) (the Laplace covariance).
    cov_end : ndarray (n + p, n + p)
        The same mapped to (x_end, θ).
    cost : float
        J at the optimum ÷ the number of scalar measurements (≈ 1 for a correct model).
    iterations : int
    noise_std : ndarray (r,)
    n_meas : int
        Scalar measurements in the window.
    process_noise : float
        q of the fit's model: 0 for the output-error fit of :func:`fit_map`, the estimated
        intensity of the noise on φ for :func:`~thetahat.estimation.statistical.likelihood.fit_process_noise`
        (the model error the data revealed).
    core_cost, burst_fraction : float
        For the fit with process noise: the Gaussian-core variance of its normalised
        innovations and the fraction of them beyond ±3
        (:class:`~thetahat.estimation.statistical.likelihood.ProcessNoiseFit`); NaN otherwise.
    q_window : int
        For the fit with process noise: the samples of the window on which q was last searched
        (:func:`fit_record`); 0 otherwise.
    step_se : float
        The Gauss–Newton step still to go at the returned point (projected onto Θ), in
        standard errors of θ (its largest component): below :data:`STEP_TOL` when the fit
        converged; inf when no step was computed.
    substeps : int
        The RK4 sub-steps' accuracy floor the fit propagated with.
    """

    k0: int
    k1: int
    x_start: FloatArray
    x_end: FloatArray
    theta: FloatArray
    cov: FloatArray
    cov_end: FloatArray
    cost: float
    iterations: int
    noise_std: FloatArray
    n_meas: int = 1
    process_noise: float = 0.0
    core_cost: float = math.nan
    burst_fraction: float = math.nan
    q_window: int = 0
    step_se: float = 0.0
    substeps: int = 1

    @property
    def finite(self) -> bool:
        """θ, x at the window's end and the covariance are finite (a fit that may be used)."""
        return bool(np.all(np.isfinite(self.theta)) and np.all(np.isfinite(self.cov))
                    and np.all(np.isfinite(self.x_end)))

    @property
    def consistent(self) -> bool:
        """The residuals are those of the noise model; otherwise the fit is stuck or the model
        is wrong, and stage 2 does not take it.

        Either the cost per measurement is within 6 standard deviations of its χ² mean (1),
        or, for the fit with process noise (whose θ is fitted with Huber's loss, for records
        with bursts the model leaves out), the innovations' Gaussian core is: its variance
        within 6 standard deviations of 1 (:func:`~thetahat.estimation.statistical.noise_level.mad_variance`)
        with at most :data:`MAX_BURST_FRACTION` of them beyond ±3. On EMPS's measured record
        from sample 9000 on the final fit's mean square is 1.29 (a few force bursts) and its
        core 0.92 (benchmarks/bench_emps.py --fits).
        """
        if not (np.isfinite(self.cost) and np.all(np.isfinite(self.cov_end))):
            return False
        root_n = math.sqrt(max(self.n_meas, 1))
        if self.cost <= 1.0 + 6.0 * math.sqrt(2.0) / root_n:
            return True
        return bool(self.core_cost <= 1.0 + 6.0 * MAD_VARIANCE_SD / root_n
                    and self.burst_fraction <= MAX_BURST_FRACTION)

    def rejection(self, previous: FitResult | None = None) -> str | None:
        """Why this fit must not be applied, or None: a fit that did not fit is never applied.

        A fit is rejected when it is not finite, when it stopped more than
        :data:`REJECT_STEP_SE` of its standard errors short of its optimum (it did not
        converge), or when a standard error of θ grew more than :data:`REJECT_SE_GROWTH` times
        against ``previous``, the last fit applied (a fit of more data has smaller standard
        errors; growth by orders of magnitude is a fit that lost the optimum, whatever its cost
        says).

        Parameters
        ----------
        previous : FitResult, optional
            The last fit applied.

        Returns
        -------
        str or None
            One sentence naming the samples, the check and the numbers.
        """
        where = f"the fit of samples {self.k0}…{self.k1 - 1}"
        if not self.finite:
            return f"{where} came back non-finite"
        if not self.step_se <= REJECT_STEP_SE:
            return (f"{where} stopped {self.step_se:.3g} standard errors short of its optimum "
                    f"(more than {REJECT_STEP_SE:g}): it did not converge")
        if previous is not None and previous.finite:
            old, new = previous.theta_se, self.theta_se
            ok = (old > 0) & np.isfinite(old)
            if np.any(ok) and np.any(new[ok] > REJECT_SE_GROWTH * old[ok]):
                ratio = float(np.max(new[ok] / old[ok]))
                return (f"{where} has standard errors up to {ratio:.3g} times the previous "
                        f"fit's (of samples {previous.k0}…{previous.k1 - 1}): it lost the "
                        "optimum")
        return None

    @classmethod
    def of_process_noise(cls, pf: ProcessNoiseFit, k1: int, x_hat0: FloatArray,
                         x_sd: FloatArray) -> FitResult:
        """The fit of samples 0 … k1 − 1 with process noise on φ as a FitResult.

        The covariances put the filter's x covariance (at the start: the prior N(x_hat0,
        diag(x_sd²)); at the end: the filter's) beside θ's.
        """
        x_sd = np.asarray(x_sd, dtype=np.float64)
        n, p = x_sd.shape[0], pf.theta.shape[0]
        cov = np.zeros((n + p, n + p))
        cov[:n, :n] = np.diag(x_sd ** 2)
        cov[n:, n:] = pf.cov
        cov_end = cov.copy()
        cov_end[:n, :n] = pf.P_end
        return cls(k0=0, k1=k1, x_start=np.array(x_hat0, dtype=np.float64), x_end=pf.x_end,
                   theta=pf.theta, cov=cov, cov_end=cov_end, cost=pf.cost,
                   iterations=pf.iterations, noise_std=pf.noise_std, n_meas=pf.n_meas,
                   process_noise=pf.q, core_cost=pf.core_cost,
                   burst_fraction=pf.burst_fraction, step_se=pf.step_se,
                   substeps=pf.substeps)

    @property
    def theta_se(self) -> FloatArray:
        """Standard errors of θ, √diag of its covariance block."""
        n = self.x_start.shape[0]
        return np.sqrt(np.maximum(np.diag(self.cov)[n:], 0.0))

    def __repr__(self) -> str:
        return (f"FitResult(samples {self.k0}…{self.k1 - 1}, theta={self.theta}, "
                f"se={self.theta_se}, cost={self.cost:.3g}, iterations={self.iterations})")


def solve_scaled(M: FloatArray, g: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(M⁺ g, M⁺) for a symmetric PSD M, by Jacobi scaling and a symmetric eigendecomposition.

    Directions whose scaled eigenvalue is below 1e-12 of the largest are left out (the
    pseudo-inverse): the fits' Gauss–Newton solve, and an information from a covariance.

    Parameters
    ----------
    M : ndarray (q, q)
    g : ndarray (q,)

    Returns
    -------
    tuple of ndarray
        M⁺ g (q,) and M⁺ (q, q).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.map_fit import solve_scaled
    >>> d, Minv = solve_scaled(np.diag([4.0, 1e-3]), np.array([2.0, 1.0]))
    >>> d.round(6).tolist()
    [0.5, 1000.0]
    """
    d = np.sqrt(np.maximum(np.diag(M), 1e-300))
    Ms = M / np.outer(d, d)
    lam, V = np.linalg.eigh(Ms)
    keep = lam > 1e-12 * max(lam[-1], 1e-300)
    inv = (V[:, keep] / lam[keep]) @ V[:, keep].T
    Minv = inv / np.outer(d, d)
    return Minv @ g, Minv


def fit_map(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray, *,
            k0: int, k1: int, q_start: FloatArray, q_prior: FloatArray,
            prior_info: FloatArray, noise_std: FloatArray, max_iter: int = 6,
            skip_first: bool = False, hold: str = DEFAULT_HOLD, substeps: int | None = None,
            h_rho: float = H_RHO, compiled: bool | None = None) -> FitResult:
    """One Gauss–Newton MAP fit of q = col(x(t_{k0}), θ) on samples k0 … k1 − 1.

    Parameters
    ----------
    system : PerturbedLinearSystem
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        The record (validated by the caller); U the samples stage 2 reconstructs u from
        (:func:`~thetahat.estimation.statistical.input_hold.stage2_samples`); NaN in Y marks
        missing samples.
    k0, k1 : int
        The window.
    q_start : ndarray (n + p,)
        Starting point (warm start).
    q_prior, prior_info : ndarray (n + p,), (n + p, n + p)
        The prior mean q̄ and information Π⁻¹ (the arrival cost).
    noise_std : ndarray (r,)
    max_iter : int
    skip_first : bool
        Leave y_{k0} out (it is already summarised by the arrival cost).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples (:mod:`~thetahat.estimation.hold`).
    substeps : int, optional
        The RK4 sub-steps' accuracy floor; default: chosen on the window at ``q_start``
        (:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`).
    h_rho : float
    compiled : bool, optional

    Returns
    -------
    FitResult
        With ``step_se``: the Gauss–Newton step still to go at the returned point, in standard
        errors of θ (below :data:`STEP_TOL` when the fit converged).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.map_fit import fit_map
    >>> sys_ = lugre.system()
    >>> d = lugre.simulate(seed=0, t_end=0.3)
    >>> U, Y = np.array(d.u), np.array(d.y)
    >>> fit = fit_map(sys_, d.t, U, Y, k0=0, k1=301, q_start=np.array([0.0, 0.0, 0.5]),
    ...               q_prior=np.array([0.0, 0.0, 0.5]),
    ...               prior_info=np.diag([1e-2, 1e-2, 1 / 0.2375 ** 2]),
    ...               noise_std=np.array([0.02]), max_iter=20, compiled=False)
    >>> bool(abs(fit.theta[0] - 0.28) < 3 * fit.theta_se[0] + 1e-3), fit.step_se < STEP_TOL
    (True, True)
    """
    model = model_kernel(system, compiled=compiled)
    sw = sweep_kernel(model)
    n, p = system.n, system.p
    nq = n + p
    theta_set = system.require_parameter_set("stage 2")
    Rinv = 1.0 / noise_std ** 2
    A, b, T = np.empty((nq, nq)), np.empty(nq), np.empty((n, nq))
    X = np.empty((k1 - k0, n))
    tt = np.ascontiguousarray(t, dtype=np.float64)
    Uc = np.ascontiguousarray(U, dtype=np.float64)
    if substeps is None:
        substeps = choose_substeps(model, tt[k0:k1], Uc[k0:k1], Y[k0:k1], q_start[n:],
                                   q_start[:n], noise_std, hold=hold, h_rho=h_rho)
    pc, WT = Propagation(hold=hold, substeps=substeps, h_rho=h_rho).arrays()

    def total(q: FloatArray, want: bool) -> float:
        d = q - q_prior
        Jd = sw(q[:n].copy(), q[n:].copy(), Uc, Y, tt, k0, k1, skip_first, Rinv, pc, WT, want,
                A, b, T, X)
        return Jd + float(d @ prior_info @ d)

    q = q_start.copy()
    q[n:] = project_theta(theta_set, q[n:])
    iterations = 0
    J = total(q, True)
    Minv = np.zeros((nq, nq))
    at_q = True                                 # X holds q's trajectory (not a trial's)
    for it in range(max_iter):
        M = A + prior_info
        g = b - prior_info @ (q - q_prior)
        delta, Minv = solve_scaled(M, g)
        se = np.sqrt(np.maximum(np.diag(Minv)[n:], 1e-300))
        if _step_se(theta_set, q[n:], delta[n:], Minv[n:, n:], se) < STEP_TOL:
            # converged where it stands: a trial step this small only meets the rounding of
            # J, a sum over the window (LuGre's mle at 10⁶ samples: its fit of 865 242 was
            # refused ten times, 12 sweeps where 2 suffice; a one-off count)
            break
        iterations = it + 1
        step, accepted = 1.0, False
        for _ in range(MAX_HALVINGS):
            q_new = q + step * delta
            q_new[n:] = project_theta(theta_set, q_new[n:], Minv[n:, n:])
            # the trial's pass computes the Gauss–Newton terms too (1.4× a pass without on
            # LuGre): an accepted step, the usual case, then needs no second pass
            J_new = total(q_new, True)
            at_q = False
            if math.isfinite(J_new) and J_new <= J:
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break
        # the next iteration's test of the step still to go decides convergence (A, b are
        # the new point's: no sweep): a move below STEP_TOL is not one, when the step was
        # damped (two_inertia: a step of 0.56 standard errors taken at 1/64 stopped the fit)
        q, J = q_new, J_new                     # A, b, T, X are the new point's
        at_q = True
    if not at_q:
        J = total(q, True)
    M = A + prior_info
    delta, Minv = solve_scaled(M, b - prior_info @ (q - q_prior))
    se = np.sqrt(np.maximum(np.diag(Minv)[n:], 1e-300))
    step_se = _step_se(theta_set, q[n:], delta[n:], Minv[n:, n:], se)
    x_end = X[-1].copy()
    Tq = np.zeros((nq, nq))
    Tq[:n] = T
    Tq[n:, n:] = np.eye(p)
    cov_end = Tq @ Minv @ Tq.T
    n_meas = max(int(np.isfinite(Y[k0:k1]).sum()), 1)
    return FitResult(k0=k0, k1=k1, x_start=q[:n].copy(), x_end=x_end, theta=q[n:].copy(),
                     cov=Minv, cov_end=0.5 * (cov_end + cov_end.T),
                     cost=float(J) / n_meas, iterations=iterations, noise_std=noise_std,
                     n_meas=n_meas, step_se=step_se, substeps=int(substeps))


def _step_se(theta_set: ParameterSet, theta: FloatArray, delta: FloatArray,
             cov: FloatArray, se: FloatArray) -> float:
    """The Gauss–Newton step still to go from θ, projected onto Θ (a fit that ends on Θ's face
    has converged there), in standard errors: its largest component."""
    th_next = project_theta(theta_set, theta + delta, cov)
    return float(np.max(np.abs(th_next - theta) / se, initial=0.0))


def doubling_schedule(first: float, cap: float = math.inf) -> Callable[[int], float]:
    """Fit times first·2ʲ until ``cap``, then every ``cap`` seconds: j ↦ t_j.

    Times in seconds, for a caller who knows the process's time scale and must bound a
    stream's memory (``FitSchedule(times=…, full_window=…)``); no default: the estimators'
    own schedule counts samples (:func:`information_schedule`).

    Parameters
    ----------
    first : float
        Time of fit j = 0, in seconds.
    cap : float
        Largest doubling step, in seconds (default inf: doubling throughout): once first·2ʲ
        would exceed it, the fits follow every ``cap`` seconds after the last doubled time.

    Returns
    -------
    callable
        j ↦ t_j (int → float seconds), increasing.

    Examples
    --------
    >>> from thetahat.estimation.statistical.map_fit import doubling_schedule
    >>> at = doubling_schedule(0.1, 0.4)
    >>> [round(at(j), 2) for j in range(5)]
    [0.1, 0.2, 0.4, 0.8, 1.2]
    """
    def at(j: int) -> float:
        t = first * 2.0 ** j
        if t <= cap:
            return t
        jc = int(math.floor(math.log2(cap / first) + 1e-9))
        return first * 2.0 ** jc + (j - jc) * cap
    return at


@dataclass(frozen=True, slots=True, eq=False)
class FitSchedule:
    """When and on which window the MAP fits run (see the module docstring).

    Parameters
    ----------
    system : PerturbedLinearSystem
    times : callable j ↦ t_j, optional
        Fit times in seconds (increasing), for a caller that must bound the stream's memory;
        default None: the sample counts of :meth:`sample_counts` (:func:`information_schedule`
        from :func:`first_fit_samples`), every fit of all the data so far.
    full_window : float
        With ``times``: fits at t ≤ ``full_window`` (s) refit all data; later ones use blocks
        with arrival cost (default inf: all data).
    x_sd : float or array_like (n,), optional
        Prior standard deviation of x(0); default
        :func:`~thetahat.estimation.statistical.common.x_prior_sd` of x̂(0).
    noise_std : optional
        σ; default estimated from the window's data.
    max_iter, first_max_iter : int
        Gauss–Newton iterations (the first fit starts cold and may need more).
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples (:mod:`~thetahat.estimation.hold`; default ``"smooth"``).
    substeps : int, optional
        The RK4 sub-steps' accuracy floor of the record (the estimators choose it once per
        record, :func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`);
        default None: each fit chooses on its own window.
    noise_substeps : int, optional
        The floor of the fits with process noise; default None: each chooses its own
        (:func:`~thetahat.estimation.statistical.likelihood.fit_process_noise`). The
        estimators set it to the ``substeps`` their caller gave.
    h_rho : float
    compiled : bool, optional
    """

    system: PerturbedLinearSystem
    times: Callable[[int], float] | None = None
    full_window: float = math.inf
    x_sd: ArrayLike | None = None
    noise_std: ArrayLike | None = None
    max_iter: int = 6
    first_max_iter: int = 25
    hold: str = DEFAULT_HOLD
    substeps: int | None = None
    noise_substeps: int | None = None
    h_rho: float = H_RHO
    compiled: bool | None = None

    def __post_init__(self) -> None:
        check_hold(self.hold)

    def given_substeps(self, substeps: int | None) -> FitSchedule:
        """This schedule with a caller's sub-steps as the floor of every fit (``substeps`` and
        ``noise_substeps``); unchanged for None.

        Parameters
        ----------
        substeps : int or None

        Returns
        -------
        FitSchedule

        Examples
        --------
        >>> from thetahat.models import lugre
        >>> FitSchedule(system=lugre.system()).given_substeps(4).noise_substeps
        4
        """
        if substeps is None:
            return self
        return replace(self, substeps=substeps, noise_substeps=substeps)

    def sample_counts(self, growth: float | None = None) -> Callable[[int], int]:
        """The fits' sample counts when ``times`` is None: j ↦ k_j.

        :func:`information_schedule` from max(:func:`first_fit_samples`, the samples the
        noise estimate needs when σ is not given), growth :data:`INFO_GROWTH` unless given.

        Parameters
        ----------
        growth : float, optional

        Returns
        -------
        callable
            j ↦ k_j (the fit j covers samples 0 … k_j − 1).
        """
        least = 3 if self.noise_std is not None else MIN_SAMPLES
        return information_schedule(max(first_fit_samples(self.system), least),
                                    INFO_GROWTH if growth is None else growth)

    def fit_samples(self, t: FloatArray, *, growth: float | None = None,
                    least: int | None = None) -> list[int]:
        """The sample counts k₁ at which a record ``t`` is fitted (window 0 … k₁ − 1).

        With ``times``: the last sample at or before each t_j; else :meth:`sample_counts`
        below N, then N itself (the whole record).

        Parameters
        ----------
        t : ndarray (N,)
        growth : float, optional
            As :meth:`sample_counts`.
        least : int, optional
            The fewest samples of a fit (default 3 when σ is given, else
            :data:`~thetahat.estimation.statistical.noise_level.MIN_SAMPLES`).

        Returns
        -------
        list of int
            Increasing; the last is N whenever N admits a fit (``times`` None).

        Examples
        --------
        >>> import numpy as np
        >>> from thetahat.models import lugre
        >>> FitSchedule(system=lugre.system()).fit_samples(np.arange(40.0))
        [12, 17, 25, 36, 40]
        """
        N = int(t.shape[0])
        if least is None:
            least = 3 if self.noise_std is not None else MIN_SAMPLES
        if self.times is not None:
            ks: list[int] = []
            j = 0
            while self.times(j) <= t[-1] - t[0] + 1e-12:
                k1 = int(np.searchsorted(t - t[0], self.times(j) + 1e-12, side="right"))
                if k1 >= least and (not ks or k1 > ks[-1]):
                    ks.append(k1)
                j += 1
            return ks
        at = self.sample_counts(growth)
        ks, j = [], 0
        while at(j) < N:
            ks.append(at(j))
            j += 1
        return ks + [N] if N >= least else ks

    def initial_prior(self, x_hat0: FloatArray, theta_hat0: FloatArray
                      ) -> tuple[FloatArray, FloatArray]:
        """(q̄, Π⁻¹) at t = 0: (x̂(0), θ̂(0)) with sd (:func:`~.common.x_prior_sd`, |Θ|/4)."""
        sd = np.concatenate([x_prior_sd(x_hat0, self.x_sd), theta_prior_sd(self.system)])
        return np.concatenate([x_hat0, theta_hat0]), np.diag(1.0 / sd ** 2)

    def fit(self, t: FloatArray, U: FloatArray, Y: FloatArray, k1: int,
            previous: FitResult | None, prior0: tuple[FloatArray, FloatArray],
            elapsed: float | None = None) -> FitResult:
        """The fit due when sample k1 − 1 has arrived, warm-started from ``previous``.

        ``elapsed`` is the time since the start of the experiment (default t[k1−1] − t[0];
        a streaming caller that trimmed old samples from ``t`` passes it).
        """
        n = self.system.n
        el = float(t[k1 - 1] - t[0]) if elapsed is None else float(elapsed)
        full = previous is None or el <= self.full_window + 1e-12
        if full or previous is None:            # (full already holds if previous is None)
            k0 = 0
            q_prior, info = prior0
            q_start = (q_prior.copy() if previous is None
                       else np.concatenate([previous.x_start, previous.theta]))
        else:
            k0 = previous.k1 - 1                 # the block starts where the last one ended
            q_prior = np.concatenate([previous.x_end, previous.theta])
            # arrival cost: θ's marginal from the older data; x at the block start stays wide
            # (its covariance given θ is nearly singular for a model without process noise,
            # and the data of the block determine it)
            _, info_th = solve_scaled(previous.cov[n:, n:], np.zeros(self.system.p))
            info = np.zeros((n + self.system.p, n + self.system.p))
            info[:n, :n] = prior0[1][:n, :n]
            info[n:, n:] = info_th
            q_start = q_prior.copy()
        if not full and previous is not None and self.noise_std is None \
                and k1 - k0 < MIN_SAMPLES:
            sigma = previous.noise_std          # a block too short to estimate σ from
        else:
            sigma = resolve_noise_std(self.noise_std, Y[:k1] if full else Y[k0:k1])
        return fit_map(self.system, t, U, Y, k0=k0, k1=k1, q_start=q_start, q_prior=q_prior,
                       prior_info=info, noise_std=sigma, skip_first=not full,
                       max_iter=self.first_max_iter if previous is None else self.max_iter,
                       hold=self.hold, substeps=self.substeps, h_rho=self.h_rho,
                       compiled=self.compiled)


#: Growth of the information between consecutive fits of :func:`information_schedule`.
INFO_GROWTH = math.sqrt(2.0)


def first_fit_samples(system: PerturbedLinearSystem) -> int:
    """Samples before the first fit of :func:`information_schedule`: max(MIN_SAMPLES, 4(n + p)).

    The fit has n + p unknowns and the noise level needs :data:`MIN_SAMPLES` samples; four
    scalar measurements per unknown is the least at which the Gauss–Newton information is of
    full rank with margin. A count of samples, not seconds: it holds at any sampling rate.

    Parameters
    ----------
    system : PerturbedLinearSystem

    Returns
    -------
    int

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.map_fit import first_fit_samples
    >>> first_fit_samples(lugre.system())
    12
    """
    return max(MIN_SAMPLES, 4 * (system.n + system.p))


def information_schedule(first: int, growth: float = INFO_GROWTH) -> Callable[[int], int]:
    """Fit j after k_j samples, k_0 = ``first``, k_{j+1} = ⌈growth · k_j⌉: j ↦ k_j.

    The Fisher information of a fit of all the data grows in proportion to the samples while
    the excitation is steady, so a fit at every ``growth``-fold sample count is a fit each time
    the information has grown by that factor (the Cramér–Rao bound has shrunk by √growth).
    Counts of samples, never seconds: the schedule is the same for a process sampled at 10 Hz
    for minutes and one sampled at 10 kHz for milliseconds. The total cost of refitting all the
    data at each k_j is at most growth/(growth − 1) times that of one fit of the whole record.

    Parameters
    ----------
    first : int
        k_0 ≥ 1 (see :func:`first_fit_samples`).
    growth : float
        Factor > 1 between consecutive sample counts (default √2).

    Returns
    -------
    callable
        j ↦ k_j (int → int), strictly increasing.

    Examples
    --------
    >>> from thetahat.estimation.statistical.map_fit import information_schedule
    >>> at = information_schedule(12)
    >>> [at(j) for j in range(6)]
    [12, 17, 25, 36, 51, 73]
    """
    if not (isinstance(first, (int, np.integer)) and first >= 1):
        raise DimensionError(f"information_schedule: first must be an integer >= 1; got "
                             f"{first!r}.")
    if not (math.isfinite(growth) and growth > 1.0):
        raise DimensionError(f"information_schedule: growth must be a finite number > 1; got "
                             f"{growth!r}.")
    ks = [int(first)]

    def at(j: int) -> int:
        while len(ks) <= j:
            ks.append(max(ks[-1] + 1, math.ceil(growth * ks[-1] - 1e-9)))
        return ks[j]
    return at


def fit_record(schedule: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray, k1: int,
               previous: FitResult | None, prior0: tuple[FloatArray, FloatArray], *,
               final: bool = False) -> FitResult:
    """The fit of samples 0 … k1 − 1 that the data support: output error, or with process noise.

    First the output-error MAP fit of all the data (:meth:`FitSchedule.fit`, warm-started from
    ``previous``). When it is not consistent (its cost per measurement is not that of the
    measurement noise: a model error, or a fit stuck far from the optimum) the fit of the
    model with process noise on φ (:func:`~thetahat.estimation.statistical.likelihood.fit_process_noise`)
    is tried from its θ and taken if it is consistent, or if neither is but it explains the data
    better (a smaller cost per measurement: real innovations have heavier tails than the χ²
    test allows on a long record, while a wrong output-error model misses by orders of
    magnitude); q is estimated anew on the ``final`` fit, whenever ``previous`` has none,
    once the window has grown :data:`Q_SEARCH_GROWTH` times since q's last search, and when
    the fit at the kept q is refused as below (kept from ``previous`` otherwise, and when a
    search on this window fails); a search after a fit whose q is at least q₀ starts at that q
    (``q_near`` of :func:`~thetahat.estimation.statistical.likelihood.fit_process_noise`).

    Which model is tried first: the output-error one, unless ``previous`` took process noise
    of at least the data's own scale q₀
    (:func:`~thetahat.estimation.statistical.likelihood.process_noise_scale`: an effect the
    model leaves out, visible in y), when the fit with process noise is tried first, from
    ``previous``'s θ, and taken if it is consistent (the output-error fit, which that model
    error makes inconsistent on every longer window, is then not paid for); when it is not
    and q was kept, q is searched on this window from that fit's θ (near the kept q, whose
    fit of θ is not run again) and the result taken if it is consistent. A q below q₀ (a fit
    with process noise taken on a short window, where an output-error fit can stall far from
    its optimum) does not decide the later fits; the ``final`` fit, whose q is searched anew on
    the whole record, skips the output-error fit only when that q̂ is still at least q₀ (the
    whole record's likelihood shows the model error). On EMPS's record, measured once through
    the API: guarded 11.5 → 6.3 s and mle 15.2 → 6.4 s of CPU (the final output-error fit,
    at the free run's 16 sub-steps a sample, was half of mle's time), θ̂ moved by 0.001 %.

    Parameters
    ----------
    schedule : FitSchedule
        Its ``full_window`` must cover the record (the fit is of all the data).
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
    k1 : int
        The window is 0 … k1 − 1.
    previous : FitResult or None
    prior0 : tuple of ndarray
        (q̄, Π⁻¹) of :meth:`FitSchedule.initial_prior`.
    final : bool
        The last fit of the record (q is searched anew).

    Returns
    -------
    FitResult
        ``process_noise`` > 0 when the model with process noise was taken.
    """
    n = schedule.system.n
    x_hat0, x_sd = prior0[0][:n], 1.0 / np.sqrt(np.diagonal(prior0[1])[:n])
    q = previous.process_noise if previous is not None else 0.0
    q_window = previous.q_window if previous is not None else 0
    search = final or q == 0.0 or k1 >= Q_SEARCH_GROWTH * q_window

    def with_q(start: FitResult, q_fixed: float | None, at_q_near: bool = False
               ) -> FitResult:
        return _with_process_noise(schedule, t, U, Y, k1, start, x_hat0, x_sd, q=q_fixed,
                                   at_q_near=at_q_near)
    # q₀ of this window (the scale a fit with process noise here is judged against), needed
    # only when the last fit took process noise
    q0 = _noise_scale(schedule, t, Y, k1) if q > 0.0 else math.inf
    if previous is not None and q >= q0:     # the record shows a model error: that model first
        first: FitResult | None
        try:
            first = with_q(previous, None if search else q)
        except NonFiniteError:
            first = None                 # the output-error fit below decides
        if first is not None and not (first.consistent or search):
            # the kept q was an economy this window refuses: q is searched on it, from the
            # θ just fitted, before the output-error fit is tried
            try:
                first, search = with_q(first, None, at_q_near=True), True
            except NonFiniteError:
                pass                     # keep the first; the output-error fit decides
        if first is not None and first.consistent and (not final
                                                       or first.process_noise >= q0):
            return replace(first, q_window=k1 if search else q_window)
    fit = schedule.fit(t, U, Y, k1, previous, prior0)
    if final and schedule.substeps is not None and fit.finite:
        # the record's sub-steps were chosen at the start values: check them at the estimate
        n = choose_substeps(model_kernel(schedule.system, compiled=schedule.compiled),
                            t[:k1], U[:k1], Y[:k1], fit.theta, fit.x_start, fit.noise_std,
                            hold=schedule.hold, h_rho=schedule.h_rho)
        if n > schedule.substeps:
            return fit_record(replace(schedule, substeps=n), t, U, Y, k1, fit, prior0,
                              final=True)
    if fit.consistent:
        return fit
    try:
        alt = with_q(fit, None if search else q)
    except NonFiniteError:
        if not search or q == 0.0:
            raise
        alt, search = with_q(fit, q), False  # the search failed on this window: keep q
    alt = replace(alt, q_window=k1 if search else q_window)
    return alt if alt.consistent or alt.cost < fit.cost else fit


def _noise_scale(schedule: FitSchedule, t: FloatArray, Y: FloatArray, k1: int) -> float:
    """q₀ of samples 0 … k1 − 1 (:func:`~.likelihood.process_noise_scale` at the window's σ),
    the scale above which a fit's process noise is a model error the record shows."""
    from .likelihood import process_noise_scale
    sigma = resolve_noise_std(schedule.noise_std, Y[:k1])
    return process_noise_scale(schedule.system, sample_interval(t[:k1]), sigma)


def _with_process_noise(schedule: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
                        k1: int, previous: FitResult, x_hat0: FloatArray, x_sd: FloatArray, *,
                        q: float | None, at_q_near: bool = False) -> FitResult:
    """The fit of samples 0 … k1 − 1 by the likelihood with process noise on φ, as a FitResult,
    from the θ of the fit ``previous`` (this window's output-error fit, or the last
    window's). ``q``: the intensity (None: estimated with θ, from ``previous``'s q when that is
    at least the data's scale, a model error the record shows; ``at_q_near``: ``previous`` is
    the fit of these samples at that q, whose θ is not fitted again before q is searched).
    Its sub-steps are the schedule's ``noise_substeps`` (a caller's), else the innovations'
    own (:func:`~thetahat.estimation.statistical.likelihood.fit_process_noise`): not the
    free run's of the output-error fit, whose error accumulates over the record where the
    filter corrects it at every sample, and which compares nothing where the free run leaves
    the data at once (a drive's rigid-body mode). Their search starts at the floor of
    ``previous`` when that is a fit with process noise of a shorter window (the error is
    allowed over more samples here, so that floor is rarely too many; it is never lowered)."""
    from .likelihood import fit_process_noise
    sigma = resolve_noise_std(schedule.noise_std, Y[:k1])
    # the floor of a shorter window's fit with process noise is where this one's search
    # starts: a record's floors are kept or raised from fit to fit, the smaller not run again
    known = (previous.substeps if previous.process_noise > 0.0 and previous.k0 == 0
             and previous.k1 <= k1 else 1)
    pf = fit_process_noise(schedule.system, t[:k1], U[:k1], Y[:k1], theta0=previous.theta,
                           x_hat0=x_hat0, x_sd=x_sd, noise_std=sigma, q=q,
                           max_nfev=60 if q is None else 20, hold=schedule.hold,
                           substeps=schedule.noise_substeps, h_rho=schedule.h_rho,
                           compiled=schedule.compiled, min_substeps=known,
                           q_near=previous.process_noise if q is None else None,
                           at_q_near=at_q_near and previous.k1 == k1 and previous.k0 == 0)
    return FitResult.of_process_noise(pf, k1, x_hat0, x_sd)


def why_not_applied(fit: FitResult, applied: FitResult | None) -> str | None:
    """Why stage 2 must not take a fit, or None: the one rule of the guarded estimator's fits
    and of the MAP estimator's window fits.

    Not applied: a fit whose residuals are not those of the noise model
    (:attr:`FitResult.consistent`; an output-error fit of a record with model error), or one
    :meth:`FitResult.rejection` refuses against ``applied`` (non-finite, not converged,
    standard errors grown by orders of magnitude).

    Parameters
    ----------
    fit : FitResult
    applied : FitResult or None
        The last fit applied.

    Returns
    -------
    str or None
        One sentence naming the samples and the numbers.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.map_fit import FitResult, why_not_applied
    >>> fit = FitResult(k0=0, k1=100, x_start=np.zeros(1), x_end=np.zeros(1),
    ...                 theta=np.ones(1), cov=np.eye(2), cov_end=np.eye(2), cost=9.0,
    ...                 iterations=3, noise_std=np.ones(1), n_meas=100)
    >>> why_not_applied(fit, None)
    'the fit of samples 0…99 is not consistent with the noise (cost 9 per measurement)'
    """
    if not fit.consistent:
        return (f"the fit of samples {fit.k0}…{fit.k1 - 1} is not consistent with the noise "
                f"(cost {fit.cost:.3g} per measurement)")
    return fit.rejection(applied)


def fit_as_prior(system: PerturbedLinearSystem, fit: FitResult, h: float, q_x: float = 0.0
                 ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """A fit as the joint EKF's state at the fit's last sample: (s, P, R, Q_x).

    The fit's Gauss–Newton posterior N(col(x_end, θ), cov_end) summarises every sample of its
    window (the arrival cost of the samples that follow), so an EKF started from it and fed
    the later samples approximates the MAP estimate of all the data at each of them — the
    estimate between two scheduled fits of :class:`MapEstimator` and stage 2's restart in
    :class:`~thetahat.estimation.statistical.guarded.GuardedEstimator`.

    Parameters
    ----------
    system : PerturbedLinearSystem
    fit : FitResult
    h : float
        The sampling interval (> 0) over which the fit's process-noise intensity, if any,
        becomes a covariance per sample.
    q_x : float
        Process-noise variance per sample on x added to the fit's own (default 0).

    Returns
    -------
    s : ndarray (n + p,)
        col(x̂, θ̂) at the fit's last sample.
    P : ndarray (n + p, n + p)
        Their joint covariance (C order: the compiled kernels update it in place).
    R : ndarray (r, r)
        diag(σ̂²) of the fit.
    Q_x : ndarray (n, n)
        q_x I plus the fit's process noise on φ over one sample (none: zero).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone as prop3
    >>> from thetahat.estimation.statistical.mle import MapEstimator
    >>> from thetahat.estimation.statistical.map_fit import fit_as_prior
    >>> sys_ = prop3.system()
    >>> d = prop3.simulate(seed=0, t_end=2.0)
    >>> fit = MapEstimator(system=sys_, compiled=False).run(d.t, d.u, d.y).diagnostics.fits[-1]
    >>> s, P, R, Q = fit_as_prior(sys_, fit, 0.01)
    >>> bool(np.allclose(s[sys_.n:], fit.theta)), P.shape, bool(np.all(Q == 0.0))
    (True, (3, 3), True)
    """
    n = system.n
    s = np.concatenate([fit.x_end, fit.theta]).astype(np.float64)
    P = np.array(fit.cov_end, dtype=np.float64, order="C")
    R = np.diag(np.asarray(fit.noise_std, dtype=np.float64) ** 2)
    Q_x = q_x * np.eye(n)
    if fit.process_noise > 0.0:
        from .likelihood import unit_process_noise
        Q_x = Q_x + fit.process_noise * unit_process_noise(system.A, system.E, h)
    return s, P, R, Q_x
