"""The projection onto a ball or an ellipsoid in a covariance's norm, as a scalar kernel.

Π_Θ(z) = argmin over {(θ − c)ᵀQ(θ − c) ≤ 1} of (θ − z)ᵀM⁻¹(θ − z), M symmetric positive
(semi-)definite: the KKT conditions M⁻¹(θ − z) + λQ(θ − c) = 0 give (I + λ M Q)(θ − c) = z − c,
and g(λ) = (θ − c)ᵀQ(θ − c) decreases in λ ≥ 0; λ is bracketed by doubling and found by
bisection (no inverse of M is formed, so a singular M is fine). If M is so degenerate that no λ
reaches the boundary, the Euclidean projection (M = I) is used. The result is pulled radially
inside so that (θ − c)ᵀQ(θ − c) ≤ 1 − margin, so that membership holds however Θ's own test
rounds: :data:`ELLIPSOID_MARGIN` (far above rounding) for stage 2, :data:`OBSERVER_MARGIN` (a
few ulps) for the observer, whose run must stay within rounding of the NumPy path's. A box (``ell`` all zeros) is a clip.
:func:`project_into` allocates nothing (its scratch is an argument): the observer's kernel is
compiled without numba's reference counting; :func:`project_kernel` allocates it.

Written in numba's subset of Python, so that one definition serves every compiled kernel that
projects onto Θ: the paper observer's (emitted into its generated module by
:mod:`~thetahat.estimation.observer.kernel_source`, with M = Γ: the Γ⁻¹-weighted projection of
the update laws) and stage 2's EKF, MAP fit and guard
(:mod:`~thetahat.estimation.statistical.stage2_set`, with M a covariance). Θ is data: ``lo``,
``hi`` (p,) and ``ell`` (p + 1, p), row 0 the centre c and rows 1… Q (a ball is Q = I/R²).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ...model.paramset import Ball, Ellipsoid, ParameterSet

__all__ = ["BOX_QP_ITERATIONS", "DIAGONAL_ATOL", "ELLIPSOID_MARGIN", "LAMBDA_BISECTIONS",
           "LAMBDA_DOUBLINGS", "OBSERVER_MARGIN", "clip_kernel", "ellipsoid_data",
           "project_box_metric", "project_into", "project_kernel"]

FloatArray = NDArray[np.float64]

#: Projections onto an ellipsoid end at (θ − c)ᵀQ(θ − c) ≤ 1 − ELLIPSOID_MARGIN, i.e. a relative
#: 5e-13 of the semi-axes inside: far above rounding (1e-16), far below any statistical scale.
ELLIPSOID_MARGIN = 1e-12
#: Doublings of λ allowed while bracketing (2**400 covers any double-precision scale ratio).
LAMBDA_DOUBLINGS = 400
#: The paper observer's projections end at (θ − c)ᵀQ(θ − c) ≤ 1 − OBSERVER_MARGIN: 16 ulps of 1
#: (a relative 1.8e-15 of the semi-axes) inside, so that θ̂ stays in Θ however its test rounds,
#: and within rounding of the NumPy path's nearest point on ∂Θ (a larger margin, pushed back
#: at every projected step, would move the compiled run away from the NumPy one).
OBSERVER_MARGIN = 16 * 2.0 ** -52
#: Bisection steps on λ once bracketed within a factor 2 (2**-60: below double precision).
LAMBDA_BISECTIONS = 60
#: A metric whose off-diagonal entries are all within this of 0 projects onto a box by a clip:
#: the rule of :meth:`~thetahat.model.paramset.Box.nearest` (``np.allclose(W, diag(W))`` with
#: NumPy's default atol), kept so that the kernel and the NumPy path take the same branch.
DIAGONAL_ATOL = 1e-8
#: Working-set changes allowed in :func:`project_box_metric`: each frees or fixes one of p ≤ a
#: few coordinates, and the active-set method ends after at most a few p of them; the cap
#: only guards against cycling on a degenerate (rounding-level) multiplier.
BOX_QP_ITERATIONS = 100


def _eliminate(work: FloatArray, p: int, out: int) -> None:
    """Solve the augmented system in rows 0…p−1 of ``work`` (p × p matrix, right-hand side
    in column p) by Gaussian elimination with partial pivoting; the solution into row
    ``out``. The rows are overwritten."""
    for col in range(p):
        piv = col
        for i in range(col + 1, p):
            if abs(work[i, col]) > abs(work[piv, col]):
                piv = i
        if piv != col:
            for j in range(p + 1):
                tmp = work[col, j]
                work[col, j] = work[piv, j]
                work[piv, j] = tmp
        for i in range(col + 1, p):
            f = work[i, col] / work[col, col]
            for j in range(col, p + 1):
                work[i, j] -= f * work[col, j]
    for i in range(p - 1, -1, -1):
        acc = work[i, p]
        for j in range(i + 1, p):
            acc -= work[i, j] * work[out, j]
        work[out, i] = acc / work[i, i]


def _solve_shifted(M: FloatArray, euclid: bool, ell: FloatArray, lam: float,
                   work: FloatArray) -> float:
    """d = (I + λ M Q)⁻¹ d0 by Gaussian elimination with partial pivoting; returns dᵀQd.

    Q = ell[1:]; M is I when ``euclid``. ``work`` (p + 2, p + 1): rows 0…p−1 the augmented
    matrix, row p d0 (read), row p + 1 d (written).
    """
    p = ell.shape[1]
    for i in range(p):
        for j in range(p):
            acc = 0.0
            for k in range(p):
                m = (1.0 if i == k else 0.0) if euclid else M[i, k]
                acc += m * ell[1 + k, j]
            work[i, j] = lam * acc + (1.0 if i == j else 0.0)
        work[i, p] = work[p, i]
    _eliminate(work, p, p + 1)
    q = 0.0
    for i in range(p):
        for j in range(p):
            q += work[p + 1, i] * ell[1 + i, j] * work[p + 1, j]
    return q


def _ellipsoid_in_metric(theta: FloatArray, M: FloatArray, euclid: bool, ell: FloatArray,
                         target: float, work: FloatArray) -> bool:
    """θ ← c + d with d the M⁻¹-nearest point of {dᵀQd ≤ target}; False if M cannot reach it."""
    p = theta.shape[0]
    for i in range(p):
        work[p, i] = theta[i] - ell[0, i]
    # λ's scale: 1/mean eigenvalue of M Q (trace), so that the first λ is O(1) in effect
    tr = 0.0
    for i in range(p):
        for k in range(p):
            m = (1.0 if i == k else 0.0) if euclid else M[i, k]
            tr += m * ell[1 + k, i]
    lam_hi = p / tr if tr > 0.0 else 1.0
    lam_lo = 0.0
    found = False
    for _ in range(LAMBDA_DOUBLINGS):
        if _solve_shifted(M, euclid, ell, lam_hi, work) <= target:
            found = True
            break
        lam_lo = lam_hi
        lam_hi *= 2.0
    if not found:
        return False
    for _ in range(LAMBDA_BISECTIONS):
        mid = 0.5 * (lam_lo + lam_hi)
        if _solve_shifted(M, euclid, ell, mid, work) <= target:
            lam_hi = mid
        else:
            lam_lo = mid
    _solve_shifted(M, euclid, ell, lam_hi, work)         # the feasible end of the bracket
    for i in range(p):
        theta[i] = ell[0, i] + work[p + 1, i]
    return True


def _quadratic(theta: FloatArray, ell: FloatArray) -> float:
    """(θ − c)ᵀQ(θ − c)."""
    p = theta.shape[0]
    q = 0.0
    for i in range(p):
        for j in range(p):
            q += (theta[i] - ell[0, i]) * ell[1 + i, j] * (theta[j] - ell[0, j])
    return q


def project_into(theta: FloatArray, M: FloatArray, lo: FloatArray, hi: FloatArray,
                 ell: FloatArray, work: FloatArray, margin: float) -> None:
    """:func:`project_kernel` with its scratch and margin given: it allocates nothing.

    Parameters
    ----------
    theta, M, lo, hi, ell
        As for :func:`project_kernel`.
    work : ndarray, shape (p + 2, p + 1)
        Scratch.
    margin : float
        The result ends at (θ − c)ᵀQ(θ − c) ≤ 1 − margin (points there are left unchanged):
        :data:`ELLIPSOID_MARGIN`, or :data:`OBSERVER_MARGIN`.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Ellipsoid
    >>> th = np.array([0.0, 5.0])
    >>> project_into(th, np.eye(2), np.zeros(2), np.zeros(2),
    ...              ellipsoid_data(Ellipsoid([0.0, 0.0], np.diag([1.0, 0.25]))),
    ...              np.zeros((4, 3)), OBSERVER_MARGIN)
    >>> np.round(th, 9).tolist()
    [0.0, 2.0]
    """
    p = theta.shape[0]
    is_box = True
    for i in range(p):
        for j in range(p):
            if ell[1 + i, j] != 0.0:
                is_box = False
    if is_box:
        clip_kernel(theta, M, lo, hi, ell)
        return
    target = 1.0 - margin
    if _quadratic(theta, ell) <= target:
        return
    ok = False
    finite_m = True
    for i in range(p):
        for j in range(p):
            if not math.isfinite(M[i, j]):
                finite_m = False
    if finite_m:
        ok = _ellipsoid_in_metric(theta, M, False, ell, target, work)
    if not ok:
        _ellipsoid_in_metric(theta, M, True, ell, target, work)
    # rounding of c + d: pull radially inside until the test computed from θ holds
    for _ in range(60):
        q = _quadratic(theta, ell)
        if q <= target:
            return
        f = math.sqrt(target / q) * (1.0 - margin)
        for i in range(p):
            theta[i] = ell[0, i] + f * (theta[i] - ell[0, i])
    for i in range(p):
        theta[i] = ell[0, i]


def clip_kernel(theta: FloatArray, M: FloatArray, lo: FloatArray, hi: FloatArray,
                ell: FloatArray) -> None:
    """:func:`project_kernel` for a box Θ: clip θ to [lo, hi] in place (``M``, ``ell`` unread).

    The projection of every kernel onto a box. Stage 2's kernels for a box Θ are compiled with
    it instead of :func:`project_kernel`, whose ellipsoid branch is most of their first
    compilation's time and never runs for a box.

    Parameters
    ----------
    theta : ndarray, shape (p,)
    M : ndarray, shape (p, p)
        Not read (the signature of :func:`project_kernel`).
    lo, hi : ndarray, shape (p,)
    ell : ndarray, shape (p + 1, p)
        Not read.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.kernels.set_projection import clip_kernel
    >>> th = np.array([-2.0, 0.5, 9.0])
    >>> clip_kernel(th, np.eye(3), np.zeros(3), np.ones(3), np.zeros((4, 3)))
    >>> th.tolist()
    [0.0, 0.5, 1.0]
    """
    for i in range(theta.shape[0]):
        theta[i] = min(max(theta[i], lo[i]), hi[i])


def project_kernel(theta: FloatArray, M: FloatArray, lo: FloatArray, hi: FloatArray,
                   ell: FloatArray) -> None:
    """Project θ onto Θ in place, in the norm ‖·‖_{M⁻¹} (numba's subset; module docstring).

    Parameters
    ----------
    theta : ndarray, shape (p,)
        Overwritten with Π_Θ(θ); left unchanged when inside Θ.
    M : ndarray, shape (p, p)
        Symmetric positive semi-definite covariance defining the metric (I: Euclidean).
    lo, hi : ndarray, shape (p,)
        A box Θ (clip); for an ellipsoid its bounding box (not used).
    ell : ndarray, shape (p + 1, p)
        Row 0 the ellipsoid's centre c, rows 1… its Q; all zeros for a box.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Ball
    >>> from thetahat.estimation.kernels.set_projection import ellipsoid_data, project_kernel
    >>> ell = ellipsoid_data(Ball([0.0, 0.0], 1.0))
    >>> th = np.array([3.0, 4.0])
    >>> project_kernel(th, np.eye(2), -np.ones(2), np.ones(2), ell)
    >>> np.round(th, 9).tolist()
    [0.6, 0.8]
    """
    p = theta.shape[0]
    project_into(theta, M, lo, hi, ell, np.empty((p + 2, p + 1)), ELLIPSOID_MARGIN)


def ellipsoid_data(parameter_set: ParameterSet) -> FloatArray:
    """``ell`` (p + 1, p) of :func:`project_kernel`: centre and Q, or zeros for a box.

    Parameters
    ----------
    parameter_set : ParameterSet
        A Box, Ball or Ellipsoid (a ConvexSet gives zeros: it is projected in Python).

    Returns
    -------
    ndarray, shape (p + 1, p)

    Examples
    --------
    >>> from thetahat.model.paramset import Ball
    >>> ellipsoid_data(Ball([1.0], 2.0)).tolist()
    [[1.0], [0.25]]
    """
    p = parameter_set.dim
    ell = np.zeros((p + 1, p))
    if isinstance(parameter_set, Ball):
        ell[0] = parameter_set.center
        ell[1:] = np.eye(p) / parameter_set.radius ** 2
    elif isinstance(parameter_set, Ellipsoid):
        ell[0] = parameter_set.center
        ell[1:] = parameter_set.shape
    return ell


def _box_qp_solve(W: FloatArray, work: FloatArray) -> None:
    """The minimiser y over the free coordinates, the held ones at x, into ``work[p + 3]``.

    ``work`` rows 0…p−1: the augmented system (built here, then eliminated with partial
    pivoting); row p the iterate x, row p + 1 the target c, row p + 2 the flags (0 free,
    −1/+1 held at the lower/upper bound), row p + 3 y (:func:`project_box_metric`).
    """
    p = W.shape[0]
    for i in range(p):
        if work[p + 2, i] != 0.0:
            for j in range(p):
                work[i, j] = 1.0 if i == j else 0.0
            work[i, p] = work[p, i]
        else:
            acc = 0.0
            for j in range(p):
                acc += W[i, j] * work[p + 1, j]
            for j in range(p):
                if work[p + 2, j] != 0.0:
                    acc -= W[i, j] * work[p, j]
                    work[i, j] = 0.0
                else:
                    work[i, j] = W[i, j]
            work[i, p] = acc
    _eliminate(work, p, p + 3)


def project_box_metric(theta: FloatArray, W: FloatArray, lo: FloatArray, hi: FloatArray,
                       work: FloatArray) -> None:
    """θ ← argmin over lo ≤ θ' ≤ hi of (θ' − θ)ᵀW(θ' − θ), in place (W symmetric positive
    definite); θ inside the box is left as it is.

    The projection of :meth:`~thetahat.model.paramset.Box.nearest` with a metric, for the
    compiled filtered least-squares law (W = R⁺, the information): a clip when W is diagonal
    (:data:`DIAGONAL_ATOL`), else the primal active-set method of quadratic programming from
    the clipped point: solve for the free coordinates with the others held at their bounds;
    step to the first bound crossed and hold it, or, at the free minimiser, free the held
    coordinate whose multiplier has the wrong sign (the most wrong), until none has. The
    minimiser is unique and the method ends at it exactly (to rounding), as SciPy's bounded
    least squares (``bvls``) of the NumPy path does. Allocates nothing.

    Parameters
    ----------
    theta : ndarray, shape (p,)
    W : ndarray, shape (p, p)
    lo, hi : ndarray, shape (p,)
    work : ndarray, shape (p + 4, p + 1)
        Scratch.

    Examples
    --------
    >>> import numpy as np
    >>> th = np.array([2.0, 0.0])        # W couples the coordinates: not the clip (1, 0)
    >>> project_box_metric(th, np.array([[1.0, 0.9], [0.9, 1.0]]), -np.ones(2), np.ones(2),
    ...                    np.zeros((6, 3)))
    >>> np.round(th, 12).tolist()
    [1.0, 0.9]
    """
    p = theta.shape[0]
    inside = True
    diagonal = True
    for i in range(p):
        if not (lo[i] <= theta[i] <= hi[i]):
            inside = False
        for j in range(p):
            if i != j and abs(W[i, j]) > DIAGONAL_ATOL:
                diagonal = False
    if inside:
        return
    x, c, flag = p, p + 1, p + 2
    for i in range(p):
        work[c, i] = theta[i]
        work[x, i] = min(max(theta[i], lo[i]), hi[i])
        work[flag, i] = -1.0 if theta[i] < lo[i] else (1.0 if theta[i] > hi[i] else 0.0)
        theta[i] = work[x, i]
    if diagonal:
        return
    for _ in range(BOX_QP_ITERATIONS):
        _box_qp_solve(W, work)
        alpha = 1.0
        block = -1
        for i in range(p):
            if work[flag, i] == 0.0:
                yi, xi = work[p + 3, i], work[x, i]
                if yi < lo[i] and (lo[i] - xi) / (yi - xi) < alpha:
                    alpha, block = (lo[i] - xi) / (yi - xi), i
                elif yi > hi[i] and (hi[i] - xi) / (yi - xi) < alpha:
                    alpha, block = (hi[i] - xi) / (yi - xi), i
        if block >= 0:                       # step to the first bound crossed, hold it
            for i in range(p):
                if work[flag, i] == 0.0:
                    work[x, i] += alpha * (work[p + 3, i] - work[x, i])
            below = work[p + 3, block] < lo[block]
            work[x, block] = lo[block] if below else hi[block]
            work[flag, block] = -1.0 if below else 1.0
            continue
        for i in range(p):
            if work[flag, i] == 0.0:
                work[x, i] = work[p + 3, i]
        worst, free = 0.0, -1                # multipliers: W (x − c) at the held coordinates
        for i in range(p):
            if work[flag, i] != 0.0:
                grad = 0.0
                for j in range(p):
                    grad += W[i, j] * (work[x, j] - work[c, j])
                wrong = -grad if work[flag, i] < 0.0 else grad
                if wrong > worst:
                    worst, free = wrong, i
        if free < 0:
            break
        work[flag, free] = 0.0
    for i in range(p):
        theta[i] = min(max(work[x, i], lo[i]), hi[i])
