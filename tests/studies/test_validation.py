"""Free-run simulation and validation (thetahat.studies.free_run, thetahat.studies.validation):
the simulation against SciPy's adaptive integrator on four shipped models, the holds against
the signals they reconstruct, the scores against their definitions, the output-error fit
against the θ that made its data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from thetahat.estimation.hold import BANDLIMITED_ERROR
from thetahat.errors import DimensionError, NonFiniteError, OptionError
from thetahat.modelfile import load_model
from thetahat.studies.free_run import (FreeRun, converged_substeps, input_path,
                                       simulate_output)
from thetahat.studies.validation import fit_output_error, validate_free_run

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

#: Agreement asked of the simulation with a converged solve_ivp, relative to the output's RMS:
#: the simulation converges to DEFAULT_RTOL = 1e-4 by its own test, solve_ivp runs at 1e-10;
#: 5× margin.
AGREE = 5e-4


def _record(name: str, N: int = 300) -> tuple:
    """A shipped model with its scenario's θ and a smooth two-sine input at its rate."""
    spec = load_model(EXAMPLES / f"{name}.toml")
    sc = spec.scenario
    t = np.arange(N) / sc.fs
    amps = np.atleast_2d(sc.u_amplitudes)
    freqs = np.atleast_2d(sc.u_frequencies)
    u = np.column_stack([sum(a * np.sin(2 * np.pi * f * t) for a, f in zip(amps[i], freqs[i]))
                         for i in range(spec.system.m)])
    return spec, np.asarray(sc.theta, dtype=float), t, u


def _reference(system, theta, t, u, x0, hold):
    """The same model by solve_ivp (DOP853, tight tolerances), g evaluated by the
    perturbation itself (not the plant kernel), the input held or interpolated directly;
    one solve per sample interval (the input's kinks and jumps are at the samples)."""
    A, B, C, E = system.A, system.B, system.C, system.E
    g = system.perturbation
    Y = np.empty((t.size, C.shape[0]))
    x = np.array(x0, dtype=float)
    Y[0] = C @ x
    for k in range(t.size - 1):
        t0, h, u0, du = t[k], t[k + 1] - t[k], u[k], u[k + 1] - u[k]

        def f(s, x, t0=t0, h=h, u0=u0, du=du):
            us = u0 if hold == "zoh" else u0 + (s - t0) / h * du
            v = np.concatenate([us, C @ x])
            return A @ x + B @ us + E @ np.atleast_1d(g.g(v, x, theta))

        x = solve_ivp(f, (t0, t[k + 1]), x, method="DOP853", rtol=1e-10, atol=1e-13).y[:, -1]
        Y[k + 1] = C @ x
    return Y


@pytest.mark.parametrize("name", ["silverbox", "emps", "spring_friction", "actuator"])
@pytest.mark.parametrize("hold", ["foh", "zoh"])
def test_simulate_output_agrees_with_solve_ivp(name, hold):
    if name == "silverbox":
        spec = load_model(EXAMPLES / "silverbox.toml")
        theta = np.array([5.167e-6, 2.157e-4, 0.9523, 3.789, 6.2e-3])
        t = np.arange(300) / 610.3515625
        rng = np.random.default_rng(3)
        u = 0.05 * rng.standard_normal((300, 1))              # white: every frequency
    else:
        spec, theta, t, u = _record(name)
    x0 = np.linspace(0.1, 0.2, spec.system.n) * (1e-2 if name == "silverbox" else 1.0)
    y = simulate_output(spec.system, theta, t, u, x0=x0, hold=hold)
    ref = _reference(spec.system, theta, t, u, x0, hold)
    scale = np.sqrt(np.mean(ref ** 2))
    assert np.sqrt(np.mean((y - ref) ** 2)) <= AGREE * scale


def test_the_holds_reconstruct_what_they_claim():
    """zoh holds, foh interpolates linearly, smooth linearly through the corrected samples,
    bandlimited returns a sampled sine between its samples (a band-limited signal is its own
    band-limited interpolation)."""
    h, w = 1.0 / 610.35, 2 * np.pi * 68.0                        # 9 samples per period
    t = np.arange(400) * h
    u = np.sin(w * t)[:, None]
    S = 4
    mid = (np.repeat(t[:-1], S) + (np.tile(np.arange(S), t.size - 1) + 0.5) * h / S)
    UA, UM, UB, DT = input_path(t, u, "bandlimited", S)
    inner = slice(40 * S, -40 * S)                              # away from the clamped ends
    # estimation.hold's stated in-band bound (BANDLIMITED_ERROR, relative, up to 0.8 of
    # Nyquist; here 0.22), for a unit sine, with a 10× margin for rounding of 32 taps
    assert np.max(np.abs(UM[inner, 0] - np.sin(w * mid[inner]))) < 10 * BANDLIMITED_ERROR
    np.testing.assert_allclose(DT, h / S, rtol=1e-12)
    lin = input_path(t, u, "foh", S)[1][:, 0]
    k = np.repeat(np.arange(t.size - 1), S)
    a = (mid - t[k]) / h
    np.testing.assert_allclose(lin, (1 - a) * u[k, 0] + a * u[k + 1, 0], atol=1e-14)
    # at 9 samples per period the linear interpolant misses the sine by several per cent
    assert np.max(np.abs(lin[inner] - np.sin(w * mid[inner]))) > 0.01
    # "smooth": the line through the corrected samples (a 68 Hz sine at 610 Hz, ωh = 0.70 <
    # π/3: corrected), whose interval means are closer to the sine's than the raw line's
    # (measured 0.37× at this ωh, where the causal estimate of ü is itself coarse)
    from thetahat.estimation.statistical.input_hold import stage2_samples
    ut = stage2_samples(u, "smooth")[0][:, 0]
    smooth = input_path(t, u, "smooth", S)[1][:, 0]
    np.testing.assert_allclose(smooth, (1 - a) * ut[k] + a * ut[k + 1], atol=1e-14)
    mean = lambda v: v.reshape(-1, S).mean(axis=1)[40:-40]     # per interval, inner
    exact = (np.cos(w * t[:-1]) - np.cos(w * t[1:]))[40:-40] / (w * h)
    assert (np.max(np.abs(mean(smooth) - exact))
            < 0.5 * np.max(np.abs(mean(lin) - exact)))
    zoh = input_path(t, u, "zoh", S)
    for part in zoh[:3]:
        np.testing.assert_array_equal(part[:, 0], u[k, 0])
    with pytest.raises(DimensionError, match="uniformly sampled"):
        spec = load_model(EXAMPLES / "silverbox.toml")
        FreeRun.of(spec.system, np.array([0.0, 1.0, 3.0]), np.zeros((3, 1)), "bandlimited")
    with pytest.raises(OptionError, match="hold"):
        input_path(t, u, "cubic", 2)


def test_the_sub_steps_converge_at_RK4s_order():
    """Doubling the sub-steps divides the error by about 16 (RK4); converged_substeps stops
    where two simulations agree to rtol."""
    spec, theta, t, u = _record("spring_friction", 200)
    run = FreeRun.of(spec.system, t, u, "foh")
    x0 = np.zeros(spec.system.n)
    ys = [run.run(theta, x0, S, want=False)[0] for S in (1, 2, 4, 8)]
    d1, d2 = (np.sqrt(np.mean((ys[i] - ys[3]) ** 2)) for i in (0, 1))
    assert 8 < d1 / d2 < 32                                      # 2⁴ = 16, with a margin
    S = converged_substeps(spec.system, theta, t, u, x0=x0, rtol=1e-6)
    assert S >= 2 and (S & (S - 1)) == 0


def test_sensitivities_match_finite_differences():
    spec = load_model(EXAMPLES / "silverbox.toml")
    theta = np.array([5.167e-6, 2.157e-4, 0.9523, 3.789, 6.2e-3])
    t = np.arange(120) / 610.3515625
    u = 0.1 * np.sin(2 * np.pi * 50 * t)[:, None]
    run = FreeRun.of(spec.system, t, u, "bandlimited")
    x0 = np.array([0.01, -1.0])
    Y, SX, ST = run.run(theta, x0, 4, want=True)
    for j in range(theta.size):
        d = 1e-6 * theta[j]
        up = run.run(theta + d * np.eye(5)[j], x0, 4, want=False)[0]
        dn = run.run(theta - d * np.eye(5)[j], x0, 4, want=False)[0]
        fd = (up - dn) / (2 * d)
        # central differences: error O(d²), relative 1e-6 of the sensitivity's scale
        assert np.max(np.abs(fd[:, 0] - ST[:, 0, j])) <= 1e-5 * np.max(np.abs(fd))
    for j in range(2):
        d = 1e-6
        up = run.run(theta, x0 + d * np.eye(2)[j], 4, want=False)[0]
        dn = run.run(theta, x0 - d * np.eye(2)[j], 4, want=False)[0]
        np.testing.assert_allclose((up - dn)[:, 0] / (2 * d), SX[:, 0, j], rtol=1e-5,
                                   atol=1e-8)


def test_validation_scores_by_their_definitions():
    """RMS and fit % over the samples after the window; a perfect model scores 0 and 100 %;
    the window's x(0) fit recovers the true x(0)."""
    spec, theta, t, u = _record("spring_friction", 400)
    x0 = np.array([0.05, 0.1])
    y = simulate_output(spec.system, theta, t, u, x0=x0, substeps=8)
    rng = np.random.default_rng(0)
    noisy = y + 1e-3 * rng.standard_normal(y.shape)
    check = validate_free_run(spec.system, theta, t, u, noisy, {"a": (0, 400), "b": (100, 300)},
                              init_window=40, substeps=8)
    a = check["a"]
    np.testing.assert_allclose(a.x0, x0, atol=0.01)              # 40 samples at σ = 1e-3
    err = noisy[40:, 0] - a.y_sim[40:, 0]
    assert a.rms[0] == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-12)
    ys = noisy[40:, 0]
    fit = 100 * (1 - np.linalg.norm(err) / np.linalg.norm(ys - ys.mean()))
    assert a.fit_percent[0] == pytest.approx(fit, rel=1e-12)
    assert a.rms[0] == pytest.approx(1e-3, rel=0.15)             # the noise, 360 samples
    assert check["b"].y_sim.shape == (200, 1)
    at_rest = simulate_output(spec.system, theta, t, u, x0=[0.05, 0.0], substeps=8)
    exact = validate_free_run(spec.system, theta, t, u, at_rest, init_window=0, substeps=8)
    assert exact["record"].rms[0] < 1e-12 and exact["record"].fit_percent[0] > 100 - 1e-9
    with pytest.raises(OptionError, match="segment 'c'"):
        validate_free_run(spec.system, theta, t, u, y, {"c": (300, 500)})
    with pytest.raises(OptionError, match="no sample after"):
        validate_free_run(spec.system, theta, t, u, y, {"c": (0, 30)}, init_window=40)


def test_a_diverging_simulation_names_its_sample():
    spec, theta, t, u = _record("spring_friction", 100)
    bad = theta.copy()
    bad[2] = -1e6                                                 # F_v < 0: unstable
    with pytest.raises(NonFiniteError, match="not finite at sample"):
        simulate_output(spec.system, bad, t, 1e3 * u, x0=[0.0, 1.0], substeps=1)


@pytest.mark.parametrize("hold", ["foh", "bandlimited"])
@pytest.mark.needs_speed
def test_output_error_fit_recovers_the_theta_of_its_data(hold):
    """Data simulated with θ and the same hold, plus noise: the fit returns θ within four of
    its own Cramér–Rao standard deviations, and its RMS is the noise's."""
    spec = load_model(EXAMPLES / "silverbox.toml")
    theta = np.array([5.2e-6, 2.2e-4, 0.95, 3.8, 6.2e-3])
    N = 3000
    t = np.arange(N) / 610.3515625
    rng = np.random.default_rng(7)
    u = 0.08 * rng.standard_normal((N, 1))
    y = simulate_output(spec.system, theta, t, u, x0=[0.0, 0.0], hold=hold, substeps=8)
    y += 3e-4 * rng.standard_normal(y.shape)
    fit = fit_output_error(spec.system, t, u, y, theta0=spec.estimator.theta_hat0, hold=hold)
    assert fit.success
    assert np.all(np.abs(fit.theta - theta) <= 4 * fit.theta_sd)
    assert fit.rms[0] == pytest.approx(3e-4, rel=0.1)
    assert spec.system.parameter_set.contains(fit.theta)
