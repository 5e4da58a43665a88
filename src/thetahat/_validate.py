"""Private helpers that coerce arrays and check shape and finiteness at the public boundary.

Every public function validates its input here, once, and gets back float64 arrays. Messages
name the argument, the expected shape and the actual shape.
"""

from __future__ import annotations

import math

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import DimensionError, InputLimitError, NonFiniteError

FloatArray = NDArray[np.float64]


def _shape_str(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"


def check_finite(name: str, arr: NDArray[Any]) -> None:
    """Raise :class:`NonFiniteError` if ``arr`` holds NaN or inf."""
    if arr.dtype.kind == "f" and math.isfinite(np.add.reduce(arr, axis=None)):
        return                          # a finite sum has finite terms (one reduction)
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))
        where = tuple(int(i) for i in bad[0]) if bad.size else ()
        raise NonFiniteError(
            f"{name} contains NaN or inf (first at index {where}, {len(bad)} entries in all); "
            f"clean or interpolate the data before passing it."
        )


def as_matrix(name: str, M: Any, shape: tuple[int | None, int | None] = (None, None),
              *, finite: bool = True, allow_empty: bool = True) -> FloatArray:
    """Return ``M`` as a 2-D float64 array, checking its shape (``None`` = any size).

    Scalars and 1-D input are *not* silently reshaped except a scalar for a (1, 1) matrix:
    a 1-D array is ambiguous (row or column), so the message says which one was expected.
    """
    arr = _real_array(name, M)
    if arr.ndim == 0 and shape in ((1, 1), (None, None), (1, None), (None, 1)):
        arr = arr.reshape(1, 1)
    if arr.ndim != 2:
        raise DimensionError(
            f"{name} must be a 2-D matrix of shape {_shape_str(shape)}; got an array with "
            f"ndim={arr.ndim} and shape {arr.shape}. Use a column (e.g. np.reshape(v, (-1, 1))) "
            f"or a row (np.reshape(v, (1, -1))) explicitly."
        )
    for axis, (want, got) in enumerate(zip(shape, arr.shape)):
        if want is not None and want != got:
            raise DimensionError(
                f"{name} must have shape {_shape_str(shape)}; got {arr.shape} "
                f"(axis {axis}: expected {want}, found {got})."
            )
    if not allow_empty and arr.size == 0:
        raise DimensionError(f"{name} must not be empty; got shape {arr.shape}.")
    if finite:
        check_finite(name, arr)
    return arr


def as_vector(name: str, v: Any, size: int | None = None, *, finite: bool = True) -> FloatArray:
    """Return ``v`` as a 1-D float64 array of length ``size`` (scalars become length 1)."""
    arr = _real_array(name, v)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise DimensionError(f"{name} must be a 1-D vector of length {size if size is not None else '?'}; "
                             f"got shape {arr.shape}.")
    if size is not None and arr.shape[0] != size:
        raise DimensionError(f"{name} must have length {size}; got {arr.shape[0]}.")
    if finite:
        check_finite(name, arr)
    return arr


def as_square(name: str, M: Any, n: int | None = None) -> FloatArray:
    """A square float64 matrix, of size ``n`` when given."""
    arr = as_matrix(name, M, (n, n))
    if arr.shape[0] != arr.shape[1]:
        raise DimensionError(f"{name} must be square; got shape {arr.shape}.")
    return arr


def _real_array(name: str, M: Any) -> FloatArray:
    """``M`` as a float64 array of any shape.

    Complex numbers, booleans, text, dates and other non-numbers are refused; the masked
    entries of a masked array become NaN (so the caller's NaN rule applies: refused, or a
    dropout of an output under ``nan_policy="skip"``); integers too large for float64 are
    refused.
    """
    if isinstance(M, np.ma.MaskedArray):
        if M.dtype.kind not in "biuf":
            raise DimensionError(f"{name} must be real numbers; got a masked array of "
                                 f"{M.dtype}.")
        M = np.ma.filled(M.astype(np.float64), np.nan)
    try:
        arr = np.asarray(M)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DimensionError(f"{name} must be a numeric array; got {type(M).__name__} "
                             f"({exc}).") from exc
    kind = arr.dtype.kind
    if kind == "c":
        raise DimensionError(f"{name} must be real; got a complex array.")
    if kind == "b":
        raise DimensionError(f"{name} must be real numbers; got booleans (convert them "
                             f"explicitly, e.g. {name}.astype(float), if 0/1 is meant).")
    if kind in "mM":
        raise DimensionError(f"{name} must be real numbers; got dates or times ({arr.dtype}).")
    if kind in "USV":
        raise DimensionError(f"{name} must be real numbers; got text ({arr.dtype}); convert "
                             f"it with float() where it is read.")
    try:
        out = arr.astype(np.float64, copy=False)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DimensionError(f"{name} must be a numeric array; got {type(M).__name__} "
                             f"({exc}).") from exc
    if kind == "O" and any(isinstance(v, (bool, np.bool_, str, bytes)) for v in arr.flat):
        raise DimensionError(f"{name} must be real numbers; got booleans or text.")
    return out


def as_samples(name: str, a: Any) -> FloatArray:
    """Samples (u, y, records) as a float64 array of any shape, with the rules of
    :func:`_real_array` (masked entries become NaN; booleans, text, dates refused)."""
    return _real_array(name, a)


def seconds_from_first(name: str, t: Any) -> Any:
    """Datetimes (``datetime64``) or durations (``timedelta64``) as float seconds from the
    first sample; anything else unchanged."""
    arr = t if isinstance(t, np.ndarray) else None
    if arr is None:
        try:
            arr = np.asarray(t)
        except (TypeError, ValueError):
            return t
    if arr.dtype.kind not in "mM" or arr.size == 0:
        return t
    if np.isnat(arr).any():
        raise NonFiniteError(f"{name} holds a missing time (NaT).")
    return np.asarray((arr - arr.ravel()[0]) / np.timedelta64(1, "ns"), dtype=np.float64) * 1e-9


def as_triple(A: Any, B: Any, C: Any, *, names: tuple[str, str, str] = ("A", "B", "C")
              ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Validate a state-space triple: A (n, n), B (n, m), C (r, n)."""
    An, Bn, Cn = names
    A_ = as_square(An, A)
    n = A_.shape[0]
    B_ = _real_array(Bn, B)
    if B_.ndim == 1 and B_.shape[0] == n:
        raise DimensionError(f"{Bn} must be 2-D of shape ({n}, ?); got a 1-D array of length {n}. "
                             f"For a single input use np.reshape({Bn}, ({n}, 1)).")
    B_ = as_matrix(Bn, B_, (n, None))
    C_ = _real_array(Cn, C)
    if C_.ndim == 1 and C_.shape[0] == n:
        raise DimensionError(f"{Cn} must be 2-D of shape (?, {n}); got a 1-D array of length {n}. "
                             f"For a single output use np.reshape({Cn}, (1, {n})).")
    C_ = as_matrix(Cn, C_, (None, n))
    for name, M in ((An, A_), (Bn, B_), (Cn, C_)):
        check_magnitude(name, M)
    return A_, B_, C_


def check_magnitude(name: str, M: FloatArray) -> None:
    """Refuse a system matrix with entries beyond :data:`thetahat.limits.MAX_MATRIX_ENTRY`
    (products of its entries would overflow float64)."""
    from . import limits

    big = np.abs(M) > limits.MAX_MATRIX_ENTRY
    if big.any():
        where = tuple(int(i) for i in np.argwhere(big)[0])
        raise InputLimitError(f"{name}[{where[0]}, {where[1]}] = {M[where]:g} exceeds "
                              f"{limits.MAX_MATRIX_ENTRY:g} in magnitude "
                              f"(thetahat.limits.MAX_MATRIX_ENTRY): products of such entries "
                              f"overflow float64. Rescale the model's units.")


def positive_scalar(name: str, value: Any) -> float:
    """A finite float > 0."""
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise DimensionError(f"{name} must be a real number; got {value!r}.") from exc
    if not np.isfinite(x):
        raise NonFiniteError(f"{name} must be finite; got {x}.")
    if x <= 0:
        raise DimensionError(f"{name} must be > 0; got {x}.")
    return x


def readonly(a: Any, dtype: Any = np.float64) -> NDArray[Any]:
    """A read-only copy of ``a`` (as ``dtype``; ``None`` keeps the input's dtype).

    Frozen dataclasses store their arrays this way, so that frozen means frozen.
    """
    arr = np.array(a, dtype=dtype, copy=True)
    arr.setflags(write=False)
    return arr


def as_time_grid(t: Any) -> tuple[FloatArray, FloatArray]:
    """Sampling instants ``t`` (finite, at least one, strictly increasing) and ``diff(t)``.

    Datetimes and durations (``datetime64``, ``timedelta64``) are converted to seconds from
    the first sample.

    Raises :class:`DimensionError` naming the first offending pair of samples.
    """
    t_ = as_vector("t", seconds_from_first("t", t))
    if t_.shape[0] == 0:
        raise DimensionError("t must hold at least one sampling instant; got none.")
    dts = np.diff(t_)
    if t_.shape[0] > 1 and not (dts > 0).all():
        i = int(np.argmax(dts <= 0))
        raise DimensionError(f"t must be strictly increasing; t[{i + 1}] = {t_[i + 1]!r} <= "
                             f"t[{i}] = {t_[i]!r}. Sort the record and drop duplicate time "
                             "stamps.")
    return t_, dts
