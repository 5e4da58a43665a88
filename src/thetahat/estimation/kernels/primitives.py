"""The vocabulary the formulas are written in, and the NumPy functions it is printed into.

The formulas (:mod:`~thetahat.estimation.observer.formulas`,
:mod:`~thetahat.estimation.observer.laws.formulas`) use Python's arithmetic, subscripts, block
statements over views and products (:mod:`~thetahat.estimation.kernels.subset`) and these
names, each printed for its target:

=========================  ===========================  =================================
name                       scalar (numba, C)            NumPy (one row | rows on axis 0)
=========================  ===========================  =================================
``where(c, a, b)``         ``a if c else b``            same | ``np.where``
``clip(a, lo, hi)``        ``min(max(a, lo), hi)``      same | :func:`clip`
``exp(a)``                 scalar ``exp`` (no libm      ``np.exp``
                           underflow path)
``isfinite``, ``isnan``    ``math.isfinite``, ``isnan`` ``math.…`` | ``np.…``
``not_``, ``and_``,        ``not``, ``and``, ``or``     same | ``np.logical_…``
``or_``
``any_(b)``, ``count_(b)`` over the rows: ``b``,        same | :func:`any_rows`,
                           ``1 if b else 0``            :func:`count_rows`
``solve(M, rhs)``          scalar ``solve(q, M, rhs)``  :func:`solve_row` | :func:`solve_rows`
                           (pivoted elimination)
``expm(Z, E, T, U)``       scalar ``expm`` (Taylor)     :func:`expm` (SciPy's)
``norm(a)``                scalar ``norm(n, a)``        :func:`norm`
``sumsq(a)``               scalar ``sumsq(n, a)``       :func:`sumsq_row` | :func:`sumsq_rows`
``eye(q)`` (in a block)    ``1.0 if i == j else 0.0``   :func:`identity`
``A @ x``, ``A @ B``       loops                        ``@`` | :func:`product`, :func:`matmul`
=========================  ===========================  =================================

In NumPy a vector is an array of shape (..., size) and a matrix (a, b), (1, a, b) shared by the
rows or (B, a, b) per row. ``solve`` returns ``ST_OK``, or ``ST_SINGULAR`` at a zero pivot (per
row). The scalar functions live in :mod:`~thetahat.estimation.kernels.scalar_primitives`.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.linalg.lapack import dgesv as _gesv

from ...model.set_geometry import safe_norm
from ..status import Status

__all__ = ["VOCABULARY", "any_rows", "clip", "count_rows", "expm", "identity", "matmul", "norm",
           "product", "solve_row", "solve_rows", "sumsq_row", "sumsq_rows", "transpose"]

FloatArray = NDArray[np.float64]

#: The names the formulas may call besides other formulas, the model functions and hooks.
VOCABULARY = ("where", "clip", "exp", "isfinite", "isnan", "not_", "and_", "or_", "any_",
              "count_", "solve", "expm", "norm", "sumsq", "eye")


def product(M: FloatArray, x: FloatArray) -> FloatArray:
    """M x for M (a, b), (1, a, b) or (B, a, b) and x (b,) or (B, b).

    Parameters
    ----------
    M : ndarray
    x : ndarray

    Returns
    -------
    ndarray, shape (a,) or (B, a)

    Examples
    --------
    >>> product(np.eye(2)[None], np.array([[1.0, 2.0], [3.0, 4.0]])).tolist()
    [[1.0, 2.0], [3.0, 4.0]]
    """
    if M.ndim == 2:
        return M @ x if x.ndim == 1 else x @ M.T
    if M.shape[0] == 1:
        return x @ M[0].T
    if x.ndim == 1:
        return M @ x
    return np.matmul(M, x[..., None])[..., 0]


@functools.cache
def identity(q: int) -> FloatArray:
    """The identity of size q (one read-only array per q: no allocation per step).

    Parameters
    ----------
    q : int

    Returns
    -------
    ndarray, shape (q, q)

    Examples
    --------
    >>> identity(2).tolist(), identity(2) is identity(2)
    ([[1.0, 0.0], [0.0, 1.0]], True)
    """
    out = np.eye(q)
    out.setflags(write=False)
    return out


def matmul(A: FloatArray, B: FloatArray) -> FloatArray:
    """A B for matrices (a, c), (1, a, c) or (B, a, c) and (c, b), …: ``np.matmul``.

    Parameters
    ----------
    A, B : ndarray

    Returns
    -------
    ndarray

    Examples
    --------
    >>> matmul(np.ones((1, 2, 3)), np.ones((3, 1))).shape
    (1, 2, 1)
    """
    return np.matmul(A, B)


def transpose(B: FloatArray) -> FloatArray:
    """Bᵀ of each matrix (the last two axes swapped).

    Parameters
    ----------
    B : ndarray, shape (..., a, b)

    Returns
    -------
    ndarray, shape (..., b, a)

    Examples
    --------
    >>> transpose(np.zeros((4, 2, 3))).shape
    (4, 3, 2)
    """
    return np.swapaxes(B, -1, -2)


def clip(a: Any, lo: Any, hi: Any) -> Any:
    """min(max(a, lo), hi) elementwise: NaN in ``a`` stays NaN, as in the scalar ``clip``.

    Parameters
    ----------
    a, lo, hi : float or ndarray

    Returns
    -------
    float or ndarray

    Examples
    --------
    >>> clip(np.array([-2.0, np.nan, 0.5]), -1.0, 1.0).tolist()
    [-1.0, nan, 0.5]
    """
    return np.minimum(np.maximum(a, lo), hi)


def any_rows(b: Any) -> bool:
    """Whether ``b`` holds in some row.

    Parameters
    ----------
    b : bool or ndarray of bool

    Returns
    -------
    bool

    Examples
    --------
    >>> any_rows(np.array([False, True])), any_rows(False)
    (True, False)
    """
    if isinstance(b, (bool, np.bool_)):
        return bool(b)
    return bool(b.any())


def count_rows(b: Any) -> int:
    """In how many rows ``b`` holds.

    Parameters
    ----------
    b : bool or ndarray of bool

    Returns
    -------
    int

    Examples
    --------
    >>> count_rows(np.array([True, False, True])), count_rows(True)
    (2, 1)
    """
    if isinstance(b, (bool, np.bool_)):
        return int(b)
    return int(np.count_nonzero(b))


def solve_row(M: FloatArray, rhs: FloatArray) -> int:
    """rhs ← M⁻¹ rhs for one row (LAPACK's gesv); the status.

    Parameters
    ----------
    M : ndarray, shape (q, q)
    rhs : ndarray, shape (q,)
        Overwritten; NaN when M is singular.

    Returns
    -------
    int
        ``Status.OK``, or ``Status.SINGULAR`` at a zero pivot of LAPACK's LU (info > 0).

    Examples
    --------
    >>> r = np.array([2.0, 3.0])
    >>> solve_row(np.diag([2.0, 1.0]), r), r.tolist()
    (0, [1.0, 3.0])
    """
    _, _, x, info = _gesv(M, rhs)
    if info > 0:
        rhs[...] = np.nan
        return int(Status.SINGULAR)
    rhs[...] = x
    return int(Status.OK)


def solve_rows(M: FloatArray, rhs: FloatArray) -> Any:
    """rhs ← M⁻¹ rhs per row; the status per row (as :func:`solve_row`).

    Parameters
    ----------
    M : ndarray, shape (B, q, q) or (q, q)
    rhs : ndarray, shape (B, q) or (q,)

    Returns
    -------
    int or ndarray of int

    Examples
    --------
    >>> r = np.array([[1.0, 1.0], [1.0, 1.0]])
    >>> solve_rows(np.stack([np.eye(2), np.zeros((2, 2))]), r).tolist()  # OK, SINGULAR
    [0, 6]
    """
    if M.ndim == 2:
        return solve_row(M, rhs)
    status = np.full(M.shape[:-2], int(Status.OK))
    try:
        rhs[...] = np.linalg.solve(M, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:       # some row is singular: find it, row by row
        for i in np.ndindex(*M.shape[:-2]):
            status[i] = solve_row(M[i], rhs[i])
    return status


def expm(Z: FloatArray, E: FloatArray, T: Any = None, U: Any = None) -> None:
    """E ← exp(Z) (SciPy's, per row); ``T``, ``U`` (the scalar version's scratch) unused.

    Parameters
    ----------
    Z : ndarray, shape (..., q, q)
    E : ndarray, shape (..., q, q)
    T, U : ndarray or None

    Examples
    --------
    >>> E = np.empty((1, 1))
    >>> expm(np.zeros((1, 1)), E); E.tolist()
    [[1.0]]
    """
    E[...] = scipy.linalg.expm(Z)


def norm(a: FloatArray) -> Any:
    """The Euclidean norm of each row, without overflow.

    Parameters
    ----------
    a : ndarray, shape (..., n)

    Returns
    -------
    float or ndarray

    Examples
    --------
    >>> float(norm(np.array([3e300, 4e300])))
    5e+300
    """
    return safe_norm(a)


def sumsq_row(a: FloatArray) -> float:
    """Σ a[i]² of one row.

    Parameters
    ----------
    a : ndarray, shape (n,)

    Returns
    -------
    float

    Examples
    --------
    >>> sumsq_row(np.array([3.0, 4.0]))
    25.0
    """
    return float(np.dot(a, a))


def sumsq_rows(a: FloatArray) -> Any:
    """Σ a[i]² of each row.

    Parameters
    ----------
    a : ndarray, shape (..., n)

    Returns
    -------
    float or ndarray

    Examples
    --------
    >>> sumsq_rows(np.array([[3.0, 4.0], [1.0, 0.0]])).tolist()
    [25.0, 1.0]
    """
    if a.ndim == 1:
        return sumsq_row(a)
    return np.einsum("...i,...i->...", a, a)
