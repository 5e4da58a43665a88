"""Plant simulation: accuracy against closed-form solutions, the convergence check, the
seeded measurement noise, and error paths."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import scipy.linalg as sla

from thetahat.errors import (
    ConvergenceWarning,
    DimensionError,
    NonFiniteError,
    SimulationError,
    ThetahatWarning,
)
from thetahat.model.system import PerturbedLinearSystem
from thetahat.simulation.noise import (
    ColoredNoise,
    WhiteNoise,
    make_rng,
    measurement_noise,
)
from thetahat.simulation.signals import Multisine, Steps
from thetahat.simulation.simulate import convergence_check, simulate_plant

#: With rtol = 1e-8 and atol = 1e-10 the global error of Radau/LSODA on the oscillator below
#: is ~2e-9 .. 2e-8 (measured); 1e-7 leaves margin for platform differences.
ACCURATE_ATOL = 1e-7
#: convergence_check estimates the true error to within ~3 % on the oscillator (measured for
#: Radau, BDF, LSODA, RK45, DOP853); accept a factor 1.25 either way.
ESTIMATE_RATIO = 1.25
#: Sample std of N iid Gaussians has relative standard error 1/sqrt(2N); 5 of them bound a
#: false failure at ~6e-7.
CI_SIGMAS = 5.0

STEP_TIME = 0.55          # between two samples of the 10 Hz grid: the integrator must restart
THETA = -1.0              # φ = θ·x1 closes the loop: Ā = A + E [θ, 0]


@pytest.fixture(scope="module")
def oscillator() -> PerturbedLinearSystem:
    """A damped oscillator with φ entering like the input."""
    return PerturbedLinearSystem(A=[[0.0, 1.0], [-4.0, -0.4]], B=[[0.0], [1.0]],
                                 C=[[1.0, 0.0]], E=[[0.0], [1.0]])


def phi_linear(t, x, u, theta):
    return (theta[..., 0] * x[..., 0])[..., None]


def dphi_linear(t, x, u, theta):
    return np.array([[theta[0], 0.0]])


def exact_step_response(sys: PerturbedLinearSystem, t: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """x(t) for u = unit step at STEP_TIME and φ = θ x1, from the matrix exponential."""
    Abar = sys.A + sys.E @ np.array([[THETA, 0.0]])
    x_jump = sla.expm(Abar * STEP_TIME) @ x0
    out = []
    for ti in t:
        if ti < STEP_TIME:
            out.append(sla.expm(Abar * ti) @ x0)
        else:
            Phi = sla.expm(Abar * (ti - STEP_TIME))
            out.append(Phi @ x_jump + np.linalg.solve(Abar, (Phi - np.eye(2)) @ sys.B[:, 0]))
    return np.array(out)


def run(sys, **kw):
    args = {"phi": phi_linear, "dphi_dx": dphi_linear, "u": Steps([STEP_TIME], [1.0]),
            "t_end": 10.0, "fs": 10.0, "x0": [1.0, 0.0], "theta": [THETA], "rtol": 1e-8,
            "atol": 1e-10}
    args.update(kw)
    return simulate_plant(sys, **args)


@pytest.mark.parametrize("method", ["Radau", "BDF", "LSODA", "DOP853"])
def test_matches_closed_form_with_step_between_samples(oscillator, method):
    rtol = 1e-11 if method == "BDF" else 1e-8    # BDF is low order: needs tighter rtol
    traj = run(oscillator, method=method, rtol=rtol, atol=rtol * 1e-2)
    exact = exact_step_response(oscillator, traj.t, np.array([1.0, 0.0]))
    assert traj.stats.n_segments == 2             # restarted at the jump
    np.testing.assert_allclose(traj.x, exact, atol=ACCURATE_ATOL, rtol=0)
    np.testing.assert_allclose(traj.y_clean[:, 0], traj.x[:, 0], rtol=0, atol=0)
    np.testing.assert_array_equal(traj.u[:, 0], (traj.t >= STEP_TIME).astype(float))


def test_trajectory_fields_are_consistent(oscillator):
    traj = run(oscillator, noise=WhiteNoise(0.1), seed=4)
    assert traj.t.shape == (101,) and traj.x.shape == (101, 2) and traj.phi.shape == (101, 1)
    assert traj.y.shape == traj.y_clean.shape == (101, 1)
    np.testing.assert_allclose(traj.phi, phi_linear(traj.t, traj.x, traj.u, traj.theta))
    np.testing.assert_array_equal(traj.v, np.hstack([traj.u, traj.y]))
    np.testing.assert_array_equal(traj.theta, [THETA])
    assert traj.seed == 4 and traj.fs == 10.0
    with pytest.raises(ValueError, match="read-only"):
        traj.x[0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        traj.y = traj.y_clean  # type: ignore[misc]
    assert "PlantTrajectory(N=101" in repr(traj)


def test_noise_is_seeded_and_added_to_clean_output(oscillator):
    a = run(oscillator, noise=WhiteNoise(0.1), seed=11)
    b = run(oscillator, noise=WhiteNoise(0.1), seed=11)
    c = run(oscillator, noise=WhiteNoise(0.1), seed=12)
    np.testing.assert_array_equal(a.y, b.y)
    np.testing.assert_array_equal(a.y_clean, c.y_clean)
    assert not np.allclose(a.y, c.y)
    expected = WhiteNoise(0.1).sample(make_rng(11), a.t.size, 1, a.fs)
    np.testing.assert_array_equal(a.noise, a.y - a.y_clean)
    np.testing.assert_allclose(a.noise, expected, atol=1e-15)
    clean = run(oscillator)
    np.testing.assert_array_equal(clean.y, clean.y_clean)
    assert clean.seed is None


def test_generic_callable_input_equals_signal(oscillator):
    sig = Multisine([0.5], [0.3])
    a = run(oscillator, u=sig)
    b = run(oscillator, u=lambda t: [0.5 * np.sin(2 * np.pi * 0.3 * t)])
    np.testing.assert_allclose(a.x, b.x, atol=1e-12)
    np.testing.assert_allclose(a.u, b.u, atol=1e-15)


def test_explicit_method_gets_no_jacobian(oscillator):
    with warnings.catch_warnings():
        warnings.simplefilter("error")           # scipy warns if jac reaches RK45
        traj = run(oscillator, method="RK45", rtol=1e-9, atol=1e-11)
    exact = exact_step_response(oscillator, traj.t, np.array([1.0, 0.0]))
    np.testing.assert_allclose(traj.x, exact, atol=ACCURATE_ATOL)


@pytest.mark.parametrize("method", ["Radau", "LSODA"])
def test_convergence_check_estimates_true_error(oscillator, method):
    kw = {"phi": phi_linear, "dphi_dx": dphi_linear, "u": Steps([STEP_TIME], [1.0]),
          "t_end": 10.0, "fs": 10.0, "x0": [1.0, 0.0], "theta": [THETA], "method": method,
          "rtol": 1e-6, "atol": 1e-8}
    traj = simulate_plant(oscillator, **kw)
    true_error = np.abs(traj.x - exact_step_response(oscillator, traj.t,
                                                     np.array([1.0, 0.0]))).max()
    rep = convergence_check(oscillator, **kw)
    assert 1 / ESTIMATE_RATIO < rep.max_diff / true_error < ESTIMATE_RATIO
    assert rep.reference_rtol == pytest.approx(1e-8)
    assert rep.max_diff == pytest.approx(rep.max_diff_per_state.max())


def test_convergence_check_error_shrinks_with_tolerance(oscillator):
    kw = {"phi": lambda t, x, u, th: (th[..., 0] * np.sin(x[..., 0]))[..., None],
          "u": Multisine([1.0], [0.3]), "t_end": 10.0, "fs": 20.0, "x0": [1.0, 0.0],
          "theta": [-2.0]}
    loose = convergence_check(oscillator, rtol=1e-4, atol=1e-6, **kw)
    tight = convergence_check(oscillator, rtol=1e-7, atol=1e-9, **kw)
    # Radau is order 5; a 1000x tighter tolerance must buy at least two decades.
    assert tight.max_diff < loose.max_diff / 100
    with pytest.warns(ConvergenceWarning, match="not converged"):
        convergence_check(oscillator, rtol=1e-4, atol=1e-6, bound=loose.max_diff / 10, **kw)


def test_white_noise_statistics_per_output():
    std = np.array([0.02, 0.5, 0.0])
    n = 40_000
    e = measurement_noise(WhiteNoise(std), n_samples=n, n_outputs=3, fs=1000.0, seed=7)
    half_width = CI_SIGMAS / np.sqrt(2 * n)
    s = e.std(axis=0)
    assert np.all(np.abs(s[:2] / std[:2] - 1) < half_width)
    assert np.all(e[:, 2] == 0.0)
    assert abs(e[:, 0].mean()) < CI_SIGMAS * 0.02 / np.sqrt(n)
    lag1 = np.corrcoef(e[1:, 1], e[:-1, 1])[0, 1]
    assert abs(lag1) < CI_SIGMAS / np.sqrt(n)          # white: uncorrelated in time


def test_colored_noise_std_and_correlation():
    noise = ColoredNoise(0.02, bandwidth=5.0)
    n, fs = 200_000, 1000.0
    e = measurement_noise(noise, n_samples=n, n_outputs=1, fs=fs, seed=3)[:, 0]
    a = noise.pole(fs)
    # Var of the sample variance of an AR(1) sequence: 2σ⁴/N · (1 + a²)/(1 - a²).
    rel_se = np.sqrt((1 + a * a) / (1 - a * a) / (2 * n))
    assert abs(e.std() / 0.02 - 1) < CI_SIGMAS * rel_se
    lag1 = np.corrcoef(e[1:], e[:-1])[0, 1]
    assert abs(lag1 - a) < 0.01
    assert not np.array_equal(e, measurement_noise(noise, n_samples=n, n_outputs=1, fs=fs,
                                                   seed=4)[:, 0])


def test_noise_seed_validation():
    with pytest.raises(TypeError, match="seed"):
        make_rng(None)  # type: ignore[arg-type]
    with pytest.raises(DimensionError, match=">= 0"):
        make_rng(-1)
    with pytest.raises(DimensionError, match="outputs"):
        WhiteNoise([0.1, 0.2]).sample(make_rng(0), 10, 3, 100.0)
    with pytest.raises(DimensionError, match=">= 0"):
        WhiteNoise(-0.1)
    ss = np.random.SeedSequence(5)
    np.testing.assert_array_equal(make_rng(ss).normal(size=3),
                                  make_rng(np.random.SeedSequence(5)).normal(size=3))


def test_blow_up_raises_typed_error():
    sys = PerturbedLinearSystem(A=[[0.0]], B=np.zeros((1, 0)), C=[[1.0]], E=[[1.0]])
    with pytest.raises(SimulationError, match="integrator failed"):
        simulate_plant(sys, phi=lambda t, x, u, th: x**2, u=None, t_end=2.0, fs=10.0,
                       x0=[1.0], theta=[0.0])


@pytest.mark.parametrize("change, exc, match", [
    ({"x0": [1.0]}, DimensionError, "x0"),
    ({"x0": [np.nan, 0.0]}, NonFiniteError, "x0"),
    ({"theta": [np.inf]}, NonFiniteError, "theta"),
    ({"method": "Euler"}, DimensionError, "method"),
    ({"phi": lambda t, x, u, th: np.zeros(2)}, DimensionError, "phi"),
    ({"phi": lambda t, x, u, th: np.array([np.nan])}, NonFiniteError, "phi"),
    ({"dphi_dx": lambda t, x, u, th: np.zeros(3)}, DimensionError, "dphi_dx"),
    ({"u": Multisine([[1.0], [1.0]], [1.0])}, DimensionError, "channels"),
    ({"u": None}, DimensionError, "u must be given"),
    ({"fs": 0.0}, DimensionError, "fs"),
    ({"atol": [1e-9, 1e-9, 1e-9]}, DimensionError, "atol"),
])
def test_input_errors(oscillator, change, exc, match):
    with pytest.raises(exc, match=match):
        run(oscillator, **change)


def test_non_batch_phi_is_reported(oscillator):
    with pytest.raises(DimensionError, match="batch"):
        run(oscillator, phi=lambda t, x, u, th: np.array([th[0] * x[0]]))


def test_theta_outside_parameter_set_warns():
    from thetahat.models import lugre
    sys = lugre.system()
    phi = lugre.true_phi()
    with pytest.warns(ThetahatWarning, match="outside the parameter set"):
        simulate_plant(sys, phi=phi, u=Steps([0.0], [0.5]), t_end=0.01, fs=1000.0,
                       x0=[0.0, 0.0], theta=[2.0], method="LSODA")
