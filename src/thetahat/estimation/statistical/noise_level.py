"""The measurement-noise level estimated from the data: no covariance for the user to tune.

For a smooth output sampled fast, the second difference d_k = y_{k+1} − 2 y_k + y_{k−1} of
white noise e_k with standard deviation σ has variance 6 σ², while the signal contributes only
h² ÿ. The median of |d_k| (the median absolute deviation, robust to the few samples where the
signal changes abruptly, e.g. at the velocity reversals of a friction model) estimates it:
σ̂ = median|d| / (0.6745 √6), 0.6745 = Φ⁻¹(3/4) being the MAD of a unit normal.

"Sampled fast" is checked on the data, not assumed: a process sampled at only a few samples
per time constant (a coil's current at 10 kHz) leaves h² ÿ comparable with σ, and the second
difference overstates σ. The o-th difference has noise variance C(2o, o) σ² and signal
h^o y^(o), which falls geometrically with o for a smooth output; so σ̂_o is computed for
o = 2, 3, … and the first o is taken after which σ̂ no longer falls by more than its own
scatter (2/√M relative, M the number of differences), up to :data:`MAX_ORDER`.

What it may import: NumPy and the package's errors; nothing of the estimation wing (every
statistical estimator imports it).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import DimensionError

__all__ = ["estimate_noise_std", "mad_variance", "MIN_SAMPLES", "MAX_ORDER", "MAD_VARIANCE_SD"]

#: Fewest samples from which σ̂ is computed (10 second differences).
MIN_SAMPLES = 12
#: Highest order of the differences tried (the signal of a smooth output at a few samples per
#: time constant is gone by then; higher orders only add scatter).
MAX_ORDER = 5
_MAD_NORMAL = 0.6744897501960817
#: Standard deviation × √N of :func:`mad_variance` on N unit-normal samples: the sample median
#: of |v| has asymptotic sd 1/(2 f(m) √N), f the half-normal density at its median m = 0.6745,
#: i.e. 1.166 m/√N; squaring doubles the relative spread: 2.33
#: (tests/estimation/test_noise_level.py measures it).
MAD_VARIANCE_SD = 2.33


def mad_variance(v: Any) -> float:
    """The variance of ``v``'s Gaussian core: (median|v| / 0.6745)² (NaN samples ignored).

    Unlike the mean of v², a burst of outliers (a few per cent of the samples) moves it by
    only a few per cent; for N unit-normal samples it is 1 ± :data:`MAD_VARIANCE_SD`/√N.

    Parameters
    ----------
    v : array_like
        Samples (e.g. normalised innovations), any shape.

    Returns
    -------
    float
        NaN when no sample is finite.

    Examples
    --------
    >>> import numpy as np
    >>> v = np.random.default_rng(0).standard_normal(10_000)
    >>> v[:200] = 50.0                       # 2 % of the samples in a burst
    >>> bool(abs(mad_variance(v) - 1.0) < 0.1), bool(np.mean(v * v) > 40)
    (True, True)
    """
    a = np.abs(np.asarray(v, dtype=np.float64).ravel())
    a = a[np.isfinite(a)]
    return float(np.median(a) / _MAD_NORMAL) ** 2 if a.size else math.nan


def _sigma_of_order(y: NDArray[np.float64], order: int) -> tuple[float, int]:
    """(σ̂ from the order-th differences of one channel, the number of finite differences)."""
    d = np.diff(y, n=order)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return math.nan, 0
    return (float(np.median(np.abs(d))) / (_MAD_NORMAL * math.sqrt(math.comb(2 * order, order))),
            int(d.size))


def estimate_noise_std(y: Any) -> NDArray[np.float64]:
    """σ̂ per output channel from the differences of y (median absolute deviation).

    The second differences, or higher ones where the data show the signal still in them
    (see the module docstring).

    Parameters
    ----------
    y : array_like, shape (N,) or (N, r)
        Output samples at a constant rate; NaN samples are ignored.

    Returns
    -------
    ndarray, shape (r,)
        σ̂ per channel (0 for noise-free, piecewise-linear data).

    Raises
    ------
    DimensionError
        Fewer than :data:`MIN_SAMPLES` samples.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.noise_level import estimate_noise_std
    >>> rng = np.random.default_rng(0)
    >>> t = np.arange(4000) * 1e-3
    >>> y = np.sin(2 * np.pi * t) + 0.02 * rng.standard_normal(t.size)
    >>> bool(abs(estimate_noise_std(y)[0] / 0.02 - 1) < 0.05)
    True
    """
    Y = np.asarray(y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    if Y.ndim != 2 or Y.shape[0] < MIN_SAMPLES:
        raise DimensionError(f"the output noise level σ is estimated from y of shape (N, r) "
                             f"with N >= {MIN_SAMPLES}; got {np.shape(y)}: give σ (noise_std=σ "
                             f"in Python; thetahat estimate --noise-std σ), or use a record of "
                             f"at least {MIN_SAMPLES} samples.")
    out = np.empty(Y.shape[1])
    for j in range(Y.shape[1]):
        sigma, M = _sigma_of_order(Y[:, j], 2)
        for order in range(3, MAX_ORDER + 1):
            nxt, M_next = _sigma_of_order(Y[:, j], order)
            if not (M_next > 0 and nxt < sigma * (1.0 - 2.0 / math.sqrt(M))):
                break                           # no longer falling beyond its scatter
            sigma, M = nxt, M_next
        out[j] = sigma
    return out
