"""The EMPS benchmark (issue 19): the shipped record and the benchmark's own validation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from thetahat.errors import ModelFileError, ParameterSetError
from thetahat.models import emps

#: The description's eq. (11) errors of the published θ come from its Simulink model, whose
#: solver and handling of sign(0) are not published. Our loop integrates the plant exactly
#: between samples, so its position and velocity errors may only be smaller than Simulink's
#: (we measure 0.0012 % and 0.164 % against 0.0138 % and 0.229 %). The force error is dominated
#: by the measured force's ripple, which no rigid-body model reproduces: we measure 5.30 %
#: against 5.85 %; 15 % relative leaves a margin of 1.5x over that 9 % gap.
FORCE_REL = 0.15
#: A wrong mass by 10 % must be visible: it raises the force error by more than half
#: (measured: 5.3 % -> 9.8 %).
SENSITIVITY = 1.5
#: solve_ivp at rtol 1e-10 against the exact interval solution: both are exact to ~1e-10 of
#: the position's scale (0.2 m); 1e-8 m leaves two decades.
INTEGRATOR_ATOL = 1e-8


@pytest.fixture(scope="module")
def record() -> emps.EmpsRecord:
    return emps.load()


def test_record_shape_and_rate(record):
    assert record.t.shape == (24841,) and record.u.shape == record.y.shape == (24841, 1)
    steps = np.diff(record.t)
    assert abs(np.median(steps) - 1e-3) < 1e-7 and np.all(steps > 0)  # 1 kHz, logged times
    assert 24.8 < record.t[-1] < 24.9
    assert not record.u.flags.writeable


def test_published_table():
    assert emps.PUBLISHED.names == ("M", "Fv", "Fc", "offset")
    rel = emps.PUBLISHED.sigma / np.abs(emps.PUBLISHED.value)
    # The description prints σ to 4 decimals: the offset's 0.0444 ± 0.00005 moves its ratio
    # by ± 0.0016 %; 2e-3 % covers that rounding.
    np.testing.assert_allclose(rel * 100, [0.1141, 0.5631, 0.4964, 1.4021], atol=2e-3)


def test_validation_reproduces_the_published_figures(record):
    check = emps.validate(emps.PUBLISHED.value, record)
    pub = emps.PUBLISHED_VALIDATION
    assert check.position <= pub["position"]
    assert check.velocity <= pub["velocity"]
    assert abs(check.force - pub["force"]) <= FORCE_REL * pub["force"]
    assert "published IDIM-LS" in check.table()


def test_validation_discriminates(record):
    good = emps.validate(emps.PUBLISHED.value, record).force
    for factor in (0.9, 1.1):
        theta = emps.PUBLISHED.value * np.array([factor, 1, 1, 1])
        assert emps.validate(theta, record).force > SENSITIVITY * good


def test_closed_loop_agrees_with_scipy_integrator(record):
    """Without Coulomb friction the plant is linear: integrate the same sampled-data loop with
    solve_ivp, sample by sample, as an independent check of the exact interval solution."""
    n = 1500
    short = dataclasses.replace(record, t=record.t[:n], u=record.u[:n], y=record.y[:n],
                                q_ref=record.q_ref[:n])
    M, Fv, offset = 95.0, 200.0, -3.0
    q_sim, nu_sim = emps.simulate_closed_loop([M, Fv, 0.0, offset], short)
    x = np.array([short.y[0, 0], 0.0])
    q_prev = q_f_prev = x[0]
    for k in range(n):
        assert abs(q_sim[k] - x[0]) < INTEGRATOR_ATOL
        q_f = 0.5 * (x[0] + q_prev)
        vel = (q_f - q_f_prev) / (short.t[k] - short.t[k - 1]) if k else 0.0
        nu = np.clip(emps.KP * emps.KV * (short.q_ref[k] - x[0]) - emps.KV * vel,
                     -emps.SATURATION, emps.SATURATION)
        assert nu == pytest.approx(nu_sim[k], abs=1e-6)
        q_prev, q_f_prev = x[0], q_f
        if k + 1 < n:
            tau = emps.G_TAU * nu
            sol = solve_ivp(lambda _t, s: [s[1], (tau - Fv * s[1] - offset) / M],
                            (short.t[k], short.t[k + 1]), x, rtol=1e-10, atol=1e-13)
            x = sol.y[:, -1]


def test_controller_velocity_is_a_delayed_central_difference():
    t = np.arange(6) * 1e-3
    q = t ** 2
    v = emps.controller_velocity(q, t)
    np.testing.assert_allclose(v[2:], (q[2:] - q[:-2]) / 2e-3, rtol=1e-12)


def test_bad_theta_and_missing_file(record, tmp_path):
    with pytest.raises(ParameterSetError, match="M > 0"):
        emps.validate([-1.0, 200.0, 20.0, 0.0], record)
    with pytest.raises(ModelFileError, match="not found"):
        emps.load(tmp_path / "none.mat")


def test_shipped_model_file():
    """examples/emps.toml: Assumption 1 holds; Θ at least the issue's box, holding the
    published θ; θ̂(0) not the answer: an estimator that does not move fails issue 19's
    acceptance (3 % on M, Fv, Fc; 0.5 N on the offset)."""
    from pathlib import Path

    from thetahat.modelfile import analyze_model, load_model

    spec = load_model(Path(__file__).resolve().parents[2] / "examples" / "emps.toml")
    assert analyze_model(spec).ok
    assert spec.parameter_names == emps.PUBLISHED.names
    box = spec.system.parameter_set
    assert np.all(box.lower <= [50, 50, 0, -20]) and np.all(box.upper >= [150, 400, 50, 20])
    assert box.contains(emps.PUBLISHED.value)
    start, published = spec.estimator.theta_hat0, emps.PUBLISHED.value
    relative = np.abs(start[:3] - published[:3]) / published[:3]
    assert np.any(relative > 0.03) and abs(start[3] - published[3]) > 0.5
    assert spec.data is not None and spec.data.u[0].column == "vir"
    assert spec.data.u[0].scale == emps.G_TAU
