"""Tests of the second observer of Sec. VI (thetahat.estimation.observer.redesign), alone and attached to
the modified high-gain observer.

The LuGre g of Sec. VIII is written out by hand (as in test_observer.py; candidates for a
shared conftest fixture) so that nothing here shares code with thetahat.models.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
from scipy.integrate import solve_ivp

from thetahat.errors import DimensionError, NonFiniteError
from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.estimation.observer.redesign import SecondObserver
from thetahat.estimation.observer.laws import ConstantLaw, UpdateLaw
from thetahat.model.paramset import Box
from thetahat.model.system import PerturbedLinearSystem
from motor_model import (ALPHA0, ALPHA2, A_MOTOR, B_MOTOR, C_MOTOR, E_MOTOR, J, SIGMA0,
                         THETA_SET, LuGreG, ZeroG)

#: Exact-discretisation comparisons: rounding amplified by ‖e^{hM}‖ over a few hundred steps.
EXACT_RTOL = 1e-9
#: Noise-free DC motor, θ known, ε = 1, 1 kHz ZOH, 1.5 s <= t <= 2 s: largest |ω − ω̂₂|
#: measured 6.5e-3 (g on y) and 6.8e-3 (g on estimates), mostly the half-sample ZOH delay; over
#: longer records velocity reversals reach 2.4e-2, where the low-gain (poles −1, −2) observer
#: lags the steep ζ(ω) of ω0 = 0.01. A lost term or a wrong θ̂ source is far above 2e-2.
REFINED_OMEGA_BOUND = 2e-2
#: Standalone step (ZOH, dt = 1e-4) vs. Radau of rhs driven by smooth signals: the O(dt) hold
#: error of a y that moves 2 rad/s at 1.5 Hz; measured ≈ 1e-3 rad/s.
STEP_VS_IVP_OMEGA = 3e-3


class DriftLaw(UpdateLaw):
    """θ̂̇ = c: moves θ̂ steadily (projected onto Θ by the default step)."""

    def __init__(self, c: float) -> None:
        self._c = c

    @property
    def parameter_set(self):
        return THETA_SET

    def rate(self, v, x_hat, phi_hat, theta_hat):
        return np.full_like(np.asarray(theta_hat, dtype=float), self._c)


def motor_system():
    return PerturbedLinearSystem(A=A_MOTOR, B=B_MOTOR, C=C_MOTOR, E=E_MOTOR,
                                 perturbation=LuGreG())


def first_gains(eps):
    Ae = np.array([[-ALPHA2 / J, -SIGMA0 / J, 0.0], [1.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    Ce = np.array([[1.0, 0.0, 0.0]])
    K = np.linalg.solve(np.vstack([Ce, Ce @ Ae, Ce @ Ae @ Ae]),
                        [6.0 / eps, 11.0 / eps**2, 6.0 / eps**3])
    return K[:2, None], K[2:, None]


def second_gain(eps):
    """Sec. VIII: σ1 = 0 design system of x only, poles of H at −1, −2."""
    Ad = np.array([[-ALPHA2 / J, -SIGMA0 / J], [1.0, 0.0]])
    return np.linalg.solve(np.vstack([C_MOTOR, C_MOTOR @ Ad]), [3.0 / eps, 2.0 / eps**2])[:, None]


def composite(g_on_estimates=False, law=None, **options):
    K_x, K_phi = first_gains(1.0)
    second = SecondObserver(system=motor_system(), K_x=second_gain(1.0),
                            g_on_estimates=g_on_estimates)
    return ModifiedHighGainObserver(system=motor_system(), K_x=K_x, K_phi=K_phi,
                                    update_law=law or ConstantLaw([ALPHA0], THETA_SET),
                                    second=second, **options)


def motor_input(t):
    return 0.7 * np.sin(2 * np.pi * 0.5 * t) + 0.25 * np.sin(2 * np.pi * 1.3 * t)


@pytest.fixture(scope="module")
def motor1k():
    """2 s of the true plant (|ω| inside φ) at 1 kHz, Radau at tight tolerance."""
    g, th = LuGreG(), np.array([ALPHA0])

    def f(t, x):
        u = motor_input(t)
        return A_MOTOR @ x + B_MOTOR[:, 0] * u + E_MOTOR[:, 0] * g.g(np.array([u, x[0]]), x, th)

    def jac(t, x):
        v = np.array([motor_input(t), x[0]])
        G = g.dg_dx(v, x, th)[0] + np.array([g.dg_dv(v, x, th)[0, 1], 0.0])
        return A_MOTOR + np.outer(E_MOTOR[:, 0], G)

    t = np.arange(2001) * 1e-3
    sol = solve_ivp(f, (0.0, t[-1]), [0.0, 0.0], method="Radau", t_eval=t, jac=jac,
                    rtol=1e-10, atol=1e-13)
    return t, motor_input(t), sol.y.T


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def exact_reference(A, B, C, K, t, U, Y, x0, skip=None):
    """Exact ZOH discretisation of ẋ = (A − K C) x + B u + K y (K = 0 on skipped samples)."""
    n, q = A.shape[0], U.shape[1] + Y.shape[1]
    x, out = x0, [x0]
    for i in range(len(t) - 1):
        KK = 0 * K if (skip is not None and skip[i]) else K
        big = np.zeros((n + q, n + q))
        big[:n, :n], big[:n, n:] = A - KK @ C, np.hstack([B, KK])
        w = np.concatenate([U[i], np.nan_to_num(Y[i])])
        x = (scipy.linalg.expm((t[i + 1] - t[i]) * big) @ np.concatenate([x, w]))[:n]
        out.append(x)
    return np.array(out)


# --------------------------------------------------------------------------- paper numbers
def test_second_gain_matches_paper():
    """Sec. VIII: poles −1, −2, ε = 1 'translates to K(ε) ≈ [3, 0]ᵀ'."""
    np.testing.assert_allclose(second_gain(1.0)[:, 0], [3.0, -0.0020485], rtol=1e-4)


# --------------------------------------------------------------------------- standalone
def test_zero_perturbation_is_exact_luenberger(rng):
    n, m, r = 3, 2, 2
    A, B, C = rng.standard_normal((n, n)), rng.standard_normal((n, m)), rng.standard_normal((r, n))
    K = scipy.signal.place_poles(A.T, C.T, [-2.0, -3.0, -4.0]).gain_matrix.T
    plant = PerturbedLinearSystem(A=A, B=B, C=C, E=rng.standard_normal((n, 1)),
                                  perturbation=ZeroG((n, m, r, 1, 1)))
    obs2 = SecondObserver(system=plant, K_x=K)
    t = np.cumsum(rng.uniform(5e-3, 1.5e-2, 150))
    U, Y = rng.standard_normal((150, m)), rng.standard_normal((150, r))
    x = x0 = rng.standard_normal(n)
    states = [x0]
    for i in range(len(t) - 1):
        x = obs2.step(x, U[i], Y[i], [0.5], t[i + 1] - t[i])
        states.append(x)
    ref = exact_reference(A, B, C, K, t, U, Y, x0)
    np.testing.assert_allclose(np.array(states), ref, rtol=EXACT_RTOL, atol=EXACT_RTOL)


@pytest.mark.parametrize("g_on_estimates", [False, True])
def test_step_converges_to_solve_ivp_of_rhs(g_on_estimates):
    obs2 = SecondObserver(system=motor_system(), K_x=second_gain(1.0),
                          g_on_estimates=g_on_estimates)
    theta = np.array([0.3])

    def v_of(t):
        return np.array([motor_input(t), 2.0 * np.sin(2 * np.pi * 1.5 * t) + 0.3])

    x0, T = np.array([0.5, 1e-3]), 0.3
    sol = solve_ivp(lambda t, x: obs2.rhs(t, x, v_of(t), theta), (0.0, T), x0,
                    method="Radau", rtol=1e-10, atol=1e-13, dense_output=True)
    err = []
    for dt in (4e-4, 1e-4):
        t = np.linspace(0.0, T, round(T / dt) + 1)
        x, worst = x0, 0.0
        for i in range(len(t) - 1):
            v = v_of(t[i])
            x = obs2.step(x, v[:1], v[1:], theta, t[i + 1] - t[i])
            worst = max(worst, abs(x[0] - sol.sol(t[i + 1])[0]))
        err.append(worst)
    assert err[1] < STEP_VS_IVP_OMEGA
    assert err[0] / err[1] > 3.0             # converges (first order or better) in dt


def test_g_on_estimates_takes_y_out_of_g():
    """With K_x2 = 0, x̂₂̇ depends on y only through g; g_on_estimates removes that."""
    x2, th = np.array([1.0, 1e-3]), np.array([0.3])
    rhs = {flag: SecondObserver(system=motor_system(), K_x=np.zeros((2, 1)),
                                g_on_estimates=flag).rhs for flag in (False, True)}
    assert not np.allclose(rhs[False](0.0, x2, [0.2, 2.0], th), rhs[False](0.0, x2, [0.2, 0.5], th))
    np.testing.assert_array_equal(rhs[True](0.0, x2, [0.2, 2.0], th),
                                  rhs[True](0.0, x2, [0.2, 0.5], th))
    # ... and equals g evaluated at y = C x̂₂ = 1.0
    np.testing.assert_allclose(rhs[True](0.0, x2, [0.2, 9.0], th),
                               rhs[False](0.0, x2, [0.2, 1.0], th), rtol=1e-14)


# --------------------------------------------------------------------------- attached
def test_attached_run_equals_loop_of_step_and_the_cascade(motor1k):
    t, u, x = (a[:400] for a in motor1k)
    obs = composite(g_on_estimates=True, law=DriftLaw(0.5))
    s0 = obs.init(x_hat0=[0.1, 0.0], theta_hat0=[0.2], x_hat_refined0=[-0.1, 0.0])
    assert obs.state_size == 2 + 1 + 1 + 2
    res = obs.run(t, u, x[:, 0], state0=s0)
    s, states = s0, [s0]
    for i in range(len(t) - 1):
        s = obs.step(s, [u[i]], [x[i, 0]], t[i + 1] - t[i])
        states.append(s)
    states = np.array(states)
    np.testing.assert_array_equal(res.x_hat_refined, states[:, 4:])
    np.testing.assert_array_equal(res.theta_hat, states[:, 3:4])
    assert np.ptp(res.theta_hat) > 0.15                           # θ̂ really moved
    # The cascade: the second observer alone, fed the first observer's θ̂(t_i), is the same.
    x2, alone = np.array([-0.1, 0.0]), [np.array([-0.1, 0.0])]
    for i in range(len(t) - 1):
        x2 = obs.second.step(x2, [u[i]], [x[i, 0]], res.theta_hat[i], t[i + 1] - t[i])
        alone.append(x2)
    np.testing.assert_allclose(np.array(alone), res.x_hat_refined, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("g_on_estimates", [False, True])
def test_refined_estimates_converge_noise_free(motor1k, g_on_estimates):
    t, u, x = motor1k
    obs = composite(g_on_estimates)
    res = obs.run(t, u, x[:, 0], state0=obs.init(x_hat0=[0.3, 0.0]))
    late = t >= 1.5
    assert res.x_hat_refined.shape == x.shape
    assert np.abs(res.x_hat_refined - x)[late, 0].max() < REFINED_OMEGA_BOUND


def test_refined_estimates_reject_output_noise(motor1k, rng):
    """Sec. VIII: g on estimates only keeps the noise of y out of x̂₂."""
    t, u, x = motor1k
    obs = composite(g_on_estimates=True)
    clean = obs.run(t, u, x[:, 0])
    noisy = obs.run(t, u, x[:, 0] + 0.1 * rng.standard_normal(t.shape))
    late = t >= 1.0

    def rms(a):
        return np.sqrt(np.mean(a[late] ** 2, axis=0))

    induced_first = rms(noisy.x_hat - clean.x_hat)
    induced_second = rms(noisy.x_hat_refined - clean.x_hat_refined)
    assert np.all(induced_second < 0.1 * induced_first)          # measured ≈ 1/48
    assert rms(noisy.x_hat_refined - x)[0] < 0.5 * rms(noisy.x_hat - x)[0]   # measured 1/6.6


def test_skip_predicts_both_observers(rng):
    n, m, r = 2, 1, 1
    A, B, C = rng.standard_normal((n, n)), rng.standard_normal((n, m)), rng.standard_normal((r, n))
    E = rng.standard_normal((n, 1))
    plant = PerturbedLinearSystem(A=A, B=B, C=C, E=E, perturbation=ZeroG((n, m, r, 1, 1)))
    K2 = scipy.signal.place_poles(A.T, C.T, [-2.0, -3.0]).gain_matrix.T
    obs = ModifiedHighGainObserver(system=plant, K_x=np.ones((n, r)), K_phi=np.ones((1, r)),
                                   update_law=ConstantLaw([0.5], Box([0.0], [1.0])),
                                   second=SecondObserver(system=plant, K_x=K2),
                                   nan_policy="skip", allow_nonminimum_phase=True)
    t = np.arange(50) * 1e-2
    U, Y = rng.standard_normal((50, m)), rng.standard_normal((50, r))
    missing = np.zeros(50, bool)
    missing[[4, 5, 6, 30]] = True
    Y[missing] = np.nan
    x0 = rng.standard_normal(n)
    res = obs.run(t, U, Y, state0=obs.init(x_hat0=x0))
    ref = exact_reference(A, B, C, K2, t, U, Y, x0, skip=missing)
    np.testing.assert_allclose(res.x_hat_refined, ref, rtol=EXACT_RTOL, atol=EXACT_RTOL)


# --------------------------------------------------------------------------- errors
def test_validation():
    with pytest.raises(DimensionError, match="K_x"):
        SecondObserver(system=motor_system(), K_x=np.ones((1, 2)))
    with pytest.raises(DimensionError, match="perturbation"):
        SecondObserver(system=PerturbedLinearSystem(A=A_MOTOR, B=B_MOTOR, C=C_MOTOR, E=E_MOTOR),
                       K_x=second_gain(1.0))
    other = PerturbedLinearSystem(A=[[-1.0]], B=[[1.0]], C=[[1.0]], E=[[1.0]],
                                  perturbation=ZeroG((1, 1, 1, 1, 1)))
    K_x, K_phi = first_gains(1.0)
    with pytest.raises(DimensionError, match="second observer"):
        ModifiedHighGainObserver(system=motor_system(), K_x=K_x, K_phi=K_phi,
                                 update_law=ConstantLaw([ALPHA0], THETA_SET),
                                 second=SecondObserver(system=other, K_x=[[1.0]]))
    plain = ModifiedHighGainObserver(system=motor_system(), K_x=K_x, K_phi=K_phi,
                                     update_law=ConstantLaw([ALPHA0], THETA_SET))
    with pytest.raises(DimensionError, match="no second observer"):
        plain.init(x_hat_refined0=[0.0, 0.0])
    obs2 = SecondObserver(system=motor_system(), K_x=second_gain(1.0))
    with pytest.raises(NonFiniteError):
        obs2.step(np.zeros(2), [0.0], [np.nan], [0.3], 1e-3)
    with pytest.raises(DimensionError, match="theta_hat"):
        obs2.step(np.zeros(2), [0.0], [0.0], [0.3, 0.1], 1e-3)


def test_defaults_from_design_and_repr():
    obs = composite(g_on_estimates=True)
    s = obs.init(x_hat0=[0.4, 0.0])
    np.testing.assert_array_equal(s[4:], [0.4, 0.0])               # x̂₂₀ defaults to x̂₀

    class Design:
        K = second_gain(1.0)

    obs2 = SecondObserver.from_design(motor_system(), Design(), g_on_estimates=True)
    np.testing.assert_array_equal(obs2.K_x, obs.second.K_x)
    assert obs2.g_on_estimates and "g_on_estimates=True" in repr(obs2)
