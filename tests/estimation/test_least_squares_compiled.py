"""The filtered least-squares law on the compiled path: the numba kernel against the Python
observer (the reference) on shipped models, θ̂ ∈ Θ at every sample, and the law's NaN rule
in both prints of its one formula."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import ThetahatWarning, UnsupportedError
from thetahat.estimation.kernels.kernel_cache import load_module
from thetahat.estimation.kernels.set_projection import project_box_metric
from thetahat.estimation.observer.kernel_data import kernel_parts
from thetahat.estimation.observer.kernel_source import kernel_source
from thetahat.estimation.observer.laws.least_squares import FilteredLeastSquares
from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.io.datafile import read_data
from thetahat.model.paramset import Ball, Box
from thetahat.model.parse import parse_perturbation
from thetahat.model.system import PerturbedLinearSystem
from thetahat.modelfile import (auto_gamma, build_estimator, load_model, loads_model,
                                simulate_model, start_x_hat)

from test_least_squares_law import least_squares_file

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

#: Compiled vs Python, relative to the scale of θ̂ (and of x̂): the two prints of the same
#: formulas differ in the summation order of the small products, the pivoted elimination in
#: place of LAPACK's gesv (R⁺ and the implicit step), the active-set QP in place of SciPy's
#: bvls for the projection in R⁺'s metric, and g printed by SymPy in place of lambdified:
#: each a few ulps a step. The law is a contraction in θ̂ (R only grows) and the observer's
#: error dynamics are stable, so the differences do not grow: measured 1e-15–1e-12 here.
#: 1e-9 leaves three decades for other platforms' BLAS and libm while failing at once if a
#: formula, an offset of the law's state or the φ-matrix of a step were wrong (those show at
#: 1e-3 or more).
AGREEMENT_RTOL = 1e-9
#: The same for Silverbox, whose information R spans 15 decades (its "auto" Γ₀ runs from
#: 4e-19 to 2e-4: m ≈ 2e-6 kg next to k₃ ≈ 10), and whose θ̂ sits on Θ's boundary for
#: 1000–2500 of the 3000 samples (the projection in R⁺'s metric at every step): each solve
#: with R⁺ loses digits to its conditioning; measured 5.6e-10 (k₃), so 1e-8.
ILL_CONDITIONED_RTOL = 1e-8


def _python_and_compiled(obs, t, u, y, state0):
    """The observer's own run (Python, the reference) and the compiled kernel's."""
    from thetahat.estimation.observer.compiled import compile_observer
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ThetahatWarning)
        ref = obs.run(t, u, y, state0=state0)
    fast = compile_observer(obs, dt=float(t[1] - t[0]))
    return ref, fast.run(t, u, y, state0=state0)


def _assert_agree(ref, res, theta_set, rtol=AGREEMENT_RTOL):
    lo, hi = theta_set.lower, theta_set.upper
    scale_th = np.maximum(np.max(np.abs(ref.theta_hat), axis=0), hi - lo)
    scale_x = np.maximum(np.max(np.abs(ref.x_hat), axis=0), 1e-300)
    assert np.all(np.abs(res.theta_hat - ref.theta_hat) <= rtol * scale_th)
    assert np.all(np.abs(res.x_hat - ref.x_hat) <= rtol * scale_x)
    for r in (ref, res):                                     # θ̂ ∈ Θ at every sample
        assert np.all((r.theta_hat >= lo) & (r.theta_hat <= hi))


@pytest.mark.parametrize("name", ["prop3", "prop4", "heater", "actuator"])
def test_compiled_agrees_with_python_on_simulated_models(name):
    pytest.importorskip("numba")
    # ten times the file's noise and a gap of missing samples (predicted over: the law and
    # its state are held there), Γ₀ "auto"
    text = least_squares_file(name)
    spec = loads_model(text)
    d = simulate_model(spec, 3)
    rng = np.random.default_rng(3)
    y = np.array(d.y, dtype=float).reshape(d.t.size, -1)
    y += 10 * spec.scenario.noise_std * rng.standard_normal(y.shape)
    G = auto_gamma(spec, d.t, d.u, y)
    y[d.t.size // 3:d.t.size // 3 + 7] = np.nan
    obs = build_estimator(spec, method="paper", Gamma=G, nan_policy="skip")
    state0 = obs.init(x_hat0=start_x_hat(spec, y), theta_hat0=spec.estimator.theta_hat0)
    ref, res = _python_and_compiled(obs, d.t, d.u, y, state0)
    _assert_agree(ref, res, spec.system.parameter_set)


@pytest.mark.parametrize("name, stop, hold", [("emps", 4000, "foh"), ("silverbox", 3000, "zoh")])
def test_compiled_agrees_with_python_on_measured_records(name, stop, hold):
    pytest.importorskip("numba")
    # the shipped measured benchmarks, whose files select the law, on the start of their
    # training records (the Python path takes minutes on the whole of them); EMPS with the
    # first-order hold
    spec = load_model(EXAMPLES / f"{name}.toml")
    data = {"emps": "emps/DATA_EMPS.mat", "silverbox": "silverbox/SNLS80mV.mat"}[name]
    rec = read_data(EXAMPLES / "data" / data, spec.layout)          # the file's split
    t, u, y = rec.t[:stop], rec.u[:stop], rec.y[:stop]
    obs = build_estimator(spec, method="paper", Gamma=auto_gamma(spec, t, u, y), hold=hold)
    state0 = obs.init(x_hat0=start_x_hat(spec, y), theta_hat0=spec.estimator.theta_hat0)
    ref, res = _python_and_compiled(obs, t, u, y, state0)
    ps = spec.system.parameter_set
    if name == "silverbox":
        # θ̂ rests on Θ's boundary here: the compiled projection in R⁺'s metric is exercised
        assert np.any((ref.theta_hat == ps.lower) | (ref.theta_hat == ps.upper))
    _assert_agree(ref, res, ps, ILL_CONDITIONED_RTOL if name == "silverbox" else AGREEMENT_RTOL)


def _toy_law():
    """g = √a·u + b·u on a one-state plant: ∂g/∂a = u/(2√a) is infinite at a = 0 while g is
    finite, and g overflows at u = 1e308, b = 5 while J is finite: the law meets a
    non-finite J, and a non-finite z."""
    g = parse_perturbation("sqrt(a)*u + b*u", u=["u"], y=["y"], x=["x"], theta=["a", "b"])
    s = PerturbedLinearSystem(A=[[-1.0]], B=[[0.0]], C=[[1.0]], E=[[1.0]], perturbation=g)
    law = FilteredLeastSquares(g, 10.0, Box([0.0, -5.0], [5.0, 5.0]))
    obs = ModifiedHighGainObserver(system=s, K_x=[[20.0]], K_phi=[[100.0]], update_law=law)
    return obs, obs.update_law


def test_a_non_finite_sample_leaves_theta_and_R_in_both_prints():
    # the formula printed for NumPy (the law's advance) and as scalar loops (the kernel's
    # module run as plain Python): where J or z is not finite, θ̂ and R are kept bit for bit,
    # w and w_b decay through the filter (w⁺ = A_d w), and both prints give the same state
    obs, law = _toy_law()
    n, _, _, p, k = law.perturbation.dims
    dt = 1e-3
    parts = kernel_parts(obs)
    mod = load_module(kernel_source(parts.perturbation, None, None, "least_squares_law",
                                    numba=False, law_size=parts.law_size), "thetahat_lstest")
    rng = np.random.default_rng(0)
    state = law.init_state(np.zeros(p)) + np.concatenate(
        [rng.standard_normal((n + k) * (p + 1) + k), np.zeros(p * p)])
    nw = (n + k) * p
    R0 = state[nw + n + k + k:].reshape(p, p)
    cases = [(np.array([1e308, 0.3]), np.array([0.7]), np.array([1.0, 5.0])),   # g, z inf
             (np.array([1.0, 0.3]), np.array([0.7]), np.array([0.0, 0.5])),      # J inf
             (np.array([1.0, 0.3]), np.array([0.7]), np.array([1.0, 0.5]))]      # finite
    x = np.array([0.2])
    Ad, _ = law.filter.discrete(dt)
    for i, (v, phi, th) in enumerate(cases):
        th1, S1 = law.advance(v[None], x[None], phi[None], th[None], state[None], dt)
        LP = law.law_arrays(dt)
        thn, lsn = np.empty(p), state.copy()
        with np.errstate(all="ignore"):
            status = mod.least_squares_law(LP, v, x, 0, phi, th, 0, dt, thn, lsn)
        assert status == 0
        np.testing.assert_allclose(thn, th1[0], rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(lsn, S1[0], rtol=1e-12, atol=1e-15)
        if i < 2:
            assert np.array_equal(th1[0], th) and np.array_equal(thn, th)
            assert np.array_equal(S1[0, nw + n + k + k:].reshape(p, p), R0)
            assert np.array_equal(lsn[nw + n + k + k:].reshape(p, p), R0)
            np.testing.assert_allclose(S1[0, :nw].reshape(n + k, p),
                                       Ad @ state[:nw].reshape(n + k, p), rtol=1e-13)
        else:
            assert not np.array_equal(th1[0], th)                       # it learns


def test_ls_law_refusals_of_the_compiled_path():
    # a Ball Θ (its projection in R⁺'s metric is compiled for a box only) is refused with a
    # ThetahatError naming it, and the runner keeps the Python observer; so is the C step
    obs, law = _toy_law()
    ball = FilteredLeastSquares(law.perturbation, 10.0, Ball([2.0, 0.0], 2.0))
    ob = ModifiedHighGainObserver(system=obs.system, K_x=obs.K_x, K_phi=obs.K_phi,
                                  update_law=ball)
    with pytest.raises(UnsupportedError, match="FilteredLeastSquares on a Ball"):
        kernel_parts(ob)
    from thetahat.codegen import generate_c
    with pytest.raises(UnsupportedError, match="FilteredLeastSquares"):
        generate_c(obs, dt=1e-3)


def test_the_box_projection_in_a_metric_is_the_box_nearest_point():
    # the compiled projection (an active-set QP) against Box.nearest (SciPy's bvls) on random
    # boxes, metrics and points outside: the same minimiser. Its objective is never above
    # bvls's by more than rounding (1e-12 relative) for metrics of any conditioning up to
    # 1e7, and the points agree to 1e-10 of the box's width where the metric's condition
    # number is at most 1e3 (the minimiser moves by cond × rounding)
    rng = np.random.default_rng(0)
    for trial in range(400):
        p = int(rng.integers(1, 6))
        A = rng.standard_normal((p, p))
        spread = 3.5 if trial % 2 else 0.75                 # cond up to ~1e7, or ~1e3
        D = np.diag(10 ** rng.uniform(-spread / 2, spread / 2, p))
        W = D @ (A @ A.T + 0.1 * np.eye(p)) @ D
        hi = rng.uniform(0.1, 2.0, p) * 10 ** rng.uniform(-3, 3, p)
        box = Box(-hi, hi)
        th = 3 * hi * rng.standard_normal(p)
        ref = box.nearest(th, metric=W)
        out = th.copy()
        project_box_metric(out, W, -hi, hi, np.zeros((p + 4, p + 1)))
        assert np.all((out >= -hi) & (out <= hi))
        f_out, f_ref = (out - th) @ W @ (out - th), (ref - th) @ W @ (ref - th)
        assert f_out <= f_ref * (1 + 1e-12)
        if np.linalg.cond(W) <= 1e3:
            assert np.all(np.abs(out - ref) <= 1e-10 * 2 * hi)
