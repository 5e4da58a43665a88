"""The initial state estimate from the first output sample: x̂(0) = x̂₀ + C⁺(y(0) − C x̂₀).

A record that begins in motion has y(0) far from C x̂₀ (x̂₀ = 0 by default): the high-gain
observer then peaks (its error starts at ‖y(0) − C x̂₀‖, amplified by ε⁻ʲ in the j-th
derivative) and the peak reaches the update law. Starting x̂ at the least-squares fit of the
first sample removes the part of the initial error the output sees, and keeps x̂₀ (the model
file's, or 0) as the prior for the part it does not (the null space of C). Every entry point
that starts an estimator from a model file uses :func:`x_hat_from_output` (the CLI's
``estimate``, ``fleet``, :func:`~thetahat.modelfile.run_estimator`), and the generated C
harness applies the same correction, with the same C⁺ (:func:`output_pinv`), on its first
sample.

What lives here: :func:`x_hat_from_output` and :func:`output_pinv`. What it may import: NumPy
and the package's validation only.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_vector
from ...errors import DimensionError

__all__ = ["output_pinv", "x_hat_from_output"]

FloatArray = NDArray[np.float64]


def output_pinv(C: ArrayLike) -> FloatArray:
    """C⁺, the Moore–Penrose pseudo-inverse of C (r × n), from its SVD; shape (n, r).

    Singular values below ``max(n, r)·eps·σ_max`` count as zero (NumPy's default for
    ``pinv``): directions C does not see are left alone.

    Parameters
    ----------
    C : array_like, shape (r, n)

    Returns
    -------
    ndarray, shape (n, r)

    Examples
    --------
    >>> output_pinv([[1.0, 0.0]]).tolist()
    [[1.0], [0.0]]
    """
    C_ = np.atleast_2d(np.asarray(C, dtype=np.float64))
    return np.asarray(np.linalg.pinv(C_), dtype=np.float64)


def x_hat_from_output(C: ArrayLike, y0: ArrayLike, x_hat0: ArrayLike | None = None
                      ) -> FloatArray:
    """x̂₀ + C⁺(y(0) − C x̂₀): the state estimate nearest x̂₀ that fits the first sample.

    Among the x minimising ‖y(0) − C x‖, the one nearest x̂₀ (the prior). A y(0) with a NaN
    (a dropout) gives x̂₀ (the generated C's ``<name>_start_from_y`` does the same).

    Parameters
    ----------
    C : array_like, shape (r, n)
        The output matrix of (1).
    y0 : array_like, shape (r,)
        The first output sample.
    x_hat0 : array_like, shape (n,), optional
        The prior (default 0).

    Returns
    -------
    ndarray, shape (n,)

    Raises
    ------
    DimensionError
        Wrong shapes.

    Examples
    --------
    Position measured, velocity not: the position is taken from y(0), the velocity kept.

    >>> x_hat_from_output([[1.0, 0.0]], [0.18], [0.0, 0.5]).tolist()
    [0.18, 0.5]
    """
    C_ = np.atleast_2d(np.asarray(C, dtype=np.float64))
    r, n = C_.shape
    x0 = np.zeros(n) if x_hat0 is None else as_vector("x_hat0", x_hat0, n)
    y = np.asarray(y0, dtype=np.float64).reshape(-1)
    if y.shape != (r,):
        raise DimensionError(f"y0 must have {r} entries (one per output); got {y.size}.")
    if not np.all(np.isfinite(y)):
        return x0.copy()
    return x0 + output_pinv(C_) @ (y - C_ @ x0)
