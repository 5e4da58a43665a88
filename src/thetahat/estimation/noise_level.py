"""The measurement-noise level estimated from the data: no covariance for the user to tune.

For a smooth output sampled fast, the second difference d_k = y_{k+1} − 2 y_k + y_{k−1} of
white noise e_k with standard deviation σ has variance 6 σ², while the signal contributes only
h² ÿ. The median of |d_k| (the median absolute deviation, robust to the few samples where the
signal changes abruptly, e.g. at the velocity reversals of a friction model) estimates it:
σ̂ = median|d| / (0.6745 √6), 0.6745 = Φ⁻¹(3/4) being the MAD of a unit normal.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import DimensionError

__all__ = ["estimate_noise_std", "MIN_SAMPLES"]

#: Fewest samples from which σ̂ is computed (10 second differences).
MIN_SAMPLES = 12
_MAD_NORMAL = 0.6744897501960817


def estimate_noise_std(y: Any) -> NDArray[np.float64]:
    """σ̂ per output channel from the second differences of y (median absolute deviation).

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
    >>> from thetahat.estimation.noise_level import estimate_noise_std
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
        raise DimensionError(f"estimate_noise_std needs y of shape (N, r) with N >= "
                             f"{MIN_SAMPLES}; got {np.shape(y)}. Pass noise_std explicitly "
                             "for shorter records.")
    d = Y[2:] - 2.0 * Y[1:-1] + Y[:-2]
    out = np.empty(Y.shape[1])
    for j in range(Y.shape[1]):
        dj = d[np.isfinite(d[:, j]), j]
        out[j] = np.median(np.abs(dj)) / (_MAD_NORMAL * np.sqrt(6.0)) if dj.size else np.nan
    return out
