"""The noise level from the data: past the second difference when the signal is still in it."""

from __future__ import annotations

import math

import numpy as np

from thetahat.estimation.statistical.noise_level import estimate_noise_std


def test_few_samples_per_period_do_not_inflate_sigma():
    """A 131 Hz sine sampled at 10 kHz (76 samples per period, the actuator's coil current):
    its second difference has amplitude 1.5 (ωh)² = 0.010, ten times σ = 1e-3, so the second
    difference alone reads σ several times too large; the estimate stays within 5 % of σ
    (5000 samples: the MAD's relative standard error is ≈ 1.2 %)."""
    rng = np.random.default_rng(3)
    t = np.arange(5000) * 1e-4
    clean = 1.5 * np.sin(2 * math.pi * 131.0 * t)
    d2 = np.diff(clean, n=2)
    assert np.median(np.abs(d2)) / (0.6745 * math.sqrt(6.0)) > 3e-3      # the signal is there
    y = clean + 1e-3 * rng.standard_normal(t.size)
    assert abs(estimate_noise_std(y)[0] / 1e-3 - 1.0) < 0.05


def test_white_noise_keeps_the_second_difference():
    """Pure noise: the higher differences do not fall beyond their scatter, so σ̂ is the
    second difference's (the same number as before the higher orders were tried)."""
    rng = np.random.default_rng(4)
    e = 0.02 * rng.standard_normal((3000, 2))
    d = np.diff(e, n=2, axis=0)
    second = np.median(np.abs(d), axis=0) / (0.6745 * math.sqrt(6.0))
    assert np.allclose(estimate_noise_std(e), second, rtol=1e-4)


def test_mad_variance_scatter_is_the_stated_one():
    """MAD_VARIANCE_SD = 2.33 (the median's asymptotic variance): over 1 000 draws of 10⁴ unit
    normals, sd(mad_variance)·√N is within 10 % of it (the sd of 1 000 draws has a relative
    standard error of 2.2 %: 10 % is 4.5 of them), and the mean is 1 within 4 of its standard
    errors."""
    from thetahat.estimation.statistical.noise_level import MAD_VARIANCE_SD, mad_variance
    rng = np.random.default_rng(7)
    N, draws = 10_000, 1000
    s = np.array([mad_variance(rng.standard_normal(N)) for _ in range(draws)])
    assert abs(s.std() * np.sqrt(N) / MAD_VARIANCE_SD - 1.0) < 0.10
    assert abs(s.mean() - 1.0) < 4 * MAD_VARIANCE_SD / np.sqrt(N * draws)
