"""Compact convex parameter sets Θ and their projection (Krstić et al. 1995, App. E).

A parameter set answers three questions for the update laws of Sec. IV:

* ``contains(theta)``: is θ ∈ Θ (batch over leading axes)?
* ``nearest(theta, metric=W)``: the point of Θ closest to θ in the norm ‖z‖²_W = zᵀ W z
  (Euclidean when ``metric`` is None); the discrete-time projection.
* ``constraint(theta)`` / ``constraint_grad(theta)``: smooth convex functions P_j with
  Θ = {θ : P_j(θ) ≤ 0 for every j} and their gradients; what the continuous-time projection
  operator Proj of Krstić et al. (App. E) needs. Balls, ellipsoids and general convex sets use a
  single function (q = 1); the box uses one function per coordinate (q = p), because a single
  smooth P cannot describe its corners.

The functions P_j of the built-in sets are normalised so that P_j = -1 at the centre and
P_j = 0 on the boundary; the boundary layer of the smooth projection (``layer`` in
:class:`thetahat.estimation.observer.laws.projection.Projection`) is measured in these units.
"""

from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, final

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from .._validate import as_samples, readonly
from ..errors import (ConvergenceWarning, DimensionError, NonFiniteError, ParameterSetError,
                      UnsupportedError)
from .set_geometry import (SYMMETRY_RTOL, metric_factor, project_ellipsoid, retract,
                           safe_norm, shrink_inside)

FloatArray = NDArray[np.float64]

__all__ = ["ParameterSet", "Box", "Ball", "Ellipsoid", "ConvexSet", "safe_norm"]

#: Stopping tolerance of the Newton iteration that projects onto a :class:`ConvexSet` (relative
#: size of the last step); Newton converges quadratically, so this costs one extra iteration.
CONVEX_RTOL = 1e-12
#: ... or stop when the scaled KKT residual is this small (the equations are O(1) after scaling).
KKT_RTOL = 1e-13
#: Iteration cap of that Newton iteration: 3 to 10 iterations are typical; far points of very
#: elongated sets (axis ratio 100, distance 1000) were seen to need up to about 200.
CONVEX_MAX_ITER = 400
#: Relative step of the central finite differences that check a user's grad_P on construction;
#: eps**(1/3) balances truncation and rounding error.
FD_STEP = np.finfo(float).eps ** (1 / 3)
#: Accepted relative mismatch between grad_P and its finite-difference estimate.
FD_RTOL = 1e-4
#: Radius (in multiples of the interior point's scale, at least 1) beyond which a ConvexSet that
#: still has P <= 0 along a ray is declared unbounded.
UNBOUNDED_RADIUS = 1e8


#: Box projections in a non-diagonal metric pull points farther than this many box widths in
#: along the ray from the centre: least squares would square their coordinates and overflow.
FAR_PULL = 1e100


def _as_theta(name: str, theta: ArrayLike, p: int) -> FloatArray:
    arr = np.asarray(theta, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != p:
        raise DimensionError(f"{name} must have shape (..., {p}) for a {p}-parameter set; "
                             f"got shape {arr.shape}.")
    return arr


def _finite_theta(name: str, theta: ArrayLike, p: int) -> FloatArray:
    arr = _as_theta(name, theta, p)
    if not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{name} contains NaN or inf; only finite points can be projected "
                             f"onto Θ.")
    return arr


def _vector(owner: str, name: str, value: ArrayLike) -> FloatArray:
    try:
        arr = as_samples(f"{owner}: {name}", value)
    except DimensionError as exc:          # text, booleans, ragged lists
        raise ParameterSetError(f"{exc} Give numbers, one bound per parameter.") from None
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1 or arr.size == 0:
        raise ParameterSetError(f"{owner}: {name} must be a non-empty 1-D vector; got shape "
                                f"{arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ParameterSetError(f"{owner}: {name} must be finite (a compact Θ); got {arr}.")
    return arr


class ParameterSet(ABC):
    """Abstract compact convex Θ ⊂ R^p.

    Concrete classes are final frozen dataclasses (``Box``, ``Ball``, ``Ellipsoid``,
    ``ConvexSet``). Besides the abstract ``dim``, ``contains`` and ``nearest``, a set used with
    the continuous projection operator provides ``interior_point``, ``constraint`` and
    ``constraint_grad``; the defaults here raise :class:`NotImplementedError`.
    """

    @property
    @abstractmethod
    def dim(self) -> int:
        """p, the number of parameters."""

    @abstractmethod
    def contains(self, theta: FloatArray, *, tol: float = 0.0) -> bool | NDArray[np.bool_]:
        """Membership θ ∈ Θ (batch over leading axes); with ``tol`` > 0, dist(θ, Θ) <= tol."""

    @abstractmethod
    def nearest(self, theta: FloatArray, *, metric: ArrayLike | None = None) -> FloatArray:
        """Projection of θ onto Θ in the norm zᵀWz, W = ``metric`` (Euclidean when None)."""

    @property
    def interior_point(self) -> FloatArray:
        """A point with every P_j < 0 (the centre for the built-in sets); shape (p,)."""
        raise UnsupportedError(f"{type(self).__name__} must define interior_point.")

    def constraint(self, theta: FloatArray) -> FloatArray:
        """Smooth convex P_j(θ), Θ = {all P_j <= 0}; shape (..., q)."""
        raise UnsupportedError(f"{type(self).__name__} must define constraint().")

    def constraint_grad(self, theta: FloatArray) -> FloatArray:
        """Gradients ∇P_j(θ); shape (..., q, p)."""
        raise UnsupportedError(f"{type(self).__name__} must define constraint_grad().")

    def sample(self, rng: np.random.Generator, n: int) -> FloatArray:
        """``n`` random points of Θ, shape (n, p).

        The default draws a random direction from ``interior_point``, finds the boundary along
        it by bisection and picks a radius fraction u**(1/p): uniform for star-shaped sets
        measured from the interior point's view, not uniform in general.
        """
        c = np.asarray(self.interior_point, dtype=np.float64)
        p = c.shape[0]
        d = rng.standard_normal((n, p))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        P = lambda t: np.max(self.constraint(t), axis=-1)  # noqa: E731
        scale = max(1.0, float(np.max(np.abs(c))))
        R = np.full(n, scale)
        while True:
            far = P(c + R[:, None] * d) > 0
            if np.all(far) or np.max(R) > UNBOUNDED_RADIUS * scale:
                break
            R = np.where(far, R, 2 * R)
        edge = retract(c + R[:, None] * d, c, P)
        return c + (edge - c) * rng.uniform(size=(n, 1)) ** (1 / p)

    def _contains_by_nearest(self, theta: FloatArray, inside: NDArray[np.bool_],
                             tol: float) -> bool | NDArray[np.bool_]:
        if tol > 0 and not np.all(inside):
            with np.errstate(invalid="ignore"):
                fin = np.all(np.isfinite(theta), axis=-1)
            cand = ~inside & fin
            if np.any(cand):
                pts = theta[cand]
                inside = inside.copy()
                inside[cand] = safe_norm(pts - self.nearest(pts)) <= tol
        return bool(inside) if inside.ndim == 0 else inside


@final
@dataclass(frozen=True, slots=True, eq=False)
class Box(ParameterSet):
    """The box Θ = {θ : lower <= θ <= upper} (componentwise).

    Parameters
    ----------
    lower, upper : array_like, shape (p,)
        Finite bounds with lower < upper in every coordinate.

    Raises
    ------
    ParameterSetError
        Bounds of different lengths, not finite, or lower >= upper somewhere.

    Notes
    -----
    For the continuous projection the box is described coordinate by coordinate,
    P_i(θ) = ((θ_i - m_i)/h_i)² - 1 with centre m and half-widths h, so q = p constraints.
    The Euclidean projection is a clip; the projection in a non-diagonal metric W is a
    bound-constrained least-squares problem solved exactly (SciPy's BVLS) for each point.

    Examples
    --------
    >>> from thetahat.model.paramset import Box
    >>> box = Box([0.0, -1.0], [2.0, 1.0])
    >>> box.contains([1.0, 0.5]), box.nearest([3.0, 0.0]).tolist()
    (True, [2.0, 0.0])
    """

    lower: FloatArray
    upper: FloatArray

    def __init__(self, lower: ArrayLike, upper: ArrayLike) -> None:
        lo = _vector("Box", "lower", lower)
        hi = _vector("Box", "upper", upper)
        if lo.shape != hi.shape:
            raise ParameterSetError(f"Box: lower has length {lo.size} but upper has length "
                                    f"{hi.size}; give one bound per parameter.")
        bad = np.flatnonzero(~(lo < hi))
        if bad.size:
            i = int(bad[0])
            raise ParameterSetError(f"Box: lower < upper is required in every coordinate; "
                                    f"coordinate {i} has lower={lo[i]} >= upper={hi[i]}. Swap "
                                    f"or widen the bounds.")
        object.__setattr__(self, "lower", readonly(lo))
        object.__setattr__(self, "upper", readonly(hi))

    @property
    def dim(self) -> int:
        """p, the number of parameters."""
        return int(self.lower.shape[0])

    @property
    def interior_point(self) -> FloatArray:
        """The centre (lower + upper)/2."""
        return 0.5 * (self.lower + self.upper)

    def contains(self, theta: ArrayLike, *, tol: float = 0.0) -> bool | NDArray[np.bool_]:
        """θ ∈ Θ (dist(θ, Θ) <= tol when tol > 0); shape (...)."""
        th = _as_theta("theta", theta, self.dim)
        inside = np.all((th >= self.lower) & (th <= self.upper), axis=-1)
        return self._contains_by_nearest(th, np.asarray(inside), tol)

    def nearest(self, theta: ArrayLike, *, metric: ArrayLike | None = None) -> FloatArray:
        """Projection onto the box; a clip unless ``metric`` is not diagonal. Shape (..., p)."""
        th = _finite_theta("theta", theta, self.dim)
        clipped = np.clip(th, self.lower, self.upper)
        if metric is None:
            return clipped
        W = np.asarray(metric, dtype=np.float64)
        L = metric_factor(W, self.dim)
        if L is None or np.allclose(W, np.diag(np.diag(W))):
            return clipped
        flat = th.reshape(-1, self.dim)
        out = clipped.reshape(-1, self.dim).copy()
        # pull far points in along the ray from the centre (squares of 1e300 overflow); for a
        # box the active set, hence the projection, is the same beyond a finite distance
        m, h = self.interior_point, float(np.max(self.upper - self.lower))
        dist = np.max(np.abs(flat - m), axis=-1, keepdims=True)
        # (points within FAR_PULL·h stay exactly as they are; the denominator is never 0)
        scale = FAR_PULL * h / np.maximum(dist, FAR_PULL * h)
        flat = np.where(dist > FAR_PULL * h, m + (flat - m) * scale, flat)
        LT = L.T
        for i in np.flatnonzero(np.any(flat != out, axis=-1)):
            res = scipy.optimize.lsq_linear(LT, LT @ flat[i], bounds=(self.lower, self.upper),
                                            method="bvls")
            out[i] = np.clip(res.x, self.lower, self.upper)
        return out.reshape(th.shape)

    def constraint(self, theta: ArrayLike) -> FloatArray:
        """P_i(θ) = ((θ_i - m_i)/h_i)² - 1; shape (..., p)."""
        th = _as_theta("theta", theta, self.dim)
        h = 0.5 * (self.upper - self.lower)
        return ((th - self.interior_point) / h) ** 2 - 1.0

    def constraint_grad(self, theta: ArrayLike) -> FloatArray:
        """∇P_i = 2 (θ_i - m_i)/h_i² e_i; shape (..., p, p) (diagonal)."""
        th = _as_theta("theta", theta, self.dim)
        h = 0.5 * (self.upper - self.lower)
        g = 2.0 * (th - self.interior_point) / h**2
        return g[..., :, None] * np.eye(self.dim)

    def sample(self, rng: np.random.Generator, n: int) -> FloatArray:
        """``n`` uniform points of the box, shape (n, p)."""
        return rng.uniform(self.lower, self.upper, size=(n, self.dim))

    def __repr__(self) -> str:
        return f"Box(lower={self.lower.tolist()}, upper={self.upper.tolist()})"


@final
@dataclass(frozen=True, slots=True, eq=False)
class Ball(ParameterSet):
    """The closed Euclidean ball Θ = {θ : ‖θ - center‖ <= radius}.

    Parameters
    ----------
    center : array_like, shape (p,)
    radius : float
        Finite and > 0.

    Raises
    ------
    ParameterSetError
        Non-finite centre or radius, or radius <= 0.

    Notes
    -----
    P(θ) = ‖θ - c‖²/R² - 1. The Euclidean projection is radial; the projection in another
    metric is the ellipsoid projection with Q = I/R².

    Examples
    --------
    >>> from thetahat.model.paramset import Ball
    >>> ball = Ball([0.0, 0.0], 2.0)
    >>> ball.nearest([4.0, 0.0]).tolist()
    [2.0, 0.0]
    """

    center: FloatArray
    radius: float

    def __init__(self, center: ArrayLike, radius: float) -> None:
        c = _vector("Ball", "center", center)
        try:
            R = float(radius)
        except (TypeError, ValueError) as exc:
            raise ParameterSetError(f"Ball: radius must be a number; got {radius!r}.") from exc
        if not (np.isfinite(R) and R > 0):
            raise ParameterSetError(f"Ball: radius must be finite and > 0; got {R}. Use a "
                                    f"positive radius slightly larger than the parameter range.")
        object.__setattr__(self, "center", readonly(c))
        object.__setattr__(self, "radius", R)

    @property
    def dim(self) -> int:
        """p, the number of parameters."""
        return int(self.center.shape[0])

    @property
    def interior_point(self) -> FloatArray:
        """The centre."""
        return self.center

    def contains(self, theta: ArrayLike, *, tol: float = 0.0) -> bool | NDArray[np.bool_]:
        """θ ∈ Θ (dist(θ, Θ) <= tol when tol > 0); shape (...)."""
        th = _as_theta("theta", theta, self.dim)
        with np.errstate(invalid="ignore"):
            inside = np.asarray(safe_norm(th - self.center) <= self.radius + tol)
        return bool(inside) if inside.ndim == 0 else inside

    def nearest(self, theta: ArrayLike, *, metric: ArrayLike | None = None) -> FloatArray:
        """Projection onto the ball (radial when Euclidean); shape (..., p)."""
        th = _finite_theta("theta", theta, self.dim)
        L = None if metric is None else metric_factor(metric, self.dim)
        inside_ball = lambda t: safe_norm(t - self.center) - self.radius  # noqa: E731
        if L is not None:
            Q = np.eye(self.dim) / self.radius**2
            res = project_ellipsoid(th, self.center, Q, L)
            return shrink_inside(res, self.center, inside_ball)  # contains() uses the norm
        d = th - self.center
        r = safe_norm(d)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(r > self.radius, self.radius / r, 1.0)
        res = self.center + d * scale[..., None]
        res = shrink_inside(res, self.center, inside_ball)
        return np.where((r <= self.radius)[..., None], th, res)  # identity inside Θ

    def constraint(self, theta: ArrayLike) -> FloatArray:
        """P(θ) = ‖θ - c‖²/R² - 1; shape (..., 1)."""
        th = _as_theta("theta", theta, self.dim)
        return (np.sum((th - self.center) ** 2, axis=-1) / self.radius**2 - 1.0)[..., None]

    def constraint_grad(self, theta: ArrayLike) -> FloatArray:
        """∇P = 2 (θ - c)/R²; shape (..., 1, p)."""
        th = _as_theta("theta", theta, self.dim)
        return (2.0 * (th - self.center) / self.radius**2)[..., None, :]

    def sample(self, rng: np.random.Generator, n: int) -> FloatArray:
        """``n`` uniform points of the ball, shape (n, p)."""
        d = rng.standard_normal((n, self.dim))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return self.center + self.radius * d * rng.uniform(size=(n, 1)) ** (1 / self.dim)

    def __repr__(self) -> str:
        return f"Ball(center={self.center.tolist()}, radius={self.radius})"


@final
@dataclass(frozen=True, slots=True, eq=False)
class Ellipsoid(ParameterSet):
    """The ellipsoid Θ = {θ : (θ - center)ᵀ shape (θ - center) <= 1}.

    Convention: ``shape`` is the matrix Q of the quadratic form (not its inverse); its
    eigenvalues are 1/a_i² for semi-axes a_i. ``Ellipsoid(c, np.eye(p) / R**2)`` is the ball of
    radius R.

    Parameters
    ----------
    center : array_like, shape (p,)
    shape : array_like, shape (p, p)
        Q, symmetric positive definite.

    Raises
    ------
    ParameterSetError
        Non-finite entries, wrong shape, Q not symmetric or not positive definite.

    Notes
    -----
    P(θ) = (θ - c)ᵀQ(θ - c) - 1, ∇P = 2Q(θ - c). The Euclidean projection of z outside Θ is
    x = c + V (I + tΛ)⁻¹ Vᵀ(z - c) with Q = VΛVᵀ, where t > 0 solves the secular equation
    Σ λ_i u_i²/(1 + tλ_i)² = 1, u = Vᵀ(z - c). It is solved by Newton's method safeguarded by
    a bracket [0, ‖Λ^(-1/2) u‖] (the function is convex and decreasing, so the bracket always
    contains the root and the iteration cannot fail); a projection in the metric W becomes a
    Euclidean projection after the change of variables ζ = Lᵀθ, W = LLᵀ.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Ellipsoid
    >>> ell = Ellipsoid([0.0, 0.0], np.diag([1.0, 1 / 4]))  # semi-axes 1 and 2
    >>> np.round(ell.nearest([0.0, 5.0]), 12).tolist()
    [0.0, 2.0]
    """

    center: FloatArray
    shape: FloatArray
    _eig: tuple[FloatArray, FloatArray] = field(init=False, repr=False)

    def __init__(self, center: ArrayLike, shape: ArrayLike) -> None:
        c = _vector("Ellipsoid", "center", center)
        p = c.shape[0]
        Q = np.asarray(shape, dtype=np.float64)
        if Q.shape != (p, p):
            raise ParameterSetError(f"Ellipsoid: shape must be a ({p}, {p}) matrix to match the "
                                    f"centre; got shape {Q.shape}.")
        if not np.all(np.isfinite(Q)):
            raise ParameterSetError("Ellipsoid: shape contains NaN or inf.")
        scale = max(float(np.max(np.abs(Q))), np.finfo(float).tiny)
        if np.max(np.abs(Q - Q.T)) > SYMMETRY_RTOL * scale:
            raise ParameterSetError("Ellipsoid: shape must be symmetric; symmetrise it, e.g. "
                                    "0.5 * (Q + Q.T).")
        Q = 0.5 * (Q + Q.T)
        lam, V = np.linalg.eigh(Q)
        if not lam[0] > 0:
            raise ParameterSetError(f"Ellipsoid: shape must be positive definite (a bounded "
                                    f"Θ); its smallest eigenvalue is {lam[0]:.3g}. Each "
                                    f"eigenvalue is 1/a² for a semi-axis a.")
        object.__setattr__(self, "center", readonly(c))
        object.__setattr__(self, "shape", readonly(Q))
        object.__setattr__(self, "_eig", (readonly(lam), readonly(V)))

    @property
    def dim(self) -> int:
        """p, the number of parameters."""
        return int(self.center.shape[0])

    @property
    def interior_point(self) -> FloatArray:
        """The centre."""
        return self.center

    def contains(self, theta: ArrayLike, *, tol: float = 0.0) -> bool | NDArray[np.bool_]:
        """θ ∈ Θ (dist(θ, Θ) <= tol when tol > 0); shape (...)."""
        th = _as_theta("theta", theta, self.dim)
        with np.errstate(over="ignore", invalid="ignore"):
            inside = np.asarray(self.constraint(th)[..., 0] <= 0)
        return self._contains_by_nearest(th, inside, tol)

    def nearest(self, theta: ArrayLike, *, metric: ArrayLike | None = None) -> FloatArray:
        """Projection onto the ellipsoid (secular equation); shape (..., p)."""
        th = _finite_theta("theta", theta, self.dim)
        L = None if metric is None else metric_factor(metric, self.dim)
        return project_ellipsoid(th, self.center, self.shape, L)

    def constraint(self, theta: ArrayLike) -> FloatArray:
        """P(θ) = (θ - c)ᵀQ(θ - c) - 1; shape (..., 1)."""
        th = _as_theta("theta", theta, self.dim)
        d = th - self.center
        return (np.einsum("...i,ij,...j->...", d, self.shape, d) - 1.0)[..., None]

    def constraint_grad(self, theta: ArrayLike) -> FloatArray:
        """∇P = 2Q(θ - c); shape (..., 1, p)."""
        th = _as_theta("theta", theta, self.dim)
        return (2.0 * (th - self.center) @ self.shape)[..., None, :]

    def sample(self, rng: np.random.Generator, n: int) -> FloatArray:
        """``n`` uniform points of the ellipsoid, shape (n, p)."""
        lam, V = self._eig
        d = rng.standard_normal((n, self.dim))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        ball = d * rng.uniform(size=(n, 1)) ** (1 / self.dim)
        return self.center + (ball / np.sqrt(lam)) @ V.T

    def __repr__(self) -> str:
        return f"Ellipsoid(center={self.center.tolist()}, shape={self.shape.tolist()})"


#: Relative pull of ConvexSet's projection toward its interior point (see ``nearest``): far
#: above rounding (1e-16), far below any tolerance on the projection itself.
INWARD = 1e-12


@final
@dataclass(frozen=True, slots=True, eq=False)
class ConvexSet(ParameterSet):
    """A compact convex set Θ = {θ : P(θ) <= 0} given by a smooth convex function.

    Parameters
    ----------
    P : callable
        ``P(theta)`` with theta of shape (..., p) returns shape (...,); smooth and convex.
    grad_P : callable
        ``grad_P(theta)`` returns ∇P, shape (..., p).
    interior_point : array_like, shape (p,)
        A point with P < 0. Used for the sanity checks, the retraction onto Θ and sampling.

    Raises
    ------
    ParameterSetError
        P(interior_point) is not < 0 or not finite; a callable returns the wrong shape; grad_P
        disagrees with finite differences of P near the interior point; or P stays <= 0 along a
        ray out to 1e8 (Θ is not bounded).

    Notes
    -----
    ``nearest`` solves min ½‖θ - z‖²_W subject to P(θ) <= 0 for the points z outside Θ by a
    damped Newton iteration on the KKT system W(θ - z) + λ∇P(θ) = 0, P(θ) = 0 (λ >= 0),
    vectorised over the batch. It starts at the radial retraction of z (the last point of Θ on
    the segment from the interior point to z, found by bisection), the Hessian of P comes from
    central differences of ``grad_P``, the step is halved until the residual norm decreases,
    and the equations are scaled by max(1, ‖z - θ₀‖) so that far points (1e300) do not
    overflow. The result is retracted onto Θ the same way, so membership is exact whatever the
    accuracy. A :class:`~thetahat.errors.ConvergenceWarning` is issued if the iteration stops
    at the cap. Convexity of P is not checked; it is what makes the KKT point unique.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import ConvexSet
    >>> disk = ConvexSet(P=lambda t: np.sum(t**2, axis=-1) - 1.0, grad_P=lambda t: 2 * t,
    ...                  interior_point=[0.0, 0.0])
    >>> np.round(disk.nearest([3.0, 4.0]), 8).tolist()
    [0.6, 0.8]
    """

    P: Callable[[FloatArray], FloatArray]
    grad_P: Callable[[FloatArray], FloatArray]
    interior_point: FloatArray

    def __init__(self, P: Callable[[FloatArray], Any], grad_P: Callable[[FloatArray], Any],
                 interior_point: ArrayLike) -> None:
        if not (callable(P) and callable(grad_P)):
            raise ParameterSetError("ConvexSet: P and grad_P must be callables of theta with "
                                    "shape (..., p).")
        c = _vector("ConvexSet", "interior_point", interior_point)
        p = c.shape[0]
        object.__setattr__(self, "P", P)
        object.__setattr__(self, "grad_P", grad_P)
        object.__setattr__(self, "interior_point", readonly(c))
        Pc = self._P(c)
        if Pc.shape != () or not (np.isfinite(Pc) and Pc < 0):
            raise ParameterSetError(f"ConvexSet: P(interior_point) must be a finite scalar < 0; "
                                    f"got {Pc!r}. Choose a point strictly inside Θ.")
        self._check_gradient(np.random.default_rng(0), p)
        self._check_bounded(np.random.default_rng(1), p)

    def _P(self, theta: FloatArray) -> FloatArray:
        val = np.asarray(self.P(theta), dtype=np.float64)
        if val.shape != theta.shape[:-1]:
            raise ParameterSetError(f"ConvexSet: P must map shape (..., p) to (...); for input "
                                    f"{theta.shape} it returned {val.shape}.")
        return val

    def _grad(self, theta: FloatArray) -> FloatArray:
        val = np.asarray(self.grad_P(theta), dtype=np.float64)
        if val.shape != theta.shape:
            raise ParameterSetError(f"ConvexSet: grad_P must map shape (..., p) to (..., p); "
                                    f"for input {theta.shape} it returned {val.shape}.")
        return val

    def _check_gradient(self, rng: np.random.Generator, p: int) -> None:
        c = self.interior_point
        scale = max(1.0, float(np.max(np.abs(c))))
        pts = c + 0.1 * scale * rng.standard_normal((3, p))
        for pt in pts:
            g = self._grad(pt)
            fd = np.empty(p)
            for i in range(p):
                h = FD_STEP * max(1.0, abs(pt[i]))
                e = np.zeros(p)
                e[i] = h
                fd[i] = (self._P(pt + e) - self._P(pt - e)) / (2 * h)
            if not np.all(np.isfinite(g)) or (np.linalg.norm(g - fd)
                                               > FD_RTOL * max(1.0, float(np.linalg.norm(fd)))):
                raise ParameterSetError(f"ConvexSet: grad_P disagrees with finite differences "
                                        f"of P at {pt.tolist()}: grad_P={g.tolist()}, "
                                        f"estimate={fd.tolist()}. Check grad_P.")

    def _check_bounded(self, rng: np.random.Generator, p: int) -> None:
        c = self.interior_point
        R = UNBOUNDED_RADIUS * max(1.0, float(np.max(np.abs(c))))
        d = rng.standard_normal((2 * p + 2, p))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        d = np.concatenate([d, np.eye(p), -np.eye(p)])
        with np.errstate(all="ignore"):
            far = self._P(c + R * d)
        if np.any(far <= 0):
            raise ParameterSetError(f"ConvexSet: P is still <= 0 at distance {R:.0e} from the "
                                    f"interior point; Θ must be bounded (compact).")

    @property
    def dim(self) -> int:
        """p, the number of parameters."""
        return int(self.interior_point.shape[0])

    def contains(self, theta: ArrayLike, *, tol: float = 0.0) -> bool | NDArray[np.bool_]:
        """θ ∈ Θ, i.e. P(θ) <= 0 (dist(θ, Θ) <= tol when tol > 0); shape (...)."""
        th = _as_theta("theta", theta, self.dim)
        with np.errstate(all="ignore"):
            inside = np.asarray(self._P(th) <= 0)
        return self._contains_by_nearest(th, inside, tol)

    def nearest(self, theta: ArrayLike, *, metric: ArrayLike | None = None) -> FloatArray:
        """Projection onto Θ (Newton on the KKT conditions, see Notes); shape (..., p)."""
        th = _finite_theta("theta", theta, self.dim)
        p = self.dim
        flat = th.reshape(-1, p)
        out = flat.copy()
        with np.errstate(over="ignore", invalid="ignore"):
            outside = ~(self._P(flat) <= 0)
        if not np.any(outside):
            return th.copy()
        W = np.eye(p) if metric is None else np.asarray(metric, dtype=np.float64)
        if metric is not None:
            metric_factor(W, p)  # validates shape and definiteness
        W = 0.5 * (W + W.T) / np.max(np.diag(W))  # the projection ignores the metric's scale
        out[outside] = self._nearest_kkt(flat[outside], W)
        return out.reshape(th.shape)

    def _hessian(self, y: FloatArray) -> FloatArray:
        """Central-difference Hessian of P from grad_P, symmetrised; shape (N, p, p)."""
        p = y.shape[-1]
        h = FD_STEP * np.maximum(1.0, np.abs(y))  # (N, p)
        E = np.eye(p)[None, :, :] * h[:, :, None]  # row j = h_j e_j
        plus = self._grad(y[:, None, :] + E)
        minus = self._grad(y[:, None, :] - E)
        H = (plus - minus) / (2.0 * h[:, :, None])
        return 0.5 * (H + np.swapaxes(H, -1, -2))

    def _nearest_kkt(self, z: FloatArray, W: FloatArray) -> FloatArray:
        """Damped Newton on the KKT system of min ½‖θ - z‖²_W s.t. P(θ) = 0 (batch)."""
        c = self.interior_point
        N, p = z.shape
        y = retract(z, c, self._P)
        s = np.maximum(1.0, safe_norm(z - y))[:, None]  # residual scale; multiplier μ = λ/s
        zs = z / s
        g = self._grad(y)
        # multiplier as if ∇P were aligned with W(z - y): small values make the first steps huge
        mu = safe_norm((W @ (z - y).T).T / s) / safe_norm(g)

        def residual(y: FloatArray, mu: FloatArray) -> tuple[FloatArray, FloatArray]:
            gy = self._grad(y)
            r1 = (W @ y.T).T / s - (W @ zs.T).T + mu[:, None] * gy
            return r1, self._P(y)

        def merit(r1: FloatArray, r2: FloatArray) -> FloatArray:
            return safe_norm(r1) + np.abs(r2)

        done = np.zeros(N, dtype=bool)
        with np.errstate(all="ignore"):
            for _ in range(CONVEX_MAX_ITER):
                r1, r2 = residual(y, mu)
                m0 = merit(r1, r2)
                g = self._grad(y)
                K = np.zeros((N, p + 1, p + 1))
                K[:, :p, :p] = W / s[:, :, None] + mu[:, None, None] * self._hessian(y)
                K[:, :p, p] = g
                K[:, p, :p] = g
                rhs = -np.concatenate([r1, r2[:, None]], axis=-1)
                try:
                    step = np.linalg.solve(K, rhs[..., None])[..., 0]
                except np.linalg.LinAlgError:
                    break
                alpha = np.ones(N)
                for _ in range(30):  # backtracking on the residual norm
                    y_try = y + alpha[:, None] * step[:, :p]
                    mu_try = np.maximum(mu + alpha * step[:, p], 0.0)
                    worse = ~(merit(*residual(y_try, mu_try)) <= (1 - 1e-4 * alpha) * m0)
                    if not np.any(worse):
                        break
                    alpha = np.where(worse, 0.5 * alpha, alpha)
                dy = safe_norm(step[:, :p])  # the full Newton step: small only near KKT
                y = np.where(done[:, None], y, y_try)
                mu = np.where(done, mu, mu_try)
                done |= dy <= CONVEX_RTOL * (1.0 + safe_norm(y))
                # or the KKT residual (scaled to O(1) by s) is at rounding level: at flat
                # boundary points (zero curvature) Newton converges only linearly
                done |= merit(*residual(y, mu)) <= KKT_RTOL
                if np.all(done):
                    break
        if not np.all(done) or not np.all(np.isfinite(y)):
            warnings.warn(f"ConvexSet.nearest: the KKT iteration did not converge for "
                          f"{int(np.sum(~done))} point(s); returning points of Θ that may not be "
                          f"the nearest.", ConvergenceWarning, stacklevel=3)
            y = np.where(np.isfinite(y), y, c)
        y = retract(y, c, self._P)  # membership despite rounding
        # and a hair toward the interior point: P is convex with P(c) < 0, so the result has
        # P <= INWARD·P(c) < 0, a margin that survives P evaluated along another NumPy code
        # path (a single θ vs a batch rounds x**4 differently by an ulp: found by hypothesis,
        # a KKT point with P = 0 in the batch and P = 2.2e-16 alone)
        return c + (1.0 - INWARD) * (y - c)

    def constraint(self, theta: ArrayLike) -> FloatArray:
        """P(θ); shape (..., 1)."""
        th = _as_theta("theta", theta, self.dim)
        return self._P(th)[..., None]

    def constraint_grad(self, theta: ArrayLike) -> FloatArray:
        """∇P(θ); shape (..., 1, p)."""
        th = _as_theta("theta", theta, self.dim)
        return self._grad(th)[..., None, :]

    def __repr__(self) -> str:
        name = getattr(self.P, "__name__", type(self.P).__name__)
        return f"ConvexSet(P={name}, dim={self.dim}, interior_point={self.interior_point.tolist()})"
