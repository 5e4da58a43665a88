"""Sampled checks of condition (13)/(14) and of persistency of excitation."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from thetahat.errors import DimensionError, NonFiniteError
from thetahat.estimation.observer.checks import check_monotonicity, excitation_report
from thetahat.model.paramset import Ball, Box
from thetahat.model.perturbation import SymbolicPerturbation
from thetahat.models import prop3_monotone, prop4_pe

#: Window integrals use the trapezoid rule on a grid of 1e-3: errors are O(dt²) per window.
QUAD_ATOL = 1e-4

u, y, x1, x2 = sp.symbols("u y x1 x2")
th = sp.Symbol("theta")
V_BOX = Box([-2.0, -3.0], [2.0, 3.0])
X_BOX = Box([-3.0, -3.0], [3.0, 3.0])


def _g(expr, theta=(th,)):
    return SymbolicPerturbation.from_sympy(expr, u=[u], y=[y], x=[x1, x2], theta=list(theta))


def test_violation_found_for_a_non_monotone_g():
    """g = sin θ on Θ = [0, 3]: ∂g/∂θ = cos θ changes sign at π/2, so (13) fails."""
    rep = check_monotonicity(_g(sp.sin(th)), v_box=V_BOX, x_box=X_BOX,
                             parameter_set=Box([0.0], [3.0]), n_samples=500, seed=1)
    assert not rep.holds and rep.worst_eigenvalue < -0.5
    t1, t2 = float(rep.theta1[0]), float(rep.theta2[0])
    assert (t1 - np.pi / 2) * (t2 - np.pi / 2) < 0  # the pair straddles π/2
    assert rep.worst_eigenvalue == pytest.approx(4 * np.cos(t1) * np.cos(t2) / 2, rel=1e-12)
    assert "VIOLATED" in repr(rep)
    # restricted to [0, 1.4] the same g is monotone
    ok = check_monotonicity(_g(sp.sin(th)), v_box=V_BOX, x_box=X_BOX,
                            parameter_set=Box([0.0], [1.4]), n_samples=500, seed=1)
    assert ok.holds and ok.P_bound >= np.cos(1.4) ** 2 - 1e-12


def test_prop3_example_satisfies_13_with_P_at_least_1():
    sys = prop3_monotone.system()
    rep = check_monotonicity(sys.perturbation, prop3_monotone.M, v_box=V_BOX, x_box=X_BOX,
                             parameter_set=prop3_monotone.PARAMETER_SET, n_samples=3000)
    assert rep.holds and rep.P_bound >= 1.0
    # sharp: the minimum 2(2 + sin y)(1 + θ₂²) >= 2 is approached at sin y -> -1, θ₂ -> 0
    assert rep.P_bound < 1.3


def test_prop4_example_fails_13_but_satisfies_14():
    sys = prop4_pe.system()
    kw = {"v_box": V_BOX, "x_box": X_BOX, "parameter_set": prop4_pe.PARAMETER_SET,
          "n_samples": 1000}
    rep13 = check_monotonicity(sys.perturbation, **kw)
    assert not rep13.holds  # ψψᵀ is singular: no P > 0
    assert abs(rep13.worst_eigenvalue) < 1e-12
    rep14 = check_monotonicity(sys.perturbation, S=prop4_pe.S, **kw)
    assert rep14.holds and rep14.with_S
    # with a too large S (3ψψᵀ) the check fails
    big = check_monotonicity(sys.perturbation, S=lambda v, x: 3 * prop4_pe.S(v, x), **kw)
    assert not big.holds


def test_check_is_reproducible_and_validates():
    g = _g(sp.sin(th))
    kw = {"v_box": V_BOX, "x_box": X_BOX, "parameter_set": Ball([1.0], 1.0),
          "n_samples": 200}
    a, b = check_monotonicity(g, seed=5, **kw), check_monotonicity(g, seed=5, **kw)
    assert a.worst_eigenvalue == b.worst_eigenvalue and np.array_equal(a.theta1, b.theta1)
    with pytest.raises(DimensionError, match="v_box must be a Box of dimension 2"):
        check_monotonicity(g, v_box=Box([0.0], [1.0]), x_box=X_BOX,
                           parameter_set=Box([0.0], [1.0]))
    with pytest.raises(DimensionError, match="parameter_set must be a ParameterSet of dimension 1"):
        check_monotonicity(g, v_box=V_BOX, x_box=X_BOX, parameter_set=Box([0, 0], [1, 1]))
    with pytest.raises(NonFiniteError), np.errstate(invalid="ignore"):  # √θ for θ < 0
        check_monotonicity(_g(sp.sqrt(th)), v_box=V_BOX, x_box=X_BOX,
                           parameter_set=Box([-1.0], [1.0]), n_samples=50)


def test_excitation_of_l_matches_the_analytic_value():
    t = np.linspace(0.0, 30.0, 30001)
    l = np.clip(np.sin(t), 0.0, None)  # ∫ over any 2π window = 2
    rep = excitation_report(t, l=l, window=2 * np.pi)
    assert rep.sigma_l == pytest.approx(2.0, abs=QUAD_ATOL) and rep.is_exciting
    short = excitation_report(t, l=l, window=2.0)  # a window inside sin < 0 sees nothing
    assert short.sigma_l == pytest.approx(0.0, abs=QUAD_ATOL)
    assert np.sin(short.t_l + 1.0) < 0 and not short.is_exciting
    assert rep.n_windows == np.sum(t + 2 * np.pi <= t[-1] + 1e-9)


def test_excitation_of_S_detects_rank_deficiency():
    t = np.linspace(0.0, 20.0, 20001)
    psi = np.stack([np.cos(t), np.sin(t)], axis=-1)
    S = psi[:, :, None] * psi[:, None, :]  # ∫ over 2π = πI
    rep = excitation_report(t, S=S, window=2 * np.pi)
    assert rep.sigma_S == pytest.approx(np.pi, abs=QUAD_ATOL)
    flat = np.stack([np.sin(t), 2 * np.sin(t)], axis=-1)  # ψ always along (1, 2): not PE
    Sf = flat[:, :, None] * flat[:, None, :]
    bad = excitation_report(t, S=Sf, window=2 * np.pi)
    assert abs(bad.sigma_S) < 1e-9 and not bad.is_exciting
    both = excitation_report(t, l=np.ones_like(t), S=S, window=1.0)
    assert both.sigma_l == pytest.approx(1.0) and "sigma_S" in repr(both)


def test_excitation_report_validates():
    t = np.linspace(0.0, 1.0, 11)
    with pytest.raises(DimensionError, match="shorter than the window"):
        excitation_report(t, l=np.ones(11), window=2.0)
    with pytest.raises(DimensionError, match="strictly increasing"):
        excitation_report(t[::-1], l=np.ones(11), window=0.5)
    with pytest.raises(DimensionError, match="give l"):
        excitation_report(t, window=0.5)
    with pytest.raises(DimensionError, match=r"S must have shape \(11, p, p\)"):
        excitation_report(t, S=np.ones((11, 2)), window=0.5)
    with pytest.raises(NonFiniteError):
        excitation_report(t, l=np.full(11, np.nan), window=0.5)


# ------------------------------------------------------------- the law's conditions along a run
def _stribeck_run(t_end=10.0):
    """The newcomer's Stribeck model (examples/stribeck.toml) along a synthetic run: the mass
    oscillates at 0.05 m/s amplitude, θ̂ held at the true (F_c, F_s, v_s) = (1, 1.5, 0.02)."""
    from pathlib import Path
    from thetahat.modelfile import load_model
    spec = load_model(Path(__file__).resolve().parents[2] / "examples" / "stribeck.toml")
    t = np.linspace(0.0, t_end, 2001)
    vel = 0.05 * np.sin(2 * np.pi * 0.5 * t)
    pos = -0.05 / (np.pi) * np.cos(2 * np.pi * 0.5 * t)
    X = np.column_stack([pos, vel])
    V = np.column_stack([np.sin(t), pos])                       # col(u, y)
    TH = np.tile([1.0, 1.5, 0.02], (t.size, 1))
    return spec, t, V, X, TH


def test_stribeck_fails_14_for_v_s_and_names_the_velocity():
    """∂g/∂v_s = (F_s − F_c)·2v²/v_s³·e^{−(v/v_s)²}·tanh(v/ε_v): its sign follows v, and flips
    with F_s − F_c, which the file's Θ lets change sign: (14) fails for v_s (and only for
    v_s: ∂g/∂F_c and ∂g/∂F_s follow sign(v) alone, whatever θ)."""
    from thetahat.estimation.observer.checks import law_conditions_on_record
    spec, t, V, X, TH = _stribeck_run()
    s = spec.system
    rep = law_conditions_on_record(s.perturbation, t, V, X, TH, s.parameter_set,
                                   law=spec.estimator.update_law, names=spec.parameter_names,
                                   signal_names=("u", "y", "x", "v"))
    assert rep.failing == ("v_s",)
    assert rep.sign_with[2] == "v"
    w = rep.warnings[0]
    assert "condition (14)" in w and "v_s" in w and "its sign follows v" in w
    lo = s.parameter_set.lower
    F_c, F_s = rep.witness[2][0], rep.witness[2][1]
    assert F_s < F_c and np.all(rep.witness[2] >= lo)          # a point of Θ with F_s < F_c


@pytest.mark.parametrize("name", ["prop4", "heater", "actuator"])
def test_linear_in_theta_models_meet_14_along_their_scenario(name):
    """g linear in θ (prop4: θ1 sin y + θ2 tanh u; the heater; the actuator): ∂g/∂θ does not
    depend on θ, so every diagonal entry of (14) is (∂g/∂θᵢ)² ≥ 0 and the scenario's input
    excites every quarter of the record."""
    from pathlib import Path
    from thetahat.estimation.observer.checks import law_conditions_on_record
    from thetahat.modelfile import load_model, simulate_model
    spec = load_model(Path(__file__).resolve().parents[2] / "examples" / f"{name}.toml")
    s = spec.system
    d = simulate_model(spec, 0)
    N = d.t.size
    TH = np.tile(spec.scenario.theta, (N, 1))
    rep = law_conditions_on_record(s.perturbation, d.t, np.column_stack([d.u, d.y]), d.x, TH,
                                   s.parameter_set, law=spec.estimator.update_law)
    assert rep.proposition == "(14)" and rep.failing == () and rep.exciting
    assert rep.warnings == ()


def test_a_quiet_quarter_is_reported_as_missing_excitation():
    """prop4 with u ≡ 0 and y ≡ 0 over the last 30 % of the run: ∂g/∂θ = (sin y, tanh u)
    vanishes there, and a whole window of a quarter of the record has no excitation."""
    from thetahat.estimation.observer.checks import law_conditions_on_record
    g = prop4_pe.system().perturbation
    t = np.linspace(0.0, 20.0, 2001)
    quiet = t > 14.0
    V = np.column_stack([np.where(quiet, 0.0, np.sin(1.3 * t)), np.where(quiet, 0.0, np.cos(t))])
    X = np.column_stack([V[:, 1], np.zeros_like(t)])
    TH = np.tile(prop4_pe.THETA, (t.size, 1))
    rep = law_conditions_on_record(g, t, V, X, TH, prop4_pe.PARAMETER_SET,
                                   law=prop4_pe.update_law(1.0))
    assert not rep.exciting and rep.failing == ()
    assert any("excitation the update law needs" in w for w in rep.warnings)
    assert rep.excitation.t_S >= 13.99                 # the window lies in the quiet part
