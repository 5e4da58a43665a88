"""The Cramér–Rao lower bound of θ for a model, an input record and a noise level, over time.

With y_k = C x(t_k; θ, x(0)) + e_k, e_k ~ N(0, diag σ²) white, the Fisher information about
the unknowns q (θ, or col(θ, x(0)) when x(0) is unknown) in the samples up to t is

    I(t) = Σ_{t_k ≤ t} ψ_kᵀ R⁻¹ ψ_k,   ψ_k = C ∂x(t_k)/∂q,

and any unbiased estimator of θ from those data has covariance ≥ CRLB(t) = [I(t)⁻¹]_θθ (the
θ block of the inverse, i.e. the inverse of the Schur complement when x(0) is unknown). The
trajectory and its sensitivities S_k = ∂x_k/∂q are those of the sampled-data map every
estimator of stage 2 uses (:mod:`~thetahat.estimation.statistical.plant_kernel`: RK4 sub-steps,
u between the samples as the hold reconstructs it), chained through the map's exact
Jacobians,

    S_{k+1} = Φ_k S_k + [Γ_k  0],   S_0 = [0  I₀]   (I₀ the columns of x(0), when unknown),

with the sub-steps chosen so that the trajectory is accurate to a tenth of a standard error
(:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`): the bound is the
information of the model the fits fit, under the same hold.

What it may import: :mod:`thetahat.model`, the package's helpers, the record checks of
:mod:`~thetahat.estimation.records`, and, in this room, :mod:`~thetahat.estimation.statistical.plant_kernel`
and :mod:`~thetahat.estimation.statistical.input_hold`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from ..._validate import as_vector
from ...errors import DimensionError, SimulationError
from ...model.system import PerturbedLinearSystem
from ..hold import DEFAULT_HOLD
from ..records import check_record
from .input_hold import stage2_samples
from .plant_kernel import ModelKernel, Propagation, choose_substeps, model_kernel, printed_kernels

__all__ = ["CRLBResult", "crlb", "SINGULAR_RTOL", "sensitivities", "sensitivity_kernel"]

FloatArray = NDArray[np.float64]

#: An information matrix whose smallest eigenvalue is below this fraction of its largest,
#: once scaled to unit diagonal (so that the units of θ and x(0) do not count), is treated as
#: singular (the bound is infinite there: the data do not yet identify q).
SINGULAR_RTOL = 1e-12


@dataclass(frozen=True, slots=True, eq=False)
class CRLBResult:
    """The bound as a function of time.

    Attributes
    ----------
    t : ndarray, shape (N,)
    cov : ndarray, shape (N, p, p)
        CRLB(t_k) on cov(θ̂) using the samples 0 … k (inf while the data do not identify q).
    sensitivity : ndarray, shape (N, r, n_q)
        ψ_k = ∂y_k/∂q, q = θ (x(0) known) or col(θ, x(0)).
    x : ndarray, shape (N, n)
        The noise-free trajectory.
    noise_std : ndarray, shape (r,)
    x0_known : bool

    Examples
    --------
    See :func:`crlb`.
    """

    t: FloatArray
    cov: FloatArray
    sensitivity: FloatArray
    x: FloatArray
    noise_std: FloatArray
    x0_known: bool

    @property
    def std(self) -> FloatArray:
        """√diag CRLB(t), shape (N, p)."""
        return np.sqrt(np.diagonal(self.cov, axis1=1, axis2=2))

    def std_at(self, t: float) -> FloatArray:
        """√diag CRLB using the samples up to time t, shape (p,)."""
        k = int(np.searchsorted(self.t, t, side="right")) - 1
        return self.std[max(k, 0)].copy()

    def time_to(self, rel: float, theta: Any, n_sigma: float = 3.0) -> float:
        """First t from which n_sigma·√CRLB(t) ≤ rel·|θ| in every component (inf if never)."""
        th = np.abs(np.asarray(theta, dtype=np.float64)).reshape(1, -1)
        ok = np.all(n_sigma * self.std <= rel * th, axis=1)
        return float(self.t[int(np.argmax(ok))]) if ok.any() else float("inf")

    def __repr__(self) -> str:
        return (f"CRLBResult(N={self.t.shape[0]}, p={self.cov.shape[1]}, "
                f"std[-1]={self.std[-1]}, x0_known={self.x0_known})")


# Names of the printed module (declared for the type checker; bound when printed).
propagate_into: Callable[..., Any]
plant_work: Callable[..., Any]


def sensitivities(x0: Any, th: Any, U: Any, tt: Any, pc: Any, WT: Any, S0: Any, X: Any,
                  SENS: Any) -> int:
    """The trajectory X (N, n) and S_k = ∂x_k/∂q into SENS (N, n, nq) from x(t_0) = x0 and
    S_0 = S0 (n, nq; columns 0 … p − 1 for θ), by the model's ``propagate_into``; returns −1, or
    the first sample that is not finite.

    Parameters
    ----------
    x0 : ndarray, shape (n,)
    th : ndarray, shape (p,)
    U : ndarray, shape (N, m)
    tt : ndarray, shape (N,)
    pc, WT : ndarray
        :meth:`~thetahat.estimation.statistical.plant_kernel.Propagation.arrays`.
    S0 : ndarray, shape (n, nq)
    X : ndarray, shape (N, n)
    SENS : ndarray, shape (N, n, nq)
        Output.

    Returns
    -------
    int
    """
    n = x0.shape[0]
    p = th.shape[0]
    nq = S0.shape[1]
    N = tt.shape[0]
    x = x0.copy()
    S = S0.copy()
    Sn = np.empty((n, nq))
    Phi = np.empty((n, n))
    Gam = np.empty((n, p))
    work = plant_work(n, p, p, U.shape[1], WT.shape[1])
    for k in range(N):
        if k > 0:
            propagate_into(x, x, th, U, k - 1, tt[k] - tt[k - 1], pc, WT, n > 0, Phi, Gam,
                           *work)
            for i in range(n):
                for j in range(nq):
                    acc = Gam[i, j] if j < p else 0.0
                    for a in range(n):
                        acc += Phi[i, a] * S[a, j]
                    Sn[i, j] = acc
            for i in range(n):
                for j in range(nq):
                    S[i, j] = Sn[i, j]
        for i in range(n):
            if not math.isfinite(x[i]):
                return k
            X[k, i] = x[i]
            for j in range(nq):
                SENS[k, i, j] = S[i, j]
    return -1


@functools.lru_cache(maxsize=16)
def sensitivity_kernel(model: ModelKernel) -> Callable[..., int]:
    """:func:`sensitivities` printed over a model's plant kernels (built once per model kernel;
    the free run's sensitivities of :mod:`thetahat.studies.free_run` run it too).

    Parameters
    ----------
    model : ModelKernel

    Returns
    -------
    callable
        ``sensitivities(x0, th, U, t, pc, WT, S0, X, SENS) -> −1 or the first bad sample``.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.plant_kernel import Propagation, model_kernel
    >>> run = sensitivity_kernel(model_kernel(lugre.system(), compiled=False))
    >>> t = np.arange(5) * 1e-3
    >>> X, S = np.empty((5, 2)), np.empty((5, 2, 1))
    >>> pc, WT = Propagation().arrays()
    >>> run(np.zeros(2), np.array([0.28]), np.ones((5, 1)), t, pc, WT, np.zeros((2, 1)), X, S)
    -1
    """
    mod, (name,) = printed_kernels(
        "thetahat_crlb", "Printed by thetahat.estimation.statistical.crlb: the sensitivities "
        "of one model; do not edit (content-addressed).", [sensitivities],
        {"propagate_into": model.propagate_into, "plant_work": model.plant_work},
        model.compiled)
    fn: Callable[..., int] = getattr(mod, name)
    return fn


def crlb(system: PerturbedLinearSystem, t: Any, u: Any, *, theta: Any, noise_std: Any,
         x0: Any = None, x0_known: bool = True, hold: str = DEFAULT_HOLD,
         substeps: int | None = None, compiled: bool | None = None) -> CRLBResult:
    """The Cramér–Rao lower bound of θ on an experiment, as a function of time.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model, with a symbolic g (the plant: y = C x is substituted into g).
    t : array_like, shape (N,)
        Sampling instants of the experiment.
    u : array_like, shape (N, m) or (N,)
        The input record.
    theta : array_like, shape (p,)
        The true θ at which the bound is evaluated.
    noise_std : float or array_like (r,)
        σ of the white output noise, > 0.
    x0 : array_like, shape (n,), optional
        Initial state (default zeros).
    x0_known : bool
        If False, x(0) is estimated as well and the bound is the θ block of the joint one.
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples (:mod:`~thetahat.estimation.hold`; ``"smooth"``:
        :func:`~thetahat.estimation.statistical.input_hold.stage2_samples`).
    substeps : int, optional
        The RK4 sub-steps' accuracy floor; default: chosen at θ from x0 so that the
        trajectory is accurate to a tenth of a standard error at this σ
        (:func:`~thetahat.estimation.statistical.plant_kernel.choose_substeps`).
    compiled : bool, optional
        numba kernels (default: when installed).

    Returns
    -------
    CRLBResult

    Raises
    ------
    DimensionError
        Wrong shapes, σ ≤ 0, or a non-symbolic perturbation.
    SimulationError
        The model's trajectory is not finite.

    Examples
    --------
    >>> from thetahat import crlb
    >>> from thetahat.models import lugre
    >>> data = lugre.simulate(seed=0, t_end=0.3)
    >>> bound = crlb(lugre.system(), data.t, data.u, theta=[0.28], noise_std=0.02,
    ...              compiled=False)
    >>> bool(bound.std[-1, 0] < 2e-3 * 0.28)      # below 0.2 % of θ after 0.3 s
    True
    >>> bool(bound.std[100, 0] > bound.std[-1, 0])   # and it shrinks with more data
    True
    """
    n, m, r, p = system.n, system.m, system.r, system.p
    t_, U, _ = check_record(t, u, np.zeros((np.size(t), r)), m=m, r=r)
    th = as_vector("theta", theta, p)
    x0_ = np.zeros(n) if x0 is None else as_vector("x0", x0, n)
    sigma = np.broadcast_to(np.asarray(noise_std, dtype=np.float64), (r,)).copy()
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise DimensionError(f"noise_std must be finite and > 0; got {sigma}.")
    kern = model_kernel(system, compiled=compiled)
    Us = stage2_samples(U, hold)[0]
    if substeps is None:
        Y0 = np.full((t_.shape[0], r), np.nan)
        substeps = choose_substeps(kern, t_, Us, Y0, th, x0_, sigma, hold=hold)
    pc, WT = Propagation(hold=hold, substeps=substeps).arrays()
    nq = p + (0 if x0_known else n)
    S0 = np.zeros((n, nq))
    if not x0_known:
        S0[:, p:] = np.eye(n)
    N = t_.shape[0]
    X, S = np.empty((N, n)), np.empty((N, n, nq))
    bad = sensitivity_kernel(kern)(x0_, th, Us, t_, pc, WT, S0, X, S)
    if bad >= 0:
        raise SimulationError(f"the model's trajectory is not finite from t[{bad}] = "
                              f"{float(t_[bad]):.6g} on: check the input record and θ (the "
                              "model may be unstable there).")
    C = np.asarray(system.C, dtype=np.float64)
    psi = np.einsum("rn,knq->krq", C, S)
    w = psi / sigma[None, :, None]
    fim = np.cumsum(np.einsum("krq,krs->kqs", w, w), axis=0)
    # scaled to unit diagonal (Jacobi) before the test and the inverse: the units of θ and
    # x(0) (a mass of 5e-6 beside a stiffness of 4) must not make an informative record look
    # singular; F⁻¹ = D⁻¹ (D⁻¹ F D⁻¹)⁻¹ D⁻¹ with D = √diag F
    d = np.sqrt(np.maximum(np.diagonal(fim, axis1=1, axis2=2), 0.0))
    informed = np.all(d > 0.0, axis=1)
    d_safe = np.where(d > 0.0, d, 1.0)
    lam, V = np.linalg.eigh(fim / (d_safe[:, :, None] * d_safe[:, None, :]))
    ok = informed & (lam[:, 0] > SINGULAR_RTOL * np.maximum(lam[:, -1], 1e-300))
    lam_safe = np.where(ok[:, None], lam, 1.0)
    full = (np.einsum("kqi,ki,ksi->kqs", V, 1.0 / lam_safe, V)
            / (d_safe[:, :, None] * d_safe[:, None, :]))
    cov = full[:, :p, :p].copy()
    cov[~ok] = np.inf
    return CRLBResult(t=t_, cov=cov, sensitivity=psi, x=X, noise_std=sigma,
                      x0_known=bool(x0_known))
