"""Invariant zeros, normal rank, left-invertibility and the minimum-phase test.

The paper (Assumption 1, Lemma 1 and its proof in the Appendix) defines the invariant zeros of a
triple (C, A, E) through the Rosenbrock system matrix

$$
P(s) = \\begin{bmatrix} sI - A & -B \\\\ C & D \\end{bmatrix},
$$

as the values of ``s`` where ``P(s)`` loses rank below its *normal rank* (its rank for almost
every ``s``). Input and output decoupling zeros (uncontrollable or unobservable modes) are
therefore zeros too, which a transfer-function method would miss. The triple is left-invertible
when the normal rank is ``n + m``, and minimum-phase when every invariant zero lies in the open
left half-plane.

The zeros are computed with the orthogonal staircase reduction of Emami-Naeini and Van Dooren
(1982): every step is an SVD-based compression, and every rank decision is taken relative to the
norm of the *normalised* data (see :func:`invariant_zeros`, Notes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from .._validate import as_matrix, as_triple, check_finite, positive_scalar
from ..errors import DimensionError

__all__ = [
    "invariant_zeros",
    "normal_rank",
    "is_left_invertible",
    "unstable_zeros",
    "is_minimum_phase",
    "MINIMUM_PHASE_RTOL",
]

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

_EPS = float(np.finfo(np.float64).eps)

#: Default relative margin of :func:`unstable_zeros`: a zero counts as *not* minimum-phase when
#: ``Re z >= -MINIMUM_PHASE_RTOL * scale``. A simple zero is computed to about ``eps * scale``
#: and a double zero only to about ``sqrt(eps) * scale ~ 1.5e-8 * scale``; the margin must exceed
#: both, so that a (double) zero at the origin computed as ``-1e-17`` or ``-1e-8`` is still
#: reported. A zero this close to the imaginary axis leaves no usable stability margin for the
#: observer anyway (A_a in the SCB (5)/(6) must be Hurwitz), so erring on the unstable side is safe.
MINIMUM_PHASE_RTOL = 1e-6


# --------------------------------------------------------------------------------------------
# Validation and normalisation
# --------------------------------------------------------------------------------------------

def _as_system(A: Any, B: Any, C: Any, D: Any) -> tuple[FloatArray, FloatArray, FloatArray,
                                                         FloatArray]:
    """Validate (A, B, C, D); ``D=None`` means the zero matrix of shape (r, m)."""
    A_, B_, C_ = as_triple(A, B, C)
    r, m = C_.shape[0], B_.shape[1]
    if D is None:
        D_ = np.zeros((r, m))
    else:
        D_ = as_matrix("D", D, (r, m))
    return A_, B_, C_, D_


def _default_tol(n: int, m: int, r: int) -> float:
    """Default relative rank tolerance, ``(n + r) * (n + m) * eps``.

    This is the SLICOT AB08ND default: every compression is a product of at most
    ``max(n + r, n + m)`` orthogonal transformations of the normalised system matrix, each of
    which adds a rounding error of a few ``eps`` times its norm.
    """
    return max(1, (n + r) * (n + m)) * _EPS


def _resolve_tol(tol: float | None, n: int, m: int, r: int) -> float:
    if tol is None:
        return _default_tol(n, m, r)
    return positive_scalar("tol", tol)


def _norm2(M: FloatArray) -> float:
    return float(np.linalg.norm(M, 2)) if M.size else 0.0


@dataclass(frozen=True, slots=True)
class _Normalised:
    """A system rescaled so that its zeros are ``freq_scale`` times the zeros of (A, B, C, D).

    ``A/a``, ``B/||B||``, ``C/||C||`` and ``D a / (||B|| ||C||)`` with ``a = ||A||``: dividing the
    state rows of ``P(s)`` by ``a`` maps the zero ``z`` to ``z / a``; scaling inputs and outputs
    by scalars leaves the zeros unchanged. ``threshold`` is the absolute singular-value
    threshold used for every rank decision in the reduction.
    """

    A: FloatArray
    B: FloatArray
    C: FloatArray
    D: FloatArray
    freq_scale: float
    threshold: float


def _normalise(A: FloatArray, B: FloatArray, C: FloatArray, D: FloatArray,
               tol: float) -> _Normalised:
    a = _norm2(A) or 1.0
    b = _norm2(B) or 1.0
    c = _norm2(C) or 1.0
    A_n, B_n, C_n, D_n = A / a, B / b, C / c, D * (a / (b * c))
    system = np.block([[A_n, B_n], [C_n, D_n]])
    threshold = tol * max(_norm2(system), 1.0)
    return _Normalised(A_n, B_n, C_n, D_n, a, threshold)


# --------------------------------------------------------------------------------------------
# SVD compressions
# --------------------------------------------------------------------------------------------

def _row_compression(M: FloatArray, threshold: float
                     ) -> tuple[int, FloatArray, FloatArray]:
    """Numerical rank ``rho`` of ``M`` (k, l), an orthogonal ``U`` (k, k) and the singular values.

    ``U.T @ M`` has its ``rho`` independent rows *first* and (numerically) zero rows after.
    """
    k, l = M.shape
    if k == 0 or l == 0:
        return 0, np.eye(k), np.zeros(0)
    U, s, _ = np.linalg.svd(M, full_matrices=True)
    return int(np.count_nonzero(s > threshold)), U, s


def _column_compression(M: FloatArray, threshold: float) -> tuple[int, FloatArray]:
    """Numerical rank ``rho`` of ``M`` (k, l) and an orthogonal ``V`` (l, l).

    ``M @ V`` has its (numerically) zero columns *first* and ``rho`` independent columns last.
    """
    k, l = M.shape
    if k == 0 or l == 0:
        return 0, np.eye(l)
    _, s, Vt = np.linalg.svd(M, full_matrices=True)
    rho = int(np.count_nonzero(s > threshold))
    V = Vt.T
    return rho, np.hstack([V[:, rho:], V[:, :rho]])


def _split_rows_of_d(D: FloatArray, noise: FloatArray, threshold: float
                     ) -> tuple[int, FloatArray, FloatArray]:
    """Orthogonal split of the output rows into those facing zero rows of D and the rest.

    The rank of ``D`` (p, m) is decided on the rows weighted by ``threshold / noise`` (each row
    has its own rounding level ``noise``, see :func:`_created_row_noise`). Returns ``rho`` and
    an orthogonal ``Q = [Q0, Q1]`` (p, p): ``Q0.T @ D`` (p - rho rows) is zero within the noise
    and is discarded, ``Q1.T @ D`` has full row rank ``rho``.
    """
    p = D.shape[0]
    rho, U, _ = _row_compression((threshold / noise)[:, None] * D, threshold)
    if rho == p:
        return rho, np.eye(p), np.eye(p)
    # left null vectors y of the weighted D give left null vectors (threshold / noise) * y of D
    Z = (threshold / noise)[:, None] * U[:, rho:]
    Q, _ = np.linalg.qr(Z, mode="complete")
    return rho, Q, Q[:, p - rho:]


def _created_row_noise(threshold: float, pivot: float, norm_b: float) -> float:
    """Rounding level of the D rows ``B2`` created by eliminating the states ``x2``.

    ``x2`` spans the row space of ``Ĉ1``, whose rows are rows of the Rosenbrock matrix known to
    within ``threshold``; a backward perturbation of that size turns the subspace by up to
    ``threshold / pivot`` (Wedin's theorem; ``pivot`` = smallest retained singular value of
    ``Ĉ1``), which moves ``B2 = V2.T B`` by ``norm_b * threshold / pivot``. Treating such
    ``B2`` as zero is therefore a backward-stable decision; without this allowance a structurally
    zero Markov parameter (``C A B = 0`` computed as 1e-14 after a rotation) shows up as a
    spurious zero near ``1 / 1e-14``. The C part of the new rows is *not* given this allowance,
    so genuine (small) rows are never dropped.
    """
    return threshold * (1.0 + norm_b / pivot)


# --------------------------------------------------------------------------------------------
# The staircase reduction
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class _Reduced:
    """Result of the reduction: a system with the same finite zeros and a square invertible D.

    ``removed_rank`` is the rank that the eliminated rows and columns carried, so that
    ``normal rank P = removed_rank + n + m`` for the reduced (A, B, C, D).
    """

    A: FloatArray
    B: FloatArray
    C: FloatArray
    D: FloatArray
    removed_rank: int


def _reduce_to_full_row_rank_d(A: FloatArray, B: FloatArray, C: FloatArray, D: FloatArray,
                               threshold: float
                               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, int]:
    """One pass of Emami-Naeini & Van Dooren's reduction: make D of full row rank.

    Split the outputs orthogonally so that D becomes ``[0; D2]``; the rows ``C1`` facing the
    zero rows of D are row-compressed to ``Ĉ1`` (sigma independent rows; the zero rows of P are
    dropped), and a state rotation ``V`` makes ``Ĉ1 V = [0, Ĉ12]`` with ``Ĉ12`` invertible
    (sigma, sigma). The rows of ``Ĉ1`` and the states ``x2`` then carry rank exactly sigma and
    can be removed: (A11, B1, [A21; C21], [B2; D2]) has the same finite zeros, and its normal
    rank is lower by sigma. Each step removes sigma >= 1 states or drops rows, so the loop ends.
    """
    removed = 0
    noise = np.full(C.shape[0], threshold)
    while True:
        p = C.shape[0]
        rho, Q, Q1 = _split_rows_of_d(D, noise, threshold)
        if rho == p:
            return A, B, C, D, removed
        Q0 = Q[:, : p - rho]
        C1, C2, D2 = Q0.T @ C, Q1.T @ C, Q1.T @ D
        noise_2 = np.sqrt((Q1**2).T @ noise**2)
        sigma, W, s = _row_compression(C1, threshold)
        if sigma == 0:  # the rows Q0.T [C D] are zero rows of P: drop them
            C, D, noise = C2, D2, noise_2
            continue
        _, V = _column_compression(W[:, :sigma].T @ C1, threshold)
        n1 = A.shape[0] - sigma
        new_noise = _created_row_noise(threshold, float(s[sigma - 1]), _norm2(B))
        A_t, B_t, C2_t = V.T @ A @ V, V.T @ B, C2 @ V
        A, B = A_t[:n1, :n1], B_t[:n1]
        C = np.vstack([A_t[n1:, :n1], C2_t[:, :n1]])
        D = np.vstack([B_t[n1:], D2])
        noise = np.concatenate([np.full(sigma, new_noise), noise_2])
        removed += sigma


def _reduce(A: FloatArray, B: FloatArray, C: FloatArray, D: FloatArray,
            threshold: float) -> _Reduced:
    """Alternate the reduction on the system and on its dual until D is square and invertible.

    In exact arithmetic one pass on each suffices (Emami-Naeini & Van Dooren); looping
    makes the result consistent even when rounding moves a rank decision between the passes.
    Each pass either removes states or rows/columns, or changes nothing; when neither pass
    changes anything, D has full row and full column rank, hence is square.
    """
    removed = 0
    while True:
        A, B, C, D, k1 = _reduce_to_full_row_rank_d(A, B, C, D, threshold)
        At, Ct, Bt, Dt, k2 = _reduce_to_full_row_rank_d(A.T, C.T, B.T, D.T, threshold)
        A, B, C, D = At.T, Bt.T, Ct.T, Dt.T
        removed += k1 + k2
        if D.shape[0] == D.shape[1]:
            return _Reduced(A, B, C, D, removed)


def _finite_eigenvalues(Af: FloatArray, Bf: FloatArray, tol: float,
                        threshold: float) -> ComplexArray:
    """Finite generalised eigenvalues of the pencil ``Af - s Bf``.

    A pair ``(alpha, beta)`` is infinite when ``|beta| <= tol * |alpha|``: then ``|s|`` exceeds
    ``1 / tol`` in normalised units, beyond what the rank decisions can resolve. A pair with
    both ``|alpha|`` and ``|beta|`` below the rank threshold is indeterminate (a singular
    remainder) and is not a zero.
    """
    if Af.shape[0] == 0:
        return np.zeros(0, dtype=complex)
    w = scipy.linalg.eig(Af, Bf, left=False, right=False, homogeneous_eigvals=True)
    alpha, beta = np.asarray(w[0]), np.asarray(w[1])
    determinate = np.hypot(np.abs(alpha), np.abs(beta)) > threshold
    finite = determinate & (np.abs(beta) > tol * np.abs(alpha))
    return np.asarray(alpha[finite] / beta[finite], dtype=complex)


def _zero_pencil(red: _Reduced, threshold: float) -> tuple[FloatArray, FloatArray]:
    """Column-compress ``[C D]`` of the reduced system: ``[C D] W = [0, D̄]``.

    The first ``n`` columns ``N`` of ``W`` span the kernel of ``[C D]``; the zeros are the
    generalised eigenvalues of ``[A B] N - s [I 0] N`` (an (n, n) pencil).
    """
    n = red.A.shape[0]
    CD = np.hstack([red.C, red.D])
    _, W = _column_compression(CD, threshold)
    N = W[:, :n]
    Af = np.hstack([red.A, red.B]) @ N
    Bf = N[:n, :]
    return Af, Bf


def _sorted(z: ComplexArray) -> ComplexArray:
    order = np.lexsort((z.imag, z.real))
    return np.asarray(z[order], dtype=complex)


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------

def invariant_zeros(A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike | None = None, *,
                    tol: float | None = None) -> ComplexArray:
    """Invariant zeros of (A, B, C, D): where the Rosenbrock matrix drops below its normal rank.

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, m)
    C : array_like, shape (r, n)
    D : array_like, shape (r, m), optional
        Feedthrough; ``None`` (default) means zero, as for the triple (C, A, E) of the paper.
    tol : float, optional
        Relative tolerance of the rank decisions: a singular value counts as zero when it is at
        most ``tol`` times the norm of the normalised system matrix (see Notes). Default
        ``(n + r) * (n + m) * eps`` (the SLICOT AB08ND default). The same ``tol`` separates
        infinite from finite eigenvalues of the final pencil.

    Returns
    -------
    zeros : ndarray of complex, shape (n_z,)
        The finite invariant zeros with multiplicity, sorted by real part, then imaginary part.
        Input and output decoupling zeros (uncontrollable or unobservable modes) are included.

    Raises
    ------
    DimensionError
        A matrix has the wrong shape, or ``tol`` is not positive.
    NonFiniteError
        A matrix holds NaN or inf.

    Notes
    -----
    The zeros are the values ``s`` where the Rosenbrock system matrix

    $$
    P(s) = \\begin{bmatrix} sI - A & -B \\\\ C & D \\end{bmatrix}
    $$

    has rank below its normal rank, as in the proof of Lemma 1. They are computed with the
    staircase algorithm of Emami-Naeini & Van Dooren: SVD row compressions of D, column
    compressions of the rows of C that face zero rows of D, and elimination of the states they
    determine, first on the system, then on its dual, until D is square and invertible; the zeros
    are then the generalised eigenvalues of the pencil obtained by column-compressing [C D].

    Rank decisions use the normalised system ``(A/a, B/||B||, C/||C||, D a/(||B|| ||C||))`` with
    ``a = ||A||`` (spectral norms): its zeros are those of (A, B, C, D) divided by ``a``, so it is
    used throughout and the eigenvalues are multiplied by ``a`` at the end. A small ``B`` or
    ``C`` is thus never mistaken for zero, and the result does not change when inputs or
    outputs are rescaled. Simple zeros are accurate to about ``eps`` times their condition
    number times ``||A||``; a zero of multiplicity ``k`` only to about ``eps**(1/k)``.

    One refinement over the plain staircase: when states are eliminated through rows ``Ĉ1``
    whose smallest singular value (the pivot) is small, the D rows this creates may be treated
    as zero up to ``tol * (1 + ||B|| / pivot)``, since a backward perturbation of ``Ĉ1`` of size
    ``tol`` turns the eliminated subspace by ``tol / pivot``. This keeps a structurally zero
    Markov parameter (``C A B = 0``) that rounding leaves at 1e-14 after a similarity transform
    from producing a spurious zero near 1e14. Systems whose normalised Markov parameters
    ``C A^k B / (||C|| ||A||^k ||B||)`` fall near ``tol`` (high relative degree together with
    ``||A||`` far above the spectral radius, e.g. rotated companion forms) are ill-posed for any
    norm-wise method; a spurious far zero may still appear there.

    References
    ----------
    A. Emami-Naeini and P. Van Dooren, "Computation of zeros of linear multivariable systems",
    Automatica 18(4):415-430, 1982.

    Examples
    --------
    G(s) = (s + 3) / ((s + 1)(s + 2)) in controllable canonical form has the single zero -3:

    >>> from thetahat.structure.zeros import invariant_zeros
    >>> invariant_zeros([[0, 1], [-2, -3]], [[0], [1]], [[3, 1]]).round(12)
    array([-3.+0.j])

    An unobservable mode at 4 is an invariant (output decoupling) zero:

    >>> invariant_zeros([[-1, 0], [0, 4]], [[1], [1]], [[1, 0]]).round(12)
    array([4.+0.j])
    """
    A_, B_, C_, D_ = _as_system(A, B, C, D)
    n, m, r = A_.shape[0], B_.shape[1], C_.shape[0]
    tol_ = _resolve_tol(tol, n, m, r)
    sysn = _normalise(A_, B_, C_, D_, tol_)
    red = _reduce(sysn.A, sysn.B, sysn.C, sysn.D, sysn.threshold)
    Af, Bf = _zero_pencil(red, sysn.threshold)
    z = _finite_eigenvalues(Af, Bf, tol_, sysn.threshold) * sysn.freq_scale
    return _sorted(z)


def normal_rank(A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike | None = None, *, tol: float | None = None) -> int:
    """Normal rank of the Rosenbrock system matrix ``[[sI - A, -B], [C, D]]``.

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, m)
    C : array_like, shape (r, n)
    D : array_like, shape (r, m), optional
        ``None`` (default) means zero.
    tol : float, optional
        Relative rank tolerance, as in :func:`invariant_zeros`.

    Returns
    -------
    int
        The rank of ``P(s)`` for almost every ``s``; equals ``n`` plus the normal rank of the
        transfer matrix ``C (sI - A)^{-1} B + D``.

    Raises
    ------
    DimensionError, NonFiniteError
        As for :func:`invariant_zeros`.

    Notes
    -----
    Computed from the staircase reduction of :func:`invariant_zeros`: every elimination step
    removes ``sigma`` rows and ``sigma`` state columns that carry rank exactly ``sigma``, zero
    rows and columns carry none, and the final system has a square invertible ``D``, so its
    Rosenbrock matrix has full normal rank ``n_f + m_f``. The sum is the normal rank. (The rank
    of ``P(s)`` at a few random complex points gives the same number and is used as a
    cross-check in the tests.)

    Examples
    --------
    Two inputs acting through the same column of B: the normal rank is n + 1, not n + 2.

    >>> from thetahat.structure.zeros import normal_rank
    >>> normal_rank([[0, 1], [0, 0]], [[0, 0], [1, 1]], [[1, 0]])
    3
    """
    A_, B_, C_, D_ = _as_system(A, B, C, D)
    n, m, r = A_.shape[0], B_.shape[1], C_.shape[0]
    tol_ = _resolve_tol(tol, n, m, r)
    sysn = _normalise(A_, B_, C_, D_, tol_)
    red = _reduce(sysn.A, sysn.B, sysn.C, sysn.D, sysn.threshold)
    return red.removed_rank + red.A.shape[0] + red.D.shape[1]


def is_left_invertible(A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike | None = None, *,
                       tol: float | None = None) -> bool:
    """Whether (C, A, B) (with feedthrough D) is left-invertible: normal rank ``n + m``.

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, m)
    C : array_like, shape (r, n)
    D : array_like, shape (r, m), optional
        ``None`` (default) means zero.
    tol : float, optional
        Relative rank tolerance, as in :func:`invariant_zeros`.

    Returns
    -------
    bool
        True when the Rosenbrock matrix has full column normal rank ``n + m``, i.e. the input
        is uniquely determined by the output and the initial state (Assumption 1). This needs
        ``r >= m`` and ``B`` (together with ``D``) of full column rank.

    Raises
    ------
    DimensionError, NonFiniteError
        As for :func:`invariant_zeros`.

    Examples
    --------
    >>> from thetahat.structure.zeros import is_left_invertible
    >>> is_left_invertible([[0, 1], [0, 0]], [[0], [1]], [[1, 0]])
    True
    >>> is_left_invertible([[0, 1], [0, 0]], [[0, 0], [1, 1]], [[1, 0]])
    False
    """
    A_, B_, C_, D_ = _as_system(A, B, C, D)
    return normal_rank(A_, B_, C_, D_, tol=tol) == A_.shape[0] + B_.shape[1]


def unstable_zeros(zeros: ArrayLike, *, scale: float,
                   rtol: float = MINIMUM_PHASE_RTOL) -> ComplexArray:
    """The zeros in the closed right half-plane, with a margin: ``Re z >= -rtol * scale``.

    Parameters
    ----------
    zeros : array_like of complex, shape (n_z,)
        Zeros, e.g. from :func:`invariant_zeros`.
    scale : float
        A natural magnitude of the system, > 0; :func:`is_minimum_phase` uses
        ``max(1, ||A||_2)`` of the original data, the size of the rounding errors in the zeros.
    rtol : float, optional
        Relative margin, default :data:`MINIMUM_PHASE_RTOL` (``1e-6``): large enough that a
        (double) zero on the imaginary axis, computed slightly in the left half-plane, still
        counts as not minimum-phase.

    Returns
    -------
    ndarray of complex, shape (n_u,)
        The zeros with ``Re z >= -rtol * scale``, in their input order.

    Raises
    ------
    DimensionError
        ``zeros`` is not 1-D, or ``scale`` / ``rtol`` is not positive.
    NonFiniteError
        ``zeros`` holds NaN or inf, or ``scale`` / ``rtol`` is not finite.

    Examples
    --------
    A zero at the origin computed as -1e-17 is not minimum-phase:

    >>> from thetahat.structure.zeros import unstable_zeros
    >>> unstable_zeros([-1e-17, -2.0, 1 + 1j], scale=1.0)
    array([-1.e-17+0.j,  1.e+00+1.j])
    """
    z = np.asarray(zeros, dtype=complex)
    if z.ndim == 0:
        z = z.reshape(1)
    if z.ndim != 1:
        raise DimensionError(f"zeros must be a 1-D array of complex numbers; got shape {z.shape}.")
    check_finite("zeros", z)
    scale_ = positive_scalar("scale", scale)
    rtol_ = positive_scalar("rtol", rtol)
    return np.asarray(z[z.real >= -rtol_ * scale_], dtype=complex)


def is_minimum_phase(A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike | None = None, *, tol: float | None = None,
                     rtol: float = MINIMUM_PHASE_RTOL) -> bool:
    """Whether every invariant zero of (A, B, C, D) lies in the open left half-plane.

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, m)
    C : array_like, shape (r, n)
    D : array_like, shape (r, m), optional
        ``None`` (default) means zero.
    tol : float, optional
        Relative rank tolerance, as in :func:`invariant_zeros`.
    rtol : float, optional
        Margin of :func:`unstable_zeros`, applied with ``scale = max(1, ||A||_2)``.

    Returns
    -------
    bool
        False when some zero has ``Re z >= -rtol * max(1, ||A||_2)`` (Assumption 1 fails).

    Raises
    ------
    DimensionError, NonFiniteError
        As for :func:`invariant_zeros`.

    Notes
    -----
    The paper calls (C, A, E) minimum-phase when its invariant zeros (Rosenbrock definition,
    Appendix) are in the open left half-plane; then A_a in the SCB (5)-(7) is Hurwitz. A system
    without finite zeros is minimum-phase.

    Examples
    --------
    >>> from thetahat.structure.zeros import is_minimum_phase
    >>> is_minimum_phase([[0, 1], [-2, -3]], [[0], [1]], [[3, 1]])   # zero at -3
    True
    >>> is_minimum_phase([[0, 1], [-2, -3]], [[0], [1]], [[0, 1]])   # zero at 0
    False
    """
    A_, B_, C_, D_ = _as_system(A, B, C, D)
    z = invariant_zeros(A_, B_, C_, D_, tol=tol)
    scale = max(1.0, _norm2(A_))
    return unstable_zeros(z, scale=scale, rtol=rtol).size == 0
