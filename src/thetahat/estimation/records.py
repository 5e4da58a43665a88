"""Sampled records checked once, before anything is integrated: shapes, real values, inf, and
NaN against the observer's NaN policy.

One definition for every estimator: :func:`check_records` checks the records of the
observer's ``run``, ``run_batch`` and compiled path; :func:`check_record` checks one record
(t, u, y) for the statistical estimators (NaN in y marks a missing sample) with the same
rules. :func:`as_signal` and :func:`as_signals` shape one signal (u or y) of one or of B
records.

What it may import: the package's helpers (``_validate``, ``errors``); nothing of the
estimation wing (every estimator imports it).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_samples, as_time_grid, check_finite
from ..errors import DimensionError, InputLimitError, NonFiniteError, OptionError
from ..limits import MAX_SIGNAL_MAGNITUDE, MIN_SIGNAL_MAGNITUDE

#: What an observer does with a NaN output sample: refuse it, or skip it (a prediction).
NAN_POLICIES = ("raise", "skip")


def check_nan_policy(nan_policy: str) -> str:
    """``nan_policy`` if it is one of :data:`NAN_POLICIES`.

    Parameters
    ----------
    nan_policy : str

    Returns
    -------
    str

    Raises
    ------
    OptionError
        Another value.

    Examples
    --------
    >>> from thetahat.estimation.records import check_nan_policy
    >>> check_nan_policy("skip")
    'skip'
    """
    if nan_policy not in NAN_POLICIES:
        raise OptionError(f"nan_policy must be one of {NAN_POLICIES}; got {nan_policy!r}.")
    return nan_policy

__all__ = ["NAN_POLICIES", "Dimensions", "RecordShape", "as_signal", "as_signals",
           "check_magnitude", "check_nan_policy", "check_real", "check_record", "check_records",
           "plain_sample_ok"]

FloatArray = NDArray[np.float64]


class Dimensions(Protocol):
    """The dimensions a record is checked against (an observer's ``StateLayout`` has them)."""

    @property
    def m(self) -> int:
        """Inputs."""
        ...

    @property
    def r(self) -> int:
        """Outputs."""
        ...


def check_real(name: str, a: ArrayLike) -> None:
    """Refuse complex samples.

    Parameters
    ----------
    name : str
        The argument's name, for the message.
    a : array_like

    Raises
    ------
    DimensionError
        ``a`` is complex.

    Examples
    --------
    >>> check_real("y", [1.0, 2.0])
    >>> check_real("y", [1j])
    Traceback (most recent call last):
    ...
    thetahat.errors.DimensionError: y must be real; got complex samples. ...
    """
    if np.iscomplexobj(a):
        raise DimensionError(f"{name} must be real; got complex samples. Pass the real part "
                             "explicitly if that is what was measured.")


def plain_sample_ok(values: list[float], *, missing: bool) -> bool:
    """Whether plain floats pass the sample checks at once: each finite and within
    :func:`check_magnitude`'s bounds (0, or 1e-150 ≤ |v| ≤ 1e150), or NaN when ``missing``.

    The fast path of :func:`~thetahat.estimation.protocol.check_sample` and of the step
    length's check: a True accepts what the full checks accept; a False decides nothing (the
    full checks then run and say what is wrong).

    Parameters
    ----------
    values : list of float
    missing : bool
        NaN is a missing sample (y), not an error.

    Returns
    -------
    bool

    Examples
    --------
    >>> plain_sample_ok([0.0, -2.5, float("nan")], missing=True)
    True
    >>> plain_sample_ok([float("inf")], missing=True), plain_sample_ok([1e-200], missing=False)
    (False, False)
    """
    for v in values:
        a = abs(v)
        if not (a <= MAX_SIGNAL_MAGNITUDE and (a >= MIN_SIGNAL_MAGNITUDE or a == 0.0)):
            if not (missing and v != v):
                return False
    return True


def check_magnitude(name: str, a: ArrayLike, *, small: bool = True) -> None:
    """Refuse samples whose magnitude float64 arithmetic of a model cannot take.

    Every finite sample must have |value| ≤ :data:`~thetahat.limits.MAX_SIGNAL_MAGNITUDE`
    (1e150) and, when ``small``, be 0 or have |value| ≥
    :data:`~thetahat.limits.MIN_SIGNAL_MAGNITUDE` (1e-150): the estimators square their
    signals, and those squares must stay normal float64 numbers. NaN and inf are left to the
    finiteness checks. One definition for records (:func:`check_records`), samples and step
    lengths (:func:`~thetahat.estimation.protocol.check_sample`,
    :func:`~thetahat.estimation.protocol.check_step_length`).

    Parameters
    ----------
    name : str
        The signal, for the message ("y", "t", "dt").
    a : array_like
    small : bool
        Also refuse nonzero values below the smallest magnitude.

    Raises
    ------
    InputLimitError
        A value beyond a bound; the message names the value, the bound and the fix (rescale
        the unit).

    Examples
    --------
    >>> check_magnitude("y", [0.0, 1e-3, 2.5e6])
    >>> check_magnitude("y", [1.0, 3e-301])
    Traceback (most recent call last):
    ...
    thetahat.errors.InputLimitError: y: a value of magnitude 3e-301, below 1e-150 ...
    """
    arr = np.asarray(a, dtype=np.float64)
    if arr.size <= 16:                      # a sample of step: plain floats are faster
        mags = [abs(v) for v in arr.ravel().tolist()]
        big = max((v for v in mags if v != float("inf")), default=0.0)
        tiny = min((v for v in mags if v > 0.0), default=float("inf")) if small else 1.0
    else:
        mags_a = np.abs(arr[np.isfinite(arr)])
        big = float(mags_a.max(initial=0.0))
        pos = mags_a[mags_a > 0.0]
        tiny = float(pos.min(initial=np.inf)) if small else 1.0
    if big > MAX_SIGNAL_MAGNITUDE:
        where, bound, limit = "above", MAX_SIGNAL_MAGNITUDE, "MAX_SIGNAL_MAGNITUDE"
        value = big
    elif tiny < MIN_SIGNAL_MAGNITUDE:
        where, bound, limit = "below", MIN_SIGNAL_MAGNITUDE, "MIN_SIGNAL_MAGNITUDE"
        value = tiny
    else:
        return
    column = "t" if name in ("dt", "the steps of t") else name
    raise InputLimitError(
        f"{name}: a value of magnitude {value:.3g}, {where} {bound:g} "
        f"(thetahat.limits.{limit}): the estimators square their signals, and float64 cannot "
        f"hold the result. Rescale {name} to a unit in which it is of order 1 (a model file's "
        f"[data] scale does it, e.g. {column[:1].lower()} = {{ column = \"{column}\", scale "
        f"= 1e-3 }}), and the model with it.")


class RecordShape(NamedTuple):
    """The widths of a record's signals: m inputs and r outputs (a :class:`Dimensions`).

    Attributes
    ----------
    m : int
        Inputs.
    r : int
        Outputs.
    """

    m: int
    r: int


def as_signal(name: str, a: ArrayLike, N: int, width: int) -> FloatArray:
    """One signal of a record, N samples, as a C-contiguous (N, width) float64 array.

    Parameters
    ----------
    name : str
        The argument's name, for the message.
    a : array_like, shape (N, width), or (N,) when width = 1
    N : int
        Number of samples (the length of t).
    width : int
        Samples' width (m or r).

    Returns
    -------
    ndarray, shape (N, width)

    Raises
    ------
    DimensionError
        Complex samples or the wrong shape.

    Examples
    --------
    >>> as_signal("y", [1.0, 2.0, 3.0], 3, 1).shape
    (3, 1)
    """
    arr = as_samples(name, a)
    if arr.ndim == 1 and width == 1:
        arr = arr.reshape(-1, 1)
    if arr.ndim != 2 or arr.shape != (N, width):
        raise DimensionError(f"{name} must have shape ({N}, {width})"
                             f"{' or (N,)' if width == 1 else ''} to match t; got "
                             f"{arr.shape}.")
    return np.ascontiguousarray(arr)


def as_signals(name: str, a: ArrayLike, B: int | None, N: int, width: int) -> FloatArray:
    """One signal of B records of N samples as a C-contiguous (B, N, width) float64 array.

    Parameters
    ----------
    name : str
        The argument's name, for the message.
    a : array_like, shape (B, N, width), or (B, N) when width = 1
    B : int or None
        Number of records (None: any).
    N : int
        Number of samples.
    width : int
        Samples' width (m or r).

    Returns
    -------
    ndarray, shape (B, N, width)

    Raises
    ------
    DimensionError
        Complex samples or the wrong shape.

    Examples
    --------
    >>> as_signals("Y", [[1.0, 2.0], [3.0, 4.0]], None, 2, 1).shape
    (2, 2, 1)
    """
    arr = as_samples(name, a)
    if arr.ndim == 2 and width == 1:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[1:] != (N, width) or (B is not None and arr.shape[0] != B):
        b = "B" if B is None else str(B)
        raise DimensionError(f"run_batch: {name} must have shape ({b}, {N}, {width})"
                             f"{f' or ({b}, {N})' if width == 1 else ''}: one record per run "
                             f"on the shared time grid t; got {arr.shape}.")
    return np.ascontiguousarray(arr)


def check_records(layout: Dimensions, nan_policy: str, t: ArrayLike, u: ArrayLike | None,
                  y: ArrayLike, batch: int | None = None
                  ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Validate sampled records against the NaN policy (before anything is integrated).

    Parameters
    ----------
    layout : Dimensions
        The observer's dimensions (m, r).
    nan_policy : {"raise", "skip"}
        The observer's NaN policy.
    t : array_like, shape (N,)
        Strictly increasing sampling instants.
    u : array_like, shape ([B,] N, m), or ([B,] N) when m = 1
        ``None`` when m = 0.
    y : array_like, shape ([B,] N, r), or ([B,] N) when r = 1
    batch : int, optional
        None: one record (no leading axis); else the records carry a leading axis of
        length B (-1: any B).

    Returns
    -------
    t, dts : ndarray, shapes (N,), (N - 1,)
    U, Y : ndarray, shapes (B, N, m), (B, N, r)
        B = 1 for a single record.
    ok : ndarray of bool, shape (B, N)
        Samples whose y is present.

    Raises
    ------
    DimensionError
        Wrong shapes, or ``t`` not strictly increasing.
    NonFiniteError
        NaN or inf in t or u; inf in y; NaN in y under ``nan_policy="raise"``.
    InputLimitError
        |t|, a step of t, or a nonzero |u| or |y| beyond the magnitudes of
        :func:`check_magnitude`.

    Examples
    --------
    >>> from thetahat.estimation.observer.plan import StateLayout
    >>> lay = StateLayout(n=2, m=1, r=1, k=1, p=1, second=False, law_size=0)
    >>> t, dts, U, Y, ok = check_records(lay, "skip", [0.0, 1.0], [0.0, 0.0],
    ...                                  [1.0, float("nan")])
    >>> ok.tolist()
    [[True, False]]
    """
    lay = layout
    t_, dts = as_time_grid(t)
    N = t_.shape[0]
    if batch is None:
        Y = as_signal("y", y, N, lay.r)[None]
        U = as_signal("u", np.zeros((N, 0)) if u is None else u, N, lay.m)[None]
        names = ("u", "y")
    else:
        Y = as_signals("Y", y, None if batch < 0 else batch, N, lay.r)
        B = Y.shape[0]
        U = as_signals("U", np.zeros((B, N, 0)) if u is None else u, B, N, lay.m)
        names = ("U", "Y")
    check_finite(names[0], U)
    check_magnitude("t", t_, small=False)
    check_magnitude("the steps of t", dts)
    check_magnitude(names[0], U)
    check_magnitude(names[1], Y)
    if np.isinf(Y).any():
        raise NonFiniteError(f"{names[1]} contains inf; only NaN marks a missing sample.")
    ok = np.asarray(np.isfinite(Y).all(axis=2), dtype=np.bool_)
    if not ok.all() and nan_policy == "raise":
        b, i = (int(a[0]) for a in np.nonzero(~ok))
        run = f" in run {b}" if batch is not None else ""
        raise NonFiniteError(f"{names[1]} contains NaN ({int((~ok).sum())} samples, first"
                             f"{run} at index {i}) and nan_policy='raise'; pass "
                             "nan_policy='skip' to the observer to predict over missing "
                             "samples, or clean the data.")
    return t_, dts, U, Y, ok


def check_record(t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *, m: int, r: int
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One record for the statistical estimators: t (N ≥ 2), U (N, m), Y (N, r) checked.

    The rules of :func:`check_records` with ``nan_policy="skip"`` (NaN in y marks a missing
    sample; NaN or inf in t or u and inf in y are refused), and at least two samples (a
    sampling interval).

    Parameters
    ----------
    t : array_like, shape (N,)
        Strictly increasing sampling instants (datetimes are taken as seconds from the first).
    u : array_like, shape (N, m), or (N,) when m = 1
        ``None`` when m = 0.
    y : array_like, shape (N, r), or (N,) when r = 1
    m, r : int
        The model's inputs and outputs.

    Returns
    -------
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        Own writable C-contiguous float64 copies (the compiled kernels then see one array
        type whatever the caller passes).

    Raises
    ------
    DimensionError
        Wrong shapes, fewer than 2 samples, or ``t`` not strictly increasing.
    NonFiniteError
        NaN or inf in t or u; inf in y.

    Examples
    --------
    >>> t, U, Y = check_record([0.0, 0.1, 0.2], None, [1.0, float("nan"), 2.0], m=0, r=1)
    >>> U.shape, Y.shape, bool(Y.flags.writeable)
    ((3, 0), (3, 1), True)
    """
    t_, _, U, Y, _ = check_records(RecordShape(m=m, r=r), "skip", t, u, y)
    if t_.shape[0] < 2:
        raise DimensionError(f"t must hold at least 2 sampling instants; got {t_.shape[0]}.")
    return np.array(t_), np.array(U[0]), np.array(Y[0])
