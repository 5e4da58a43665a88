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


def test_summary_says_not_settled_when_the_band_is_entered_at_the_end():
    """θ̂ that enters its 1 % band only in the record's last quarter has not settled (the
    issue: "settled at t = 29.996 of a 30 s record"); one inside it for the last half has."""
    import numpy as np
    from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics
    from thetahat.studies.metrics import estimate_summary
    t = np.linspace(0.0, 30.0, 3001)
    z = np.zeros((t.size, 1))
    drifting = (1.0 + t / 30.0)[:, None]                    # still moving at the end
    res = EstimateResult(t=t, x_hat=z, phi_hat=z, theta_hat=drifting,
                         skipped=np.zeros(t.size, bool), diagnostics=ObserverDiagnostics())
    line = estimate_summary(res, ["theta"]).splitlines()[1]
    assert line.startswith("NOT settled") and "only from t = 29.4" in line   # 1 % of 2
    early = np.where(t < 15.0, 1.0 + t / 15.0, 2.0)[:, None]
    res2 = EstimateResult(t=t, x_hat=z, phi_hat=z, theta_hat=early,
                          skipped=np.zeros(t.size, bool), diagnostics=ObserverDiagnostics())
    assert estimate_summary(res2, ["theta"]).splitlines()[1].startswith("settled (within 1 %")
