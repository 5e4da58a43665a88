"""The least-squares law on the filtered regressor: the observer's error filter against an
independent simulation, the law's rest point on noise-free records of shipped models, θ̂ ∈ Θ
on noisy ones (box and ball), and its refusals."""

from __future__ import annotations

import dataclasses
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

from thetahat.errors import ModelFileError, ThetahatWarning, UpdateLawError
from thetahat.estimation.observer.laws.least_squares import FilteredLeastSquares, error_filter
from thetahat.estimation.observer.laws import ConstantLaw
from thetahat.model.paramset import Ball
from thetahat.modelfile import (auto_gamma, build_estimator, loads_model, simulate_model,
                                start_x_hat)

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def least_squares_file(name: str, *, noise: float | None = None) -> str:
    """A shipped model file with the least-squares law (Γ₀ "auto"), optionally its noise."""
    text = (EXAMPLES / f"{name}.toml").read_text()
    text = re.sub(r'law = "gradient"', 'law = "least_squares"', text)
    text = re.sub(r"\nGamma = [^\n]*", "\n", text)
    if noise is not None:
        text = re.sub(r"\nnoise_std = [^\n]*", "", text)
        if "\n[scenario]" in text:
            text = text.replace("\n[scenario]", f"\n[scenario]\nnoise_std = {noise!r}", 1)
        else:
            text += f"\n[scenario]\nnoise_std = {noise!r}\n"
    return text


def run_paper(spec, d, Gamma=None):
    est = build_estimator(spec, method="paper", Gamma=Gamma)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ThetahatWarning)       # the law runs in Python
        return est.run(d.t, d.u, d.y, state0=est.init(x_hat0=start_x_hat(spec, d.y),
                                                      theta_hat0=spec.estimator.theta_hat0))


@pytest.mark.parametrize("name", ["prop4", "heater", "actuator"])
def test_the_residual_is_the_filtered_regressor_times_the_error(name):
    # θ̂ held at θ̂₀ ≠ θ on a noise-free record of a model linear in θ: the observer's
    # residual z = φ̂ − g(v, x̂, θ̂₀) is F[∂g/∂θ](θ − θ̂₀), F the error filter, here simulated
    # independently by scipy.signal.lsim (the observer steps its own exact discretisation)
    spec = loads_model(least_squares_file(name, noise=0.0))
    d = simulate_model(spec, 0)
    s, th0 = spec.system, np.asarray(spec.estimator.theta_hat0)
    theta = np.asarray(spec.scenario.theta)
    obs = build_estimator(spec, method="paper", Gamma=np.eye(s.p))
    held = type(obs)(system=s, K_x=obs.K_x, K_phi=obs.K_phi,
                     update_law=ConstantLaw(th0, s.parameter_set),
                     second=obs.second)
    res = held.run(d.t, d.u, d.y, state0=held.init(x_hat0=start_x_hat(spec, d.y),
                                                   theta_hat0=th0))
    v = np.concatenate([np.asarray(d.u).reshape(d.t.size, -1),
                        np.asarray(d.y).reshape(d.t.size, -1)], axis=1)
    pert = s.perturbation
    z = res.phi_hat - pert.g(v, res.x_hat, th0)
    J = pert.dg_dtheta(v, res.x_hat, th0)                            # (N, k, p)
    F = error_filter(s, obs.K_x, obs.K_phi)
    sys_ = scipy.signal.StateSpace(F.L, F.G, F.H, np.zeros((s.k, s.k)))
    _, Wth, _ = scipy.signal.lsim(sys_, J @ (theta - th0), d.t, interp=False)
    Wth = Wth.reshape(d.t.size, s.k)
    tail = slice(d.t.size // 4, None)                                 # past the start-up
    scale = np.max(np.abs(Wth[tail]))
    # J uses the measured y only, so what is left is the sampled data's hold: 0.1–0.2 % of the
    # residual's scale on prop4 and the heater, 1.4 % on the actuator, whose observer holds u
    # while its plant saw a continuous sine at 131 Hz
    assert np.max(np.abs(z[tail] - Wth[tail])) < 0.02 * scale


@pytest.mark.parametrize("name", ["prop3", "prop4", "heater", "actuator"])
def test_noise_free_records_give_theta(name):
    # with a prior worth 1e-5 of the record (Γ₀ = 1000 × "auto"), the law's rest point on a
    # noise-free record is θ; what is left is the sampled observer's discretisation and, for
    # prop3, g's nonlinearity in θ: the heater (ε = 1, the slowest observer) is at 1.5 % of
    # the initial error, prop4 at 0.04 %
    spec = loads_model(least_squares_file(name, noise=0.0))
    d = simulate_model(spec, 0)
    G = auto_gamma(spec, d.t, d.u, d.y)
    res = run_paper(spec, d, Gamma=1e3 * G)
    theta, th0 = np.asarray(spec.scenario.theta), np.asarray(spec.estimator.theta_hat0)
    assert np.all(np.abs(res.theta_hat[-1] - theta) <= 0.03 * np.abs(th0 - theta)), \
        (res.theta_hat[-1], theta)


@pytest.mark.parametrize("name", ["prop4", "two_inertia", "spring_friction"])
def test_theta_hat_stays_in_a_box_and_a_ball_on_noisy_records(name):
    # ten times the file's noise, default Γ₀: θ̂ in Θ at every sample, for the file's box
    # and for the ball inscribed in it (the R-weighted projection onto a ball)
    spec = loads_model(least_squares_file(name))
    d = simulate_model(spec, 1)
    rng = np.random.default_rng(1)
    y = np.asarray(d.y) + 10 * spec.scenario.noise_std * rng.standard_normal(np.shape(d.y))
    d = dataclasses.replace(d, y=y)
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    res = run_paper(spec, d, Gamma=auto_gamma(spec, d.t, d.u, d.y))
    assert np.all(np.isfinite(res.theta_hat))
    assert np.all((res.theta_hat >= lo) & (res.theta_hat <= hi))
    ball = Ball(0.5 * (lo + hi), 0.5 * float(np.min(hi - lo)))
    law = FilteredLeastSquares(spec.system.perturbation, np.eye(spec.system.p), ball)
    obs = build_estimator(spec, method="paper", Gamma=np.eye(spec.system.p))
    ob = type(obs)(system=spec.system, K_x=obs.K_x, K_phi=obs.K_phi, update_law=law,
                   second=obs.second)
    th0 = ball.nearest(spec.estimator.theta_hat0)
    r2 = ob.run(d.t, d.u, d.y, state0=ob.init(x_hat0=start_x_hat(spec, d.y), theta_hat0=th0))
    assert np.all(ball.contains(r2.theta_hat, tol=1e-9))


def test_refusals():
    spec = loads_model(least_squares_file("prop4"))
    s = spec.system
    law = FilteredLeastSquares(s.perturbation, 1.0, s.parameter_set)
    v, x, phi, th = np.zeros((1, 2)), np.zeros((1, s.n)), np.zeros((1, 1)), np.ones((1, 2))
    with pytest.raises(UpdateLawError, match="state"):
        law.rate(v[0], x[0], phi[0], th[0])
    with pytest.raises(UpdateLawError, match="state"):
        law.step(v[0], x[0], phi[0], th[0], 0.01)
    with pytest.raises(UpdateLawError, match="not bound"):
        law.advance(v, x, phi, th, law.init_state(th), 0.01)
    obs = build_estimator(spec, method="paper", Gamma=np.eye(2))
    bound = obs.update_law
    with pytest.raises(UpdateLawError, match="Γ₀"):
        bound.advance(v, x, phi, th, bound.init_state(th), 0.01, Gamma=np.eye(2)[None])
    with pytest.raises(ModelFileError, match="theta_star"):
        loads_model(least_squares_file("prop4").replace(
            'law = "least_squares"', 'law = "least_squares"\ntheta_star = ["phi", "phi"]'))
