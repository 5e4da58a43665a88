"""Model files: the shipped examples, the estimator they build, and every error path."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from thetahat import simulate_plant
from thetahat.errors import ModelFileError, OptionError
from thetahat.io.datafile import estimate_columns, read_data
from thetahat.estimation.observer.initial_state import x_hat_from_output
from thetahat.modelfile import (
    EXAMPLE_MODEL,
    analyze_model,
    build_observer,
    load_model,
    loads_model,
    run_estimator,
)
from thetahat.models import lugre
from thetahat.studies.metrics import time_to_within

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
LUGRE = EXAMPLES / "lugre.toml"
PROP3 = EXAMPLES / "prop3.toml"

#: lugre.toml builds the same observer as lugre.observer(); its g and θ* are parsed from text
#: rather than written in Python, and run_estimator takes the fastest back end (the C, when a
#: compiler is present) where the reference runs NumPy: another order of floating-point
#: operations. Measured up to 2.2e-12 relative (the lowest supported NumPy), 8.7e-13 with the
#: lock's (tests/test_cli.py); bound 1e-10, 45 × the largest measured.
SAME_OBSERVER_RTOL = 1e-10
#: Sec. VIII: ε = 1 "translates to K(ε) ≈ [6, 0, 6]ᵀ", the second observer's to ≈ [3, 0]ᵀ;
#: the exact values of this design are [6, −0.0042, 6.0075] and [3, −0.0020].
K_ATOL = 1e-4
#: Proposition 3 on noise-free data sampled at 100 Hz: θ̂ within 1 % of θ = 1.2 after about
#: 2.5 s (measured at 200 Hz); 6 s leaves a wide margin.
PROP3_SETTLE_S = 6.0


@pytest.fixture(scope="module")
def lugre_spec():
    return load_model(LUGRE)


def _write(tmp_path: Path, doc: dict, suffix: str = ".json") -> Path:
    path = tmp_path / f"model{suffix}"
    path.write_text(json.dumps(doc))
    return path


def _lugre_doc() -> dict:
    return tomllib.loads(LUGRE.read_text())


# ------------------------------------------------------------------ the shipped examples
def test_lugre_file_builds_the_papers_observer(lugre_spec):
    data = lugre.simulate(seed=3, t_end=1.5)
    ours = run_estimator(lugre_spec, data.t, data.u, data.y, method="paper")
    ref_obs = lugre.observer()
    x0 = x_hat_from_output(ref_obs.system.C, data.y[0])   # the file's start: x̂₀ = 0 + C⁺y(0)
    ref = ref_obs.run(data.t, data.u, data.y, state0=ref_obs.init(x_hat0=x0, theta_hat0=[0.5]))
    for name in ("x_hat", "phi_hat", "theta_hat", "x_hat_refined"):
        np.testing.assert_allclose(getattr(ours, name), getattr(ref, name),
                                   rtol=SAME_OBSERVER_RTOL, atol=0, err_msg=name)


def test_lugre_analysis_has_the_papers_numbers(lugre_spec):
    rep = analyze_model(lugre_spec)
    assert rep.assumption.holds
    np.testing.assert_allclose(rep.assumption.zeros.real, [-260.0 / 0.6])   # −σ0/σ1
    assert rep.scb.chain_lengths == (2,) and rep.scb.n_a == 1             # true (4)
    assert rep.scb_design.chain_lengths == (3,) and rep.scb_design.n_a == 0  # σ1 = 0
    np.testing.assert_allclose(rep.design.K.ravel(), [6.0, -0.0041588, 6.0074994],
                               atol=K_ATOL)
    np.testing.assert_allclose(rep.design2.K.ravel(), [3.0, -0.0020485], atol=K_ATOL)
    assert rep.spectra.stable and rep.spectra2.stable
    text = str(rep)
    assert "-433.333" in text and "K(eps = 1)" in text and "6.0075" in text


def test_json_and_toml_give_the_same_model(tmp_path, lugre_spec):
    spec = load_model(_write(tmp_path, _lugre_doc()))
    assert spec.system.A.tolist() == lugre_spec.system.A.tolist()
    assert spec.estimator.A_design.tolist() == lugre_spec.estimator.A_design.tolist()
    assert spec.state_names == ("omega", "eta")
    np.testing.assert_array_equal(build_observer(spec).K_x, build_observer(lugre_spec).K_x)


def test_prop3_file_estimates_theta():
    spec = load_model(PROP3)

    def phi(t, x, u, th):
        x, th = np.asarray(x), np.asarray(th)[..., 0]
        return ((2 + np.sin(x[..., 0])) * (th + th ** 3 / 3))[..., None]

    data = simulate_plant(spec.system, phi=phi, u=lambda t: [np.sin(0.8 * t)], t_end=8.0,
                          fs=100.0, x0=[0.0, 0.0], theta=[1.2])
    res = run_estimator(spec, data.t, data.u, data.y)
    assert res.theta_hat[0, 0] == 0.0                      # the file's theta_hat0
    assert time_to_within(data.t, res.theta_hat, [1.2], 0.01) < PROP3_SETTLE_S


def test_eps_override_designs_for_that_eps(lugre_spec):
    """build_observer(eps=...) redesigns K(ε) on the σ1 = 0 design system, as lugre.designs."""
    obs = build_observer(lugre_spec, eps=0.3)
    d1, d2 = lugre.designs(0.3)
    np.testing.assert_allclose(obs.K_x, d1.K_x, rtol=SAME_OBSERVER_RTOL)
    np.testing.assert_allclose(obs.K_phi, d1.K_phi, rtol=SAME_OBSERVER_RTOL)
    np.testing.assert_allclose(obs.second.K_x, d2.K, rtol=SAME_OBSERVER_RTOL)
    assert not np.allclose(obs.K_phi, build_observer(lugre_spec).K_phi)


# ------------------------------------------------------------------ bad model files
def _drop(doc, section, key):
    del doc[section][key]
    return doc


def _set(doc, section, key, value):
    doc[section][key] = value
    return doc


BAD_FILES = {
    "missing matrix": (lambda d: _drop(d, "system", "E"), r"\[system\] E: missing"),
    "wrong shape": (lambda d: _set(d, "system", "B", [[1.0, 0.0], [0.0, 1.0]]),
                    r"\[system\] B: expected shape \(2, 1\)"),
    "ragged matrix": (lambda d: _set(d, "system", "A", [[1.0, 0.0], [1.0]]),
                      r"\[system\] A: rows have different lengths"),
    "non-numeric entry": (lambda d: _set(d, "system", "C", [[1.0, "x"]]),
                          r"\[system\] C: entry \[0\]\[1\]"),
    "code in g": (lambda d: _set(d, "perturbation", "g", "__import__('os').getcwd()"),
                  r"\[perturbation\] g: .*__import__"),
    "unknown name in g": (lambda d: _set(d, "perturbation", "g", "sigma0*zeta"),
                          r"\[perturbation\] g: .*unknown name 'zeta'"),
    "unknown law": (lambda d: _set(d, "estimator", "law", "kalman"),
                    r"\[estimator\] law: unknown law 'kalman'"),
    "typo key": (lambda d: _set(d, "estimator", "Gama", 1.0),
                 r"\[estimator\]: unknown key\(s\) \['Gama'\]"),
    "bad Gamma": (lambda d: _set(d, "estimator", "Gamma", -1.0),
                  r"\[estimator\] Gamma: .*positive"),
    "theta_hat0 outside": (lambda d: _set(d, "estimator", "theta_hat0", [2.0]),
                           r"\[estimator\] theta_hat0: .*outside"),
    "no excitation": (lambda d: _drop(d, "estimator", "excitation"),
                      r"\[estimator\] excitation: missing"),
    "theta_star uses theta": (lambda d: _set(d, "estimator", "theta_star", "theta*phi"),
                              r"\[estimator\] theta_star: .*'theta'.*phi"),
    "eps not positive": (lambda d: _set(d, "estimator", "eps", 0.0),
                         r"\[estimator\] eps: expected a finite positive number"),
    "box size": (lambda d: _set(d, "parameter_set", "lower", [0.0, 0.0]),
                 r"\[parameter_set\] lower: expected 1 number"),
    "empty box": (lambda d: _set(d, "parameter_set", "upper", [0.01]),
                  r"\[parameter_set\]: Box: lower < upper"),
    "missing table": (lambda d: d.pop("perturbation") and d,
                      r"missing table \[perturbation\]"),
    "second: bad flag": (lambda d: _set(d, "estimator", "second", {"g_on_estimates": "yes"}),
                         r"\[estimator.second\] g_on_estimates: expected true or false"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_model_files_raise_model_file_error(tmp_path, case):
    edit, match = BAD_FILES[case]
    path = _write(tmp_path, edit(_lugre_doc()))
    with pytest.raises(ModelFileError, match=match):
        load_model(path)


def test_gradient_law_rejects_inversion_keys(tmp_path):
    doc = _lugre_doc()
    doc["estimator"]["law"] = "gradient"
    with pytest.raises(ModelFileError, match=r"\[estimator\] theta_star: not used"):
        load_model(_write(tmp_path, doc))


def test_design_failure_names_the_keys(tmp_path):
    doc = _lugre_doc()
    doc["estimator"]["chain_poles"] = [[-1.0, -2.0]]      # the chain has length 3
    spec = load_model(_write(tmp_path, doc))
    with pytest.raises(ModelFileError, match=r"\[estimator\] eps/chain_poles"):
        build_observer(spec)
    assert "gain design FAILED" in str(analyze_model(spec))


@pytest.mark.parametrize("name, text, match", [
    ("model.toml", "[system\nA = 1", "not valid TOML"),
    ("model.json", "{\"system\": ", "not valid JSON: .* line 1"),
    ("model.yaml", "system: {}", "use a .toml or .json"),
])
def test_unparsable_files(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ModelFileError, match=match):
        load_model(path)


def test_missing_file(tmp_path):
    with pytest.raises(ModelFileError, match="cannot read model file"):
        load_model(tmp_path / "nope.toml")


# ------------------------------------------------------------------ data files
@pytest.mark.parametrize("text, match", [
    ("t,u\n0,1\n", r"missing column 'y'"),
    ("t,u,y\n0,1,2\n0.1,abc,3\n", r"line 3, column 'u': 'abc' is not a number"),
    ("t,u,y\n0,1,2\n0.1,1,nan\n", r"line 3, column 'y': nan is not finite"),
    ("t,u,y\n0,1,2\n0.1,1,2\n0.1,1,2\n", r"line 4: t = 0.1 does not increase"),
    ("t,u,y\n0,1,2\n0.1,1\n", r"line 3: 2 fields, but the header has 3"),
    ("t,u,y\n", "no data rows"),
    ("", "empty"),
])
def test_bad_data_files(tmp_path, lugre_spec, text, match):
    path = tmp_path / "data.csv"
    path.write_text(text)
    with pytest.raises(ModelFileError, match=match):
        read_data(path, lugre_spec.layout)


def test_data_columns_by_name_any_order(tmp_path, lugre_spec):
    path = tmp_path / "data.csv"
    path.write_text("y1,extra,t,u1\n0.5,x,0,1\n0.25,y,0.1,2\n")
    rec = read_data(path, lugre_spec.layout)
    assert rec.t.tolist() == [0.0, 0.1] and rec.u.ravel().tolist() == [1.0, 2.0]
    assert rec.y.ravel().tolist() == [0.5, 0.25] and rec.columns == ("t", "u1", "y1")


def test_estimate_columns(lugre_spec):
    cols = estimate_columns(lugre_spec.layout, refined=True)
    assert cols == ("t", "x_hat_omega", "x_hat_eta", "phi_hat_1", "theta_hat_theta",
                    "x_hat_refined_omega", "x_hat_refined_eta")
    assert re.fullmatch(r"[\w,]+", ",".join(cols))


def test_example_model_constant_matches_the_shipped_file():
    a, b = loads_model(EXAMPLE_MODEL), load_model(PROP3)
    assert a.name == b.name and a.estimator.law == b.estimator.law
    for attr in ("A", "B", "C", "E"):
        np.testing.assert_array_equal(getattr(a.system, attr), getattr(b.system, attr))
    assert a.system.perturbation.expr == b.system.perturbation.expr
    assert (a.estimator.eps, a.estimator.second) == (b.estimator.eps, b.estimator.second)


#: θ* derived by SymPy or read from the file is an exact formula: only rounding remains.
INVERSE_RTOL = 1e-12


@pytest.mark.parametrize("theta_star", [None, "asinh(phi/(1 + y**2))"])
def test_algebraic_law_inverts_g(theta_star):
    """Proposition 1 from a file: θ* solved by SymPy, or given as text, recovers θ."""
    text = EXAMPLE_MODEL.replace('"gradient"', '"algebraic"').replace(
        "(2 + sin(y))*(theta + theta**3/3)", "(1 + y**2)*sinh(theta)")
    if theta_star is not None:
        text = text.replace('law = "algebraic"', f'law = "algebraic"\ntheta_star = "{theta_star}"')
    spec = loads_model(text)
    law = spec.estimator.update_law
    v, x = np.array([[0.3, 0.7], [-1.0, 2.0]]), np.array([[0.1, 0.2], [0.0, -1.0]])
    theta = np.array([[1.3], [-0.4]])
    phi = spec.system.perturbation.g(v, x, theta)
    np.testing.assert_allclose(law.theta_star(v, x, phi), theta, rtol=INVERSE_RTOL)


@pytest.mark.parametrize("method", ["guarded", "mle"])
def test_prop3_file_with_the_two_stage_methods(method):
    # A model with p = 1, a gradient stage 1 and a different Θ: the two-stage methods are
    # built from the file alone (stage 2's model, priors from Θ, σ estimated from the data).
    spec = loads_model(EXAMPLE_MODEL.replace('law = "gradient"',
                                             f'method = "{method}"\nlaw = "gradient"'))
    assert spec.estimator.method == method

    def phi(t, x, u, th):
        x, th = np.asarray(x), np.asarray(th)[..., 0]
        return ((2 + np.sin(x[..., 0])) * (th + th ** 3 / 3))[..., None]

    from thetahat import WhiteNoise
    data = simulate_plant(spec.system, phi=phi, u=lambda t: [np.sin(0.8 * t)], t_end=3.0,
                          fs=100.0, x0=[0.0, 0.0], theta=[1.2], noise=WhiteNoise(0.01), seed=1)
    res = run_estimator(spec, data.t, data.u, data.y, compiled=False)
    assert np.all((res.theta_hat >= -2.0) & (res.theta_hat <= 2.0))
    # 1 % of θ: the data identify θ to ~1e-3 (the fits' standard error) within 3 s
    assert abs(res.theta_hat[-1, 0] - 1.2) < 0.01 * 1.2
    with pytest.raises(OptionError, match="unknown method 'newton'; expected one of"):
        run_estimator(spec, data.t, data.u, data.y, method="newton")


def test_unknown_method_in_a_model_file():
    with pytest.raises(ModelFileError, match=r"\[estimator\] method: unknown method"):
        loads_model(EXAMPLE_MODEL.replace('law = "gradient"', 'method = "ukf"\nlaw = "gradient"'))


# --- run_estimator diagnoses the run itself (what `thetahat estimate` prints, for any caller) --

def _short_record(N: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(N) * 0.01
    return t, np.sin(t)[:, None], 0.1 * np.cos(t)[:, None]


def test_a_failed_run_names_g_undefined_on_the_data():
    """g = sqrt(y − 10)·θ is NaN on every sample: the library's error says so, with the instant
    (the command line only prints it)."""
    from thetahat.errors import NonFiniteError
    from thetahat.studies.information import explain_nonfinite

    spec = loads_model(EXAMPLE_MODEL.replace('"(2 + sin(y))*(theta + theta**3/3)"',
                                             '"sqrt(y - 10)*theta"'))
    t, u, y = _short_record()
    with pytest.raises(NonFiniteError, match=r"g is undefined \(NaN or inf\) at t = 0") as info:
        run_estimator(spec, t, u, y)
    err = info.value
    assert str(err).count("g is undefined") == 1
    # explaining it again (the fleet does) adds nothing
    assert explain_nonfinite(err, spec.system, t, u, y, np.zeros(2), [0.0]) is err
    with pytest.raises(Exception) as raw:                      # diagnose=False: as it failed
        run_estimator(spec, t, u, y, diagnose=False)
    assert "g is undefined" not in str(raw.value)


def test_a_stuck_parameter_warns_from_the_library():
    """g = √|θ|(2 + sin y) from θ̂(0) = 0: ∂g/∂θ vanishes there and θ̂ never moves; the run
    warns with a ConvergenceWarning (and does not for an informative model)."""
    from thetahat.errors import ConvergenceWarning

    t, u, y = _short_record()
    stuck = loads_model(EXAMPLE_MODEL.replace('"(2 + sin(y))*(theta + theta**3/3)"',
                                              '"Abs(theta)**0.5*(2 + sin(y))"'))
    with pytest.warns(ConvergenceWarning, match="no information reached the update law for "
                                                "theta"):
        run_estimator(stuck, t, u, y, method="paper")           # the law's own information
    import warnings
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_estimator(loads_model(EXAMPLE_MODEL), t, u, y, method="paper")
    assert not [w for w in caught if issubclass(w.category, ConvergenceWarning)]


@pytest.mark.parametrize("name", ["prop1.toml", "two_inertia.toml", "heater.toml"])
def test_the_file_names_travel_with_the_result(name):
    """res.names holds the file's names; the summary and the tables use them unasked."""
    from thetahat.io.datafile import estimate_columns
    from thetahat.modelfile import simulate_model
    from thetahat.studies.metrics import estimate_summary
    from thetahat.tables import result_columns

    spec = load_model(EXAMPLES / name)
    data = simulate_model(spec, seed=0, t_end=1.0)
    res = run_estimator(spec, data.t, data.u, data.y, diagnose=False, method="paper")
    assert res.names == spec.signal_names
    assert (res.names.states, res.names.parameters) == (spec.state_names, spec.parameter_names)
    assert (res.names.inputs, res.names.outputs) == (spec.input_names, spec.output_names)
    # the CSV's columns (its writer reads the spec) and the table's, from the result alone
    columns = list(result_columns(res))
    assert columns[-1] == "skipped"
    assert ("t", *columns[:-1]) == estimate_columns(spec.layout, refined=res.x_hat_refined is not None)
    summary = estimate_summary(res).splitlines()[0]
    assert summary == "final theta_hat: " + ", ".join(
        f"{n} = {v:.6g}" for n, v in zip(spec.parameter_names, res.theta_hat[-1]))
