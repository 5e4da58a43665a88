"""X and g saturated outside it (Remark 1), and the probe of Assumption 2's global condition.

The saturated g must be g itself on X (every method shares the model's g), agree with g at
σ(x) computed independently outside X, have the Jacobian its values have (central
differences), and be Lipschitz in x where g is not; the probe must tell the shipped models
whose g grows (the CSTR's Arrhenius rate, the Silverbox's cubic spring) from those whose g
has bounded ∂g/∂x (tanh friction)."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import sympy as sp

from thetahat.errors import ModelFileError, NonFiniteError
from thetahat.model.perturbation import SymbolicPerturbation
from thetahat.model.state_set import (GROWTH_LIMIT, SATURATION_WIDTH, StateSet, StateSetError,
                                      lipschitz_growth, saturate_states, state_scale)
from thetahat.modelfile import load_model, loads_model, run_estimator, simulate_model

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: Shipped models besides LuGre: two whose g grows in x, two with bounded ∂g/∂x.
MODELS = ("cstr", "silverbox", "stribeck", "wheel")
#: Simulated seconds per model: a few periods of each scenario's input.
SECONDS = {"cstr": 900.0, "silverbox": 0.5, "stribeck": 3.0, "wheel": 2.0}


def _without_x(name: str) -> str:
    text = (EXAMPLES / f"{name}.toml").read_text()
    return re.sub(r"\[state_set\].*?(?=\[parameter_set\])", "", text, flags=re.S)


def _sigma(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """σ computed here, in NumPy, from the module docstring's formula."""
    w = SATURATION_WIDTH * (hi - lo)
    c = np.clip(x, lo, hi)
    return c + w * np.tanh((x - c) / w)


def _case(name: str):
    spec = loads_model(_without_x(name))
    d = simulate_model(spec, 0, t_end=SECONDS[name])
    x = np.asarray(d.x)
    v = np.concatenate([np.asarray(d.u).reshape(x.shape[0], -1), np.asarray(d.y)], axis=1)
    span = x.max(axis=0) - x.min(axis=0)
    pad = 0.25 * np.maximum(span, 1e-3 * np.abs(x).max(axis=0) + 1e-12)
    X = StateSet(x.min(axis=0) - pad, x.max(axis=0) + pad)
    return spec, X, v, x, np.asarray(spec.scenario.theta, dtype=np.float64)


def test_sigma_is_the_identity_on_x_continuously_differentiable_and_bounded():
    """σ on [−1, 3]: x itself inside (bit for bit), slope 1 on both sides of each face (C¹),
    within w = 0.4 of X everywhere, however far x goes."""
    x1, y = sp.symbols("x1 y")
    g = SymbolicPerturbation.from_sympy(x1, u=[], y=[y], x=[x1], theta=[sp.Symbol("th")])
    gs = saturate_states(g, StateSet([-1.0], [3.0]))
    v, th = np.zeros((1, 1)), np.zeros((1, 1))
    inside = np.linspace(-1.0, 3.0, 101)
    val = np.array([gs.g(v, np.array([[s]]), th)[0, 0] for s in inside])
    assert np.array_equal(val, inside)
    for face in (-1.0, 3.0):
        for side in (-1e-9, 1e-9):
            slope = float(gs.dg_dx(v, np.array([[face + side]]), th)[0, 0, 0])
            assert abs(slope - 1.0) < 1e-12
    far = np.array([[-1e12], [-50.0], [50.0], [1e12]])
    out = np.asarray(gs.g(np.zeros((4, 1)), far, np.zeros((4, 1)))).ravel()
    assert np.all(out >= -1.4) and np.all(out <= 3.4) and np.all(np.isfinite(out))


@pytest.mark.parametrize("name", MODELS)
def test_the_saturated_g_is_g_on_x_and_g_of_sigma_outside(name):
    """On the simulated states (inside X) g and its three Jacobians are unchanged; at states
    pushed out of X by up to 50 widths, g equals the original g at σ(x) (σ in NumPy here),
    and ∂g/∂x equals central differences of the saturated g (a Jacobian derived through
    Min, Max and tanh)."""
    spec, X, v, x, th = _case(name)
    g = spec.system.perturbation
    gs = saturate_states(g, X)
    N = x.shape[0]
    T = np.broadcast_to(th, (N, th.size))
    for which in ("g", "dg_dv", "dg_dx", "dg_dtheta"):
        a, b = getattr(g, which)(v, x, T), getattr(gs, which)(v, x, T)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-300)
    rng = np.random.default_rng(7)
    rows = rng.integers(0, N, 40)
    width = X.upper - X.lower
    far = x[rows] + rng.uniform(-50.0, 50.0, (40, x.shape[1])) * width
    Vf, Tf = v[rows], np.broadcast_to(th, (40, th.size))
    with np.errstate(all="ignore"):
        want = np.asarray(g.g(Vf, _sigma(far, X.lower, X.upper), Tf))
    np.testing.assert_allclose(gs.g(Vf, far, Tf), want, rtol=1e-10, atol=1e-12 * np.abs(want).max())
    J = np.asarray(gs.dg_dx(Vf, far, Tf))
    h = 1e-6 * width
    for i in range(x.shape[1]):
        e = np.zeros(x.shape[1])
        e[i] = h[i]
        fd = (np.asarray(gs.g(Vf, far + e, Tf)) - np.asarray(gs.g(Vf, far - e, Tf))) / (2 * h[i])
        scale = np.abs(J).max() + 1e-300
        np.testing.assert_allclose(J[..., i], fd, rtol=1e-5, atol=1e-6 * scale)


@pytest.mark.parametrize("name", MODELS)
def test_the_probe_tells_growing_g_from_bounded_and_x_bounds_it(name):
    """lipschitz_growth above GROWTH_LIMIT for the CSTR's and the Silverbox's g (exponential,
    cubic), below for the tanh-friction models; with X declared, below for every one."""
    spec, X, v, x, th = _case(name)
    g = spec.system.perturbation
    mid = x.shape[0] // 2
    scale = state_scale(x)
    grows = lipschitz_growth(g, v[mid], x[mid], th, scale)
    assert (grows > GROWTH_LIMIT) == (name in ("cstr", "silverbox")), grows
    assert lipschitz_growth(saturate_states(g, X), v[mid], x[mid], th, scale) <= GROWTH_LIMIT


def test_state_set_refuses_what_is_not_a_finite_box():
    with pytest.raises(StateSetError, match="lower < upper"):
        StateSet([0.0, 1.0], [1.0, 1.0])
    with pytest.raises(StateSetError, match="finite"):
        StateSet([0.0], [np.inf])
    with pytest.raises(StateSetError, match="one lower and one upper"):
        StateSet([0.0, 1.0], [1.0])


@pytest.mark.parametrize("table, message", [
    ("lower = [0.0, -40.0, -40.0]\nupper = [2.0, 80.0, 80.0]", r"\[state_set\] lower.*4"),
    ("lower = [0.0, -40.0, -40.0, 90.0]\nupper = [2.0, 80.0, 80.0, 80.0]", "lower < upper"),
    ("lower = [0.0, -40.0, -40.0, -40.0]\nupper = [2.0, 80.0, 80.0, inf]", "finite"),
    ("lower = [0.0, -40.0, -40.0, -40.0]\nupper = [2.0, 80.0, 80.0, 80.0]\nwidth = 3",
     "width"),
])
def test_a_bad_state_set_is_a_model_file_error_naming_it(table, message):
    text = _without_x("cstr").replace("[parameter_set]", f"[state_set]\n{table}\n\n"
                                                          "[parameter_set]")
    with pytest.raises(ModelFileError, match=message) as err:
        loads_model(text)
    assert "[state_set]" in str(err.value)


def test_the_cstr_declares_the_box_its_scenario_stays_in():
    """The shipped file's X holds the simulated reactor (g is unchanged where it runs), and
    a file without [state_set] keeps g as written."""
    spec = load_model(EXAMPLES / "cstr.toml")
    d = simulate_model(spec, 0, t_end=SECONDS["cstr"])
    assert spec.state_set is not None and spec.state_set.contains(d.x)
    assert loads_model(_without_x("cstr")).state_set is None


def test_the_paper_method_on_the_cstr_runs_with_x():
    """With the file's X the paper's observer runs a 900 s CSTR record (without it, it left
    every bound within 150 s on this record with the locked versions; the lowest versions took
    another path, so the divergence itself is not asserted): finite, θ̂ in Θ."""
    bare = loads_model(_without_x("cstr"))
    d = simulate_model(bare, 0, t_end=SECONDS["cstr"])
    spec = load_model(EXAMPLES / "cstr.toml")
    r = run_estimator(spec, d.t, d.u, d.y, method="paper", diagnose=False)
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    th = np.asarray(r.theta_hat)
    assert np.all(np.isfinite(r.x_hat)) and np.all((th >= lo) & (th <= hi))


@pytest.mark.parametrize("name, grows", [("cstr", True), ("silverbox", True),
                                         ("stribeck", False), ("wheel", False)])
def test_a_divergence_under_a_growing_g_names_assumption_2(name, grows):
    """The error a diverged observer leaves (explain_nonfinite at x̂(0), θ̂(0) of the record)
    names Assumption 2 and [state_set] exactly when g grows faster than linearly in x (the
    CSTR, the Silverbox without X), and keeps the data-scale advice otherwise; with X
    declared, no model's g grows."""
    from thetahat.modelfile import start_x_hat
    from thetahat.studies.information import explain_nonfinite

    diverged = NonFiniteError("the observer state diverged (NaN, inf, a norm above 1e+100, or "
                              "a singular implicit step) in the step from t[5] = 5")
    spec, X, v, x, th = _case(name)
    d = simulate_model(spec, 0, t_end=SECONDS[name])
    saturated = dataclasses.replace(spec.system,
                                    perturbation=saturate_states(spec.system.perturbation, X))
    for system, told in ((spec.system, grows), (saturated, False)):
        err = explain_nonfinite(diverged, system, d.t, d.u, d.y, start_x_hat(spec, d.y),
                                spec.estimator.theta_hat0)
        assert isinstance(err, NonFiniteError)
        assert ("Assumption 2 fails" in str(err) and "[state_set]" in str(err)) == told, err
        assert ("units and scale" in str(err)) == (not told)


def test_the_law_report_of_a_run_says_when_assumption_2_fails():
    """law_conditions_on_record along a run: a cubic g (the Silverbox's spring) carries the
    Assumption 2 sentence naming [state_set]; the same g saturated outside X, and a tanh
    friction g, do not."""
    from thetahat.estimation.observer.checks import law_conditions_on_record
    from thetahat.estimation.observer.laws import GradientInversion
    from thetahat.model.paramset import Box
    from thetahat.model.parse import parse_perturbation

    t = np.linspace(0.0, 10.0, 2001)
    x = np.column_stack([np.sin(t), np.cos(t)])
    v = x[:, :1]
    box = Box([0.5], [2.0])
    cubic = parse_perturbation("-th*x1**3", u=[], y=["y"], x=["x1", "x2"], theta=["th"])
    tanh = parse_perturbation("-th*tanh(x2/0.1)", u=[], y=["y"], x=["x1", "x2"],
                              theta=["th"])
    X = StateSet([-2.0, -2.0], [2.0, 2.0])
    for g, fails in ((cubic, True), (saturate_states(cubic, X), False), (tanh, False)):
        law = GradientInversion(g, Gamma=1.0, parameter_set=box)
        rep = law_conditions_on_record(g, t, v, x, np.ones((t.size, 1)), box, law=law)
        said = [w for w in rep.warnings if "Assumption 2" in w]
        assert bool(said) == fails and rep.lipschitz == (not fails)
        assert all("[state_set]" in w for w in said)


def _with_x(name: str, lower, upper) -> str:
    table = (f"[state_set]\nlower = {[float(v) for v in lower]}\n"
             f"upper = {[float(v) for v in upper]}\n\n[parameter_set]")
    return _without_x(name).replace("[parameter_set]", table, 1)


@pytest.mark.needs_speed               # the trust report of three records (minutes without numba)
@pytest.mark.parametrize("name", ["cstr", "stribeck", "wheel"])
def test_a_record_that_leaves_x_says_so(name):
    """A file whose X cuts through the record (the first output's state capped at its
    median) warns that the plant leaves X for that state, naming it; an X a quarter of the
    record's range wider on every side does not (the observer's x̂ may leave it in its
    transient: that is what the saturation is for, and not reported)."""
    import warnings as w

    from thetahat.errors import ThetahatWarning
    spec0 = loads_model(_without_x(name))
    d = simulate_model(spec0, 0, t_end=SECONDS[name])
    x = np.asarray(d.x)
    i = int(np.argmax(np.abs(spec0.system.C[0])))
    span = np.maximum(x.max(axis=0) - x.min(axis=0), 1e-6 * (np.abs(x).max(axis=0) + 1.0))
    lo, hi = x.min(axis=0) - 0.25 * span, x.max(axis=0) + 0.25 * span
    narrow = hi.copy()
    narrow[i] = float(np.median(x[:, i]))
    for upper, told in ((narrow, True), (hi, False)):
        spec = loads_model(_with_x(name, lo, upper))
        with w.catch_warnings(record=True) as caught:
            w.simplefilter("always")
            run_estimator(spec, d.t, d.u, d.y, method="paper")
        said = [str(c.message) for c in caught if issubclass(c.category, ThetahatWarning)
                and "leaves X" in str(c.message)]
        assert bool(said) == told, said
        if told:
            assert spec.state_names[i] in said[0]
