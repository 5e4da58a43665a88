"""Update laws of Propositions 1–4: convergence rates in the hypothetical case x̂ = x, φ̂ = φ
(against the Lyapunov bounds of the proofs), θ̂ ∈ Θ for every step, and the error paths."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import numpy as np
import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from thetahat.errors import DimensionError, NonFiniteError, ParameterSetError, UpdateLawError
from thetahat.estimation.observer.checks import check_monotonicity, excitation_report
from thetahat.estimation.observer.laws.projection import Saturation
from thetahat.estimation.observer.laws import (
    AlgebraicInversion,
    algebraic_from_perturbation,
    ConstantLaw,
    GradientInversion,
    IntermittentInversion,
    UpdateLaw,
    smooth_ramp,
)
from thetahat.model.paramset import Ball, Box, ConvexSet, Ellipsoid, ParameterSet
from thetahat.model.perturbation import SymbolicPerturbation
from thetahat.models import prop1_sinh, prop2_tanh, prop3_monotone, prop4_pe

#: Time step of the RK4 reference simulations: the fastest rate is ~10/s, so dt·rate <= 0.1
#: and the RK4 error (dt⁴) is far below the decay being measured.
DT = 0.01
#: log‖θ̃‖ is fitted while ‖θ̃‖ is above this floor, safely above rounding of θ ~ 1.
FIT_FLOOR = 1e-9
#: The identity log|θ̃(t)/θ̃(0)| = -γ∫l holds to rounding for the exact step; RK4 on the rate
#: with a piecewise-smooth l agrees to O(dt²) relative.
EXACT_RTOL, RK4_RTOL = 1e-9, 2e-3


# --------------------------------------------------------------------------- simulation

def _simulate(mod: ModuleType, law: UpdateLaw, theta_hat0, t_end: float, *,
              use_step: bool = False):
    """Plant with the true θ and the law fed with x̂ = x, φ̂ = φ (the hypothetical case).

    RK4 on col(x, θ̂) with θ̂̇ = law.rate, or RK4 on x and law.step for θ̂.
    Returns t, x, θ̂, v, φ on the grid.
    """
    sys = mod.system()
    g, th = sys.perturbation, mod.THETA
    A, B, C, E = sys.A, sys.B, sys.C, sys.E
    n = A.shape[0]

    def field(t, z):
        x, thh = z[:n], z[n:]
        u = mod.input_signal(t)
        v = np.concatenate([u, C @ x])
        phi = g.g(v, x, th)
        dth = np.zeros_like(thh) if use_step else law.rate(v, x, phi, thh)
        return np.concatenate([A @ x + B @ u + E @ phi, dth]), v, phi

    N = round(t_end / DT)
    t = np.arange(N + 1) * DT
    Z = np.empty((N + 1, n + len(th)))
    Z[0] = np.concatenate([[0.5, 0.0], theta_hat0])
    V, PHI = np.empty((N + 1, 2)), np.empty((N + 1, 1))
    z = Z[0].copy()
    for i in range(N):
        k1, V[i], PHI[i] = field(t[i], z)
        k2 = field(t[i] + DT / 2, z + DT / 2 * k1)[0]
        k3 = field(t[i] + DT / 2, z + DT / 2 * k2)[0]
        k4 = field(t[i] + DT, z + DT * k3)[0]
        z_new = z + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if use_step:
            z_new[n:] = law.step(V[i], z[:n], PHI[i], z[n:], DT)
        z = z_new
        Z[i + 1] = z
    _, V[N], PHI[N] = field(t[N], z)
    return t, Z[:, :n], Z[:, n:], V, PHI


def _fit_rate(t, err, t_min: float = 0.0) -> float:
    """Least-squares decay rate of log‖θ̃‖ over the part above FIT_FLOOR (and t >= t_min)."""
    keep = (err > FIT_FLOOR) & (t >= t_min)
    slope = np.polyfit(t[keep], np.log(err[keep]), 1)[0]
    return -slope


@pytest.fixture(scope="module")
def sim_p1():
    return _simulate(prop1_sinh, prop1_sinh.update_law(Gamma=2.0), [-0.45], 8.0)


@pytest.fixture(scope="module")
def sim_p2():
    return _simulate(prop2_tanh, prop2_tanh.update_law(Gamma=3.0), [2.8], 30.0)


@pytest.fixture(scope="module")
def sim_p3():
    return _simulate(prop3_monotone, prop3_monotone.update_law(Gamma=2.0), [-1.9], 8.0)


@pytest.fixture(scope="module")
def sim_p4():
    return _simulate(prop4_pe, prop4_pe.update_law(Gamma=2.0), [-1.5, 1.5], 40.0)


# --------------------------------------------------------------------------- convergence

def test_prop1_decays_at_rate_gamma(sim_p1):
    """V = ½θ̃ᵀΓ⁻¹θ̃ gives ‖θ̃‖ <= e^(-λ_min(Γ)t)‖θ̃(0)‖; with θ* = θ exactly it is equality."""
    t, _, th, _, _ = sim_p1
    err = np.abs(th[:, 0] - prop1_sinh.THETA[0])
    rate = _fit_rate(t, err)
    assert rate >= 2.0 * (1 - 1e-3)  # the bound λ_min(Γ) = 2
    assert rate == pytest.approx(2.0, rel=1e-3)
    assert err[-1] < 1e-6 and np.all(np.diff(err) <= 0)


def test_prop1_with_coupled_gain_and_active_projection():
    """p = 2, non-diagonal Γ, Θ a box the unprojected flow leaves: V still decays at
    rate >= 2λ_min(Γ), for the continuous law (RK4 on rate) and step by step for ``step``."""
    box = Box([0.0, 0.0], [1.0, 1.0])
    theta = np.array([0.95, 0.95])
    G = np.array([[3.0, 2.5], [2.5, 3.0]])  # eigenvalues 0.5 and 5.5
    law = AlgebraicInversion(lambda v, x, phi: theta + 0 * phi[..., :1], G, box)
    Gi, lam_min = np.linalg.inv(G), 0.5
    V = lambda th: 0.5 * (theta - th) @ Gi @ (theta - th)  # noqa: E731
    th0 = np.array([0.0, 0.6])
    free = theta + (th0 - theta) @ np.linalg.matrix_power(np.eye(2) - 0.01 * G, 20).T
    assert free[1] > 1.0  # without projection θ̂ would leave Θ
    args = (np.zeros(2), np.zeros(2), np.zeros(1))
    th, dt, touched = th0.copy(), 0.01, False
    for k in range(400):  # RK4 on the projected rate
        k1 = law.rate(*args, th)
        k2 = law.rate(*args, box.nearest(th + dt / 2 * k1))
        k3 = law.rate(*args, box.nearest(th + dt / 2 * k2))
        k4 = law.rate(*args, box.nearest(th + dt * k3))
        th = box.nearest(th + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4))
        touched |= bool(th[1] >= 1.0 - 1e-12)
        assert V(th) <= V(th0) * np.exp(-2 * lam_min * (k + 1) * dt) * (1 + 1e-6) + 1e-15
    assert touched
    th = th0.copy()
    for _ in range(400):  # exact flow + Γ⁻¹ projection contracts V at every step, any dt
        nxt = law.step(*args, th, 0.05)
        assert V(nxt) <= V(th) * np.exp(-2 * lam_min * 0.05) * (1 + 1e-12) + 1e-18
        th = nxt
    assert np.allclose(th, theta, atol=1e-8)


def _prop2_weight(sim):
    _, x, _, v, phi = sim
    return prop2_tanh.excitation_weight(v, x, phi)


def test_prop2_error_is_exp_of_minus_gamma_integral_of_l(sim_p2):
    """For p = 1 without projection θ̃(t) = θ̃(0) exp(-γ∫l) (Proposition 2's mechanism)."""
    th = sim_p2[2]
    l = _prop2_weight(sim_p2)
    err = np.abs(th[:, 0] - prop2_tanh.THETA[0])
    keep = err > FIT_FLOOR
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (l[1:] + l[:-1]) * DT)])
    assert np.allclose(np.log(err[keep] / err[0]), -3.0 * integral[keep],
                       rtol=RK4_RTOL, atol=RK4_RTOL)
    # the exact step reproduces it to rounding with the left-endpoint rule it uses
    sim2 = _simulate(prop2_tanh, prop2_tanh.update_law(Gamma=3.0), [2.8], 10.0, use_step=True)
    th2, l2 = sim2[2], _prop2_weight(sim2)
    err2 = np.abs(th2[:, 0] - prop2_tanh.THETA[0])
    left = np.concatenate([[0.0], np.cumsum(l2[:-1] * DT)])
    keep2 = err2 > FIT_FLOOR
    assert np.allclose(np.log(err2[keep2] / err2[0]), -3.0 * left[keep2], rtol=EXACT_RTOL,
                       atol=1e-7)


def prop2_lyapunov_rate(gamma: float, sigma: float, T: float) -> float:
    """Decay rate of ‖θ̃‖ from (16) with Γ = γ (κ = 1): V̇ <= -½μσe^(-T)‖θ̃‖², V <= ‖θ̃‖²/(2γ),
    with μ just below min(1/γ, 1/(½ + γ))."""
    mu = 0.999 * min(1.0 / gamma, 1.0 / (0.5 + gamma))
    return 0.5 * mu * sigma * np.exp(-T) * gamma


def test_prop2_rate_exceeds_the_pe_bounds(sim_p2):
    t, _, th, _, _ = sim_p2
    l = _prop2_weight(sim_p2)
    rate = _fit_rate(t, np.abs(th[:, 0] - prop2_tanh.THETA[0]))
    best_lyap, best_exact = 0.0, 0.0
    assert not excitation_report(t, l=l, window=2.0).is_exciting  # l = 0 for whole seconds
    for T in (5.0, 7.0, 2 * np.pi / 0.6):
        rep = excitation_report(t, l=l, window=T)
        assert rep.is_exciting
        best_lyap = max(best_lyap, prop2_lyapunov_rate(3.0, rep.sigma_l, T))
        best_exact = max(best_exact, 3.0 * rep.sigma_l / T)  # from θ̃ = θ̃₀e^(-γ∫l)
    assert rate > best_exact > best_lyap > 0
    assert rate < 3.0  # not faster than with l ≡ 1


def test_prop3_rate_exceeds_gamma_lambda_min_P(sim_p3):
    """(13) holds with P = λI, λ from the sampled check (>= 1); V̇ <= -θ̃ᵀPθ̃ gives rate >= γλ."""
    t, _, th, v, _ = sim_p3
    rep = check_monotonicity(prop3_monotone.system().perturbation, prop3_monotone.M,
                             v_box=Box([-2.0, -6.0], [2.0, 6.0]), x_box=Box([-6, -6], [6, 6]),
                             parameter_set=prop3_monotone.PARAMETER_SET, n_samples=4000)
    assert rep.holds and rep.P_bound >= 1.0
    err = np.abs(th[:, 0] - prop3_monotone.THETA[0])
    rate = _fit_rate(t, err, t_min=0.5)
    assert rate >= 2.0 * rep.P_bound
    # consistency: near θ, d log|θ̃|/dt = -γ ∂g/∂θ(θ) along the trajectory
    keep = (err > FIT_FLOOR) & (t >= 0.5)
    dgdth = (2 + np.sin(v[keep, 1])) * (1 + prop3_monotone.THETA[0] ** 2)
    assert rate == pytest.approx(2.0 * np.mean(dgdth), rel=0.1)


def prop4_lyapunov_rate(Gamma: np.ndarray, sigma: float, T: float, M_S: float, M_M: float,
                        L_g: float = 1.0) -> float:
    """Decay rate of ‖θ̃‖ from the proof of Proposition 4, maximised over admissible μ.

    V̇ <= -(1 - μ/2)s² - ½μσe^(-T)‖θ̃‖² + μ c s‖θ̃‖ with s² = θ̃ᵀSθ̃ and
    c = √κ M_S ‖Γ‖ M_M L_g; maximising over s gives V̇ <= -α‖θ̃‖² with
    α = ½μσe^(-T) - μ²c²/(4(1 - μ/2)); V <= ½λ_max(Γ⁻¹)‖θ̃‖² then gives rate α λ_min(Γ).
    """
    lam = np.linalg.eigvalsh(Gamma)
    kappa, normG = lam[-1] / lam[0], lam[-1]
    c = np.sqrt(kappa) * M_S * normG * M_M * L_g
    mu_max = min(1.0 / (lam[-1] * M_S),
                 2.0 / (1 + kappa * M_S**2 * normG**2 * M_M**2 * L_g**2 * np.exp(T) / sigma))
    mu = np.linspace(0, mu_max, 2001)[1:-1]
    alpha = 0.5 * mu * sigma * np.exp(-T) - mu**2 * c**2 / (4 * (1 - mu / 2))
    return float(max(alpha.max(), 0.0) * lam[0])


def test_prop4_rate_exceeds_the_lyapunov_bound(sim_p4):
    t, x, th, v, _ = sim_p4
    err = np.linalg.norm(th - prop4_pe.THETA, axis=-1)
    rate = _fit_rate(t, err)
    S = prop4_pe.S(v, x)
    psi_norm = np.sqrt(np.trace(S, axis1=-2, axis2=-1))
    M_S, M_M = float(np.max(psi_norm**2)), float(np.max(psi_norm))
    bound = 0.0
    for T in (1.0, 3.0, 10.0):
        rep = excitation_report(t, S=S, window=T)
        assert rep.is_exciting
        bound = max(bound, prop4_lyapunov_rate(2.0 * np.eye(2), rep.sigma_S, T, M_S, M_M))
    assert rate > bound > 0
    assert err[-1] < 1e-5 * err[0]
    # consistency with averaging: λ_min(Γ mean S) predicts the order of the rate
    avg = 2.0 * np.linalg.eigvalsh(S.mean(axis=0))[0]
    assert 0.3 * avg < rate < 1.5 * avg


# --------------------------------------------------------------------------- step

def test_step_agrees_with_rate_to_second_order():
    rng = np.random.default_rng(7)
    cases = [(prop1_sinh.update_law(), prop1_sinh), (prop2_tanh.update_law(), prop2_tanh),
             (prop3_monotone.update_law(), prop3_monotone), (prop4_pe.update_law(), prop4_pe)]
    for law, mod in cases:
        v = np.array([0.3, 0.7])
        x = rng.standard_normal(2)
        phi = mod.system().perturbation.g(v, x, mod.THETA)
        th = mod.PARAMETER_SET.sample(rng, 1)[0]
        r = law.rate(v, x, phi, th)
        errs = [np.linalg.norm(law.step(v, x, phi, th, dt) - (th + dt * r)) for dt in
                (1e-2, 1e-3)]
        assert errs[1] <= errs[0] / 50 + 1e-15  # O(dt²) local difference


def test_exponential_euler_is_stable_where_euler_is_not():
    """A huge γ·dt: the exponential-Euler step converges, Euler + projection bangs between
    the bounds (the reason for the default)."""
    law = prop3_monotone.update_law(Gamma=1e4)
    g = prop3_monotone.system().perturbation
    v, x = np.array([0.0, 0.3]), np.zeros(2)
    phi = g.g(v, x, prop3_monotone.THETA)
    th_exp = th_eul = np.array([-1.9])
    for _ in range(20):
        th_exp = law.step(v, x, phi, th_exp, 1.0)
        th_eul = UpdateLaw.step(law, v, x, phi, th_eul, 1.0)
    assert abs(th_exp[0] - prop3_monotone.THETA[0]) < 1e-8
    assert abs(th_eul[0] - prop3_monotone.THETA[0]) > 0.5


_x, _y, _u = sp.symbols("x0 y u")
_t1, _t2 = sp.symbols("t1 t2")
_G2 = SymbolicPerturbation.from_sympy([_u * sp.sinh(_t1) + _t2**3, sp.tanh(_t2 * _x) + _t1],
                                      u=[_u], y=[_y], x=[_x], theta=[_t1, _t2])
SETS2: dict[str, ParameterSet] = {
    "box": Box([-1.0, 0.5], [2.0, 1.5]),
    "ball": Ball([0.0, 1.0], 0.7),
    "ellipsoid": Ellipsoid([0.5, 1.0], [[4.0, 1.0], [1.0, 2.0]]),
    "convex": ConvexSet(P=lambda t: t[..., 0] ** 4 + (t[..., 1] - 1) ** 4 - 0.5,
                        grad_P=lambda t: np.stack([4 * t[..., 0] ** 3,
                                                   4 * (t[..., 1] - 1) ** 3], axis=-1),
                        interior_point=[0.0, 1.0]),
}


def _laws(ps: ParameterSet, G: np.ndarray) -> list[UpdateLaw]:
    outlier_star = lambda v, x, phi: np.where(np.abs(phi) < 1e3, phi, np.nan)  # noqa: E731
    return [
        AlgebraicInversion(lambda v, x, phi: phi, G, ps),
        IntermittentInversion(outlier_star, smooth_ramp(0.5, 1.0), G, ps, on_invalid="freeze"),
        GradientInversion(_G2, G, ps),
        GradientInversion(_G2, G, ps, layer=0.1,
                          saturation=Saturation(phi_box=Box([-5, -5], [5, 5]), margin=1.0)),
        ConstantLaw(ps.interior_point, ps),
    ]


extreme = st.one_of(st.floats(-1e3, 1e3), st.sampled_from([0.0, 1e300, -1e300, 1e-300, 7e10]))
vec2 = st.lists(extreme, min_size=2, max_size=2).map(np.array)


@settings(max_examples=50, deadline=None)
@given(name=st.sampled_from(sorted(SETS2)), v=vec2, phi=vec2,
       x=st.lists(extreme, min_size=1, max_size=1).map(np.array),
       gain=st.sampled_from([1e-6, 1.0, 1e6, 1e12]), coupled=st.booleans(),
       dt=st.sampled_from([1e-6, 0.01, 1.0, 1e6]), seed=st.integers(0, 2**16))
def test_step_stays_in_theta_for_any_data(name, v, phi, x, gain, coupled, dt, seed):
    ps = SETS2[name]
    G = gain * (np.array([[1.0, 0.95], [0.95, 1.0]]) if coupled else np.diag([1.0, 3.0]))
    rng = np.random.default_rng(seed)
    th = np.stack([ps.sample(rng, 1)[0], ps.nearest(ps.interior_point + 1e3 * rng.normal(size=2)),
                   ps.interior_point + 10 * rng.normal(size=2)])  # inside, on ∂Θ, outside
    for law in _laws(ps, G):
        nxt = law.step(v, x, phi, th, dt)
        assert nxt.shape == (3, 2) and np.all(np.isfinite(nxt))
        assert np.all(ps.contains(nxt)), (law, nxt)


# --------------------------------------------------------------------------- SymPy θ*

def test_theta_star_derived_with_sympy_matches_the_closed_form():
    rng = np.random.default_rng(8)
    v = rng.normal(size=(50, 2))
    x = rng.normal(size=(50, 2))
    derive = {prop1_sinh: algebraic_from_perturbation,
              prop2_tanh: lambda g, **kw: IntermittentInversion.from_perturbation(
                  g, prop2_tanh.excitation_weight, **kw)}
    for mod, build in derive.items():
        law = build(mod.system().perturbation, Gamma=1.0, parameter_set=mod.PARAMETER_SET)
        phi = mod.system().perturbation.g(v, x, mod.THETA)
        assert np.allclose(law.theta_star(v, x, phi), mod.theta_star(v, x, phi), rtol=1e-10)


def _scalar(expr, theta):
    return SymbolicPerturbation.from_sympy(expr, u=[_u], y=[_y], x=[_x], theta=[theta])


def test_sympy_inverse_must_be_unique_on_theta():
    th = sp.Symbol("th")
    with pytest.raises(UpdateLawError, match="not unique"):  # asin and π - asin on [0, 3]
        algebraic_from_perturbation(_scalar(sp.sin(th), th), Gamma=1.0,
                                    parameter_set=Box([0.0], [3.0]))
    with pytest.raises(UpdateLawError, match="not unique"):  # ±√φ on [-1, 1]
        algebraic_from_perturbation(_scalar(th**2, th), Gamma=1.0,
                                    parameter_set=Box([-1.0], [1.0]))
    law = algebraic_from_perturbation(_scalar(th**2, th), Gamma=1.0,
                                      parameter_set=Box([0.1], [1.0]))
    assert law.theta_star(np.zeros(2), np.zeros(1), np.array([0.25]))[0] == pytest.approx(0.5)
    with pytest.raises(UpdateLawError, match="leaves some parameters free"):
        algebraic_from_perturbation(prop4_pe.system().perturbation, Gamma=1.0,
                                    parameter_set=prop4_pe.PARAMETER_SET)
    with pytest.raises(UpdateLawError, match="needs a SymbolicPerturbation"):
        algebraic_from_perturbation(object(), Gamma=1.0,  # type: ignore[arg-type]
                                    parameter_set=Box([0.0], [1.0]))


# --------------------------------------------------------------------------- errors

BOX1 = Box([0.0], [2.0])
ARGS1 = (np.zeros(2), np.zeros(2), np.array([1.0]), np.array([1.0]))


def _each_law(Gamma) -> list[Callable[[], UpdateLaw]]:
    return [lambda: AlgebraicInversion(lambda v, x, phi: phi, Gamma, BOX1),
            lambda: IntermittentInversion(lambda v, x, phi: phi, smooth_ramp(0, 1), Gamma, BOX1),
            lambda: GradientInversion(prop3_monotone.system().perturbation, Gamma,
                                      prop3_monotone.PARAMETER_SET)]


@pytest.mark.parametrize("Gamma, match", [(-1.0, "positive definite"),
                                          ([[1.0, 2.0]], r"\(1, 1\) matrix"),
                                          (np.nan, "NaN or inf")])
def test_gain_must_be_symmetric_positive_definite(Gamma, match):
    for make in _each_law(Gamma):
        with pytest.raises(UpdateLawError, match=match):
            make()
    with pytest.raises(UpdateLawError, match="symmetric"):
        AlgebraicInversion(lambda v, x, phi: phi, [[1.0, 0.3], [0.0, 1.0]],
                           Box([0.0, 0.0], [1.0, 1.0]))


def test_initial_estimate_must_lie_in_theta():
    law = _each_law(1.0)[0]()
    with pytest.raises(ParameterSetError, match="outside Θ"):
        law.init([2.5])
    with pytest.raises(ParameterSetError, match="outside Θ"):
        ConstantLaw([-0.1], BOX1)
    assert law.init().tolist() == [1.0]  # default: the centre of Θ
    assert law.init([2.0 + 1e-14]).tolist() == [2.0]  # rounding is snapped, not rejected
    with pytest.raises(NonFiniteError):
        law.init([np.nan])


def test_theta_star_nan_where_l_positive_raises_or_freezes():
    star = lambda v, x, phi: np.where(phi > 0, 1.0 / phi, np.nan)  # noqa: E731
    ramp = smooth_ramp(0.0, 0.5)
    raising = IntermittentInversion(star, ramp, 1.0, BOX1)
    with pytest.raises(UpdateLawError, match="NaN or inf at 1 point"):
        raising.rate(np.zeros(2), np.zeros(2), np.array([-1.0]), np.array([1.0]))
    with pytest.raises(UpdateLawError, match="on_invalid='freeze'"):
        raising.step(np.zeros(2), np.zeros(2), np.array([-1.0]), np.array([1.0]), 0.1)
    frozen = IntermittentInversion(star, ramp, 1.0, BOX1, on_invalid="freeze")
    phi = np.array([[-1.0], [0.0], [2.0]])  # θ* NaN (l > 0), θ* NaN (l = 0), θ* = 0.5
    rate = frozen.rate(np.zeros(2), np.zeros(2), phi, np.array([1.0]))
    assert rate[:, 0].tolist() == [0.0, 0.0, -0.5]
    nxt = frozen.step(np.zeros(2), np.zeros(2), phi, np.array([1.0]), 0.1)
    assert nxt[:2, 0].tolist() == [1.0, 1.0] and 0.5 < nxt[2, 0] < 1.0
    # where l = 0, a NaN θ* is legitimate even with on_invalid='raise'
    assert raising.rate(np.zeros(2), np.zeros(2), np.array([0.0]), np.array([1.0]))[0] == 0.0
    with pytest.raises(UpdateLawError, match="on_invalid must be"):
        IntermittentInversion(star, ramp, 1.0, BOX1, on_invalid="ignore")  # type: ignore


def test_bad_callables_and_data():
    bad_l = IntermittentInversion(lambda v, x, phi: phi, lambda v, x, phi: 2.0, 1.0, BOX1)
    with pytest.raises(UpdateLawError, match=r"values in \[0, 1\]"):
        bad_l.rate(*ARGS1)
    bad_star = AlgebraicInversion(lambda v, x, phi: np.ones(3), 1.0, BOX1)
    with pytest.raises(UpdateLawError, match=r"theta_star must return shape \(\.\.\., 1\)"):
        bad_star.rate(*ARGS1)
    bad_M = GradientInversion(prop3_monotone.system().perturbation, 1.0,
                              prop3_monotone.PARAMETER_SET, M=lambda v, x, th: np.ones((2, 2)))
    with pytest.raises(UpdateLawError, match=r"M must return shape \(\.\.\., 1, 1\)"):
        bad_M.rate(*ARGS1)
    with pytest.raises(DimensionError, match="p = 2 parameters"):
        GradientInversion(prop4_pe.system().perturbation, 1.0, BOX1)
    law = _each_law(1.0)[0]()
    with pytest.raises(NonFiniteError, match="phi_hat contains NaN"):
        law.rate(np.zeros(2), np.zeros(2), np.array([np.nan]), np.array([1.0]))
    with pytest.raises(DimensionError, match="dt must be > 0"):
        law.step(*ARGS1, 0.0)
    with pytest.raises(DimensionError, match=r"theta_hat must have shape \(\.\.\., 1\)"):
        law.rate(np.zeros(2), np.zeros(2), np.array([1.0]), np.array([1.0, 2.0]))
    huge = prop3_monotone.update_law(Gamma=1e300)
    with pytest.raises(UpdateLawError, match="overflowed"):
        huge.rate(np.zeros(2), np.zeros(2), np.array([1e300]), np.array([0.0]))


# --------------------------------------------------------------------------- pieces

@settings(max_examples=60, deadline=None)
@given(low=st.floats(0, 5), width=st.floats(0.01, 5), a=st.floats(-10, 20), b=st.floats(-10, 20))
def test_smooth_ramp_is_a_lipschitz_weight(low, width, a, b):
    ramp = smooth_ramp(low, low + width)
    wa, wb = ramp.weight(a), ramp.weight(b)
    assert 0.0 <= wa <= 1.0
    assert abs(wa - wb) <= 1.5 / width * abs(a - b) + 1e-12
    if a <= low:
        assert wa == 0.0
    if a >= low + width:
        assert wa == 1.0


def test_smooth_ramp_validates_and_reads_phi_norm():
    with pytest.raises(UpdateLawError, match="0 <= low < high"):
        smooth_ramp(1.0, 1.0)
    with pytest.raises(UpdateLawError, match="0 <= low < high"):
        smooth_ramp(-1.0, 1.0)
    ramp = smooth_ramp(0.0, 1.0)
    assert ramp(np.zeros(2), np.zeros(2), np.array([0.3, 0.4])) == pytest.approx(0.5)
    assert repr(ramp) == "smooth_ramp(low=0.0, high=1.0)"


def test_constant_law():
    law = ConstantLaw([0.5, 1.0], SETS2["box"])
    v, x, phi = np.zeros((4, 2)), np.zeros((4, 1)), np.zeros((4, 2))
    th = SETS2["box"].sample(np.random.default_rng(9), 4)
    assert np.array_equal(law.rate(v, x, phi, th), np.zeros((4, 2)))
    assert np.array_equal(law.step(v, x, phi, th, 0.1), th)
    assert law.init().tolist() == [0.5, 1.0]


def test_saturation_removes_outliers_before_the_law():
    sat = Saturation(phi_box=Box([-1.0], [1.0]))
    law = prop1_sinh.update_law()
    clipped = AlgebraicInversion(prop1_sinh.theta_star, 2.0, prop1_sinh.PARAMETER_SET,
                                 saturation=sat)
    v, x, th = np.array([0.0, 0.5]), np.zeros(2), np.array([0.0])
    assert np.array_equal(clipped.rate(v, x, np.array([1e6]), th),
                          law.rate(v, x, np.array([1.0]), th))


@pytest.mark.parametrize("make", [lambda: prop1_sinh.update_law(),
                                  lambda: prop2_tanh.update_law(),
                                  lambda: prop3_monotone.update_law(),
                                  lambda: prop4_pe.update_law(Gamma=[[2.0, 0.5], [0.5, 1.0]])])
def test_rate_and_step_vectorise_over_a_batch(make):
    law = make()
    ps = law.parameter_set
    rng = np.random.default_rng(10)
    v = rng.normal(size=(6, 2))
    x = rng.normal(size=(6, 2))
    phi = rng.uniform(-0.95, 0.95, size=(6, 1))
    th = ps.sample(rng, 6)
    batch = law.rate(v, x, phi, th)
    single = np.stack([law.rate(v[i], x[i], phi[i], th[i]) for i in range(6)])
    assert batch.shape == (6, ps.dim) and np.allclose(batch, single, rtol=1e-12, atol=1e-14)
    steps = law.step(v, x, phi, th, 0.1)
    assert np.allclose(steps, [law.step(v[i], x[i], phi[i], th[i], 0.1) for i in range(6)],
                       rtol=1e-12, atol=1e-14)
