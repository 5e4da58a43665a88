"""Stage 2's filter: an extended Kalman filter on col(x, θ) built from any thetahat model.

The augmented state s = col(x, θ) with θ constant (no random walk) follows the sampled-data
map of :mod:`~thetahat.estimation.statistical.plant_kernel` (RK4 sub-steps, first-order hold on u):

    x_{k+1} = F(x_k, θ, ũ_k, ũ_{k+1}),   θ_{k+1} = θ_k,   y_k = C x_k + e_k,  e_k ~ N(0, R),

with ũ the input samples of :func:`~thetahat.estimation.statistical.input_hold.smooth_input`
(u_k where the input is not resolved by its sampling; where it is, corrected so that the linear
hold carries u's exact mean over each interval to O(h⁴); causal, so ``step`` and ``run`` agree)

so the transition matrix is [[Φ, Γ], [0, I]] with the exact Jacobians Φ = ∂F/∂x, Γ = ∂F/∂θ.
Prediction P ← T P Tᵀ + Q (Q = diag(Q_x, 0), Q_x the process noise on x over one sample); update with H = [C 0] in Joseph form
P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ, which keeps P symmetric positive semi-definite in
floating point; then θ is projected onto Θ in the P_θθ⁻¹-weighted norm (a box: a clip; any
convex Θ, see :mod:`~thetahat.estimation.statistical.stage2_set`). R = σ² I with σ given or
estimated from the data (:func:`~thetahat.estimation.statistical.noise_level.estimate_noise_std`); the
prior on θ comes from Θ (centre ± |Θ|/4 per component unless told), on x(0) it is wide.

The per-sample kernels (:class:`EKFKernels`) are shared by :class:`JointEKF` (the filter
alone) and the guarded estimator, and are numba-compiled when numba is installed.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_vector
from ...errors import DimensionError, NonFiniteError, OptionError, ParameterSetError
from ...errors import UnsupportedError
from ...model.paramset import Box
from ...model.system import PerturbedLinearSystem
from .plant_kernel import H_RHO, ModelKernel, jit, model_kernel
from .input_hold import InputHistory, smooth_input
from .noise_level import MIN_SAMPLES, estimate_noise_std
from .stage2_set import (clip_kernel, has_compiled_projection, project_kernel, stage2_set,
                         theta_bounds)
from ..protocol import (Diagnostics, EstimateResult, missing_samples, phi_hat_from_model,
                       stream_sample)

__all__ = ["start_values", "EKFKernels", "ekf_kernels", "ekf_sample", "sample_interval", "JointEKF",
           "divergence_error", "NIS_MODEL_ERROR", "x_prior_sd", "X_PRIOR_SD",
           "EKFDiagnostics", "EKFResult", "EKFState",
           "theta_box", "theta_prior_sd", "PRIOR_FRACTION"]

FloatArray = NDArray[np.float64]

#: A median normalised innovation squared (NIS ÷ r, 1 for a model that fits) above this before
#: a divergence is a model error, not bad luck: χ²_r/r has its median below 1 and a 99.9 %
#: quantile below 11 for every r ≥ 1 (r = 1: 10.8).
NIS_MODEL_ERROR = 11.0

#: Prior standard deviation of θ as a fraction of Θ's width per component: θ's prior
#: N(centre of Θ, (|Θ|/4)²) puts Θ's ends at 2 standard deviations.
PRIOR_FRACTION = 0.25


def theta_box(system: PerturbedLinearSystem) -> tuple[FloatArray, FloatArray]:
    """(lower, upper): Θ's bounding box, Θ itself for a :class:`~thetahat.model.paramset.Box`.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model; its ``parameter_set`` Θ may be any
        :class:`~thetahat.model.paramset.ParameterSet` (Box, Ball, Ellipsoid, ConvexSet).

    Returns
    -------
    lower, upper : ndarray, shape (p,)
        Θ's extent per component of θ (:func:`~thetahat.estimation.statistical.stage2_set.theta_bounds`),
        as float64 copies: the prior's width and the guard's widest band. Stage 2 keeps θ̂ in
        Θ itself by projecting onto Θ (:mod:`~thetahat.estimation.statistical.stage2_set`), not by
        clipping to this box unless Θ is the box.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf import theta_box
    >>> [b.tolist() for b in theta_box(lugre.system())]
    [[0.05], [1.0]]
    """
    return theta_bounds(system.require_parameter_set("stage 2"))


def start_values(system: PerturbedLinearSystem, x_hat0: Any = None, theta_hat0: Any = None
                 ) -> tuple[FloatArray, FloatArray]:
    """(x̂₀, θ̂₀) of the statistical estimators: defaults zeros and the centre of Θ, θ̂₀ in Θ.

    Parameters
    ----------
    system : PerturbedLinearSystem
        Any Θ; the default θ̂₀ is its ``interior_point`` (the centre of a box, ball or
        ellipsoid).
    x_hat0 : array_like (n,), optional
    theta_hat0 : array_like (p,), optional

    Returns
    -------
    x_hat0, theta_hat0 : ndarray

    Raises
    ------
    ParameterSetError
        θ̂₀ outside Θ.
    DimensionError
        Wrong lengths.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf import start_values
    >>> start_values(lugre.system())[1]
    array([0.525])
    """
    theta_set = system.require_parameter_set("stage 2")
    x0 = (np.zeros(system.n) if x_hat0 is None
          else as_vector("x_hat0", x_hat0, system.n))
    th0 = (np.array(theta_set.interior_point, dtype=np.float64) if theta_hat0 is None
           else as_vector("theta_hat0", theta_hat0, system.p))
    if not bool(theta_set.contains(th0)):
        raise ParameterSetError(f"theta_hat0 = {th0} lies outside Θ = {theta_set!r}; start "
                                "the estimate inside Θ.")
    return x0, th0


def theta_prior_sd(system: PerturbedLinearSystem) -> FloatArray:
    """Prior standard deviation of θ from Θ: :data:`PRIOR_FRACTION` × its width.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model; any Θ (its bounding box, :func:`theta_box`, gives the width).

    Returns
    -------
    ndarray, shape (p,)
        |Θ|/4 per component: the prior N(centre of Θ, (|Θ|/4)²) of the EKF on col(x, θ) and
        of the first MAP fit puts Θ's ends at 2 standard deviations.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf import theta_prior_sd
    >>> theta_prior_sd(lugre.system()).round(4).tolist()
    [0.2375]
    """
    lo, hi = theta_box(system)
    return PRIOR_FRACTION * (hi - lo)


#: Prior standard deviation of x(0) per unit of the start's magnitude max(1, max|x̂(0)ᵢ|):
#: wide against the state (the data determine x(0)), in the state's own scale where the start
#: gives one (x̂(0) from y(0), :func:`~thetahat.modelfile.start_x_hat`) — a heater started
#: 300 K above its reference is not pulled to the reference by a prior of ± 10 K.
X_PRIOR_SD = 10.0


def x_prior_sd(x_hat0: ArrayLike, x_sd: ArrayLike | None = None) -> FloatArray:
    """Prior standard deviation of x(0) around x̂(0): ``x_sd`` when given, else derived.

    Parameters
    ----------
    x_hat0 : array_like (n,)
        The prior mean x̂(0).
    x_sd : float or array_like (n,), optional
        Given standard deviations (used as they are). Default: :data:`X_PRIOR_SD` ×
        max(1, max|x̂(0)ᵢ|) for every component.

    Returns
    -------
    ndarray, shape (n,)
        Positive and finite.

    Raises
    ------
    OptionError
        A given ``x_sd`` that is not positive and finite.
    DimensionError
        A given ``x_sd`` that is neither a number nor one per state.

    Examples
    --------
    >>> from thetahat.estimation.statistical.ekf import x_prior_sd
    >>> x_prior_sd([0.2, 0.0]).tolist(), x_prior_sd([300.0, 0.0]).tolist()
    ([10.0, 10.0], [3000.0, 3000.0])
    """
    x0 = np.asarray(x_hat0, dtype=np.float64).reshape(-1)
    if x_sd is None:
        scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
        return np.full(x0.shape[0], X_PRIOR_SD * scale)
    try:
        sd = np.array(np.broadcast_to(np.asarray(x_sd, dtype=np.float64), x0.shape))
    except ValueError:
        raise DimensionError(f"x_sd must be a number or have {x0.shape[0]} entries (one per "
                             f"state); got shape {np.shape(x_sd)}.") from None
    if not np.all(np.isfinite(sd) & (sd > 0.0)):
        raise OptionError(f"x_sd must be positive and finite; got {sd.tolist()}.")
    return sd


@dataclass(frozen=True, slots=True, eq=False)
class EKFKernels:
    """The EKF's per-sample operations on (s, P) in place (compiled with the model kernel).

    ``predict(s, P, u0, u1, h, h_rho, Q_x, Phi, Gam)`` and
    ``update(s, P, y, R, lo, hi, ell) -> NIS`` (normalised innovation squared ÷ r, after which
    θ is projected onto Θ = (lo, hi, ell), see
    :func:`~thetahat.estimation.statistical.stage2_set.project_kernel`); ``loop(s, P, U, Y, t, k0, k1, R,
    lo, hi, ell, h_rho, Q_x, X, TH, SD, NIS) -> status`` runs samples k0 … k1−1 and returns
    −1, or the index where s became non-finite.

    Parameters
    ----------
    model : ModelKernel
        The plant kernels (f, Φ, Γ and the RK4 sampled-data map) the EKF is built on; its
        ``compiled`` flag says whether the operations below are numba-compiled.
    predict : callable
        ``predict(s, P, u0, u1, h, h_rho, Q_x, Phi, Gam) -> None``: the time update over one
        sample of length ``h`` with u linear from ``u0`` to ``u1``. Overwrites s = col(x, θ)
        (shape (n + p,)) with (F(x, θ, u0, u1), θ) and P (shape (n + p, n + p)) with
        T P Tᵀ + diag(Q_x, 0), T = [[Φ, Γ], [0, I]], Q_x (n, n); ``Phi`` (n, n) and ``Gam`` (n, p)
        are work arrays that receive Φ and Γ.
    update : callable
        ``update(s, P, y, R, lo, hi, ell) -> float``: the measurement update with y (r,) and
        R (r, r), H = [C 0], P in Joseph form, then θ projected onto Θ in the P_θθ⁻¹-weighted
        norm (``project``); returns the normalised innovation squared νᵀ S⁻¹ ν ÷ r (≈ 1 for a
        consistent filter).
    loop : callable
        ``loop(s, P, U, Y, t, k0, k1, R, lo, hi, ell, h_rho, Q_x, X, TH, SD, NIS) -> int``: the
        filter over samples k0 … k1−1 (predict from sample k−1 when k > 0, then update unless
        y_k has a non-finite entry), writing x̂ into ``X`` (N, n), θ̂ into ``TH`` (N, p),
        √diag P_θθ into ``SD`` (N, p) and the NIS into ``NIS`` (N,; NaN where not updated);
        returns −1, or the first sample index at which s became non-finite.
    project : callable
        ``project(theta, M, lo, hi, ell) -> None``: Π_Θ in place in the norm ‖·‖_{M⁻¹}
        (:func:`~thetahat.estimation.statistical.stage2_set.project_kernel`, or a ConvexSet's Python
        projection); the guard uses it with M = I.
    """

    model: ModelKernel
    predict: Callable[..., None]
    update: Callable[..., float]
    loop: Callable[..., int]
    project: Callable[..., None]


def _make(model: ModelKernel, project: Callable[..., None]) -> EKFKernels:
    prop = model.propagate
    C = model.C
    compiled = model.compiled

    def predict(s, P, u0, u1, h, h_rho, Q_x, Phi, Gam):
        n = Phi.shape[0]
        p = Gam.shape[1]
        N = n + p
        x = s[:n].copy()
        th = s[n:].copy()
        # a runtime True (n ≥ 1), not the literal: numba would compile a second
        # specialisation of propagate for Literal[bool] (≈ 0.9 s of a first run) besides the
        # one the MAP sweep and the likelihood use
        xn = prop(x, th, u0, u1, h, h_rho, n > 0, Phi, Gam)
        # T = [[Φ, Γ], [0, I]], element by element: numba's slice assignment compiles its
        # string-formatting error path (≈ 3 s of a guarded run's first compilation)
        T = np.zeros((N, N))
        for i in range(n):
            for j in range(n):
                T[i, j] = Phi[i, j]
            for j in range(p):
                T[i, n + j] = Gam[i, j]
        for i in range(n, N):
            T[i, i] = 1.0
        TP = np.zeros((N, N))
        for i in range(N):
            for j in range(N):
                acc = 0.0
                for k in range(N):
                    acc += T[i, k] * P[k, j]
                TP[i, j] = acc
        for i in range(N):
            for j in range(i, N):
                acc = 0.0
                for k in range(N):
                    acc += TP[i, k] * T[j, k]
                P[i, j] = acc
                P[j, i] = acc
        for i in range(n):
            for j in range(n):
                P[i, j] += Q_x[i, j]
            s[i] = xn[i]

    def update(s, P, y, R, lo, hi, ell):
        N = P.shape[0]
        r = C.shape[0]
        n = C.shape[1]
        PHt = np.zeros((N, r))
        for i in range(N):
            for j in range(r):
                acc = 0.0
                for k in range(n):
                    acc += P[i, k] * C[j, k]
                PHt[i, j] = acc
        S = R.copy()
        nu = y.copy()
        for i in range(r):
            for k in range(n):
                nu[i] -= C[i, k] * s[k]
            for j in range(r):
                acc = 0.0
                for k in range(n):
                    acc += C[i, k] * PHt[k, j]
                S[i, j] += acc
        # Cholesky S = L Lᵀ (S is SPD: R > 0)
        L = np.zeros((r, r))
        for i in range(r):
            for j in range(i + 1):
                acc = S[i, j]
                for k in range(j):
                    acc -= L[i, k] * L[j, k]
                if i == j:
                    L[i, i] = math.sqrt(max(acc, 1e-300))
                else:
                    L[i, j] = acc / L[j, j]
        # K = PHt S⁻¹ (row-wise solves), w = S⁻¹ ν
        K = np.zeros((N, r))
        for row in range(N):
            z = PHt[row].copy()
            for i in range(r):
                for k in range(i):
                    z[i] -= L[i, k] * z[k]
                z[i] /= L[i, i]
            for i in range(r - 1, -1, -1):
                for k in range(i + 1, r):
                    z[i] -= L[k, i] * z[k]
                z[i] /= L[i, i]
            for i in range(r):          # element by element: see predict
                K[row, i] = z[i]
        w = nu.copy()
        for i in range(r):
            for k in range(i):
                w[i] -= L[i, k] * w[k]
            w[i] /= L[i, i]
        nis = 0.0
        for i in range(r):
            nis += w[i] * w[i]
        for i in range(N):
            for j in range(r):
                s[i] += K[i, j] * nu[j]
        # Joseph form: P = (I − K H) P (I − K H)ᵀ + K R Kᵀ, H = [C 0]
        IKH = np.eye(N)
        for i in range(N):
            for j in range(n):
                acc = 0.0
                for k in range(r):
                    acc += K[i, k] * C[k, j]
                IKH[i, j] -= acc
        A = np.zeros((N, N))
        for i in range(N):
            for j in range(N):
                acc = 0.0
                for k in range(N):
                    acc += IKH[i, k] * P[k, j]
                A[i, j] = acc
        for i in range(N):
            for j in range(i, N):
                acc = 0.0
                for k in range(N):
                    acc += A[i, k] * IKH[j, k]
                for a in range(r):
                    for b in range(r):
                        acc += K[i, a] * R[a, b] * K[j, b]
                P[i, j] = acc
                P[j, i] = acc
        p = lo.shape[0]
        th = s[n:].copy()
        project(th, P[n:, n:].copy(), lo, hi, ell)
        for i in range(p):
            s[n + i] = th[i]
        return nis / r

    predict_j, update_j = jit(predict, compiled), jit(update, compiled)

    def loop(s, P, U, Y, tt, k0, k1, R, lo, hi, ell, h_rho, Q_x, X, TH, SD, NIS):
        """Samples k0 … k1−1 (predict from k−1 when k > 0, then update); -1 or the bad index."""
        n = X.shape[1]
        p = TH.shape[1]
        Phi = np.empty((n, n))
        Gam = np.empty((n, p))
        for k in range(k0, k1):
            if k > 0:
                predict_j(s, P, U[k - 1], U[k], tt[k] - tt[k - 1], h_rho, Q_x, Phi, Gam)
            finite_y = True
            for j in range(Y.shape[1]):
                if not math.isfinite(Y[k, j]):
                    finite_y = False
            NIS[k] = update_j(s, P, Y[k], R, lo, hi, ell) if finite_y else np.nan
            for i in range(n + p):
                if not math.isfinite(s[i]):
                    return k
            for i in range(n):              # element by element: see predict
                X[k, i] = s[i]
            for i in range(p):
                TH[k, i] = s[n + i]
                SD[k, i] = math.sqrt(max(P[n + i, n + i], 0.0))
        return -1

    return EKFKernels(model=model, predict=predict_j, update=update_j, loop=jit(loop, compiled),
                      project=project)


@functools.lru_cache(maxsize=16)
def _cached(model: ModelKernel, box: bool) -> EKFKernels:
    return _make(model, jit(clip_kernel if box else project_kernel, model.compiled))


@functools.lru_cache(maxsize=16)
def _cached_python_projection(model: ModelKernel, theta_set: Any) -> EKFKernels:
    st = stage2_set(theta_set)

    def project(theta, M, lo, hi, ell):
        st.project(theta, M)

    return _make(model, project)


def ekf_kernels(system: PerturbedLinearSystem, *, compiled: bool | None = None) -> EKFKernels:
    """The EKF kernels of a model (built once per model kernel).

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model of stage 2, with a
        :class:`~thetahat.model.perturbation.SymbolicPerturbation` (see
        :func:`~thetahat.estimation.statistical.plant_kernel.model_kernel`).
    compiled : bool, optional
        Compile the kernels with numba; default (None): when numba is installed and Θ has a
        compiled projection (a Box, Ball or Ellipsoid). A
        :class:`~thetahat.model.paramset.ConvexSet` Θ is projected in Python
        (:mod:`~thetahat.estimation.statistical.stage2_set`), so its kernels run uncompiled.

    Returns
    -------
    EKFKernels
        ``predict``, ``update``, ``loop`` and ``project`` on col(x, θ) for this model; the
        same object for the same model kernel (an LRU cache of 16). Θ itself is data
        (``lo, hi, ell`` of :class:`~thetahat.estimation.statistical.stage2_set.StageTwoSet`).

    Raises
    ------
    DimensionError
        The perturbation is not symbolic.
    MissingExtraError
        ``compiled=True`` without numba.
    UnsupportedError
        ``compiled=True`` with a ConvexSet Θ.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf import ekf_kernels
    >>> k = ekf_kernels(lugre.system(), compiled=False)
    >>> s, P = np.array([0.0, 0.0, 0.5]), np.diag([1.0, 1e-6, 0.05])
    >>> nis = k.update(s, P, np.array([0.1]), np.array([[4e-4]]), np.array([0.05]),
    ...                np.array([1.0]), np.zeros((2, 1)))
    >>> bool(P[0, 0] < 4e-4)           # the measurement of ω shrank its variance below R
    True
    """
    theta_set = system.require_parameter_set("stage 2")
    if has_compiled_projection(theta_set):
        return _cached(model_kernel(system, compiled=compiled), isinstance(theta_set, Box))
    if compiled:
        raise UnsupportedError(f"Θ = {theta_set!r} has no compiled projection (its P is a "
                               "Python callable); pass compiled=None or False, or give Θ as a "
                               "Box, Ball or Ellipsoid.")
    return _cached_python_projection(model_kernel(system, compiled=False), theta_set)


def ekf_sample(kernels: EKFKernels, system: PerturbedLinearSystem, s: FloatArray, P: FloatArray,
               u0: FloatArray | None, u1: FloatArray, y: FloatArray, dt: float, h_rho: float,
               Q_x: FloatArray, R: FloatArray | None, k: int) -> float:
    """One sample of the joint EKF, in place: the ``step`` of every estimator that runs it.

    Predicts s = col(x̂, θ̂) and P from the previous sample (input u0 → u1 over ``dt``; none when
    ``u0`` is None: the first sample), then updates with ``y`` (none when y holds NaN or ``R``
    is None: σ not known yet), θ̂ projected onto Θ. What :attr:`EKFKernels.loop` does for one
    sample of a record.

    Parameters
    ----------
    kernels : EKFKernels
        :func:`ekf_kernels` of ``system``.
    system : PerturbedLinearSystem
    s : ndarray (n + p,)
    P : ndarray (n + p, n + p)
        C order; both overwritten.
    u0 : ndarray (m,) or None
    u1 : ndarray (m,)
    y : ndarray (r,)
    dt : float
    h_rho : float
    Q_x : ndarray (n, n)
    R : ndarray (r, r) or None
    k : int
        The sample's index (named in the error).

    Returns
    -------
    float
        The update's normalised innovation squared ÷ r (NaN: no update).

    Raises
    ------
    NonFiniteError
        The filter diverged (s not finite).
    """
    n, p = Q_x.shape[0], s.shape[0] - Q_x.shape[0]
    if u0 is not None:
        kernels.predict(s, P, u0, u1, dt, h_rho, Q_x, np.empty((n, n)), np.empty((n, p)))
    nis = math.nan
    if R is not None and np.all(np.isfinite(y)):
        ts = stage2_set(system.require_parameter_set("stage 2"))
        nis = float(kernels.update(s, P, y, R, ts.lo, ts.hi, ts.ell))
    if not np.all(np.isfinite(s)):
        raise NonFiniteError(f"the EKF diverged at sample {k}; check the model and noise_std.")
    return nis


@dataclass(frozen=True, slots=True, eq=False)
class EKFDiagnostics(Diagnostics):
    """What :meth:`JointEKF.run` reports beyond the common estimates (``result.diagnostics``).

    Attributes
    ----------
    theta_sd : ndarray, shape (N, p)
        √diag P_θθ after each update.
    nis : ndarray, shape (N,)
        Normalised innovation squared ÷ r (≈ 1 on average for a consistent filter; NaN where
        no update was made).
    noise_std : ndarray, shape (r,)
        σ used for R.
    """

    theta_sd: FloatArray
    nis: FloatArray
    noise_std: FloatArray

    def __repr__(self) -> str:
        return (f"EKFDiagnostics(theta_sd[-1]={self.theta_sd[-1]}, "
                f"mean_nis={float(np.nanmean(self.nis)) if np.isfinite(self.nis).any() else None}, "
                f"noise_std={self.noise_std})")


#: The EKF's former result name, kept importable: :meth:`JointEKF.run` returns an
#: :class:`~thetahat.estimation.protocol.EstimateResult` with :class:`EKFDiagnostics`.
EKFResult = EstimateResult


@dataclass(frozen=True, slots=True, eq=False)
class EKFState:
    """The filter's state between two samples (from :meth:`JointEKF.init` or ``step``).

    Attributes
    ----------
    x_hat : ndarray, shape (n,)
    theta_hat : ndarray, shape (p,)
        The estimates after the last sample's update (θ̂ in Θ).
    P : ndarray, shape (n + p, n + p)
        Their covariance.
    k : int
        Samples processed.
    u_prev : ndarray, shape (m,)
        The last sample's input ũ (the next prediction holds u linear from it).
    u_history : InputHistory or None
        The raw inputs the next samples' ũ need
        (:func:`~thetahat.estimation.statistical.input_hold.smooth_input`).
    dt_prev : float
        Time from the last sample to the next one (the ``dt`` of the last ``step``).
    noise_std : ndarray, shape (r,), or None
        σ of R; None until known (then the first :data:`MIN_SAMPLES` outputs are collected in
        ``y_first`` and no update is made before σ is estimated from them).
    y_first : ndarray, shape (j, r)
        Outputs collected while σ is unknown.
    nis : float
        The last update's normalised innovation squared ÷ r (NaN: no update).
    """

    x_hat: FloatArray
    theta_hat: FloatArray
    P: FloatArray
    k: int = 0
    u_prev: FloatArray | None = None
    dt_prev: float = 0.0
    u_history: InputHistory | None = None
    noise_std: FloatArray | None = None
    y_first: FloatArray | None = None
    nis: float = math.nan

    def __repr__(self) -> str:
        return (f"EKFState(k={self.k}, x_hat={self.x_hat}, theta_hat={self.theta_hat}, "
                f"noise_std={self.noise_std})")


@dataclass(frozen=True, slots=True, eq=False)
class JointEKF:
    """Extended Kalman filter on col(x, θ) for a thetahat model (stage 2 alone).

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a symbolic g and any convex Θ (θ̂ is projected onto it after each update, see
        :mod:`~thetahat.estimation.statistical.stage2_set`).
    noise_std : float or array_like (r,), optional
        σ of the output noise; default: estimated from the record (:meth:`run`) or from the
        first samples (:meth:`step` delays its updates until :data:`MIN_SAMPLES` samples).
    theta_sd : array_like (p,), optional
        Prior standard deviation of θ; default |Θ|/4.
    x_sd : float or array_like (n,), optional
        Prior standard deviation of x(0); default :func:`x_prior_sd` of x̂(0) (wide: the
        data determine x quickly).
    q_x : float
        Process-noise variance per sample on x (default 0: the model is taken as exact).
    h_rho : float
        RK4 sub-step bound (see :mod:`~thetahat.estimation.statistical.plant_kernel`).
    compiled : bool, optional
        numba kernels (default: when installed).

    Notes
    -----
    An :class:`~thetahat.estimation.protocol.Estimator`: :meth:`init` gives an
    :class:`EKFState`, :meth:`step` processes one sample, :meth:`run` a record (also from
    the keywords ``x_hat0``, ``theta_hat0``, ``P0``); results carry :class:`EKFDiagnostics`.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf import JointEKF
    >>> data = lugre.simulate(seed=0, t_end=0.3)
    >>> res = JointEKF(system=lugre.system(), compiled=False).run(data.t, data.u, data.y,
    ...                                                           theta_hat0=[0.5])
    >>> bool(abs(res.theta_hat[-1, 0] - 0.28) < 0.01)
    True
    """

    system: PerturbedLinearSystem
    noise_std: Any = None
    theta_sd: Any = None
    x_sd: Any = None
    q_x: float = 0.0
    h_rho: float = H_RHO
    compiled: bool | None = None

    @property
    def kernels(self) -> EKFKernels:
        return ekf_kernels(self.system, compiled=self.compiled)

    def prior(self, x_hat0: Any = None, theta_hat0: Any = None) -> tuple[FloatArray, FloatArray]:
        """(s0, P0): x̂(0), θ̂(0) (default: zeros, centre of Θ) and the prior covariance."""
        sys_ = self.system
        n, p = sys_.n, sys_.p
        x0, th0 = start_values(sys_, x_hat0, theta_hat0)
        th_sd = (theta_prior_sd(sys_) if self.theta_sd is None
                 else as_vector("theta_sd", self.theta_sd, p))
        return (np.concatenate([x0, th0]),
                np.diag(np.concatenate([x_prior_sd(x0, self.x_sd), th_sd]) ** 2))

    def init(self, x_hat0: Any = None, theta_hat0: Any = None) -> EKFState:
        """The filter's state before the first sample: x̂₀, θ̂₀ and the prior covariance.

        Parameters
        ----------
        x_hat0 : array_like (n,), optional
            Default zeros.
        theta_hat0 : array_like (p,), optional
            In Θ; default the centre of Θ.

        Returns
        -------
        EKFState

        Raises
        ------
        ParameterSetError
            θ̂₀ outside Θ.
        """
        n = self.system.n
        s, P = self.prior(x_hat0, theta_hat0)
        sigma = (None if self.noise_std is None
                 else resolve_noise_std(self.noise_std, np.zeros((1, self.system.r))))
        return EKFState(x_hat=s[:n], theta_hat=s[n:], P=P, noise_std=sigma,
                        y_first=np.zeros((0, self.system.r)))

    def step(self, state: EKFState, u: Any, y: Any, dt: float) -> EKFState:
        """Process the samples of one instant: predict from the previous one, then update.

        Parameters
        ----------
        state : EKFState
            From :meth:`init` or the previous ``step`` (not modified).
        u : array_like (m,)
            The input at this instant (``None`` when m = 0).
        y : array_like (r,)
            The output; NaN: no update (the filter predicts over it).
        dt : float
            Time to the next sample, > 0 (used by the next ``step``'s prediction).

        Returns
        -------
        EKFState
            The estimates at this instant (row k of :meth:`run` after k + 1 steps). Without a
            given ``noise_std`` no update is made before :data:`MIN_SAMPLES` outputs have
            come in (σ is then estimated from them); with one, a loop of ``step`` computes
            what :meth:`run` computes.

        Raises
        ------
        DimensionError
            Wrong shapes or dt ≤ 0.
        NonFiniteError
            NaN or inf in u, inf in y, or the filter diverged.
        """
        sys_ = self.system
        n, r = sys_.n, sys_.r
        u_, y_, h = stream_sample(sys_, u, y, dt)
        s = np.concatenate([state.x_hat, state.theta_hat])
        P = np.array(state.P, dtype=np.float64, order="C")
        sigma, y_first = state.noise_std, state.y_first
        if sigma is None:
            y_first = np.vstack([np.zeros((0, r)) if y_first is None else y_first, y_[None]])
            if y_first.shape[0] >= MIN_SAMPLES:
                sigma = resolve_noise_std(None, y_first)
        u0 = (np.array(state.u_prev, dtype=np.float64)
              if state.k > 0 and state.u_prev is not None else None)
        ut, u_hist = smooth_input(u_[None], state.u_history)
        nis = ekf_sample(self.kernels, sys_, s, P, u0, ut[0], y_, state.dt_prev, self.h_rho,
                         self.q_x * np.eye(n), None if sigma is None else np.diag(sigma ** 2),
                         state.k)
        return EKFState(x_hat=s[:n], theta_hat=s[n:], P=P, k=state.k + 1, u_prev=ut[0],
                        dt_prev=h, u_history=u_hist, noise_std=sigma, y_first=y_first, nis=nis)

    def run(self, t: Any, u: Any, y: Any, *, state0: EKFState | None = None,
            x_hat0: Any = None, theta_hat0: Any = None, P0: Any = None) -> EstimateResult:
        """Filter a record: sample 0 is an update at the prior (or, from a ``state0`` that has
        seen samples, a prediction from its last sample then an update), later samples
        predict then update.

        Parameters
        ----------
        t : array_like (N,)
        u : array_like (N, m) or (N,)
        y : array_like (N, r) or (N,); NaN samples are predicted over.
        state0 : EKFState, optional
            From :meth:`init` or :meth:`step` (default ``init(x_hat0, theta_hat0)``). Its σ
            is used when known; else σ is estimated from the record.
        x_hat0, theta_hat0 : array_like, optional
            Shortcuts for ``state0=init(x_hat0, theta_hat0)`` (not with ``state0``).
        P0 : array_like (n + p, n + p), optional
            Overrides the prior covariance (not with ``state0``).

        Returns
        -------
        EstimateResult
            Row k: the estimates after sample k's update; ``diagnostics`` is an
            :class:`EKFDiagnostics` (θ's standard deviation, NIS, σ).

        Raises
        ------
        OptionError
            ``state0`` together with ``x_hat0``, ``theta_hat0`` or ``P0``.
        NonFiniteError
            The filter diverged.
        """
        sys_ = self.system
        n, m, r, p = sys_.n, sys_.m, sys_.r, sys_.p
        t_, U, Y = as_record(t, u, y, m, r)
        if state0 is not None and (x_hat0 is not None or theta_hat0 is not None
                                   or P0 is not None):
            raise OptionError("JointEKF.run: pass either state0 or x_hat0/theta_hat0/P0, not "
                              "both (state0 already holds the initial estimates).")
        st = self.init(x_hat0, theta_hat0) if state0 is None else state0
        sigma = (st.noise_std if st.noise_std is not None
                 else resolve_noise_std(self.noise_std, Y))
        R = np.diag(sigma ** 2)
        s = np.concatenate([st.x_hat, st.theta_hat])
        P = np.array(st.P, dtype=np.float64, order="C")
        if P0 is not None:
            P = np.array(P0, dtype=np.float64).reshape(n + p, n + p)
        ts = stage2_set(sys_.require_parameter_set("stage 2"))
        k = self.kernels
        Ut = np.ascontiguousarray(smooth_input(U, st.u_history)[0])
        if st.k > 0 and st.u_prev is not None:
            k.predict(s, P, np.array(st.u_prev, dtype=np.float64), Ut[0].copy(), st.dt_prev,
                      self.h_rho, self.q_x * np.eye(n), np.empty((n, n)), np.empty((n, p)))
        N = t_.shape[0]
        X, TH, SD, NIS = (np.empty((N, n)), np.empty((N, p)), np.empty((N, p)),
                          np.full(N, np.nan))
        bad = k.loop(s, P, Ut, Y, t_, 0, N, R, ts.lo, ts.hi, ts.ell, self.h_rho,
                     self.q_x * np.eye(n), X, TH, SD, NIS)
        if bad >= 0:
            raise divergence_error(t_, bad, NIS, sys_.r)
        return EstimateResult(t=t_, x_hat=X, theta_hat=TH,
                              phi_hat=phi_hat_from_model(sys_, U, Y, X, TH),
                              skipped=missing_samples(Y),
                              diagnostics=EKFDiagnostics(theta_sd=SD, nis=NIS, noise_std=sigma))

    def __repr__(self) -> str:
        return f"JointEKF(n={self.system.n}, p={self.system.p}, compiled={self.kernels.model.compiled})"


def divergence_error(t: FloatArray, bad: int, nis: FloatArray, r: int) -> NonFiniteError:
    """The error for a joint EKF whose state became non-finite at sample ``bad``.

    Parameters
    ----------
    t : ndarray (N,)
    bad : int
        The first sample with a non-finite state.
    nis : ndarray (N,)
        The normalised innovations squared of the samples before (NaN where none).
    r : int
        Outputs per sample (NIS's expectation).

    Returns
    -------
    NonFiniteError
        Says where, and — when the median NIS ÷ r before the divergence exceeds
        :data:`NIS_MODEL_ERROR` — that the model taken as exact does not fit the record and
        what to do about it.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.ekf import divergence_error
    >>> err = divergence_error(np.arange(5.0), 4, np.array([3e4, 2e4, 5e4, 4e4, np.nan]), 1)
    >>> "does not fit" in str(err)
    True
    """
    seen = np.asarray(nis[:bad], dtype=np.float64)
    seen = seen[np.isfinite(seen)]
    ratio = float(np.median(seen)) / max(r, 1) if seen.size else 0.0
    where = f"the EKF diverged at t[{bad}] = {float(t[bad]):.6g}"
    if ratio > NIS_MODEL_ERROR:
        return NonFiniteError(
            f"{where}: its innovations before were {math.sqrt(ratio):.3g}"
            " times their predicted size, so the model taken as exact (no process noise) does"
            " not fit this record; give a process noise q_x > 0, or use method 'guarded' or"
            " 'mle', which estimate it from the data.")
    return NonFiniteError(f"{where}; check the model and noise_std.")


def sample_interval(t: FloatArray) -> float:
    """The median spacing of ``t``: the sampling interval of a uniform record (1 with < 2).

    What a per-sample covariance (process noise over one sample) and the process-noise
    scale are taken over; the median keeps a few dropped samples from moving it.

    Parameters
    ----------
    t : ndarray (N,)

    Returns
    -------
    float

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.ekf import sample_interval
    >>> sample_interval(np.array([0.0, 0.1, 0.2, 0.5]))
    0.1
    """
    return float(np.median(np.diff(t))) if t.shape[0] > 1 else 1.0


def as_record(t: Any, u: Any, y: Any, m: int, r: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(t (N,), U (N, m), Y (N, r)) validated: t finite and increasing, u finite, y not inf."""
    # writable C-contiguous copies: the compiled kernels then see one array type whatever the
    # caller passes (numba compiles read-only arrays separately)
    t_ = np.array(t, dtype=np.float64).reshape(-1)
    N = t_.shape[0]
    if N < 2 or not np.all(np.isfinite(t_)) or np.any(np.diff(t_) <= 0):
        raise DimensionError("t must hold at least 2 finite, strictly increasing sampling "
                             "instants.")
    U = np.zeros((N, 0)) if u is None else np.array(u, dtype=np.float64).reshape(N, -1)
    Y = np.array(y, dtype=np.float64).reshape(N, -1)
    if U.shape != (N, m) or Y.shape != (N, r):
        raise DimensionError(f"u and y must have shapes ({N}, {m}) and ({N}, {r}) to match t; "
                             f"got {U.shape} and {Y.shape}.")
    if not np.all(np.isfinite(U)):
        raise NonFiniteError("u contains NaN or inf; clean or interpolate the input record.")
    if np.isinf(Y).any():
        raise NonFiniteError("y contains inf; only NaN marks a missing sample.")
    return t_, U, Y


def resolve_noise_std(noise_std: Any, Y: FloatArray) -> FloatArray:
    """σ per output: as given (> 0), else estimated from the record's second differences."""
    r = Y.shape[1]
    if noise_std is None:
        if Y.shape[0] < MIN_SAMPLES:
            raise DimensionError(f"noise_std cannot be estimated from {Y.shape[0]} samples "
                                 f"(need {MIN_SAMPLES}); pass noise_std.")
        sigma = estimate_noise_std(Y)
    else:
        sigma = np.broadcast_to(np.asarray(noise_std, dtype=np.float64), (r,)).copy()
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise DimensionError(f"the noise level must be finite and > 0; got σ = {sigma} (noise-"
                             "free data: pass a small noise_std, e.g. 1e-6 of the signal).")
    return sigma
