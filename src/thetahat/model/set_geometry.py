"""The geometry under the parameter sets of :mod:`thetahat.model.paramset`: an overflow-free
norm, the Cholesky factor of a projection metric, the radial retraction onto {P ≤ 0}, and the
nearest point of an ellipsoid by its secular equation.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ..errors import DimensionError

__all__ = ["BISECTION_STEPS", "SECULAR_MAX_ITER", "SECULAR_RTOL", "SMALLEST_EXPONENT",
           "SYMMETRY_RTOL", "metric_factor", "project_ellipsoid", "retract", "safe_norm",
           "secular", "shrink_inside"]

FloatArray = NDArray[np.float64]

#: Relative tolerance for the symmetry of an ellipsoid's shape matrix Q: a matrix assembled from
#: floating-point products is symmetric only to a few ulps of its norm.
SYMMETRY_RTOL = 1e-10
#: Stopping tolerance of the ellipsoid secular-equation solve (relative width of the bracket on
#: the multiplier): a few ulps, since the bracketed Newton iteration converges quadratically.
SECULAR_RTOL = 4 * np.finfo(float).eps
#: Iteration cap of the secular-equation solve; bisection alone would need < 1100 steps to
#: exhaust the double-precision range, Newton typically needs fewer than 10.
SECULAR_MAX_ITER = 200
#: Bisection steps along a segment from the interior point to the boundary, once the boundary
#: is bracketed within a factor 2: 2**-60 relative is below double precision.
BISECTION_STEPS = 60
#: 2**-1100 rounds to 0 in double precision, so the log-bisection starts from the interior point.
SMALLEST_EXPONENT = 1100


def safe_norm(z: FloatArray) -> FloatArray:
    """Euclidean norm over the last axis without overflow for entries near 1e308.

    Parameters
    ----------
    z : ndarray, shape (..., p)

    Returns
    -------
    ndarray, shape (...)

    Examples
    --------
    >>> import numpy as np
    >>> float(safe_norm(np.array([3e300, 4e300])))
    5e+300
    """
    s = np.max(np.abs(z), axis=-1)
    safe = np.where(s > 0, s, 1.0)
    return s * np.sqrt(np.sum((z / safe[..., None]) ** 2, axis=-1))


def metric_factor(metric: ArrayLike, p: int) -> FloatArray | None:
    """Cholesky factor L (W = L Lᵀ) of an SPD metric, or None when W is a multiple of I.

    Parameters
    ----------
    metric : array_like, shape (p, p)
        Symmetric positive-definite W.
    p : int
        Dimension of Θ.

    Returns
    -------
    ndarray, shape (p, p), or None

    Raises
    ------
    DimensionError
        Wrong shape, or W not symmetric positive definite.

    Examples
    --------
    >>> import numpy as np
    >>> metric_factor(2 * np.eye(2), 2) is None
    True
    """
    W = np.asarray(metric, dtype=np.float64)
    if W.shape != (p, p):
        raise DimensionError(f"metric must have shape ({p}, {p}); got {W.shape}.")
    if np.allclose(W, W[0, 0] * np.eye(p), rtol=0, atol=SYMMETRY_RTOL * abs(W[0, 0])):
        return None
    try:
        return np.asarray(np.linalg.cholesky(0.5 * (W + W.T)), dtype=np.float64)
    except np.linalg.LinAlgError as exc:
        raise DimensionError("metric must be symmetric positive definite.") from exc


def shrink_inside(pts: FloatArray, centre: FloatArray,
                   P: Callable[[FloatArray], FloatArray]) -> FloatArray:
    """Pull points with P > 0 (rounding excess only) towards ``centre`` until P <= 0.

    The pull doubles from one ulp up to 2**-12 of the distance; a point still outside after
    that (never seen: the callers' points are off by rounding) is replaced by the centre.

    Parameters
    ----------
    pts : ndarray, shape (..., p)
    centre : ndarray, shape (p,)
        An interior point (P < 0).
    P : callable
        The set's constraint, ``P(theta)`` of shape (...,).

    Returns
    -------
    ndarray, shape (..., p)
        Points with P <= 0.
    """
    out = pts
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(41):
            bad = ~(P(out) <= 0)
            if not np.any(bad):
                return out
            out = np.where(bad[..., None], centre + (out - centre) * (1 - 2.0 ** (k - 52)), out)
        return np.where((~(P(out) <= 0))[..., None], centre, out)


def retract(w: FloatArray, c: FloatArray,
             P: Callable[[FloatArray], FloatArray]) -> FloatArray:
    """The last point of Θ on each segment [c, w] (c interior); w itself when P(w) <= 0.

    The fraction s of the segment is bracketed within a factor 2 by bisection on log2(s)
    (points as far as 1e300 have their boundary at s ~ 1e-300), then refined by plain
    bisection; the feasible end of the bracket is returned.

    Parameters
    ----------
    w : ndarray, shape (..., p)
    c : ndarray, shape (p,)
        An interior point (P < 0).
    P : callable
        The set's constraint, ``P(theta)`` of shape (...,).

    Returns
    -------
    ndarray, shape (..., p)

    Examples
    --------
    >>> import numpy as np
    >>> P = lambda t: np.sum(t**2, axis=-1) - 1.0
    >>> bool(abs(retract(np.array([3.0, 0.0]), np.zeros(2), P)[0] - 1.0) < 1e-12)
    True
    """
    d = w - c
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        inside = P(w) <= 0
        lo_e = np.full(w.shape[:-1], -float(SMALLEST_EXPONENT))  # s = 2**lo_e rounds to 0
        hi_e = np.zeros(w.shape[:-1])
        while np.any(hi_e - lo_e > 1):
            mid = np.floor(0.5 * (lo_e + hi_e))
            ok = P(c + np.exp2(mid)[..., None] * d) <= 0
            lo_e = np.where(ok, mid, lo_e)
            hi_e = np.where(ok, hi_e, mid)
        lo, hi = np.exp2(lo_e), np.exp2(hi_e)
        for _ in range(BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            ok = P(c + mid[..., None] * d) <= 0
            lo = np.where(ok, mid, lo)
            hi = np.where(ok, hi, mid)
    return np.where(inside[..., None], w, c + lo[..., None] * d)


def secular(u: FloatArray, lam: FloatArray) -> FloatArray:
    """Nearest point of {x : Σ λ_i x_i² ≤ 1} to each row of u (diagonal coordinates).

    Solves Σ λ_i u_i² / (1 + t λ_i)² = 1 for t >= 0 with a bracketed (safeguarded) Newton
    iteration; x_i = u_i / (1 + t λ_i). The rows are rescaled first (u = s û, t = s τ) so
    that points as far as 1e300 neither overflow nor lose the solution.

    Parameters
    ----------
    u : ndarray, shape (N, p)
    lam : ndarray, shape (p,)
        Positive semi-axis weights λ_i.

    Returns
    -------
    ndarray, shape (N, p)

    Examples
    --------
    >>> import numpy as np
    >>> secular(np.array([[2.0, 0.0]]), np.array([1.0, 4.0])).tolist()
    [[1.0, 0.0]]
    """
    x = u.copy()
    with np.errstate(over="ignore"):
        q = np.sum(lam * u**2, axis=-1)
    out = ~(q <= 1.0)
    if not np.any(out):
        return x
    uo = u[out]
    s = np.maximum(1.0, np.max(np.abs(uo) * np.sqrt(lam), axis=-1))
    uh, eps = uo / s[:, None], 1.0 / s
    lo = np.zeros(len(uo))
    hi = np.sqrt(np.sum(uh**2 / lam, axis=-1))
    tau = hi.copy()
    with np.errstate(over="ignore", divide="ignore", invalid="ignore", under="ignore"):
        for _ in range(SECULAR_MAX_ITER):
            den = eps[:, None] + tau[:, None] * lam
            F = np.sum(lam * uh**2 / den**2, axis=-1) - 1.0
            dF = -2.0 * np.sum(lam**2 * uh**2 / den**3, axis=-1)
            lo = np.where(F > 0, tau, lo)
            hi = np.where(F > 0, hi, tau)
            newton = tau - F / dF
            ok = np.isfinite(newton) & (newton > lo) & (newton < hi)
            tau = np.where(ok, newton, 0.5 * (lo + hi))
            if np.all((hi - lo) <= SECULAR_RTOL * hi):
                break
        tau = hi  # the feasible side of the bracket
        xo = uh / (eps[:, None] + tau[:, None] * lam)
    qo = np.sum(lam * xo**2, axis=-1)
    xo = np.where((qo > 1.0)[:, None], xo / np.sqrt(qo)[:, None], xo)
    x[out] = xo
    return x


def project_ellipsoid(z: FloatArray, c: FloatArray, Q: FloatArray,
                       L: FloatArray | None) -> FloatArray:
    """Nearest point of {(θ-c)ᵀQ(θ-c) ≤ 1} in the metric W = L Lᵀ (Euclidean if L is None).

    Parameters
    ----------
    z : ndarray, shape (..., p)
    c : ndarray, shape (p,)
        Centre.
    Q : ndarray, shape (p, p)
        Shape matrix (symmetric positive definite).
    L : ndarray, shape (p, p), or None
        :func:`metric_factor` of the metric.

    Returns
    -------
    ndarray, shape (..., p)
        Points inside Θ are returned bit for bit.
    """
    flat = z.reshape(-1, z.shape[-1])
    if L is None:
        lam, V = np.linalg.eigh(Q)
        x = secular((flat - c) @ V, lam)
        res = c + x @ V.T
    else:
        Li = scipy.linalg.solve_triangular(L, np.eye(len(c)), lower=True)  # L⁻¹
        Qw = Li @ Q @ Li.T
        lam, V = np.linalg.eigh(0.5 * (Qw + Qw.T))
        T = Li.T @ V  # θ - c = T x
        x = secular((flat - c) @ L @ V, lam)
        res = c + x @ T.T
    P = lambda t: np.einsum("...i,ij,...j->...", t - c, Q, t - c) - 1  # noqa: E731
    res = shrink_inside(res, c, P)
    with np.errstate(over="ignore", invalid="ignore"):
        inside = P(flat) <= 0
    res = np.where(inside[:, None], flat, res)  # bit-for-bit identity inside Θ
    return res.reshape(z.shape)
