"""The LuGre DC motor of Sec. VIII: paper numbers, the model pieces, and the physics and
numerics of the simulated plant (default scenario: 20 s, 1 kHz, σ = 0.02 rad/s)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import cumulative_simpson, cumulative_trapezoid

from thetahat.errors import ParameterSetError, ThetahatWarning
from thetahat.models import lugre
from thetahat.simulation.simulate import convergence_check

P = lugre.LuGreParameters()

#: Same formula written two ways: round-off only.
SAME_FORMULA_RTOL = 1e-12
#: Default settings vs 100x tighter over the 20 s scenario: measured 1.3e-8 rad/s (ω) and
#: 1.3e-11 rad (η); the bounds keep a factor ~8 of margin.
CONVERGED_OMEGA = 1e-7
CONVERGED_ETA = 1e-10
#: In steady sliding η = sign(ω)ζ(ω)/σ0 up to the solver error (measured ratio ≤ 1 + 1e-8).
STEADY_SLIDING_RTOL = 1e-6
#: "Steady sliding": |ω| ≥ 0.5 rad/s = 50 ω0, where the bristle relaxation rate σ0|ω|/ζ is
#: ≥ ~460 s⁻¹ while ζ is constant to exp(-2500).
SLIDING_SPEED = 0.5
#: Mechanical energy budget, Simpson quadrature at 1 kHz: measured error 3.5e-7 J against
#: ~17 J of input work; accept 1e-5 relative.
ENERGY_RTOL = 1e-5
#: The bristle storage inequality holds exactly in continuous time; Simpson quadrature of
#: σ0 η ω leaves ~2e-10 J (measured).
PASSIVITY_SLACK = 1e-8
#: Central differences of the sampled state vs the right-hand side: the median error at
#: 1 kHz is ~1e-4 rad/s² on a ~20 rad/s² scale (measured 9e-5), i.e. the ODE holds away from
#: the velocity reversals, where 1 ms does not resolve the ~0.1 ms bristle dynamics.
FD_MEDIAN_RTOL = 1e-4


@pytest.fixture(scope="module")
def traj():
    return lugre.simulate(seed=0)


def rhs(traj, params=P):
    lin = lugre.linear_part(params)
    return traj.x @ lin.A.T + traj.u @ lin.B.T + traj.phi @ lin.E.T


def test_paper_parameters():
    # Sec. VIII: J = 0.0023, σ0 = 260, σ1 = 0.6, α0 = 0.28, α1 = 0.05, α2 = 0.176, ω0 = 0.01,
    # Θ = [0.05, 1].
    assert (P.J, P.sigma0, P.sigma1, P.alpha0, P.alpha1, P.alpha2, P.omega0) == (
        0.0023, 260.0, 0.6, 0.28, 0.05, 0.176, 0.01)
    assert (P.theta_lower, P.theta_upper) == (0.05, 1.0)


def test_linear_part_reproduces_the_physical_model(rng):
    lin = lugre.linear_part()
    x = rng.normal(size=(20, 2)) * [3.0, 1e-3]
    u = rng.normal(size=(20, 1))
    phi = rng.normal(size=(20, 1))
    xdot = x @ lin.A.T + u @ lin.B.T + phi @ lin.E.T
    omega, eta = x[:, 0], x[:, 1]
    eta_dot = omega - phi[:, 0]                              # η̇ = ω − φ
    friction = P.sigma0 * eta + P.sigma1 * eta_dot + P.alpha2 * omega
    np.testing.assert_allclose(xdot[:, 1], eta_dot, rtol=SAME_FORMULA_RTOL)
    np.testing.assert_allclose(xdot[:, 0], (u[:, 0] - friction) / P.J,
                               rtol=SAME_FORMULA_RTOL, atol=1e-9)
    np.testing.assert_array_equal(lin.C, [[1.0, 0.0]])


def test_design_system_drops_sigma1():
    des, lin = lugre.design_system(), lugre.linear_part()
    np.testing.assert_allclose(des.A, [[-P.alpha2 / P.J, -P.sigma0 / P.J], [1.0, 0.0]])
    np.testing.assert_array_equal(des.E, [[0.0], [-1.0]])
    np.testing.assert_array_equal(des.B, lin.B)
    assert lin.E[0, 0] == pytest.approx(P.sigma1 / P.J)


def test_observer_g_uses_measured_y_not_omega(rng):
    g = lugre.perturbation()
    assert g.dims == (2, 1, 1, 1, 1)
    x = np.column_stack([rng.normal(size=30) * 0.02, rng.normal(size=30) * 1e-3])
    y = rng.normal(size=30)                                  # y ≠ ω on purpose (Remark 4)
    v = np.column_stack([rng.normal(size=30), y])
    th = rng.uniform(0.05, 1.0, (30, 1))
    expected = P.sigma0 * x[:, 1] * np.abs(y) / P.zeta(x[:, 0], th[:, 0])
    np.testing.assert_allclose(g.g(v, x, th)[:, 0], expected, rtol=SAME_FORMULA_RTOL)


def test_system_bundles_true_matrices_g_and_theta_set():
    sys = lugre.system()
    np.testing.assert_array_equal(sys.A, lugre.linear_part().A)
    assert sys.parameter_set.contains([0.28]) and not sys.parameter_set.contains([1.5])
    assert lugre.perturbation() is lugre.perturbation()      # built once, cached


def test_true_phi_jacobian_matches_finite_differences(rng):
    phi = lugre.true_phi()
    # Away from ω = 0 (the kink of |ω|) and inside the Stribeck region, where ∂ζ/∂ω ≠ 0.
    omega = rng.choice([-1, 1], 25) * rng.uniform(0.002, 0.03, 25)
    x = np.column_stack([omega, rng.uniform(-1e-3, 1e-3, 25)])
    th = rng.uniform(0.05, 1.0, (25, 1))
    J = phi.dphi_dx(0.0, x, None, th)
    assert J.shape == (25, 1, 2)
    for j, h in enumerate([1e-8, 1e-10]):
        dx = np.zeros(2)
        dx[j] = h
        fd = (phi(0.0, x + dx, None, th) - phi(0.0, x - dx, None, th))[:, 0] / (2 * h)
        np.testing.assert_allclose(J[:, 0, j], fd, rtol=1e-5, atol=1e-9)


def test_true_phi_equals_observer_g_on_noise_free_data(traj):
    g = lugre.perturbation()
    v_clean = np.hstack([traj.u, traj.y_clean])
    th = np.broadcast_to(traj.theta, (traj.t.size, 1))
    np.testing.assert_allclose(g.g(v_clean, traj.x, th), traj.phi, rtol=1e-12, atol=1e-15)


def test_theta_star_inverts_g(rng):
    g, ts = lugre.perturbation(), lugre.theta_star()
    n = 40
    x = np.column_stack([rng.normal(size=n) * 0.02, rng.uniform(2e-4, 1e-3, n)])
    v = np.column_stack([rng.normal(size=n), rng.uniform(0.1, 4.0, n)])
    theta = rng.uniform(0.05, 1.0, (n, 1))
    phi_hat = g.g(v, x, theta)
    np.testing.assert_allclose(ts(v, x, phi_hat), theta, rtol=1e-10)


def test_theta_star_is_nan_where_phi_hat_is_zero():
    out = lugre.theta_star()([[0.0, 1.0], [0.0, 1.0]], [[1.0, 1e-3], [1.0, 1e-3]],
                             [[0.0], [0.5]])
    assert np.isnan(out[0, 0]) and np.isfinite(out[1, 0])   # and no RuntimeWarning (-W error)


def test_default_scenario_shapes_and_truth(traj):
    assert traj.t.size == 20001 and traj.t[-1] == pytest.approx(20.0)
    assert traj.x.shape == (20001, 2) and traj.u.shape == traj.y.shape == (20001, 1)
    np.testing.assert_array_equal(traj.theta, [0.28])
    np.testing.assert_array_equal(traj.x[0], [0.0, 0.0])
    t = traj.t
    np.testing.assert_allclose(traj.u[:, 0], 0.7 * np.sin(np.pi * t)
                               + 0.25 * np.sin(2 * np.pi * 1.3 * t), atol=1e-14)


def test_noise_statistics_and_seeds(traj):
    e = traj.noise[:, 0]
    n = e.size
    assert abs(e.std() / 0.02 - 1) < 5 / np.sqrt(2 * n)      # 5-sigma CI of the sample std
    again = lugre.simulate(seed=0, t_end=1.0)
    other = lugre.simulate(seed=1, t_end=1.0)
    # Same seed, same noise (a shorter record is a prefix of the longer one).
    np.testing.assert_allclose(again.noise, traj.noise[:1001], rtol=0, atol=1e-15)
    assert not np.allclose(other.noise, again.noise)
    np.testing.assert_array_equal(other.x, again.x)              # the seed only moves y
    np.testing.assert_array_equal(lugre.simulate(seed=1, t_end=1.0).y, other.y)


def test_friction_state_bound(traj):
    omega, eta = traj.x[:, 0], traj.x[:, 1]
    # |η| ≤ (α0 + α1)/σ0 is invariant: at the bound, sign(η)·η̇ = |ω|(±1 − σ0|η|/ζ) ≤ 0.
    assert np.abs(eta).max() <= P.eta_bound
    sliding = np.abs(omega) >= SLIDING_SPEED
    assert sliding.mean() > 0.5                                  # the test has teeth
    ratio = P.sigma0 * np.abs(eta[sliding]) / P.zeta(omega[sliding])
    assert ratio.max() <= 1 + STEADY_SLIDING_RTOL
    assert ratio.min() >= 1 - 1e-3                               # η ≈ sign(ω) ζ/σ0 there
    assert np.all(np.sign(eta[sliding]) == np.sign(omega[sliding]))


def test_excitation_for_proposition_2(traj):
    # The paper's l(v, x̂, φ̂) = 1 needs |φ| ≥ 1 some portion of the time (Sec. VIII A).
    assert np.mean(np.abs(traj.phi[:, 0]) >= 1.0) > 0.3


def test_samples_satisfy_the_ode(traj):
    f = rhs(traj)
    h = 1.0 / traj.fs
    fd = (traj.x[2:] - traj.x[:-2]) / (2 * h)
    median_err = np.median(np.abs(fd - f[1:-1]), axis=0)
    assert np.all(median_err <= FD_MEDIAN_RTOL * np.abs(f).max(axis=0))


def test_integrated_rhs_converges_at_second_order():
    # x(t) - x(0) vs the trapezoidal integral of the rhs on the samples: the error must fall
    # like h² as the sampling is refined (measured: 1.3e-4, 5.7e-6, 2.7e-7 for 2, 10, 50 kHz).
    errs = []
    for fs in (2e3, 1e4):
        tr = lugre.simulate(seed=0, t_end=1.5, fs=fs, noise_std=0.0)
        integral = cumulative_trapezoid(rhs(tr), x=tr.t, axis=0, initial=0)
        errs.append(np.abs(tr.x - tr.x[0] - integral).max(axis=0))
    order = np.log(errs[0] / errs[1]) / np.log(5.0)
    assert np.all(order > 1.7)
    assert errs[1][0] < 1e-5 and errs[1][1] < 1e-7


def test_energy_budget_and_bristle_passivity(traj):
    omega, eta = traj.x[:, 0], traj.x[:, 1]
    u = traj.u[:, 0]
    friction = P.sigma0 * eta + P.sigma1 * (omega - traj.phi[:, 0]) + P.alpha2 * omega
    kinetic = 0.5 * P.J * omega**2
    work = cumulative_simpson((u - friction) * omega, x=traj.t, initial=0)
    scale = cumulative_simpson(np.abs(u * omega), x=traj.t)[-1]
    assert np.abs(kinetic - kinetic[0] - work).max() <= ENERGY_RTOL * scale
    dissipated = cumulative_simpson(friction * omega, x=traj.t, initial=0)
    assert dissipated[-1] > 0.5 * scale                       # friction takes most of the work
    # ∫ σ0 η ω dt ≥ V(t) − V(0) with the bristle energy V = σ0 η²/2 (LuGre passivity).
    storage = 0.5 * P.sigma0 * eta**2
    supplied = cumulative_simpson(P.sigma0 * eta * omega, x=traj.t, initial=0)
    assert np.min(supplied - (storage - storage[0])) >= -PASSIVITY_SLACK


def test_default_simulation_is_converged():
    sc = lugre.Scenario()
    phi = lugre.true_phi()
    rep = convergence_check(lugre.linear_part(), phi=phi, dphi_dx=phi.dphi_dx, u=sc.u,
                            t_end=sc.t_end, fs=sc.fs, x0=sc.x0, theta=[sc.theta],
                            method=lugre.LUGRE_METHOD, rtol=lugre.LUGRE_RTOL,
                            atol=lugre.LUGRE_ATOL)
    assert rep.reference_rtol == pytest.approx(lugre.LUGRE_RTOL / 100)
    assert rep.max_diff_per_state[0] < CONVERGED_OMEGA
    assert rep.max_diff_per_state[1] < CONVERGED_ETA


@pytest.mark.slow
def test_default_simulation_agrees_with_tight_radau(traj):
    # An independent method: Radau IIA at rtol 1e-11 against the LSODA default.
    ref = lugre.simulate(seed=0, method="Radau", rtol=1e-11, atol=(1e-12, 1e-15))
    diff = np.abs(ref.x - traj.x).max(axis=0)
    assert diff[0] < CONVERGED_OMEGA and diff[1] < CONVERGED_ETA


def test_scenario_overrides_and_validation():
    quiet = lugre.simulate(seed=3, t_end=0.5, noise_std=0.0)
    np.testing.assert_array_equal(quiet.y, quiet.y_clean)
    slow = lugre.simulate(t_end=0.5, params=lugre.LuGreParameters(alpha0=0.5))
    np.testing.assert_array_equal(slow.theta, [0.5])
    assert not np.allclose(slow.x, quiet.x)
    base = lugre.Scenario(t_end=0.5, noise_std=0.0)
    np.testing.assert_array_equal(lugre.simulate(scenario=base).x, quiet.x)
    with pytest.raises(TypeError, match="unknown scenario field"):
        lugre.simulate(t_stop=1.0)
    with pytest.raises(ParameterSetError, match="outside"):
        lugre.Scenario(theta_hat0=1.5)
    with pytest.warns(ThetahatWarning, match="outside"):
        lugre.Scenario(params=lugre.LuGreParameters(alpha0=2.0))


def test_scenario_defaults():
    sc = lugre.Scenario()
    assert (sc.t_end, sc.fs, sc.x0, sc.noise_std, sc.theta_hat0, sc.theta) == (
        20.0, 1000.0, (0.0, 0.0), 0.02, 0.5, 0.28)
    np.testing.assert_array_equal(sc.u.amplitudes, [[0.7, 0.25]])
    np.testing.assert_array_equal(sc.u.frequencies, [[0.5, 1.3]])
