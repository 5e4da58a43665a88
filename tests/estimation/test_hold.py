"""The hold (thetahat.estimation.hold): its taps against their definition, the band-limited
error bound its docstring states, the free run under each hold against SciPy's DOP853 driven
by the same reconstruction on four shipped models, and the stage-2 methods' invariance to the
hold where the reconstructions coincide."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from thetahat.errors import OptionError
from thetahat.estimation.hold import (BANDLIMITED_BAND, BANDLIMITED_ERROR, HOLDS, half_width,
                                      hold_code, reconstruct, step_lines, weight_table)
from thetahat.estimation.statistical.common import theta_box
from thetahat.modelfile import build_estimator, load_model
from thetahat.studies.free_run import simulate_output

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

#: Rounding of a sum of at most 32 taps of size ≤ 1 in float64 (each ~1e-16), with margin.
TAP_ROUND = 1e-13
#: Agreement of the free run with DOP853 (rtol 1e-10) relative to the output's RMS: the free
#: run's sub-steps converge to DEFAULT_RTOL = 1e-4 by their own test; 5× margin, as in
#: tests/studies/test_validation.py.
AGREE = 5e-4
#: θ̂ paths of one method under two holds that reconstruct the same input: they differ by the
#: rounding of the band-limited taps' sum (≤ TAP_ROUND relative), amplified by the filters'
#: gains over a few hundred samples; 1e-8 relative to θ's scale leaves a wide margin while a
#: real difference of the holds (the linear hold misses a sine at 9 samples per period by %)
#: is orders larger.
PATH_RTOL = 1e-8


@pytest.mark.parametrize("hold", HOLDS)
def test_the_taps_reproduce_a_constant_and_every_sample_at_its_instant(hold):
    a = np.linspace(0.0, 1.0, 41)
    W = weight_table(hold, a)
    L = half_width(hold)
    assert W.shape == (a.size, 2 * L)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=TAP_ROUND)
    e0 = np.zeros(2 * L)
    e0[L - 1] = 1.0                                   # tap j = 0: sample k
    e1 = np.zeros(2 * L)
    e1[L] = 1.0                                       # tap j = 1: sample k + 1
    np.testing.assert_allclose(W[0], e0, atol=TAP_ROUND)
    # at a = 1 the zero-order hold is still sample k (its left limit); the others reach k + 1
    np.testing.assert_allclose(W[-1], e0 if hold == "zoh" else e1, atol=TAP_ROUND)
    # "smooth" is the first-order hold's line (through corrected samples: input_hold)
    assert hold_code(hold) == HOLDS.index("foh" if hold == "smooth" else hold)


def test_the_band_limited_error_bound_is_what_the_docstring_states():
    """max |Σ_j w_j(a) e^{iω(j − a)} − 1| over a ∈ [0, 1] (65 points) and ω up to
    BANDLIMITED_BAND of Nyquist (400 points): at most BANDLIMITED_ERROR, and not far below it
    (the constant describes the hold, it is not a loose bound)."""
    a = np.linspace(0.0, 1.0, 65)
    W = weight_table("bandlimited", a)
    L = half_width("bandlimited")
    j = np.arange(-L + 1, L + 1)
    w = np.linspace(0.0, BANDLIMITED_BAND * np.pi, 400)
    phase = np.exp(1j * w[None, None, :] * (j[None, :, None] - a[:, None, None]))
    err = np.abs(np.einsum("aj,ajw->aw", W, phase) - 1.0).max()
    assert err <= BANDLIMITED_ERROR
    assert err > 0.1 * BANDLIMITED_ERROR
    # the linear hold at the Silverbox's resonance (ω h = 0.7) misses by 1 − cos(ωh/2) ≈ 6 % at
    # mid-interval (the docstring's comparison)
    lin = weight_table("foh", [0.5])[0] @ np.exp(1j * 0.7 * (np.array([0, 1]) - 0.5))
    assert abs(lin - 1.0) == pytest.approx(1 - np.cos(0.35), rel=1e-12)


def test_reconstruct_and_step_lines_by_their_definitions():
    rng = np.random.default_rng(0)
    U = rng.standard_normal((50, 2))
    k = rng.integers(0, 49, 30)
    a = rng.uniform(0.0, 1.0, 30)
    for hold in HOLDS:
        L = half_width(hold)
        W = weight_table(hold, a)
        pad = np.concatenate([np.repeat(U[:1], L - 1, 0), U, np.repeat(U[-1:], L, 0)])
        direct = np.stack([W[i] @ pad[k[i]:k[i] + 2 * L] for i in range(a.size)])
        np.testing.assert_allclose(reconstruct(U, hold, k, a), direct, atol=TAP_ROUND)
    V0, V1 = step_lines(U, "foh")
    np.testing.assert_array_equal(V0, U[:-1])
    np.testing.assert_array_equal(V1, U[1:])
    # the band-limited line has the reconstruction's mean and first moment over each step
    V0, V1 = step_lines(U, "bandlimited")
    x, wq = np.polynomial.legendre.leggauss(40)
    s, wq = 0.5 * (x + 1.0), 0.5 * wq
    for kk in (3, 25, 46):
        v = reconstruct(U, "bandlimited", np.full(s.size, kk), s)
        line = V0[kk][None, :] * (1 - s[:, None]) + V1[kk][None, :] * s[:, None]
        np.testing.assert_allclose(wq @ v, wq @ line, atol=1e-10)
        np.testing.assert_allclose((wq * s) @ v, (wq * s) @ line, atol=1e-10)
    with pytest.raises(OptionError, match="hold"):
        weight_table("cubic", [0.5])


def _reference(system, theta, t, U, x0, hold):
    """DOP853 (rtol 1e-10) on the model with g from the perturbation itself, u(t) the hold's
    reconstruction evaluated at the integrator's own times; one solve per sample interval."""
    A, B, C, E = system.A, system.B, system.C, system.E
    g = system.perturbation
    Y = np.empty((t.size, C.shape[0]))
    x = np.array(x0, dtype=float)
    Y[0] = C @ x
    for k in range(t.size - 1):
        t0, h = t[k], t[k + 1] - t[k]

        def f(s, x, t0=t0, h=h, k=k):
            us = reconstruct(U, hold, [k], [min(max((s - t0) / h, 0.0), 1.0)])[0]
            v = np.concatenate([us, C @ x])
            return A @ x + B @ us + E @ np.atleast_1d(g.g(v, x, theta))

        x = solve_ivp(f, (t0, t[k + 1]), x, method="DOP853", rtol=1e-10, atol=1e-13).y[:, -1]
        Y[k + 1] = C @ x
    return Y


def _record(name, N):
    spec = load_model(EXAMPLES / f"{name}.toml")
    if name == "silverbox":
        theta = np.array([5.167e-6, 2.157e-4, 0.9523, 3.789, 6.2e-3])
        t = np.arange(N) / 610.3515625
        # a multisine up to 0.6 of Nyquist: inside the band-limited hold's band
        f = np.array([13.0, 61.0, 97.0, 150.0, 181.0])
        u = 0.05 * np.sin(2 * np.pi * f[None, :] * t[:, None] + np.arange(5)).sum(1)[:, None]
        return spec, theta, t, u, np.zeros(spec.system.n)
    sc = spec.scenario
    t = np.arange(N) / sc.fs
    amps, freqs = np.atleast_2d(sc.u_amplitudes), np.atleast_2d(sc.u_frequencies)
    u = np.column_stack([sum(a * np.sin(2 * np.pi * f * t) for a, f in zip(amps[i], freqs[i]))
                         for i in range(spec.system.m)])
    return spec, np.asarray(sc.theta, dtype=float), t, u, np.linspace(0.1, 0.2, spec.system.n)


@pytest.mark.parametrize("name", ["silverbox", "spring_friction", "actuator", "emps"])
def test_the_band_limited_free_run_agrees_with_DOP853(name):
    """The converged free run (error-controlled sub-steps) with the band-limited hold against
    solve_ivp driven by the same reconstruction (the zero- and first-order holds:
    tests/studies/test_validation.py)."""
    spec, theta, t, u, x0 = _record(name, 150)
    y = simulate_output(spec.system, theta, t, u, x0=x0, hold="bandlimited")
    ref = _reference(spec.system, theta, t, u, x0, "bandlimited")
    scale = np.sqrt(np.mean(ref ** 2))
    assert np.sqrt(np.mean((y - ref) ** 2)) <= AGREE * scale


@pytest.mark.parametrize("method", ["ekf", "mle", "guarded"])
@pytest.mark.parametrize("name", ["spring_friction", "actuator", "emps"])
def test_stage_2_is_invariant_to_the_hold_of_a_constant_input(method, name):
    """A record whose input is constant is reconstructed identically by the three holds (the
    taps sum to 1): each method gives the same θ̂ path under each."""
    spec = load_model(EXAMPLES / f"{name}.toml")
    sc = spec.scenario
    N = 300
    t = np.arange(N) / sc.fs
    u = np.tile(np.atleast_2d(sc.u_amplitudes).sum(axis=1), (N, 1))   # (N, m), constant
    theta = np.asarray(sc.theta, dtype=float)
    x0 = np.linspace(0.1, 0.2, spec.system.n)
    y = simulate_output(spec.system, theta, t, u, x0=x0, hold="zoh")
    y = y + 0.01 * np.std(y, axis=0) * np.random.default_rng(1).standard_normal(y.shape)
    paths = {}
    for hold in HOLDS:
        # Γ given where the file's is "auto" (chosen on a record; stage 1 is the same for
        # every hold, so any fixed Γ serves the comparison)
        gamma = np.eye(spec.system.p) if spec.estimator.gamma_auto else None
        est = dataclasses.replace(build_estimator(spec, method=method, Gamma=gamma), hold=hold)
        res = est.run(t, u, y, state0=est.init(theta_hat0=spec.estimator.theta_hat0))
        paths[hold] = res.theta_hat
    lo, hi = theta_box(spec.system)
    scale = hi - lo
    for hold in ("foh", "bandlimited"):
        assert np.all(np.abs(paths[hold] - paths["zoh"]) <= PATH_RTOL * scale)
