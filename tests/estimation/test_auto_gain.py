"""Gamma = "auto": the gradient law's Γ from the record's information (estimation.observer.auto_gain).

Evidence: the choice is invariant to the parameters' units (rescaling a parameter rescales its
estimate exactly and changes nothing else), the default of the gradient law in model files is
"auto" while an explicit Γ is kept, and the inversion laws refuse it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import ModelFileError, UpdateLawError
from thetahat.estimation.observer.auto_gain import information_gain
from thetahat.modelfile import loads_model, run_estimator, simulate_model
from thetahat.model.parse import parse_perturbation

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: Two runs that differ only in a parameter's unit agree to rounding (relative).
UNIT_RTOL = 1e-8
SCALE = 1000.0


def _prop4(scale: float, gamma: str | None) -> str:
    text = (EXAMPLES / "prop4.toml").read_text()
    text = text.replace('g = "theta1*sin(y) + theta2*tanh(u)"',
                        f'g = "theta1*sin(y) + theta2/{scale!r}*tanh(u)"')
    text = text.replace("lower = [-2.0, -2.0]", f"lower = [-2.0, {-2.0 * scale!r}]")
    text = text.replace("upper = [2.0, 2.0]", f"upper = [2.0, {2.0 * scale!r}]")
    gamma_line = "" if gamma is None else f"Gamma = {gamma}"
    return text.replace("Gamma = 4.0", gamma_line)


def test_auto_gain_does_not_depend_on_the_parameters_units():
    base = loads_model(_prop4(1.0, None))
    scaled = loads_model(_prop4(SCALE, None))
    assert base.estimator.gamma_auto and scaled.estimator.gamma_auto
    d = simulate_model(base, 0, t_end=5.0)
    a = run_estimator(base, d.t, d.u, d.y, diagnose=False)
    b = run_estimator(scaled, d.t, d.u, d.y, diagnose=False)
    assert np.allclose(b.theta_hat[:, 0], a.theta_hat[:, 0], rtol=UNIT_RTOL, atol=1e-12)
    assert np.allclose(b.theta_hat[:, 1] / SCALE, a.theta_hat[:, 1], rtol=UNIT_RTOL,
                       atol=1e-12)
    # and the law moved: θ̂ is not θ̂₀ at the end
    assert np.all(np.abs(a.theta_hat[-1] - a.theta_hat[0]) > 1e-3)


def test_explicit_gamma_is_kept_and_inversion_laws_refuse_auto():
    spec = loads_model(_prop4(1.0, "4.0"))
    assert not spec.estimator.gamma_auto
    assert np.allclose(spec.estimator.update_law.Gamma, 4.0 * np.eye(2))
    text = (EXAMPLES / "prop1.toml").read_text()
    text = text.replace("Gamma = 2.0", 'Gamma = "auto"')
    with pytest.raises(ModelFileError, match="'auto' is for the gradient and least-squares laws"):
        loads_model(text)


def test_information_gain_matches_the_definition_and_names_dead_parameters():
    g = parse_perturbation("a*y + b*u", u=["u"], y=["y"], x=["x"], theta=["a", "b"])
    rng = np.random.default_rng(1)
    v = rng.standard_normal((500, 2))
    G = information_gain(g, v, np.zeros((500, 1)), np.zeros(2), 2.0, kappa=4.0)
    # H = mean(col(y, u) col(y, u)ᵀ); Γ = κ/T diag(H)⁻¹
    assert np.allclose(np.diag(G), 4.0 / 2.0 / np.mean(v[:, ::-1] ** 2, axis=0))
    assert np.count_nonzero(G - np.diag(np.diag(G))) == 0
    v[:, 0] = 0.0                                  # u ≡ 0: b gets no information
    with pytest.raises(UpdateLawError, match=r"parameter\(s\) \[1\]"):
        information_gain(g, v, np.zeros((500, 1)), np.zeros(2), 2.0)
