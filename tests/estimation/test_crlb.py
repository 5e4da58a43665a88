"""thetahat.crlb: sensitivities against finite differences, and the bound against an EKF."""

from __future__ import annotations

import dataclasses
import numpy as np
import pytest

from thetahat import DimensionError, crlb
from thetahat.estimation.statistical.ekf import JointEKF
from thetahat.models import lugre

P = lugre.LuGreParameters()
#: Relative agreement of ∂ω/∂θ with central differences of the independent plant simulation
#: (lugre.simulate: analytic input, true |ω|): the bound sees u linear between 1 kHz samples
#: (relative effect ~3e-4 measured) and the differences have O(δθ²) truncation error
#: (~1e-4 at δθ = 1e-4 θ); 2e-3 leaves a margin of ~4. The bound's sensitivities are those of
#: the sampled-data map the estimators use (RK4 sub-steps, exact Jacobians of the map): they
#: converge to the continuous ones as the sub-steps grow, slowly where ω crosses zero (RK4
#: across the kink of |ω| loses its order): measured 1.8e-2 with the default choice (which
#: controls the output's error, a tenth of σ, not the sensitivity's), 2.3e-3 at 16, 1.1e-3
#: at 64, 6e-4 at SENSITIVITY_SUBSTEPS = 128 (the comparison runs there; margin ~3).
SENSITIVITY_RTOL = 2e-3
SENSITIVITY_SUBSTEPS = 128
#: The bound itself is insensitive to that: its final sd with the default sub-steps and with
#: 128 agree to 1e-5 measured; 1e-3 relative leaves a margin of 100.
BOUND_SUBSTEPS_RTOL = 1e-3
#: √(P_θθ of an EKF with the exact model, x(0) known, θ at its true value) ÷ √CRLB: the EKF
#: propagates the inverse information of the linearised problem; its RK4 map and the noisy
#: linearisation points differ from the bound's noise-free trajectory by ~0.3 % at 1 s.
EKF_RATIO_TOL = 0.02


@pytest.fixture(scope="module")
def record():
    return lugre.simulate(seed=0, t_end=1.0)


@pytest.fixture(scope="module")
def bound(record):
    return crlb(lugre.system(), record.t, record.u, theta=[P.alpha0], noise_std=0.02)


def test_sensitivity_matches_central_differences_of_the_plant(record, bound):
    d = 1e-4 * P.alpha0

    def omega(theta):
        p = dataclasses.replace(P, alpha0=theta)
        return lugre.simulate(0, t_end=1.0, noise_std=0.0, params=p).y_clean[:, 0]

    s_fd = (omega(P.alpha0 + d) - omega(P.alpha0 - d)) / (2 * d)
    fine = crlb(lugre.system(), record.t, record.u, theta=[P.alpha0], noise_std=0.02,
                substeps=SENSITIVITY_SUBSTEPS)
    s = fine.sensitivity[:, 0, 0]
    assert np.max(np.abs(s - s_fd)) < SENSITIVITY_RTOL * np.max(np.abs(s_fd))
    assert bound.std[-1, 0] == pytest.approx(fine.std[-1, 0], rel=BOUND_SUBSTEPS_RTOL)


def test_bound_shrinks_and_unknown_x0_costs_information(record, bound):
    sd = bound.std[:, 0]
    finite = np.isfinite(sd)
    assert finite[-1] and np.all(np.diff(sd[finite]) <= 1e-15)
    unknown = crlb(lugre.system(), record.t, record.u, theta=[P.alpha0], noise_std=0.02,
                   x0_known=False)
    assert np.all(unknown.std[finite, 0] >= sd[finite] * (1 - 1e-9))
    assert not unknown.x0_known and unknown.sensitivity.shape == (record.t.size, 1, 3)


def test_bound_scales_with_the_noise_level(record, bound):
    half = crlb(lugre.system(), record.t, record.u, theta=[P.alpha0], noise_std=0.01)
    assert half.std[-1, 0] == pytest.approx(0.5 * bound.std[-1, 0], rel=1e-9)


def test_bound_equals_the_covariance_of_an_exact_ekf(record, bound):
    ekf = JointEKF(system=lugre.system(), noise_std=0.02, compiled=False)
    st = ekf.init(x_hat0=[0.0, 0.0], theta_hat0=[P.alpha0])
    P0 = st.P.copy()
    P0[0, 0] = P0[1, 1] = 1e-18                  # x(0) known
    res = ekf.run(record.t, record.u, record.y, state0=dataclasses.replace(st, P=P0))
    sd = res.diagnostics.theta_sd
    assert sd[-1, 0] / bound.std[-1, 0] == pytest.approx(1.0, abs=EKF_RATIO_TOL)
    assert bound.time_to(0.01, [P.alpha0]) < 1.0


def test_bad_noise_level_is_refused(record):
    with pytest.raises(DimensionError, match="noise_std"):
        crlb(lugre.system(), record.t, record.u, theta=[P.alpha0], noise_std=0.0)


def test_bound_does_not_depend_on_the_units_of_theta():
    """The same model with θ in units 10⁶ times larger (g reads θ·10⁶): the bound is the
    first's × 10⁻¹² to rounding, at every sample where the first is finite, x(0) unknown.
    The singularity test used to read the raw information matrix, whose eigenvalues then
    span 10¹² more: every row of the rescaled model was declared singular (inf), as were the
    shipped Silverbox and CSTR scenarios (a mass of 5e-6 beside a stiffness of 4)."""
    from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    scaled_text = (EXAMPLE_MODEL.replace('"(2 + sin(y))*(theta + theta**3/3)"',
                                         '"(2 + sin(y))*(1e6*theta + (1e6*theta)**3/3)"')
                   .replace("lower = [-2.0]", "lower = [-2e-6]")
                   .replace("upper = [2.0]", "upper = [2e-6]"))
    plain, scaled = loads_model(EXAMPLE_MODEL).system, loads_model(scaled_text).system
    t = np.arange(0.0, 20.0, 0.01)
    u = (np.sin(t) + 0.5 * np.sin(3.1 * t))[:, None]
    a = crlb(plain, t, u, theta=[0.7], noise_std=0.01, x0=[0.1, 0.0], x0_known=False,
             compiled=False)
    b = crlb(scaled, t, u, theta=[0.7e-6], noise_std=0.01, x0=[0.1, 0.0], x0_known=False,
             compiled=False)
    finite = np.isfinite(a.cov[:, 0, 0])
    assert finite[t.size // 10:].all()              # identified within the first 2 s
    assert np.array_equal(np.isfinite(b.cov[:, 0, 0]), finite)
    # the same arithmetic up to the scaling's rounding: 1e-6 relative is loose
    np.testing.assert_allclose(b.cov[finite, 0, 0], 1e-12 * a.cov[finite, 0, 0], rtol=1e-6)


@pytest.mark.parametrize("name", ["silverbox", "cstr"])
def test_badly_scaled_shipped_scenarios_have_a_finite_bound(name):
    """θ's components span 6 (Silverbox: 5e-6 … 4) and 5 (CSTR: 2e-3 … 600) decades: the
    bound is finite over the scenario's last half, and each standard deviation is below its
    parameter's magnitude (the scenario identifies them: the guarded and MAP estimators reach
    ≈ 1 × √CRLB on the CSTR, benchmarks/bench_window.py)."""
    from pathlib import Path
    from thetahat.modelfile import load_model, simulate_model
    spec = load_model(Path(__file__).resolve().parents[2] / "examples" / f"{name}.toml")
    sc = spec.scenario
    d = simulate_model(spec, 0, t_end=min(sc.t_end, 2000.0 / sc.fs))
    b = crlb(spec.system, d.t, np.asarray(d.u), theta=sc.theta, noise_std=sc.noise_std,
             x0=sc.x0, x0_known=False)
    sd = np.sqrt(np.diagonal(b.cov, axis1=1, axis2=2))[d.t.size // 2:]
    assert np.all(np.isfinite(sd))
    assert np.all(sd < np.abs(sc.theta)), sd[-1] / np.abs(sc.theta)
