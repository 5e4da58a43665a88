"""Seeded measurement noise added to sampled outputs y (Sec. VIII B: "y corrupted by noise").

Every draw comes from a :class:`numpy.random.Generator` built from an explicit seed by
:func:`make_rng`, so the same seed always gives the same data and there is no hidden global
random state. Noise models are frozen; :meth:`NoiseModel.sample` returns an ``(N, r)`` matrix,
one column per output.
"""

from __future__ import annotations

import numbers
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_vector, positive_scalar
from ..errors import ArgumentTypeError, DimensionError

__all__ = ["ColoredNoise", "NoiseModel", "WhiteNoise", "make_rng", "measurement_noise"]

FloatArray = NDArray[np.float64]
Seed = int | np.random.SeedSequence


def make_rng(seed: Seed) -> np.random.Generator:
    """The random generator behind every noise draw: ``numpy.random.default_rng(seed)``.

    Parameters
    ----------
    seed : int or numpy.random.SeedSequence
        A non-negative integer or a seed sequence (e.g. one child of ``SeedSequence.spawn``).

    Returns
    -------
    numpy.random.Generator

    Raises
    ------
    TypeError
        ``seed`` is not an integer or a SeedSequence (``None`` and Generators are refused:
        data must be reproducible from the seed alone).
    DimensionError
        ``seed`` is negative.

    Examples
    --------
    >>> from thetahat.simulation.noise import make_rng
    >>> bool(make_rng(3).normal() == make_rng(3).normal())
    True
    """
    if isinstance(seed, np.random.SeedSequence):
        return np.random.default_rng(seed)
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ArgumentTypeError(f"seed must be a non-negative int or a numpy SeedSequence; got "
                        f"{type(seed).__name__}. Pass an explicit seed so that runs are "
                        f"reproducible.")
    if int(seed) < 0:
        raise DimensionError(f"seed must be >= 0; got {int(seed)}.")
    return np.random.default_rng(int(seed))


def _std_vector(std: ArrayLike) -> FloatArray:
    s = as_vector("std", std)
    if s.size == 0 or np.any(s < 0):
        raise DimensionError(f"std must be one value or one per output, each >= 0; got "
                             f"{s.tolist()}.")
    s = s.copy()
    s.setflags(write=False)
    return s


def _std_for(std: FloatArray, n_outputs: int) -> FloatArray:
    if std.size not in (1, n_outputs):
        raise DimensionError(f"std has {std.size} entries but the system has r = {n_outputs} "
                             f"outputs; give one value for all outputs or one per output.")
    return np.broadcast_to(std, (n_outputs,))


def _check_counts(n_samples: int, n_outputs: int) -> None:
    if n_samples < 0 or n_outputs < 1:
        raise DimensionError(f"need n_samples >= 0 and n_outputs >= 1; got n_samples="
                             f"{n_samples}, n_outputs={n_outputs}.")


class NoiseModel(ABC):
    """Abstract additive measurement noise.

    Concrete models are final frozen dataclasses: combine them, do not subclass them.
    """

    __slots__ = ()

    @abstractmethod
    def sample(self, rng: np.random.Generator, n_samples: int, n_outputs: int,
               fs: float) -> FloatArray:
        """Draw an ``(n_samples, n_outputs)`` noise matrix for outputs sampled at ``fs`` Hz.

        Parameters
        ----------
        rng : numpy.random.Generator
            Source of randomness, from :func:`make_rng`.
        n_samples : int
            N, the number of samples (rows).
        n_outputs : int
            r, the number of outputs (columns).
        fs : float
            Sampling frequency (Hz), > 0.

        Returns
        -------
        ndarray, shape (n_samples, n_outputs)
        """


@dataclass(frozen=True, slots=True, eq=False)
class WhiteNoise(NoiseModel):
    """Zero-mean white Gaussian noise, independent between samples and outputs.

    Parameters
    ----------
    std : float or array_like of shape (r,)
        Standard deviation of each sample, for all outputs or per output; >= 0.

    Notes
    -----
    The standard deviation is per *sample*, whatever the sampling rate; the equivalent
    two-sided power spectral density is ``std**2 / fs``.

    Examples
    --------
    >>> from thetahat.simulation.noise import WhiteNoise, make_rng
    >>> e = WhiteNoise(0.02).sample(make_rng(0), 20001, 1, 1000.0)
    >>> e.shape, bool(abs(e.std() - 0.02) < 1e-3)
    ((20001, 1), True)
    """

    std: FloatArray

    def __init__(self, std: ArrayLike) -> None:
        object.__setattr__(self, "std", _std_vector(std))

    def sample(self, rng: np.random.Generator, n_samples: int, n_outputs: int,
               fs: float) -> FloatArray:
        """Draw an ``(n_samples, n_outputs)`` matrix of independent N(0, std²) samples."""
        _check_counts(n_samples, n_outputs)
        positive_scalar("fs", fs)
        s = _std_for(self.std, n_outputs)
        return rng.standard_normal((n_samples, n_outputs)) * s

    def __repr__(self) -> str:
        return f"WhiteNoise(std={self.std.tolist()})"


@dataclass(frozen=True, slots=True, eq=False)
class ColoredNoise(NoiseModel):
    """Band-limited (first-order Gauss–Markov) Gaussian noise with a given stationary std.

    Each output is white noise through a first-order low-pass filter with corner frequency
    ``bandwidth``, discretised exactly and started in its stationary distribution:
    ``e[0] ~ N(0, std²)``, ``e[k] = a e[k-1] + std·√(1 - a²)·w[k]`` with
    ``a = exp(-2π·bandwidth/fs)`` and ``w[k] ~ N(0, 1)``. Hence every sample has standard
    deviation ``std`` and the autocorrelation at lag k is ``a**k``.

    Parameters
    ----------
    std : float or array_like of shape (r,)
        Stationary standard deviation, for all outputs or per output; >= 0.
    bandwidth : float
        Corner frequency of the low-pass shaping filter (Hz), > 0.

    Examples
    --------
    >>> from thetahat.simulation.noise import ColoredNoise, make_rng
    >>> e = ColoredNoise(0.02, bandwidth=5.0).sample(make_rng(0), 20001, 1, 1000.0)
    >>> e.shape
    (20001, 1)
    """

    std: FloatArray
    bandwidth: float

    def __init__(self, std: ArrayLike, bandwidth: float) -> None:
        object.__setattr__(self, "std", _std_vector(std))
        object.__setattr__(self, "bandwidth", positive_scalar("bandwidth", bandwidth))

    def pole(self, fs: float) -> float:
        """The discrete pole ``a = exp(-2π·bandwidth/fs)`` (lag-1 autocorrelation)."""
        return float(np.exp(-2.0 * np.pi * self.bandwidth / positive_scalar("fs", fs)))

    def sample(self, rng: np.random.Generator, n_samples: int, n_outputs: int,
               fs: float) -> FloatArray:
        """Draw an ``(n_samples, n_outputs)`` stationary Gauss–Markov sequence."""
        _check_counts(n_samples, n_outputs)
        a = self.pole(fs)
        s = _std_for(self.std, n_outputs)
        w = rng.standard_normal((n_samples, n_outputs))
        if n_samples == 0:
            return w
        from scipy.signal import lfilter    # here: scipy.signal costs ~0.5 s to import (1.4 s
                                            # loaded) and only coloured noise needs it
        e0 = s * w[0]
        rest = lfilter([np.sqrt(1.0 - a * a)], [1.0, -a], w[1:] * s, axis=0,
                           zi=(a * e0)[None, :])[0]
        return np.vstack([e0[None, :], rest])

    def __repr__(self) -> str:
        return f"ColoredNoise(std={self.std.tolist()}, bandwidth={self.bandwidth})"


def measurement_noise(noise: NoiseModel, *, n_samples: int, n_outputs: int, fs: float,
                      seed: Seed) -> FloatArray:
    """Draw ``noise`` for ``n_samples`` samples of ``n_outputs`` outputs from ``seed``.

    Parameters
    ----------
    noise : NoiseModel
    n_samples, n_outputs : int
    fs : float
        Sampling frequency (Hz).
    seed : int or numpy.random.SeedSequence
        Passed to :func:`make_rng`.

    Returns
    -------
    ndarray, shape (n_samples, n_outputs)

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.simulation.noise import WhiteNoise, measurement_noise
    >>> a = measurement_noise(WhiteNoise(0.1), n_samples=5, n_outputs=2, fs=100.0, seed=1)
    >>> b = measurement_noise(WhiteNoise(0.1), n_samples=5, n_outputs=2, fs=100.0, seed=1)
    >>> a.shape, bool(np.array_equal(a, b))
    ((5, 2), True)
    """
    if not isinstance(noise, NoiseModel):
        raise ArgumentTypeError(f"noise must be a thetahat NoiseModel (WhiteNoise, ColoredNoise); got "
                        f"{type(noise).__name__}.")
    return noise.sample(make_rng(seed), n_samples, n_outputs, fs)
