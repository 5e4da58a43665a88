"""Assumption 1 in one call: report, readable text, strict errors naming the zeros."""

import numpy as np
import pytest

from thetahat import NotLeftInvertibleError, NotMinimumPhaseError, check_assumption_1


def test_dc_motor_holds(dc_motor):
    A, _, E, C = dc_motor.linear()
    rep = check_assumption_1(A, E, C, strict=True)
    assert rep.holds and rep.left_invertible and rep.minimum_phase
    np.testing.assert_allclose(rep.zeros.real, [-dc_motor.sigma0 / dc_motor.sigma1], rtol=1e-9)
    text = str(rep)
    assert "holds" in text and "-433.333" in text


def test_non_minimum_phase_is_reported_and_strict_raises():
    # G(s) = (s − 2)/(s^2 + 3s + 2): zero at +2
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    E = np.array([[0.0], [1.0]])
    C = np.array([[-2.0, 1.0]])
    rep = check_assumption_1(A, E, C)
    assert rep.left_invertible and not rep.minimum_phase and not rep.holds
    np.testing.assert_allclose(rep.offending_zeros, [2.0], atol=1e-10)
    assert "offending zeros : 2" in str(rep)
    with pytest.raises(NotMinimumPhaseError, match="zero\\(s\\) 2") as info:
        check_assumption_1(A, E, C, strict=True)
    np.testing.assert_allclose(info.value.zeros, [2.0], atol=1e-10)


def test_zero_at_origin_fails_minimum_phase():
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    rep = check_assumption_1(A, [[0.0], [1.0]], [[0.0, 1.0]])
    assert not rep.minimum_phase and rep.offending_zeros.size == 1


def test_not_left_invertible_strict_raises():
    # two perturbation channels, one output: cannot be left-invertible
    A = np.diag([-1.0, -2.0])
    rep = check_assumption_1(A, np.eye(2), [[1.0, 1.0]])
    assert not rep.left_invertible and rep.normal_rank < 4
    with pytest.raises(NotLeftInvertibleError, match="normal rank"):
        check_assumption_1(A, np.eye(2), [[1.0, 1.0]], strict=True)
