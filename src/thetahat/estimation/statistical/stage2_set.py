"""Θ for stage 2: any convex parameter set, projected inside the compiled EKF, guard and MAP fit.

Stage 2 (the EKF on col(x, θ), the MAP fits, the guard) keeps θ̂ in Θ by a projection after
each update. What it needs from Θ, for every :class:`~thetahat.model.paramset.ParameterSet`:

* **the bounding box** [lo, hi] (:func:`theta_bounds`): Θ's extent per component, which
  sets the prior on θ (centre ± |Θ|/4), the guard's widest band and the trust report's
  "band was Θ's full width". It is Θ itself for a :class:`~thetahat.model.paramset.Box`;
  c ± R for a ball; c ± √diag(Q⁻¹) for an ellipsoid; the support function in ±e_i for a
  :class:`~thetahat.model.paramset.ConvexSet` (found once per set by SLSQP).
* **the projection** Π_Θ(z) in the norm ‖·‖_{M⁻¹}, M a covariance (:func:`project_kernel`,
  :func:`project_theta`). The EKF and the MAP fit pass their covariance of θ (P_θθ, the
  Gauss–Newton inverse information): the projection is then the constrained estimate of
  Simon & Chia (2002), the most likely point of Θ under the Gaussian approximation. The guard
  passes M = I (Euclidean), the norm in which Π_Θ is non-expansive for its bound
  ‖θ̂ − θ‖ ≤ ‖θ̂_G − θ‖ + ‖δ‖.

  - A **box** keeps its componentwise clip whatever M (the Euclidean projection; it is the
    M⁻¹-weighted one whenever M is diagonal — the M⁻¹-weighted projection onto a box is a
    quadratic programme with no closed form).
  - A **ball or ellipsoid** {(θ − c)ᵀQ(θ − c) ≤ 1} (a ball is Q = I/R²): the KKT conditions
    M⁻¹(θ − z) + λQ(θ − c) = 0 give (I + λ M Q)(θ − c) = z − c, and g(λ) = (θ−c)ᵀQ(θ−c)
    decreases in λ ≥ 0; λ is bracketed by doubling and found by bisection (no inverse of M is
    formed, so a singular M is fine). If M is so degenerate that no λ reaches the boundary
    (g's limit above 1), the Euclidean projection (M = I) is used. The result is pulled
    radially inside so that (θ − c)ᵀQ(θ − c) ≤ 1 − :data:`ELLIPSOID_MARGIN`, a margin far
    above rounding so that membership holds however Θ's own test rounds. This is written in
    numba's subset of Python and compiled with the EKF kernels.
  - A **ConvexSet** has no compiled projection (its P is a Python callable): stage 2 then
    runs the kernels uncompiled and projects with
    :meth:`~thetahat.model.paramset.ConvexSet.nearest` in the metric M⁻¹. Asking for
    ``compiled=True`` with a ConvexSet raises :class:`~thetahat.errors.UnsupportedError`.

The compiled kernels read Θ as data, ``lo, hi`` (p,) and ``ell`` (p + 1, p) (row 0 the
centre c, rows 1… Q; all zeros for a box): one compiled kernel serves boxes, balls and
ellipsoids of any size.

What it may import: :mod:`thetahat.model` (Θ), the package's errors and the projection
kernels of :mod:`~thetahat.estimation.kernels.set_projection`; nothing of this room.

References
----------
D. Simon and T. L. Chia, "Kalman filtering with state equality constraints", IEEE Trans.
Aerospace and Electronic Systems 38(1), 2002; D. Simon, "Kalman filtering with state
constraints: a survey", IET Control Theory & Applications 4(8), 2010.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import scipy.optimize
from numpy.typing import NDArray

from ...errors import ParameterSetError
from ...model.paramset import Ball, Box, ConvexSet, Ellipsoid, ParameterSet
from ..kernels.set_projection import ELLIPSOID_MARGIN, clip_kernel, ellipsoid_data, project_kernel

__all__ = ["ELLIPSOID_MARGIN", "BOUNDARY_RTOL", "theta_bounds", "ellipsoid_data",
           "clip_kernel", "project_kernel", "project_theta", "on_boundary", "has_compiled_projection",
           "StageTwoSet", "stage2_set"]

FloatArray = NDArray[np.float64]

#: θ̂ counts as on Θ's boundary within this fraction of Θ's width per component (box) or of
#: the constraint's range (P ≥ −BOUNDARY_RTOL for the normalised P of balls, ellipsoids).
BOUNDARY_RTOL = 1e-3


def _support(parameter_set: ConvexSet, e: FloatArray) -> float:
    """max eᵀθ over Θ (SLSQP from the interior point), the boundary point retracted into Θ."""
    c = np.asarray(parameter_set.interior_point, dtype=np.float64)
    scale = max(1.0, float(np.max(np.abs(c))))
    cons = {"type": "ineq", "fun": lambda th: -float(parameter_set.P(th)),
            "jac": lambda th: -np.asarray(parameter_set.grad_P(th), dtype=np.float64)}
    sol = scipy.optimize.minimize(lambda th: -float(e @ th) / scale, c,
                                  jac=lambda th: -e / scale, constraints=[cons],
                                  method="SLSQP", options={"ftol": 1e-12, "maxiter": 500})
    # the optimum lies on ∂Θ; push a hair outward along e so the box contains Θ for sure
    far = c + 4.0 * (np.asarray(sol.x) - c)
    edge = parameter_set.nearest(far) if bool(np.isfinite(far).all()) else sol.x
    return float(e @ np.asarray(edge)) + 1e-9 * scale


def theta_bounds(parameter_set: ParameterSet) -> tuple[FloatArray, FloatArray]:
    """The bounding box [lo, hi] of Θ (Θ itself for a Box; see the module docstring).

    Parameters
    ----------
    parameter_set : ParameterSet

    Returns
    -------
    lo, hi : ndarray, shape (p,)

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Ellipsoid
    >>> lo, hi = theta_bounds(Ellipsoid([0.0, 1.0], np.diag([1.0, 0.25])))
    >>> lo.tolist(), hi.tolist()
    ([-1.0, -1.0], [1.0, 3.0])
    """
    return stage2_set(parameter_set).bounds()


@dataclass(frozen=True, slots=True, eq=False)
class StageTwoSet:
    """Θ as stage 2's kernels read it (built once per set by :func:`stage2_set`).

    Attributes
    ----------
    parameter_set : ParameterSet
    lo, hi : ndarray, shape (p,)
        The bounding box.
    ell : ndarray, shape (p + 1, p)
        The ellipsoid's centre and Q (zeros for a box and a ConvexSet).
    compiled_projection : bool
        False for a ConvexSet: projected by :meth:`project` in Python.
    """

    parameter_set: ParameterSet
    lo: FloatArray
    hi: FloatArray
    ell: FloatArray
    compiled_projection: bool

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        """Copies of (lo, hi)."""
        return self.lo.copy(), self.hi.copy()

    def project(self, theta: FloatArray, M: FloatArray) -> None:
        """Π_Θ in the norm ‖·‖_{M⁻¹}, in place (the Python path of a ConvexSet too)."""
        if self.compiled_projection:
            project_kernel(theta, M, self.lo, self.hi, self.ell)
            return
        ps = self.parameter_set
        if bool(ps.contains(theta)):
            return
        metric = None
        if np.all(np.isfinite(M)):
            try:
                metric = np.linalg.inv(0.5 * (M + M.T))
                np.linalg.cholesky(metric)
            except np.linalg.LinAlgError:
                metric = None            # a singular covariance: the Euclidean projection
        theta[:] = ps.nearest(theta, metric=metric)

    def __repr__(self) -> str:
        return (f"StageTwoSet({self.parameter_set!r}, compiled_projection="
                f"{self.compiled_projection})")


@functools.lru_cache(maxsize=64)
def stage2_set(parameter_set: ParameterSet) -> StageTwoSet:
    """Stage 2's view of Θ: bounding box, ellipsoid data, projection path (cached per set).

    Parameters
    ----------
    parameter_set : ParameterSet
        A Box, Ball, Ellipsoid or ConvexSet.

    Returns
    -------
    StageTwoSet

    Raises
    ------
    ParameterSetError
        Not a thetahat ParameterSet.

    Examples
    --------
    >>> from thetahat.model.paramset import Ball
    >>> st = stage2_set(Ball([0.0, 0.0], 2.0))
    >>> st.lo.tolist(), st.hi.tolist(), st.compiled_projection
    ([-2.0, -2.0], [2.0, 2.0], True)
    """
    ps = parameter_set
    if not isinstance(ps, ParameterSet):
        raise ParameterSetError(f"Θ must be a thetahat ParameterSet (Box, Ball, Ellipsoid, "
                                f"ConvexSet); got {type(ps).__name__}.")
    p = ps.dim
    if isinstance(ps, Box):
        lo, hi = np.array(ps.lower, dtype=np.float64), np.array(ps.upper, dtype=np.float64)
    elif isinstance(ps, Ball):
        lo, hi = ps.center - ps.radius, ps.center + ps.radius
    elif isinstance(ps, Ellipsoid):
        half = np.sqrt(np.diag(np.linalg.inv(ps.shape)))
        lo, hi = ps.center - half, ps.center + half
    elif isinstance(ps, ConvexSet):
        eye = np.eye(p)
        hi = np.array([_support(ps, eye[i]) for i in range(p)])
        lo = np.array([-_support(ps, -eye[i]) for i in range(p)])
    else:
        raise ParameterSetError(f"stage 2 knows Box, Ball, Ellipsoid and ConvexSet; got "
                                f"{type(ps).__name__}.")
    lo, hi = np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)
    lo.setflags(write=False)
    hi.setflags(write=False)
    ell = ellipsoid_data(ps)
    ell.setflags(write=False)
    return StageTwoSet(parameter_set=ps, lo=lo, hi=hi, ell=ell,
                       compiled_projection=not isinstance(ps, ConvexSet))


def has_compiled_projection(parameter_set: ParameterSet) -> bool:
    """Whether stage 2's compiled kernels project onto this Θ (all but a ConvexSet).

    Parameters
    ----------
    parameter_set : ParameterSet

    Returns
    -------
    bool

    Examples
    --------
    >>> from thetahat.model.paramset import Box
    >>> has_compiled_projection(Box([0.0], [1.0]))
    True
    """
    return not isinstance(parameter_set, ConvexSet)


def project_theta(parameter_set: ParameterSet, theta: Any,
                  cov: FloatArray | None = None) -> FloatArray:
    """Π_Θ(θ) in the norm ‖·‖_{cov⁻¹} (Euclidean when ``cov`` is None); a new array.

    Parameters
    ----------
    parameter_set : ParameterSet
    theta : array_like, shape (p,)
        Finite.
    cov : ndarray, shape (p, p), optional
        The covariance of θ whose inverse weighs the distance (module docstring).

    Returns
    -------
    ndarray, shape (p,)
        A point of Θ; θ itself when inside.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Ellipsoid
    >>> ell = Ellipsoid([0.0, 0.0], np.diag([1.0, 1.0]))
    >>> th = project_theta(ell, [0.0, 2.0], cov=np.diag([1.0, 1e-6]))
    >>> bool(ell.contains(th)), bool(abs(th[1] - 2.0) > abs(th[0]))  # moves along θ₁ mostly
    (True, True)
    """
    th = np.array(theta, dtype=np.float64).reshape(-1)
    M = np.eye(th.shape[0]) if cov is None else np.asarray(cov, dtype=np.float64)
    stage2_set(parameter_set).project(th, M)
    return th


def on_boundary(parameter_set: ParameterSet, theta: Any) -> NDArray[np.bool_]:
    """Per component: does θ̂ sit on Θ's boundary (Θ, not the data, decided it)?

    For a box, component i is on the boundary within :data:`BOUNDARY_RTOL` of its width of a
    face. For a ball, ellipsoid or ConvexSet the boundary is one surface: every component is
    flagged when θ̂ lies within :data:`BOUNDARY_RTOL` of it, measured by the normalised
    constraint (P ≥ −2·BOUNDARY_RTOL for balls and ellipsoids, which is a relative distance of
    BOUNDARY_RTOL along the ray from the centre) — and only the components along which the
    boundary's normal points, |∇P_i|·width_i ≥ BOUNDARY_RTOL·max_j(|∇P_j|·width_j), so a
    parameter the boundary does not constrain there is not named.

    Parameters
    ----------
    parameter_set : ParameterSet
    theta : array_like, shape (p,)

    Returns
    -------
    ndarray of bool, shape (p,)

    Examples
    --------
    >>> from thetahat.model.paramset import Ball
    >>> on_boundary(Ball([0.0, 0.0], 1.0), [0.0, 1.0]).tolist()
    [False, True]
    """
    th = np.asarray(theta, dtype=np.float64).reshape(-1)
    st = stage2_set(parameter_set)
    width = st.hi - st.lo
    if isinstance(parameter_set, Box):
        return np.asarray((th - st.lo <= BOUNDARY_RTOL * width)
                          | (st.hi - th <= BOUNDARY_RTOL * width))
    ps = parameter_set
    with np.errstate(all="ignore"):
        P = float(np.max(ps.constraint(th)))
        grad = np.asarray(ps.constraint_grad(th), dtype=np.float64)[0]
    if isinstance(ps, ConvexSet):
        # P of a ConvexSet is not normalised: compare with its depth at the interior point
        depth = -float(ps.constraint(ps.interior_point)[0])
        near = P >= -2.0 * BOUNDARY_RTOL * depth
    else:
        near = P >= -2.0 * BOUNDARY_RTOL
    if not near or not np.all(np.isfinite(grad)):
        return np.zeros(th.shape[0], dtype=bool)
    reach = np.abs(grad) * width
    return np.asarray(reach >= BOUNDARY_RTOL * float(np.max(reach)))
