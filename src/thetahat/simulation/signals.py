"""Known input signals u(t) as small, frozen, vectorised callables of time (Sec. II).

The paper assumes that u is defined for all t ≥ 0 and that u̇ is well defined and piecewise
continuous. Every signal here therefore has a value and a derivative, and lists the times at
which it jumps, so that an integrator can restart there instead of stepping over a jump.

Shape convention: a signal with ``dim = m`` channels returns shape ``(m,)`` for a scalar t and
``t.shape + (m,)`` for an array t, so ``signal(t_grid)`` is an ``(N, m)`` sample matrix.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_vector, check_finite, positive_scalar, readonly
from ..errors import DimensionError, NonFiniteError
from ..limits import check_allocation

__all__ = ["FromArray", "Multisine", "Signal", "Steps", "time_grid"]

FloatArray = NDArray[np.float64]

#: Slack added to (t_end - t0)·fs before flooring, so that a t_end that is an exact multiple of
#: the sample period in decimal (20.0 s at 1 kHz) is not lost to binary round-off (19999.999...).
GRID_SLACK = 1e-9




def _as_times(t: ArrayLike) -> FloatArray:
    """Coerce evaluation times to a finite float64 array of any shape."""
    if isinstance(t, float):   # the integrator's hot path: one scalar time per call
        if not math.isfinite(t):
            raise NonFiniteError(f"t must be finite; got {t}.")
        return np.asarray(t)
    arr = np.asarray(t, dtype=np.float64)
    check_finite("t", arr)
    return arr


def _strictly_increasing(name: str, t: FloatArray) -> None:
    if t.size > 1 and not np.all(np.diff(t) > 0):
        k = int(np.argmin(np.diff(t)))
        raise DimensionError(f"{name} must be strictly increasing; {name}[{k}] = {t[k]} is "
                             f"followed by {name}[{k + 1}] = {t[k + 1]}. Sort the samples and "
                             f"drop duplicates.")


#: float64 words per sample assumed by :func:`time_grid`'s memory estimate: t, u, x, y and the
#: estimates of a small model (the LuGre example stores about a dozen).
GRID_WORDS = 16


def time_grid(t_end: float, fs: float, t0: float = 0.0) -> FloatArray:
    """Uniform sample times ``t0, t0 + 1/fs, ...`` up to and including ``t_end``.

    Parameters
    ----------
    t_end : float
        Final time (s); included when ``(t_end - t0)·fs`` is an integer.
    fs : float
        Sampling frequency (Hz), > 0.
    t0 : float, optional
        Initial time (s).

    Returns
    -------
    ndarray, shape (N,)
        ``t0 + arange(N) / fs`` with ``N = floor((t_end - t0)·fs) + 1``.

    Raises
    ------
    DimensionError
        ``fs <= 0`` or ``t_end <= t0``.
    ResourceLimitError
        The grid and the trajectories sampled on it (``GRID_WORDS`` float64 per sample)
        would not fit in memory.

    Examples
    --------
    >>> from thetahat.simulation.signals import time_grid
    >>> time_grid(1.0, 4.0)
    array([0.  , 0.25, 0.5 , 0.75, 1.  ])
    """
    fs_ = positive_scalar("fs", fs)
    t0_ = float(t0)
    span = positive_scalar("t_end - t0", float(t_end) - t0_)
    n_float = np.floor(span * fs_ + GRID_SLACK) + 1
    check_allocation(8.0 * GRID_WORDS * n_float, f"a time grid of {n_float:.3g} samples "
                     f"(t_end - t0 = {span:g} s at fs = {fs_:g} Hz) and its trajectories",
                     fix="shorten t_end or lower fs")
    n = int(n_float)
    return t0_ + np.arange(n, dtype=np.float64) / fs_


class Signal(ABC):
    """Abstract known signal u(t) with ``dim`` channels.

    Concrete signals are final frozen dataclasses: combine them, do not subclass them.
    """

    __slots__ = ()

    @property
    @abstractmethod
    def dim(self) -> int:
        """m, the number of channels."""

    @abstractmethod
    def __call__(self, t: ArrayLike) -> FloatArray:
        """u(t); shape ``np.shape(t) + (m,)``."""

    @abstractmethod
    def derivative(self, t: ArrayLike) -> FloatArray:
        """u̇(t) (zero on flat pieces, one-sided at jumps); shape ``np.shape(t) + (m,)``."""

    @property
    def breakpoints(self) -> tuple[float, ...]:
        """Times at which u jumps or kinks, sorted; integrators restart there. Default: none."""
        return ()

    def sampled(self, t: ArrayLike) -> FloatArray:
        """The signal on a 1-D time grid, as an ``(N, m)`` sample matrix.

        Parameters
        ----------
        t : array_like, shape (N,)
            Non-decreasing sample times.

        Returns
        -------
        ndarray, shape (N, m)

        Raises
        ------
        DimensionError
            ``t`` is not 1-D or decreases somewhere.
        NonFiniteError
            ``t`` holds NaN or inf.
        """
        t_ = as_vector("t", t)
        if t_.size > 1 and np.any(np.diff(t_) < 0):
            raise DimensionError("t must be non-decreasing to sample a signal on a grid; "
                                 "sort the times first.")
        return self(t_)


@dataclass(frozen=True, slots=True, eq=False)
class Multisine(Signal):
    """A sum of sines, ``u_i(t) = offset_i + Σ_j a_ij sin(2π f_ij t + φ_ij)``.

    Parameters
    ----------
    amplitudes : array_like, shape (q,) or (m, q)
        Amplitude of each of the q components; 1-D gives a single channel.
    frequencies : array_like, broadcastable to the shape of ``amplitudes``
        Frequencies in Hz, >= 0.
    phases : array_like, optional
        Phases in radians, broadcastable to the shape of ``amplitudes``; default 0.
    offset : float or array_like of shape (m,), optional
        Constant added to each channel; default 0.

    Raises
    ------
    DimensionError
        Shapes do not broadcast, or a frequency is negative.
    NonFiniteError
        An argument holds NaN or inf.

    Examples
    --------
    The input of the LuGre scenario, 0.7 sin(2π·0.5 t) + 0.25 sin(2π·1.3 t):

    >>> from thetahat.simulation.signals import Multisine
    >>> u = Multisine([0.7, 0.25], [0.5, 1.3])
    >>> u.dim
    1
    >>> u([0.0, 0.5]).round(6).tolist()
    [[0.0], [0.497746]]
    """

    amplitudes: FloatArray
    frequencies: FloatArray
    phases: FloatArray
    offset: FloatArray

    def __init__(self, amplitudes: ArrayLike, frequencies: ArrayLike,
                 phases: ArrayLike | None = None, offset: ArrayLike = 0.0) -> None:
        a = np.asarray(amplitudes, dtype=np.float64)
        if a.ndim not in (1, 2) or a.size == 0:
            raise DimensionError("amplitudes must have shape (q,) for one channel or (m, q) for "
                                 f"m channels, with q >= 1; got shape {a.shape}.")
        a2 = a.reshape(1, -1) if a.ndim == 1 else a
        try:
            f = np.broadcast_to(np.asarray(frequencies, dtype=np.float64), a2.shape)
            ph = np.broadcast_to(np.asarray(0.0 if phases is None else phases,
                                            dtype=np.float64), a2.shape)
            off = np.broadcast_to(np.asarray(offset, dtype=np.float64), (a2.shape[0],))
        except ValueError as exc:
            raise DimensionError(
                f"frequencies, phases and offset must broadcast to amplitudes of shape "
                f"{a.shape} (offset to ({a2.shape[0]},)); {exc}") from exc
        for name, arr in (("amplitudes", a2), ("frequencies", f), ("phases", ph),
                          ("offset", off)):
            check_finite(name, arr)
        if np.any(f < 0):
            raise DimensionError(f"frequencies must be >= 0 Hz; got {f.min()}. Use the phase "
                                 f"to flip the sign of a component.")
        object.__setattr__(self, "amplitudes", readonly(a2))
        object.__setattr__(self, "frequencies", readonly(f))
        object.__setattr__(self, "phases", readonly(ph))
        object.__setattr__(self, "offset", readonly(off))

    @property
    def dim(self) -> int:
        """m, the number of channels."""
        return int(self.amplitudes.shape[0])

    def _angle(self, t: ArrayLike) -> FloatArray:
        t_ = _as_times(t)
        return (2.0 * np.pi * self.frequencies) * t_[..., None, None] + self.phases

    def __call__(self, t: ArrayLike) -> FloatArray:
        """u(t); shape ``np.shape(t) + (m,)``."""
        return self.offset + np.sum(self.amplitudes * np.sin(self._angle(t)), axis=-1)

    def derivative(self, t: ArrayLike) -> FloatArray:
        """u̇(t) = Σ_j 2π f_ij a_ij cos(2π f_ij t + φ_ij); shape ``np.shape(t) + (m,)``."""
        w = 2.0 * np.pi * self.frequencies
        return np.sum(w * self.amplitudes * np.cos(self._angle(t)), axis=-1)

    def __repr__(self) -> str:
        return (f"Multisine(amplitudes={self.amplitudes.tolist()}, "
                f"frequencies={self.frequencies.tolist()}, phases={self.phases.tolist()}, "
                f"offset={self.offset.tolist()})")


@dataclass(frozen=True, slots=True, eq=False)
class Steps(Signal):
    """A piecewise-constant, right-continuous signal.

    ``u(t) = initial`` for ``t < times[0]`` and ``u(t) = values[i]`` for
    ``times[i] <= t < times[i + 1]``.

    Parameters
    ----------
    times : array_like, shape (q,)
        Strictly increasing switching times (s).
    values : array_like, shape (q,) or (q, m)
        Level after each switch; 1-D gives a single channel.
    initial : float or array_like of shape (m,), optional
        Level before ``times[0]``; default 0.

    Raises
    ------
    DimensionError
        Empty or decreasing ``times``, or ``values`` of the wrong length.
    NonFiniteError
        An argument holds NaN or inf.

    Examples
    --------
    >>> from thetahat.simulation.signals import Steps
    >>> u = Steps([1.0, 2.0], [0.5, -0.5])
    >>> u([0.0, 1.0, 1.5, 2.0, 9.0]).ravel().tolist()
    [0.0, 0.5, 0.5, -0.5, -0.5]
    """

    times: FloatArray
    values: FloatArray
    initial: FloatArray

    def __init__(self, times: ArrayLike, values: ArrayLike, initial: ArrayLike = 0.0) -> None:
        t = as_vector("times", times)
        if t.size == 0:
            raise DimensionError("times must hold at least one switching time; for a constant "
                                 "use Steps([0.0], [value]).")
        _strictly_increasing("times", t)
        v = np.asarray(values, dtype=np.float64)
        if v.ndim == 1:
            v = v.reshape(-1, 1)
        if v.ndim != 2 or v.shape[0] != t.size:
            raise DimensionError(f"values must have shape ({t.size},) or ({t.size}, m), one "
                                 f"level per switching time; got shape {np.shape(values)}.")
        check_finite("values", v)
        try:
            init = np.broadcast_to(np.asarray(initial, dtype=np.float64), (v.shape[1],))
        except ValueError as exc:
            raise DimensionError(f"initial must be a scalar or have shape ({v.shape[1]},); "
                                 f"got shape {np.shape(initial)}.") from exc
        check_finite("initial", init)
        object.__setattr__(self, "times", readonly(t))
        object.__setattr__(self, "values", readonly(v))
        object.__setattr__(self, "initial", readonly(init))

    @property
    def dim(self) -> int:
        """m, the number of channels."""
        return int(self.values.shape[1])

    @property
    def breakpoints(self) -> tuple[float, ...]:
        """The switching times."""
        return tuple(float(s) for s in self.times)

    def __call__(self, t: ArrayLike) -> FloatArray:
        """u(t); shape ``np.shape(t) + (m,)``."""
        idx = np.searchsorted(self.times, _as_times(t), side="right")
        return np.vstack([self.initial, self.values])[idx]

    def derivative(self, t: ArrayLike) -> FloatArray:
        """u̇(t) = 0 (the jumps are reported by :attr:`breakpoints`)."""
        return np.zeros(np.shape(_as_times(t)) + (self.dim,))

    def __repr__(self) -> str:
        return (f"Steps(times={self.times.tolist()}, values={self.values.tolist()}, "
                f"initial={self.initial.tolist()})")


@dataclass(frozen=True, slots=True, eq=False)
class FromArray(Signal):
    """A signal given by samples, held (``"zoh"``) or linearly interpolated (``"foh"``).

    Outside ``[t[0], t[-1]]`` the first and last samples are held.

    Parameters
    ----------
    t : array_like, shape (N,)
        Strictly increasing sample times (s).
    values : array_like, shape (N,) or (N, m)
        Samples; 1-D gives a single channel.
    hold : {"zoh", "foh"}, optional
        Zero-order hold (piecewise constant, right-continuous) or first-order hold
        (piecewise linear). Default ``"zoh"``.

    Raises
    ------
    DimensionError
        Shapes disagree, ``t`` is not strictly increasing, or ``hold`` is unknown.
    NonFiniteError
        ``t`` or ``values`` holds NaN or inf.

    Examples
    --------
    >>> from thetahat.simulation.signals import FromArray
    >>> FromArray([0.0, 1.0], [0.0, 2.0], hold="foh")([0.25, 5.0]).ravel().tolist()
    [0.5, 2.0]
    >>> FromArray([0.0, 1.0], [0.0, 2.0])([0.25, 1.0]).ravel().tolist()
    [0.0, 2.0]
    """

    t: FloatArray
    values: FloatArray
    hold: Literal["zoh", "foh"]

    def __init__(self, t: ArrayLike, values: ArrayLike,
                 hold: Literal["zoh", "foh"] = "zoh") -> None:
        t_ = as_vector("t", t)
        if t_.size == 0:
            raise DimensionError("t must hold at least one sample time.")
        _strictly_increasing("t", t_)
        v = np.asarray(values, dtype=np.float64)
        if v.ndim == 1:
            v = v.reshape(-1, 1)
        if v.ndim != 2 or v.shape[0] != t_.size:
            raise DimensionError(f"values must have shape ({t_.size},) or ({t_.size}, m), one "
                                 f"row per sample time; got shape {np.shape(values)}.")
        check_finite("values", v)
        if hold not in ("zoh", "foh"):
            raise DimensionError(f"hold must be 'zoh' or 'foh'; got {hold!r}.")
        object.__setattr__(self, "t", readonly(t_))
        object.__setattr__(self, "values", readonly(v))
        object.__setattr__(self, "hold", hold)

    @property
    def dim(self) -> int:
        """m, the number of channels."""
        return int(self.values.shape[1])

    @property
    def breakpoints(self) -> tuple[float, ...]:
        """The sample times after the first: jumps of ``"zoh"``, kinks of ``"foh"``."""
        return tuple(float(s) for s in self.t[1:])

    def _segment(self, t: ArrayLike) -> tuple[FloatArray, NDArray[np.intp]]:
        tq = _as_times(t)
        idx = np.clip(np.searchsorted(self.t, tq, side="right") - 1, 0, self.t.size - 1)
        return tq, idx

    def __call__(self, t: ArrayLike) -> FloatArray:
        """u(t); shape ``np.shape(t) + (m,)``."""
        tq, idx = self._segment(t)
        if self.hold == "zoh" or self.t.size == 1:
            return self.values[idx]
        i = np.minimum(idx, self.t.size - 2)
        w = np.clip((tq - self.t[i]) / (self.t[i + 1] - self.t[i]), 0.0, 1.0)[..., None]
        return (1.0 - w) * self.values[i] + w * self.values[i + 1]

    def derivative(self, t: ArrayLike) -> FloatArray:
        """u̇(t): 0 for ``"zoh"``; the slope of the current segment for ``"foh"``."""
        tq, idx = self._segment(t)
        out = np.zeros(np.shape(tq) + (self.dim,))
        if self.hold == "zoh" or self.t.size == 1:
            return out
        slopes = np.diff(self.values, axis=0) / np.diff(self.t)[:, None]
        inside = (tq >= self.t[0]) & (tq < self.t[-1])
        out[inside] = slopes[np.minimum(idx, self.t.size - 2)][inside]
        return out

    def __repr__(self) -> str:
        return (f"FromArray(N={self.t.size}, m={self.dim}, t=[{self.t[0]}, {self.t[-1]}], "
                f"hold={self.hold!r})")

