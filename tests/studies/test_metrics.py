"""Settling time, RMSE and divergence helpers."""

import numpy as np
import pytest

from thetahat.errors import DimensionError

from thetahat.studies.metrics import diverged, rmse, time_to_within


def test_time_to_within_is_the_last_entry_into_the_band():
    t = np.arange(6.0)
    est = [2.0, 1.0, 1.5, 1.005, 0.995, 1.0]   # inside at t=1, leaves, re-enters at t=3
    assert time_to_within(t, est, 1.0, 0.01) == 3.0
    assert time_to_within(t, est, 1.0, 1.5) == 0.0
    assert time_to_within(t[:3], [1.0, 1.0, 2.0], 1.0, 0.01) == np.inf
    with pytest.raises(DimensionError, match="3 samples but t has 6"):
        time_to_within(t, [1.0, 1.0, 2.0], 1.0, 0.01)


def test_time_to_within_vector_parameter():
    t = np.arange(3.0)
    est = np.array([[1.0, 2.0], [1.0, 2.5], [1.0, 2.0]])
    assert time_to_within(t, est, [1.0, 2.0], 0.01) == 2.0


def test_rmse_and_divergence():
    np.testing.assert_allclose(rmse([[3.0], [4.0]], [[0.0], [0.0]]), [np.sqrt(12.5)])
    np.testing.assert_allclose(rmse([[3.0], [4.0]], [[0.0], [0.0]], start=1), [4.0])
    assert diverged([1.0, np.nan], 1.0)
    assert diverged([1.0, 5e3], 1.0)
    assert not diverged([1.0, 2.0], 1.0)
