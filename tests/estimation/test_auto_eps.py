"""eps = "auto": ε from the record's one-step prediction error (estimation.observer.auto_eps).

Evidence, each against an independent computation:
- the range follows its two definitions (Nyquist rate, fifty time constants in the record);
- the prediction of a linear system from its true states is the exact solution of the ODE
  (scipy's ``solve_ivp`` at tight tolerances) for a held and for a linearly interpolated input,
  so the criterion of a perfect observer is the measurement noise's variance, whatever the
  sample spacing (jittered times included);
- the criterion is invariant to the outputs' units up to the constant 2 r log c;
- the scan finds the minimum of a known criterion between its grid points, and of equal
  values takes the largest ε;
- on shipped models, the chosen ε estimates φ nearly as well as the best ε in hindsight
  (against the simulated true φ).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from thetahat.errors import DesignError
from thetahat.estimation.observer.auto_eps import (EPS_MAX, SETTLING_TIME_CONSTANTS,
                                                   choose_eps, eps_bounds, prediction_cost)

#: The sample variance of 1000 Gaussian errors is within 3 of its standard errors
#: (√(2/1000) ≈ 4.5 %) of σ²: 13.4 % relative, log(1.134) ≈ 0.126 in J.
NOISE_LOG_TOL = 0.13
#: solve_ivp at rtol 1e-11 against the matrix exponential: agreement to ~1e-9 of the state's
#: scale; the predicted samples' errors must be far below the noise (1e-3) for J to be it.
EXACT_ATOL = 1e-7


def _mass_spring(seed: int, jitter: float):
    """A damped mass–spring with a known force φ(t), sampled at jittered instants."""
    A = np.array([[0.0, 1.0], [-4.0, -0.4]])
    B = np.array([[0.0], [1.0]])
    E = np.array([[0.0], [0.5]])
    C = np.array([[1.0, 0.0]])
    rng = np.random.default_rng(seed)
    N, dt = 1000, 0.01
    t = np.cumsum(np.full(N, dt) * (1.0 + jitter * rng.uniform(-1, 1, N)))
    t -= t[0]
    return A, B, E, C, t, rng


def _simulate(A, B, E, t, u_of_t, phi_samples):
    """x at the samples, with φ held between samples and u = u_of_t(t) (an ODE solver)."""
    x = np.zeros((t.size, 2))
    x[0] = [1.0, 0.0]
    for k in range(t.size - 1):
        f = phi_samples[k]
        sol = solve_ivp(lambda s, z: A @ z + B[:, 0] * u_of_t(s) + E[:, 0] * f,
                        (t[k], t[k + 1]), x[k], rtol=1e-11, atol=1e-13)
        x[k + 1] = sol.y[:, -1]
    return x


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_a_perfect_observer_predicts_to_the_measurement_noise(hold):
    A, B, E, C, t, rng = _mass_spring(0, jitter=0.3)
    u_samples = np.sin(3.0 * t) + 0.5 * np.cos(7.0 * t)
    if hold == "zoh":
        def u_of_t(s):
            return u_samples[max(0, np.searchsorted(t, s, side="right") - 1)]
    else:
        def u_of_t(s):
            return np.interp(s, t, u_samples)
    phi = 0.3 * np.sign(np.sin(0.5 * t))
    x = _simulate(A, B, E, t, u_of_t, phi)
    sigma = 1e-3
    y = x @ C.T + sigma * rng.standard_normal((t.size, 1))
    J = prediction_cost(A, B, E, C, t, u_samples[:, None], y, x, phi[:, None], hold=hold)
    assert abs(J - math.log(sigma ** 2)) < NOISE_LOG_TOL
    # the prediction itself is exact: noise-free samples are predicted to the solver's error
    J0 = prediction_cost(A, B, E, C, t, u_samples[:, None], x @ C.T, x, phi[:, None],
                         hold=hold)
    assert J0 < 2 * math.log(EXACT_ATOL)
    # and it is the hold that makes it exact: the other one is off by far more
    other = "foh" if hold == "zoh" else "zoh"
    J_other = prediction_cost(A, B, E, C, t, u_samples[:, None], x @ C.T, x, phi[:, None],
                              hold=other)
    assert J_other > J0 + 10.0


def test_the_criterion_is_invariant_to_the_outputs_units():
    A, B, E, C, t, rng = _mass_spring(1, jitter=0.0)
    x = np.column_stack([np.sin(t), np.cos(t)])          # not the system's states: any x̂
    y = x[:, :1] + 0.01 * rng.standard_normal((t.size, 1))
    phi = np.zeros((t.size, 1))
    J = prediction_cost(A, B, E, C, t, None if B.size == 0 else np.zeros((t.size, 1)), y, x,
                        phi)
    c = 1000.0
    Jc = prediction_cost(A, B, E, c * C, t, np.zeros((t.size, 1)), c * y, x, phi)
    assert Jc - J == pytest.approx(2 * math.log(c), abs=1e-9)


def test_missing_samples_and_non_finite_estimates():
    A, B, E, C, t, rng = _mass_spring(2, jitter=0.0)
    x = np.zeros((t.size, 2))
    y = 0.01 * rng.standard_normal((t.size, 1))
    phi = np.zeros((t.size, 1))
    J = prediction_cost(A, B, E, C, t, np.zeros((t.size, 1)), y, x, phi)
    y_gaps = y.copy()
    y_gaps[::7] = np.nan
    J_gaps = prediction_cost(A, B, E, C, t, np.zeros((t.size, 1)), y_gaps, x, phi)
    assert math.isfinite(J_gaps) and abs(J_gaps - J) < NOISE_LOG_TOL
    x_bad = x.copy()
    x_bad[10, 0] = np.nan
    assert prediction_cost(A, B, E, C, t, np.zeros((t.size, 1)), y, x_bad, phi) == math.inf


def test_bounds_follow_the_nyquist_rate_and_the_records_duration():
    poles = [1.0, 2.0, 5.0]
    lo, hi = eps_bounds(poles, dt=0.002, duration=40.0)
    assert 5.0 / lo == pytest.approx(math.pi / 0.002)          # fastest pole at Nyquist
    assert hi / 1.0 == pytest.approx(40.0 / SETTLING_TIME_CONSTANTS)  # slowest: T/50 time const.
    lo, hi = eps_bounds(poles, dt=0.1, duration=1.0)        # a record too short for both
    assert hi == lo
    lo, hi = eps_bounds(poles, dt=0.01, duration=1e4)       # the paper's ε ≤ 1
    assert hi == EPS_MAX and lo < hi
    lo, hi = eps_bounds(poles, dt=10.0, duration=1e5)       # poles beyond Nyquist even at 1
    assert lo == hi == EPS_MAX
    with pytest.raises(DesignError, match="chain poles"):
        eps_bounds([], dt=0.1, duration=1.0)
    with pytest.raises(DesignError, match="positive sample interval"):
        eps_bounds(poles, dt=0.0, duration=1.0)


def test_the_scan_finds_the_least_criterion_and_prefers_the_larger_of_equal_ones():
    # a minimum between grid points (10^-2.3): the refinement reaches it to a factor 10^(1/8)
    def J(e):
        return (math.log10(e) + 2.3) ** 2

    choice = choose_eps(J, (1e-5, 1.0))
    assert abs(math.log10(choice.eps) + 2.3) <= 1 / 16 + 1e-12
    assert choice.eps == min(dict(choice.scanned), key=J)
    assert not choice.at_edge and "tried" in repr(choice)
    # a plateau below ε = 1e-2 (a high-gain observer that follows the samples): of the
    # equal values, the largest ε
    flat = choose_eps(lambda e: max(math.log10(e) + 2.0, 0.0), (1e-5, 1.0))
    plateau = [e for e, v in flat.scanned if v == 0.0]
    assert flat.eps == max(plateau) and flat.eps <= 1e-2 + 1e-15


def test_the_scan_says_when_every_run_failed():
    with pytest.raises(DesignError, match="every ε"):
        choose_eps(lambda e: math.inf, (1e-3, 1.0))
    # the runs that failed are skipped, and an optimum at the range's end is reported
    choice = choose_eps(lambda e: math.inf if e > 0.1 else math.log(e), (1e-3, 1.0))
    assert choice.eps == pytest.approx(1e-3) and choice.at_edge
