"""The Cramér–Rao lower bound of θ for a model, an input record and a noise level, over time.

With y_k = C x(t_k; θ, x(0)) + e_k, e_k ~ N(0, diag σ²) white, the Fisher information about
the unknowns q (θ, or col(θ, x(0)) when x(0) is unknown) in the samples up to t is

    I(t) = Σ_{t_k ≤ t} ψ_kᵀ R⁻¹ ψ_k,   ψ_k = C ∂x(t_k)/∂q,

and any unbiased estimator of θ from those data has covariance ≥ CRLB(t) = [I(t)⁻¹]_θθ (the
θ block of the inverse, i.e. the inverse of the Schur complement when x(0) is unknown). The
sensitivities solve the variational equations integrated with the model (eq. (1) with
y = C x in g, from :mod:`~thetahat.estimation.statistical.plant_kernel`):

    Ṡ = F_x S + F_θ,  S(0) = 0;   Ṁ = F_x M,  M(0) = I   (S = ∂x/∂θ, M = ∂x/∂x(0)),

by ``scipy.integrate.solve_ivp`` (LSODA with the block-diagonal Jacobian), u interpolated
linearly between its samples.

What it may import: :mod:`thetahat.model`, the package's helpers, the record checks of
:mod:`~thetahat.estimation.records`, and, in this room, only
:mod:`~thetahat.estimation.statistical.plant_kernel`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import solve_ivp

from ..._validate import as_vector
from ...errors import DimensionError, SimulationError
from ...model.system import PerturbedLinearSystem
from ..records import check_record
from .plant_kernel import jit, model_kernel

__all__ = ["CRLBResult", "crlb", "CRLB_RTOL", "SINGULAR_RTOL"]

FloatArray = NDArray[np.float64]

#: Relative tolerance of the sensitivity integration (the LuGre plant's own, rtol 1e-9).
CRLB_RTOL = 1e-9
#: An information matrix whose smallest eigenvalue is below this fraction of its largest is
#: treated as singular (the bound is infinite there: the data do not yet identify q).
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


def _make_rhs(rhs_jac: Any, compiled: bool) -> Any:
    def rhs(tt, z, t, U, slopes, theta, n, p, nq):
        """col(ẋ, Ṡ[:, 0], …, Ṡ[:, nq−1]) with u linear between samples."""
        i = np.searchsorted(t, tt, side="right") - 1
        i = min(max(i, 0), t.shape[0] - 2)
        u = U[i] + (tt - t[i]) * slopes[i]
        f = np.empty(n)
        Fx = np.empty((n, n))
        Ft = np.empty((n, p))
        rhs_jac(z[:n].copy(), u, theta, f, Fx, Ft)
        out = np.empty(z.shape[0])
        for a in range(n):      # element by element: numba's array-into-slice assignment
            out[a] = f[a]       # compiles a string-formatting error path (≈ 2 s)
        for q in range(nq):
            col = z[n + q * n:n + (q + 1) * n]
            for a in range(n):
                acc = Ft[a, q] if q < p else 0.0
                for b in range(n):
                    acc += Fx[a, b] * col[b]
                out[n + q * n + a] = acc
        return out

    return jit(rhs, compiled)


def _integrate(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, theta: FloatArray,
               x0: FloatArray, with_m: bool, rtol: float, atol: float,
               compiled: bool | None) -> FloatArray:
    """Z (N, n + n·nq): x and the columns of S = ∂x/∂q, q = θ or col(θ, x(0))."""
    kern = model_kernel(system, compiled=compiled)
    n, p = system.n, system.p
    nq = p + (n if with_m else 0)
    rhs = _make_rhs(kern.rhs_jac, kern.compiled) if kern not in _RHS else _RHS[kern]
    _RHS[kern] = rhs
    slopes = np.diff(U, axis=0) / np.diff(t)[:, None]
    Fx, Ft, f = np.empty((n, n)), np.empty((n, p)), np.empty(n)
    eye = np.eye(1 + nq)
    Uc = np.ascontiguousarray(U)

    def jac(tt: float, z: FloatArray, *_: Any) -> FloatArray:
        i = min(max(int(np.searchsorted(t, tt, side="right")) - 1, 0), t.shape[0] - 2)
        kern.rhs_jac(z[:n].copy(), U[i] + (tt - t[i]) * slopes[i], theta, f, Fx, Ft)
        # block diagonal, the second-derivative couplings left out: LSODA uses the Jacobian
        # in its Newton iteration only, so the approximation costs iterations, not accuracy
        return cast(FloatArray, np.kron(eye, Fx))      # float64 inputs: float64 result

    S0 = np.zeros((nq, n))                      # row q = column q of S
    if with_m:
        S0[p:, :] = np.eye(n)
    z0 = np.concatenate([x0, S0.ravel()])
    sol = solve_ivp(rhs, (t[0], t[-1]), z0, method="LSODA", t_eval=t, jac=jac, rtol=rtol,
                    atol=atol, args=(t, Uc, slopes, theta, n, p, nq))
    if not sol.success or sol.y.shape[1] != t.shape[0]:
        raise SimulationError(f"the sensitivity integration failed: {sol.message}. Check the "
                              "input record and θ (the model may be unstable there).")
    return sol.y.T


_RHS: dict[Any, Any] = {}


def crlb(system: PerturbedLinearSystem, t: Any, u: Any, *, theta: Any, noise_std: Any,
         x0: Any = None, x0_known: bool = True, rtol: float = CRLB_RTOL,
         atol: float = 1e-12, compiled: bool | None = None) -> CRLBResult:
    """The Cramér–Rao lower bound of θ on an experiment, as a function of time.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model, with a symbolic g (the plant: y = C x is substituted into g).
    t : array_like, shape (N,)
        Sampling instants of the experiment.
    u : array_like, shape (N, m) or (N,)
        The input record (linear between samples).
    theta : array_like, shape (p,)
        The true θ at which the bound is evaluated.
    noise_std : float or array_like (r,)
        σ of the white output noise, > 0.
    x0 : array_like, shape (n,), optional
        Initial state (default zeros).
    x0_known : bool
        If False, x(0) is estimated as well and the bound is the θ block of the joint one.
    rtol, atol : float
        Tolerances of the sensitivity integration.
    compiled : bool, optional
        numba kernels for the right-hand side (default: when installed).

    Returns
    -------
    CRLBResult

    Raises
    ------
    DimensionError
        Wrong shapes, σ ≤ 0, or a non-symbolic perturbation.
    SimulationError
        The integration failed.

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
    Z = _integrate(system, t_, U, th, x0_, not x0_known, rtol, atol, compiled)
    nq = p + (0 if x0_known else n)
    X = Z[:, :n]
    S = Z[:, n:].reshape(-1, nq, n).transpose(0, 2, 1)
    C = np.asarray(system.C, dtype=np.float64)
    psi = np.einsum("rn,knq->krq", C, S)
    w = psi / sigma[None, :, None]
    fim = np.cumsum(np.einsum("krq,krs->kqs", w, w), axis=0)
    lam, V = np.linalg.eigh(fim)
    ok = lam[:, 0] > SINGULAR_RTOL * np.maximum(lam[:, -1], 1e-300)
    lam_safe = np.where(ok[:, None], lam, 1.0)
    full = np.einsum("kqi,ki,ksi->kqs", V, 1.0 / lam_safe, V)
    cov = full[:, :p, :p].copy()
    cov[~ok] = np.inf
    return CRLBResult(t=t_, cov=cov, sensitivity=psi, x=X, noise_std=sigma,
                      x0_known=bool(x0_known))
