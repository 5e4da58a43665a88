"""Bad, hostile and long input (issue 11): typed errors with useful messages, never a hang.

Each parametrized case is one distinct bad input, over the API, the CLI, model files and CSV
files; each asserts the error class (a ThetahatError subclass) and key words of its message.
The seven groups of the issue are reproduced in tests/test_hostile_groups.py.
"""

from __future__ import annotations

import re
import time

import numpy as np
import pytest
import sympy as sp

from thetahat import errors as E
from thetahat.cli import main
from thetahat.io.datafile import check_writable, read_data
from thetahat.design.design_system import apply_design
from thetahat.design.gains import high_gain, modified_high_gain
from thetahat.estimation.observer.checks import check_theta_star
from thetahat.estimation.observer.laws import GradientInversion, algebraic_from_perturbation
from thetahat.model.paramset import Box
from thetahat.model.parse import parse_expression, parse_perturbation
from thetahat.model.perturbation import SymbolicPerturbation
from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model, run_estimator
from thetahat.studies.metrics import rmse, time_to_within
from thetahat.simulation.signals import time_grid
from thetahat.structure.scb import scb
from thetahat.structure.scb_symbolic import scb_symbolic

#: Hostile input must fail fast; generous against a loaded 2-core machine (typical: < 0.5 s).
FAST_SECONDS = 10.0

NAMES = {"u": ["u"], "y": ["y"], "x": ["x1", "x2"], "theta": ["theta"]}

# ---------------------------------------------------------------------------------------------
# the formula parser (model files, parse_perturbation, theta_star, scb_symbolic strings)
# ---------------------------------------------------------------------------------------------

PARSER_CASES = [
    ("__import__('os').system('true')", E.ModelFileError, "the function \"__import__('os')"),
    ("y.__class__", E.ModelFileError, "attribute"),
    ("(lambda: 1)()", E.ModelFileError, "function"),
    ("lambda: 1", E.ModelFileError, "lambda"),
    ("[1, 2][0]", E.ModelFileError, "subscript"),
    ("y if y else 1", E.ModelFileError, "ifexp"),
    ("y[0]", E.ModelFileError, "subscript"),
    ("'abc'", E.ModelFileError, "literal"),
    ("True", E.ModelFileError, "literal"),
    ("1j*theta", E.ModelFileError, "literal"),
    ("open('x')", E.ModelFileError, "function 'open'"),
    ("exp", E.ModelFileError, "without a call"),
    ("exp(y, y)", E.ModelFileError, "exp takes 1 argument"),
    ("Max(y)", E.ModelFileError, "two or more"),
    ("exp(x=y)", E.ModelFileError, "keyword"),
    ("exp(*y)", E.ModelFileError, "starred"),
    ("y ^ 2", E.ModelFileError, "use ** for powers"),
    ("y % 2", E.ModelFileError, "operator"),
    ("y // 2", E.ModelFileError, "operator"),
    ("y << 1", E.ModelFileError, "operator"),
    ("y @ y", E.ModelFileError, "operator"),
    ("z*theta", E.ModelFileError, "unknown name 'z'"),
    ("__builtins__", E.ModelFileError, "unknown name"),
    ("y and theta", E.ModelFileError, "boolop"),
    ("y < theta", E.ModelFileError, "compare"),
    ("f'{y}'", E.ModelFileError, "joinedstr"),
    ("sin(y)(theta)", E.ModelFileError, "function"),
    ("y; theta", E.ModelFileError, "not a valid expression"),
    ("theta*y\nimport os", E.ModelFileError, "not a valid expression"),
    ("y +", E.ModelFileError, "not a valid expression"),
    ("9**9**9**9", E.ModelFileError, "not a finite float64"),
    ("1/0 + theta", E.ModelFileError, "non-finite"),
    ("y**y**y**y**y", E.InputLimitError, "tower"),
    ("(theta + y)**1000", E.InputLimitError, "exponent 1000"),
    ("y**-500 * theta", E.InputLimitError, "exponent"),
    ("+".join(["y"] * 200) + "+theta", E.InputLimitError, "nested deeper"),
    ("-" * 5000 + "theta", E.ModelFileError, "not a valid expression"),
    ("theta + " + "y" * 10_001, E.InputLimitError, "characters"),
    ("exp(" * 300 + "theta" + ")" * 300, E.ModelFileError, "not a valid expression"),
    ("y" + "**y" * 3000, E.ModelFileError, "not a valid expression"),
]


@pytest.mark.parametrize("text,error,words", PARSER_CASES,
                         ids=[f"parser{i}" for i in range(len(PARSER_CASES))])
def test_parser_refuses(text, error, words):
    start = time.perf_counter()
    with pytest.raises(error, match=re.escape(words)):
        parse_perturbation(text, **NAMES)
    assert time.perf_counter() - start < FAST_SECONDS


def test_parser_accepts_what_it_should():
    """The limits leave ordinary formulas alone (the LuGre g has depth 9)."""
    g = parse_perturbation("(2 + sin(y))*(theta + theta**3/3) + 2**10*0 + y**2.5*0",
                           **NAMES)
    assert g.dims == (2, 1, 1, 1, 1)


# ---------------------------------------------------------------------------------------------
# scb_symbolic: strings are parsed, never sympified
# ---------------------------------------------------------------------------------------------

SYMBOLIC_CASES = [
    ([["__import__('os').system('true') or 1", "0"], ["0", "0"]], E.ModelFileError,
     "boolop"),
    ([["__import__('os')", "0"], ["0", "0"]], E.ModelFileError, "function '__import__'"),
    ([["a.b", "0"], ["0", "0"]], E.ModelFileError, "attribute"),
    ([["_secret", "0"], ["0", "0"]], E.ModelFileError, "unknown name"),
    ([["a ^ 2", "0"], ["0", "0"]], E.ModelFileError, "use ** for powers"),
    ("[[1, 0], [0, 0]]", E.DimensionError, "nested lists"),
    ([[object(), 0], [0, 0]], E.DimensionError, "must be a number"),
    ([[True, 0], [0, 0]], E.DimensionError, "must be a number"),
    ([[1, 0], [0]], E.DimensionError, "different lengths"),
    (np.zeros((31, 31)).tolist(), E.DimensionError, "more than 30"),
]


@pytest.mark.parametrize("A,error,words", SYMBOLIC_CASES,
                         ids=[f"symbolic{i}" for i in range(len(SYMBOLIC_CASES))])
def test_scb_symbolic_refuses(A, error, words):
    with pytest.raises(error, match=re.escape(words)):
        scb_symbolic(A, [[0], [1]], [[1, 0]])


def test_scb_symbolic_redundant_outputs():
    with pytest.raises(E.DimensionError, match="full row rank"):
        scb_symbolic([[0, 1], [0, 0]], [[0], [1]], [[1, 0], ["2", 0]])


def test_scb_symbolic_strings_become_the_same_symbols():
    """A string naming a symbol given as SymPy elsewhere refers to that very symbol."""
    J = sp.Symbol("J", positive=True)
    res = scb_symbolic([["-a/J", "-s0/J", "s1/J"], [1, 0, -1], [0, 0, 0]], [0, 0, J],
                       [[1, 0, 0]])
    assert J in res.generic_condition.free_symbols | {J}
    assert res.chain_lengths == (2,)


# ---------------------------------------------------------------------------------------------
# model files
# ---------------------------------------------------------------------------------------------

def _model(old: str, new: str) -> str:
    assert old in EXAMPLE_MODEL, old
    return EXAMPLE_MODEL.replace(old, new)


MODEL_CASES = [
    (_model("[system]\n", "[sys]\n"), E.ModelFileError, "unknown key"),
    (_model('law = "gradient"', 'law = "newton"'), E.ModelFileError, "unknown law"),
    (_model('law = "gradient"', 'law = "gradient"\nfoo = 1'), E.ModelFileError,
     "unknown key(s) ['foo']"),
    (_model("A = [[0.0, 1.0], [-1.0, -0.5]]", "A = [[0.0, 1.0]]"), E.ModelFileError,
     "expected shape (2, 2)"),
    (_model("A = [[0.0, 1.0], [-1.0, -0.5]]", "A = [[0.0, inf], [-1.0, -0.5]]"),
     E.ModelFileError, "not a finite number"),
    (_model("A = [[0.0, 1.0], [-1.0, -0.5]]", "A = [[0.0, 1.0], [-1.0]]"), E.ModelFileError,
     "different lengths"),
    (_model("A = [[0.0, 1.0], [-1.0, -0.5]]", 'A = [["0.0", 1.0], [-1.0, -0.5]]'),
     E.ModelFileError, "not a finite number"),
    (_model("A = [[0.0, 1.0], [-1.0, -0.5]]", "A = 3"), E.ModelFileError, "nested list"),
    (_model("theta_hat0 = [0.0]", "theta_hat0 = [5.0]"), E.ModelFileError, "theta_hat0"),
    (_model("theta_hat0 = [0.0]", "theta_hat0 = [0.0, 1.0]"), E.ModelFileError,
     "expected 1 number"),
    (_model("Gamma = 2.0", "Gamma = -2.0"), E.ModelFileError, "Gamma"),
    (_model("Gamma = 2.0", 'Gamma = "big"'), E.ModelFileError, "Gamma"),
    (_model("eps = 0.5", "eps = -0.5"), E.ModelFileError, "positive"),
    (_model("eps = 0.5", 'eps = "small"'), E.ModelFileError, "finite"),
    (_model('x = ["x1", "x2"]', 'x = ["x1", "2x"]'), E.ModelFileError, "not a valid name"),
    (_model('x = ["x1", "x2"]', "x = []"), E.ModelFileError, "at least one name"),
    (_model('g = "(2 + sin(y))*(theta + theta**3/3)"', "g = 3"), E.ModelFileError,
     "must be a string"),
    (_model('g = "(2 + sin(y))*(theta + theta**3/3)"', 'g = "__import__(\'os\')"'),
     E.ModelFileError, "[perturbation] g"),
    (_model('g = "(2 + sin(y))*(theta + theta**3/3)"', 'g = "y**y**y**y**y*theta"'),
     E.ModelFileError, "tower"),
    (_model('g = "(2 + sin(y))*(theta + theta**3/3)"', 'g = "y**2"'), E.ModelFileError,
     "does not depend on θ"),
    (_model("upper = [2.0]", "upper = [-3.0]"), E.ModelFileError, "[parameter_set]"),
    (_model('law = "gradient"', 'law = "gradient"\ntheta_star = "phi"'), E.ModelFileError,
     "not used by the 'gradient' law"),
    (_model('law = "gradient"', 'law = "intermittent"'), E.ModelFileError, "excitation"),
    (_model('law = "gradient"', 'law = "algebraic"\non_invalid = "ignore"'),
     E.ModelFileError, "on_invalid"),
    (_model('law = "gradient"', 'law = "algebraic"\ntheta_star = "open(phi)"'),
     E.ModelFileError, "theta_star"),
    (_model("eps2 = 1.0", 'eps2 = 1.0\ng_on_estimates = "yes"'), E.ModelFileError,
     "true or false"),
    (_model("eps = 0.5", 'eps = 0.5\nallow_nonminimum_phase = "yes"'), E.ModelFileError,
     "allow_nonminimum_phase"),
    (_model("eps = 0.5", "eps = 0.5\nchain_poles = [-1.0, -2.0]"), E.ModelFileError,
     "chain_poles"),
    (_model("[perturbation]", "[perturbation]\nconstants = 3"), E.ModelFileError,
     "table of named numbers"),
    (_model("[perturbation]", '[perturbation]\nconstants = {c = "one"}'), E.ModelFileError,
     "real number"),
    ("x = " + "[" * 100_000 + "]" * 100_000, E.InputLimitError, "nested deeper"),
    ("a = {" + "b = {" * 50 + "}" * 51, E.InputLimitError, "nested deeper"),
    ("this is = not toml", E.ModelFileError, "not valid TOML"),
    ("", E.ModelFileError, "missing table"),
]


@pytest.mark.parametrize("text,error,words", MODEL_CASES,
                         ids=[f"model{i}" for i in range(len(MODEL_CASES))])
def test_model_file_refuses(text, error, words):
    start = time.perf_counter()
    with pytest.raises(error, match=re.escape(words)):
        loads_model(text)
    assert time.perf_counter() - start < FAST_SECONDS


JSON_CASES = [
    ("[1, 2]", E.ModelFileError, "top level must be a table"),
    ("{", E.ModelFileError, "not valid JSON"),
    ('{"a":' * 100_000 + "1" + "}" * 100_000, E.InputLimitError, "nested deeper"),
    ('{"system": 3}', E.ModelFileError, "[system] must be a table"),
]


@pytest.mark.parametrize("text,error,words", JSON_CASES,
                         ids=[f"json{i}" for i in range(len(JSON_CASES))])
def test_json_model_file_refuses(text, error, words):
    with pytest.raises(error, match=re.escape(words)):
        loads_model(text, syntax="json")


def test_model_file_with_bom_and_crlf_reads():
    spec = loads_model("\ufeff" + EXAMPLE_MODEL.replace("\n", "\r\n"))
    assert spec.system.n == 2


# ---------------------------------------------------------------------------------------------
# CSV data files
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def spec():
    return loads_model(EXAMPLE_MODEL)


CSV_CASES = [
    ("", "is empty"),
    ("t,u,y\n", "no data rows"),
    ("t,u\n0,0\n", "missing column 'y'"),
    ("time,u,y\n0,0,0\n", "missing column 't'"),
    ("t,u,y\n0,0,abc\n", "'abc' is not a number"),
    ("t,u,y\n0,0,nan\n", "nan-policy skip"),
    ("t,u,y\n0,0,\n", "nan-policy skip"),
    ("t,u,y\n0,inf,0\n", "not finite"),
    ("t,u,y\n0,nan,0\n", "every t and input sample"),
    ("t,u,y\n0,0,0,7\n", "4 fields"),
    ("t,u,y\n0,0,0\n0,0,1\n", "does not increase"),
    ("t,u,y\n1,0,0\n0,0,1\n", "does not increase"),
    ("t,u,y\n0,0,0\n0.1,0,inf\n", "not finite"),
]


@pytest.mark.parametrize("text,words", CSV_CASES, ids=[f"csv{i}" for i in range(len(CSV_CASES))])
def test_csv_refuses(tmp_path, spec, text, words):
    path = tmp_path / "data.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(E.ModelFileError, match=re.escape(words)):
        read_data(path, spec.layout)


def test_csv_not_utf8(tmp_path, spec):
    path = tmp_path / "data.csv"
    path.write_bytes(b"t,u,y\n0,0,\xff\xfe\n")
    with pytest.raises(E.ModelFileError, match="cannot read data file"):
        read_data(path, spec.layout)


def test_csv_missing_file(tmp_path, spec):
    with pytest.raises(E.ModelFileError, match="cannot read data file"):
        read_data(tmp_path / "nope.csv", spec.layout)


def test_csv_unknown_nan_policy(tmp_path, spec):
    with pytest.raises(E.OptionError, match="nan_policy must be one of"):
        read_data(tmp_path / "x.csv", spec.layout, nan_policy="drop")


def test_csv_input_dropout_is_refused_even_with_skip(tmp_path, spec):
    path = tmp_path / "data.csv"
    path.write_text("t,u,y\n0,,0\n", encoding="utf-8")
    with pytest.raises(E.ModelFileError, match=r"line 2, column 'u': nan is not finite"):
        read_data(path, spec.layout, nan_policy="skip")


def test_library_output_over_an_input_is_refused_at_the_write(tmp_path, spec):
    """The API, not only the CLI: write_estimates over the CSV that read_data read raises a
    ThetahatError and leaves the input byte for byte; once the file has changed since, it is
    no longer an input and may be written."""
    from thetahat.io.datafile import write_estimates
    path = tmp_path / "data.csv"
    t = np.arange(50) * 0.01
    np.savetxt(path, np.c_[t, np.sin(t), 0.1 * t], delimiter=",", header="t,u,y",
               comments="")
    before = path.read_bytes()
    d = read_data(path, spec.layout)
    res = run_estimator(spec, d.t, d.u, d.y)
    with pytest.raises(E.FileAccessError, match="read it as an input"):
        write_estimates(path, res, spec.layout)
    assert path.read_bytes() == before
    time.sleep(0.01)
    path.write_text("edited\n", encoding="utf-8")        # a new file: not the input any more
    write_estimates(path, res, spec.layout)
    assert path.read_text(encoding="utf-8").startswith("t,")


def test_output_path_that_is_a_directory(tmp_path):
    with pytest.raises(E.ModelFileError, match="it is a directory"):
        check_writable(tmp_path)


def test_output_path_under_a_file(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(E.ModelFileError, match="not a writable folder"):
        check_writable(blocker / "sub" / "out.csv")


# ---------------------------------------------------------------------------------------------
# the API
# ---------------------------------------------------------------------------------------------

A2 = [[0.0, 1.0], [-1.0, -0.5]]
E_OK = [[0.0], [1.0]]
C2 = [[1.0, 0.0]]

API_CASES = [
    ("eps=1e-300", lambda: modified_high_gain(A2, E_OK, C2, eps=1e-300), E.DesignError,
     "too small"),
    ("eps=0", lambda: modified_high_gain(A2, E_OK, C2, eps=0.0), E.DesignError, "eps must be > 0"),
    ("eps=nan", lambda: modified_high_gain(A2, E_OK, C2, eps=float("nan")), E.NonFiniteError,
     "finite"),
    ("eps=str", lambda: modified_high_gain(A2, E_OK, C2, eps="abc"), E.DesignError,
     "must be a number"),
    ("nonminimum-phase", lambda: modified_high_gain(A2, [[1.0], [-5.0]], C2, eps=1.0),
     E.NotMinimumPhaseError, "zero(s) 4.5"),
    ("zero at origin", lambda: high_gain(A2, [[1.0], [-0.5]], C2, eps=1.0),
     E.NotMinimumPhaseError, "not minimum-phase"),
    ("right-half-plane chain pole", lambda: high_gain(A2, E_OK, C2, 1.0, [[1.0, -2.0]]),
     E.DesignError, "open left half-plane"),
    ("wrong number of poles", lambda: high_gain(A2, E_OK, C2, 1.0, [[-1.0]]), E.DesignError,
     "needs 2 poles"),
    ("non-square A", lambda: scb([[0.0, 1.0]], E_OK, C2), E.DimensionError, "square"),
    ("1-D B", lambda: scb(A2, [0.0, 1.0], C2), E.DimensionError, "np.reshape"),
    ("complex C", lambda: scb(A2, E_OK, [[1j, 0.0]]), E.DimensionError, "must be real"),
    ("NaN in A", lambda: scb([[np.nan, 1.0], [0.0, 0.0]], E_OK, C2), E.NonFiniteError,
     "NaN or inf"),
    ("redundant outputs", lambda: scb(A2, E_OK, [[1.0, 0.0], [2.0, 0.0]]), E.DimensionError,
     "outputs [0] are linear combinations of outputs [1]"),
    ("negative tol", lambda: scb(A2, E_OK, C2, tol=-1.0), E.DimensionError, "tol must be"),
    ("not left-invertible", lambda: scb(A2, [[0.0, 0.0], [1.0, 1.0]], C2),
     E.NotLeftInvertibleError, "not left-invertible"),
    ("rmse shapes", lambda: rmse(np.zeros((10, 2)), np.zeros((9, 2))), E.DimensionError,
     "truth has shape (9, 2)"),
    ("rmse empty", lambda: rmse(np.zeros((0, 1)), np.zeros((0, 1))), E.DimensionError,
     "N >= 1"),
    ("rmse start", lambda: rmse(np.zeros((3, 1)), 0.0, start=5), E.DimensionError,
     "start must be"),
    ("time_to_within shapes", lambda: time_to_within([0, 1], [1.0, 2.0, 3.0], 1.0, 0.01),
     E.DimensionError, "3 samples but t has 2"),
    ("huge time grid", lambda: time_grid(1e9, 1e3), E.ResourceLimitError, "shorten t_end"),
    ("parse_expression non-string", lambda: parse_expression(3, {}), E.ModelFileError,
     "must be a string"),
    ("Box lower > upper", lambda: Box([1.0], [0.0]), E.ParameterSetError, "lower"),
]


@pytest.mark.parametrize("name,call,error,words", API_CASES,
                         ids=[c[0] for c in API_CASES])
def test_api_refuses(name, call, error, words):
    with pytest.raises(error, match=re.escape(words)):
        call()


def test_nonminimum_phase_error_names_the_zeros():
    with pytest.raises(E.NotMinimumPhaseError) as info:
        modified_high_gain(A2, [[1.0], [-5.0]], C2, eps=1.0)
    np.testing.assert_allclose(info.value.zeros, [4.5], rtol=1e-9)  # s + 0.5 − 5 = 0


def test_nonminimum_phase_opt_out_designs_anyway():
    d = modified_high_gain(A2, [[1.0], [-5.0]], C2, eps=1.0, allow_nonminimum_phase=True)
    assert np.max(d.eigenvalues.real) > 0          # the zero stays in the spectrum (Remark 2)


def test_unstable_design_on_the_true_system_is_an_error():
    d = modified_high_gain(A2, E_OK, C2, eps=1.0)
    A_true = [[0.0, 1.0], [50.0, 10.0]]            # a very different true system
    with pytest.raises(E.UnstableDesignError, match="unstable") as info:
        apply_design(d, A_true, E_OK, C2)
    assert np.all(info.value.eigenvalues.real >= 0) and info.value.eigenvalues.size
    assert not apply_design(d, A_true, E_OK, C2, allow_unstable=True).stable


def _pert(text: str) -> SymbolicPerturbation:
    return parse_perturbation(text, u=[], y=["y"], x=["x"], theta=["theta"])


def test_gradient_law_refuses_g_without_theta():
    with pytest.raises(E.UpdateLawError, match="does not depend on θ"):
        GradientInversion(_pert("y**2"), 1.0, Box([0.0], [1.0]))


def test_algebraic_law_refuses_g_without_theta():
    with pytest.raises(E.UpdateLawError, match="does not depend on θ"):
        algebraic_from_perturbation(_pert("sin(y)"), Gamma=1.0,
                                    parameter_set=Box([0.0], [1.0]))


def test_theta_star_branch_missing_theta():
    """θ* = +sqrt(φ/y²) inverts g = θ² y² only for θ >= 0: Θ = [−2, −1] is missed."""
    g = _pert("theta**2*y**2")
    t = np.linspace(0.0, 1.0, 11)

    def theta_star(v, x, phi):
        return np.sqrt(phi / v[..., :1] ** 2)

    with pytest.raises(E.UpdateLawError, match="branch that misses Θ"):
        check_theta_star(theta_star, g, Box([-2.0], [-1.0]), [[1.0]], t, None, 1.0 + t)


def test_theta_star_nan_on_the_data():
    g = _pert("theta*y")
    t = np.linspace(0.0, 1.0, 11)

    def theta_star(v, x, phi):
        return np.log(v[..., :1] - 1.5) * 0 + phi / v[..., :1]   # NaN where y < 1.5

    with pytest.raises(E.UpdateLawError, match="NaN or inf on the data at t = "):
        check_theta_star(theta_star, g, Box([1.0], [2.0]), [[1.0]], t, None, 1.0 + t)


def test_theta_star_data_shape():
    with pytest.raises(E.DimensionError, match="y must have shape"):
        check_theta_star(lambda v, x, p: p, _pert("theta*y"), Box([1.0], [2.0]), [[1.0]],
                         np.arange(3.0), None, np.zeros((4, 1)))


def _observer():
    return build_observer(loads_model(EXAMPLE_MODEL))


def test_observer_refuses_complex_y():
    obs = _observer()
    t = np.arange(5) * 0.01
    with pytest.raises(E.DimensionError, match="y must be real"):
        obs.run(t, np.zeros(5), np.zeros(5) + 1j)


def test_observer_refuses_unknown_hold():
    obs = _observer()
    with pytest.raises(E.OptionError, match="hold must be one of"):
        obs.with_run_options(hold="cubic")


def test_compiled_observer_refuses_complex_y():
    pytest.importorskip("numba")
    from thetahat.estimation.observer.compiled import compile_observer

    obs = _observer()
    dt = 0.01
    comp = compile_observer(obs, dt=dt)
    t = np.arange(5) * dt
    with pytest.raises(E.DimensionError, match="y must be real"):
        comp.run(t, np.zeros(5), np.zeros(5) + 1j)


# ---------------------------------------------------------------------------------------------
# the CLI: exit codes, messages, no traceback
# ---------------------------------------------------------------------------------------------

def _write(tmp_path, name: str, text: str):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


CLI_CASES = [
    (lambda p: ["analyze", str(p / "missing.toml")], 2, "cannot read model file"),
    (lambda p: ["analyze", str(_write(p, "m.yaml", "x"))], 2, "use a .toml or .json"),
    (lambda p: ["analyze", str(_write(p, "m.toml", "x = " + "[" * 5000))], 2,
     "nested deeper"),
    (lambda p: ["analyze", str(_write(p, "m.toml", _model('law = "gradient"',
                                                          'law = "?"')))], 2, "unknown law"),
    (lambda p: ["frobnicate"], 2, ""),
    (lambda p: ["estimate", str(_write(p, "m.toml", EXAMPLE_MODEL)), str(p / "none.csv"),
                "-o", str(p)], 2, "is a directory"),
    (lambda p: ["estimate", str(_write(p, "m.toml", EXAMPLE_MODEL)), str(p / "none.csv"),
                "-o", str(p / "o.csv")], 2, "cannot read data file"),
    (lambda p: ["estimate", str(_write(p, "m.toml", EXAMPLE_MODEL)),
                str(_write(p, "d.csv", "t,u,y\n0,0,0\n0.01,0,\n")), "-o", str(p / "o.csv")],
     2, "--nan-policy skip"),
    (lambda p: ["sweep", "--t-end", "1e9"], 2, "memory"),
    (lambda p: ["sweep", "--out", str(_write(p, "f", "x") / "sub")], 2, "not a writable folder"),
    (lambda p: ["tune", "--out", str(_write(p, "f", "x"))], 2, "not a writable folder"),
]


@pytest.mark.parametrize("argv,code,words", CLI_CASES, ids=[f"cli{i}" for i in range(len(CLI_CASES))])
def test_cli_refuses_without_traceback(tmp_path, capsys, argv, code, words):
    assert main(argv(tmp_path)) == code
    err = capsys.readouterr().err
    assert words in err
    assert "Traceback" not in err


def test_cli_debug_shows_the_traceback(tmp_path, capsys):
    assert main(["--debug", "analyze", str(tmp_path / "missing.toml")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "cannot read model file" in err


def test_cli_help_documents_the_exit_codes(capsys):
    assert main(["analyze", "--help"]) == 0
    out = capsys.readouterr().out
    assert "0 when Assumption 1 holds" in out and "1 when not" in out and "2 for bad" in out


def test_run_batch_refuses_complex_y():
    from thetahat.estimation.observer.batch_run import run_batch

    obs = _observer()
    t = np.arange(5) * 0.01
    with pytest.raises(E.DimensionError, match="Y must be real"):
        run_batch(obs, t, np.zeros((2, 5)), np.zeros((2, 5)) + 1j)


# =============================================================================================
# Round two (issue 22): nothing lost, nothing hangs, nothing silent
# =============================================================================================

import json as _json
import os
import signal
import subprocess
import sys
from pathlib import Path

from thetahat import limits
from thetahat.fleet import FleetResult, estimate_many, fleet_files, is_glob
from thetahat.safe_io import atomic_path, check_regular, write_text
from thetahat.studies.information import (explain_nonfinite, stuck_parameters,
                                          undefined_perturbation)
from thetahat.studies.metrics import estimate_summary
from thetahat.structure.assumptions import check_assumption_1

#: Seconds after which a read that should have been refused counts as a hang (the issue's
#: acceptance: no hang past 10 s).
HANG_SECONDS = 10


@pytest.fixture
def no_hang():
    """Turn a hang into a failure: SIGALRM interrupts a blocking open() or read()."""
    def on_alarm(signum, frame):
        raise TimeoutError(f"hung for {HANG_SECONDS} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(HANG_SECONDS)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def _record(path: Path, N: int = 200, *, y_scale: float = 0.1) -> Path:
    t = np.arange(N) * 0.01
    rows = "\n".join(f"{float(ti)!r},{float(np.sin(ti))!r},{float(y_scale * np.cos(ti))!r}"
                     for ti in t)
    path.write_text("t,u,y\n" + rows + "\n", encoding="utf-8")
    return path


@pytest.fixture
def files(tmp_path):
    """A model file and a record, with their bytes to check that nothing was overwritten."""
    model = _write(tmp_path, "m.toml", EXAMPLE_MODEL)
    data = _record(tmp_path / "d.csv")
    return model, data, {model: model.read_bytes(), data: data.read_bytes()}


def _unchanged(before: dict) -> bool:
    return all(p.read_bytes() == b for p, b in before.items())


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if ".tmp" in p.name]


# --- data loss: an output never replaces an input ---------------------------------------------

def _link(tmp_path, target, kind):
    out = tmp_path / f"{kind}.csv"
    (os.symlink if kind == "symlink" else os.link)(target, out)
    return out


OUTPUT_ON_INPUT = [
    ("data", lambda p, m, d: d, "is an input"),
    ("model", lambda p, m, d: m, "is an input"),
    ("symlink to data", lambda p, m, d: _link(p, d, "symlink"), "is an input"),
    ("hard link to data", lambda p, m, d: _link(p, d, "hardlink"), "is an input"),
    ("data via ..", lambda p, m, d: p / "sub" / ".." / d.name, "is an input"),
]


@pytest.mark.parametrize("name,output,words", OUTPUT_ON_INPUT, ids=[c[0] for c in OUTPUT_ON_INPUT])
def test_estimate_never_writes_over_an_input(tmp_path, files, capsys, name, output, words):
    model, data, before = files
    (tmp_path / "sub").mkdir()
    out = output(tmp_path, model, data)
    assert main(["estimate", str(model), str(data), "-o", str(out), "--no-progress"]) == 2
    assert words in capsys.readouterr().err
    assert _unchanged(before)


def test_estimate_refuses_an_unknown_output_suffix_before_the_work(files, tmp_path, capsys):
    model, data, _ = files
    start = time.perf_counter()
    assert main(["estimate", str(model), str(data), "-o", str(tmp_path / "e.txt")]) == 2
    assert "suffix must be one of .csv, .parquet" in capsys.readouterr().err
    assert not (tmp_path / "e.txt").exists() and time.perf_counter() - start < FAST_SECONDS


PLOT_CASES = [
    ("bad suffix", lambda p, d: p / "fig.xyz", "suffix must be one of .png"),
    ("same as -o", lambda p, d: p / "e.csv", "is also the estimates output"),
    ("the data file", lambda p, d: d, "is an input"),
    ("folder under a file", lambda p, d: d / "fig.png", "not a writable folder"),
]


@pytest.mark.parametrize("name,plot,words", PLOT_CASES, ids=[c[0] for c in PLOT_CASES])
def test_plot_path_is_checked_before_the_work(tmp_path, files, capsys, name, plot, words):
    model, data, before = files
    out = tmp_path / "e.csv"
    assert main(["estimate", str(model), str(data), "-o", str(out), "--plot",
                 str(plot(tmp_path, data)), "--no-progress"]) == 2
    assert words in capsys.readouterr().err
    assert not out.exists()                       # refused before the estimates were written
    assert _unchanged(before)


def test_single_record_parquet_output_is_parquet(tmp_path, files):
    pq = pytest.importorskip("pyarrow.parquet")
    from thetahat.io.datafile import estimate_columns

    model, data, _ = files
    out = tmp_path / "e.parquet"
    assert main(["estimate", str(model), str(data), "-o", str(out), "--no-progress",
                 "--method", "paper"]) == 0                       # the observer's columns
    table = pq.read_table(out)
    assert tuple(table.column_names) == estimate_columns(loads_model(EXAMPLE_MODEL).layout,
                                                         refined=True)
    np.testing.assert_array_equal(table.column("t").to_numpy(), np.arange(200) * 0.01)


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    out = tmp_path / "e.csv"
    out.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(out) as tmp:
            tmp.write_text("half of the new cont")
            raise RuntimeError("disk full")
    assert out.read_text() == "old" and _leftovers(tmp_path) == []


def test_atomic_write_replaces_and_keeps_the_mode(tmp_path):
    out = tmp_path / "e.json"
    out.write_text("old")
    out.chmod(0o640)
    write_text(out, "{}")
    assert out.read_text() == "{}" and (out.stat().st_mode & 0o777) == 0o640
    assert _leftovers(tmp_path) == []


def test_file_size_limit_leaves_the_old_output(tmp_path):
    """`ulimit -f` during the write: the write fails, the old output is intact (issue 22)."""
    out = tmp_path / "big.csv"
    out.write_text("the old estimates\n")
    code = ("import resource, signal, sys\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (50 * 1024, 50 * 1024))\n"
            "from thetahat.safe_io import write_text\n"
            "from thetahat.errors import FileAccessError\n"
            "try:\n"
            f"    write_text({str(out)!r}, 'x' * 200_000)\n"
            "except FileAccessError as exc:\n"
            "    print('refused:', exc); sys.exit(0)\n"
            "sys.exit(1)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=env, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "File too large" in proc.stdout
    assert out.read_text() == "the old estimates\n" and _leftovers(tmp_path) == []


def test_sweep_output_may_not_be_its_model(tmp_path, capsys):
    model = _write(tmp_path, "sweep.json", "{}")
    before = model.read_bytes()
    assert main(["sweep", str(model), "--out", str(tmp_path)]) == 2
    assert "is an input" in capsys.readouterr().err and model.read_bytes() == before


@pytest.fixture
def fleet(tmp_path):
    d = tmp_path / "fleet"
    d.mkdir()
    for i in range(2):
        _record(d / f"r{i}.csv", y_scale=0.1 * (i + 1))
    model = _write(tmp_path, "m.toml", EXAMPLE_MODEL)
    return model, d


FLEET_OUTPUTS = [
    ("a record", lambda d: d / "r0.csv", "is an input"),
    ("new file in the fleet folder", lambda d: d / "results.csv", "fleet's folder"),
    (".txt", lambda d: d.parent / "results.txt", "suffix must be one of .csv, .parquet"),
    ("the model", lambda d: d.parent / "m.toml", "is an input"),
]


@pytest.mark.parametrize("name,output,words", FLEET_OUTPUTS, ids=[c[0] for c in FLEET_OUTPUTS])
def test_fleet_output_is_checked_before_the_work(fleet, capsys, name, output, words):
    model, d = fleet
    before = {p: p.read_bytes() for p in [model, *d.iterdir()]}
    start = time.perf_counter()
    assert main(["estimate", str(model), str(d), "-o", str(output(d)), "--no-progress"]) == 2
    assert words in capsys.readouterr().err
    assert _unchanged(before) and time.perf_counter() - start < FAST_SECONDS


def test_fleet_result_write_refuses_its_inputs(fleet):
    model, d = fleet
    res = estimate_many(model, d, progress=False)
    with pytest.raises(E.ModelFileError, match="is an input"):
        res.write(d / "r1.csv")
    with pytest.raises(E.ModelFileError, match="suffix"):
        res.write(d.parent / "res.xlsx")


# --- hangs: only regular files are read --------------------------------------------------------

def _fifo(tmp_path, name):
    path = tmp_path / name
    os.mkfifo(path)
    return path


def _devlink(tmp_path, name, device="/dev/zero"):
    path = tmp_path / name
    os.symlink(device, path)
    return path


SPECIAL_MODEL = [
    ("fifo", lambda p: _fifo(p, "m.toml"), "FIFO"),
    ("symlink to /dev/zero", lambda p: _devlink(p, "m.toml"), "character device"),
    ("symlink to /dev/urandom", lambda p: _devlink(p, "m.json", "/dev/urandom"),
     "character device"),
]


@pytest.mark.parametrize("name,make,words", SPECIAL_MODEL, ids=[c[0] for c in SPECIAL_MODEL])
def test_analyze_refuses_special_model_files(tmp_path, capsys, no_hang, name, make, words):
    assert main(["analyze", str(make(tmp_path))]) == 2
    err = capsys.readouterr().err
    assert words in err and "only regular files" in err


SPECIAL_DATA = [
    ("/dev/zero", lambda p: Path("/dev/zero"), "character device"),
    ("fifo", lambda p: _fifo(p, "d.csv"), "FIFO"),
    ("symlink to /dev/zero", lambda p: _devlink(p, "d.csv"), "character device"),
    ("fifo parquet", lambda p: _fifo(p, "d.parquet"), "FIFO"),
]


@pytest.mark.parametrize("name,make,words", SPECIAL_DATA, ids=[c[0] for c in SPECIAL_DATA])
def test_estimate_refuses_special_data_files(tmp_path, capsys, no_hang, name, make, words):
    model = _write(tmp_path, "m.toml", EXAMPLE_MODEL)
    assert main(["estimate", str(model), str(make(tmp_path)), "-o", str(tmp_path / "e.csv"),
                 "--no-progress"]) == 2
    assert words in capsys.readouterr().err


def test_fleet_reports_special_entries_as_failed_rows(fleet, no_hang):
    model, d = fleet
    _fifo(d, "pipe.csv")
    _devlink(d, "zero.csv")
    # the paper's observer: the regular records' work stays well inside the alarm on every back end
    # (guarded's fits take ~30 s for these two records in plain Python, no numba)
    res = estimate_many(model, d, progress=False, method="paper")
    assert res.n_ok == 2
    assert "FIFO" in res.failed[str(d / "pipe.csv")]
    assert "character device" in res.failed[str(d / "zero.csv")]


def test_model_file_size_limit(tmp_path, monkeypatch):
    from thetahat.modelfile import load_model

    monkeypatch.setattr(limits, "MAX_MODEL_FILE_BYTES", 100)
    path = _write(tmp_path, "m.toml", EXAMPLE_MODEL)
    with pytest.raises(E.InputLimitError, match="MAX_MODEL_FILE_BYTES|more than the limit"):
        load_model(path)


def test_data_file_size_limit(tmp_path, spec, monkeypatch):
    monkeypatch.setattr(limits, "MAX_DATA_FILE_BYTES", 1000)
    with pytest.raises(E.InputLimitError, match="more than the limit of 1000 bytes"):
        read_data(_record(tmp_path / "d.csv"), spec.layout)


def test_check_regular_refuses_a_directory(tmp_path):
    with pytest.raises(E.ModelFileError, match="it is a directory"):
        check_regular(tmp_path, "data file")


# --- names: NFKC, as formulas -----------------------------------------------------------------

NAME_CASES = [
    ({"x": ["eta", "\uff45ta"]}, "declared twice"),                   # full-width e
    ({"x": ["x1", "x2"], "theta": ["\u00b5"], "y": ["\u03bc"]}, "declared twice"),
    ({"x": ["\ufb01x", "fix"]}, "declared twice"),                    # the ligature fi
]


@pytest.mark.parametrize("groups,words", NAME_CASES, ids=["fullwidth", "micro-mu", "ligature"])
def test_look_alike_names_are_refused(groups, words):
    names = {"u": [], "y": ["y"], "x": ["x1", "x2"], "theta": ["theta"], **groups}
    with pytest.raises(E.ModelFileError, match=words):
        parse_perturbation(f"{names['theta'][0]}*{names['y'][0]}", **names)


def test_look_alike_constants_are_refused():
    with pytest.raises(E.ModelFileError, match="NFKC"):
        parse_perturbation("y*theta", **NAMES, constants={"\u03bc0": 1.0, "\u00b50": 2.0})


def test_a_full_width_name_is_the_ascii_name():
    """Python reads the formula's identifiers in NFKC; the declared name is read the same."""
    g = parse_perturbation("eta*theta", u=[], y=["y"], x=["\uff45ta"], theta=["theta"])
    assert float(g.g([1.0], [3.0], [2.0])[0]) == 6.0


def test_model_file_look_alike_states(tmp_path):
    text = _model('x = ["x1", "x2"]', 'x = ["x1", "\uff58\uff11"]')      # full-width x1
    with pytest.raises(E.ModelFileError, match="declared twice"):
        loads_model(text)


# --- numbers ------------------------------------------------------------------------------------

NUMBER_CASES = [
    ("((theta**100)**100)**100*y", E.InputLimitError, "product of nested exponents"),
    ("(y**50*theta)**3", E.InputLimitError, "exponent of 150"),
    ("sqrt((theta**60)**2)*y", E.InputLimitError, "exponent of 120"),
]


@pytest.mark.parametrize("text,error,words", NUMBER_CASES,
                         ids=[f"nested{i}" for i in range(len(NUMBER_CASES))])
def test_nested_exponents_multiply(text, error, words):
    with pytest.raises(error, match=re.escape(words)):
        parse_perturbation(text, **NAMES)


def test_nested_exponents_within_the_limit_parse():
    g = parse_perturbation("(theta**2)**3*y", **NAMES)              # exponent 6
    assert float(g.g([0.0, 2.0], [0.0, 0.0], [2.0])[0]) == 128.0


BIG = "1" + "0" * 400
HUGE_NUMBERS = [
    ("json matrix", '{"system": {"A": [[' + BIG + ', 1], [0, 0]]}}', "json", "system.A[0][0]"),
    ("toml eps", _model("eps = 0.5", f"eps = {BIG}"), "toml", "estimator.eps"),
    ("toml bound", _model("upper = [2.0]", f"upper = [{BIG}]"), "toml",
     "parameter_set.upper[0]"),
    ("toml constant", _model("[perturbation]", "[perturbation]\nconstants = {c = " + BIG + "}"),
     "toml", "perturbation.constants.c"),
]


@pytest.mark.parametrize("name,text,syntax,where", HUGE_NUMBERS, ids=[c[0] for c in HUGE_NUMBERS])
def test_huge_integers_name_their_field(name, text, syntax, where):
    with pytest.raises(E.ModelFileError, match=re.escape(where) + ".*401 digits"):
        loads_model(text, syntax=syntax)


def test_huge_integer_constant_in_the_api():
    with pytest.raises(E.ModelFileError, match="401 digits"):
        parse_perturbation("y*theta*c", **NAMES, constants={"c": int(BIG)})


def test_json_duplicate_keys_are_refused():
    doc = '{"name": "a", "name": "b"}'
    with pytest.raises(E.ModelFileError, match="'name' is given twice"):
        loads_model(doc, syntax="json")


def test_huge_eps_is_a_design_error(tmp_path, capsys):
    model = _write(tmp_path, "m.toml", _model("eps = 0.5", "eps = 1e300"))
    data = _record(tmp_path / "d.csv")
    assert main(["estimate", str(model), str(data), "-o", str(tmp_path / "e.csv"),
                 "--no-progress"]) == 2
    assert "too large" in capsys.readouterr().err


def test_analyze_huge_matrix_entries(tmp_path, capsys):
    model = _write(tmp_path, "m.toml", _model("A = [[0.0, 1.0], [-1.0, -0.5]]",
                                              "A = [[0.0, 1e308], [-1.0, -0.5]]"))
    assert main(["analyze", str(model)]) == 2
    err = capsys.readouterr().err
    assert "[system]" in err and "MAX_MATRIX_ENTRY" in err


def test_check_assumption_1_refuses_entries_of_1e300():
    with pytest.raises(E.InputLimitError, match=r"A\[0, 1\] = 1e\+300"):
        check_assumption_1([[0.0, 1e300], [-1.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]])


def test_linalg_failure_names_the_data_scale():
    g = _pert("theta*y")
    system = type("S", (), {"perturbation": g, "parameter_set": Box([0.0], [1.0])})()
    err = explain_nonfinite(np.linalg.LinAlgError("Singular matrix"), system, [0.0, 0.1],
                            None, [[1e30], [1e30]], [0.0], [0.5])
    assert isinstance(err, E.SimulationError) and "|y| = 1e+30" in str(err)


# --- types of data --------------------------------------------------------------------------------

T_API = np.arange(200) * 0.01


def _api_run(y, **kw):
    spec_ = loads_model(EXAMPLE_MODEL)
    t = kw.pop("t", T_API)
    return run_estimator(spec_, t, np.sin(T_API), y, method="paper", **kw)


def test_masked_y_is_refused_under_raise():
    y = np.ma.masked_array(0.1 * np.cos(T_API), mask=T_API > 1.0)
    with pytest.raises(E.NonFiniteError, match="y contains NaN"):
        _api_run(y)


def test_masked_y_is_a_dropout_under_skip():
    y = 0.1 * np.cos(T_API)
    masked = np.ma.masked_array(y, mask=(T_API > 1.0) & (T_API < 1.2))
    filled = np.where(masked.mask, np.nan, y)
    a = _api_run(masked, nan_policy="skip")
    b = _api_run(filled, nan_policy="skip")
    np.testing.assert_array_equal(a.theta_hat, b.theta_hat)
    assert a.skipped.sum() == masked.mask.sum()


def test_datetime_t_is_seconds_from_the_first_sample():
    stamps = np.datetime64("2024-05-01T12:00:00") + (T_API * 1e6).astype("timedelta64[us]")
    a = _api_run(0.1 * np.cos(T_API), t=stamps)
    b = _api_run(0.1 * np.cos(T_API))
    np.testing.assert_allclose(a.t, T_API, rtol=0, atol=1e-12)   # µs stamps: exact to 1e-12
    np.testing.assert_allclose(a.theta_hat, b.theta_hat, rtol=0, atol=1e-9)


SAMPLE_TYPES = [
    ("bool y", lambda: np.cos(T_API) > 0, "booleans"),
    ("text y", lambda: np.array(["0.1"] * 200), "text"),
    ("text list y", lambda: ["a"] * 200, "text"),
    ("datetime y", lambda: np.datetime64("2024-01-01") + np.arange(200).astype("timedelta64[s]"),
     "dates or times"),
]


@pytest.mark.parametrize("name,y,words", SAMPLE_TYPES, ids=[c[0] for c in SAMPLE_TYPES])
def test_samples_of_the_wrong_kind_are_refused(name, y, words):
    with pytest.raises(E.DimensionError, match=words):
        _observer().run(T_API, np.sin(T_API), y())


CSV_ROUND_TWO = [
    ("t,u,y\n0,0,1_000\n0.01,0,0\n", "digit separators"),
    ("t,u,y,y\n0,0,0,1\n0.01,0,0,1\n", "appear more than once"),
    ("t,u,y,y1\n0,0,0,1\n0.01,0,0,1\n", "name the same signal"),
    ("t,u,y\n0,0,0.1\n", "one data row"),
    ("t,u,y\n2024-01-01T00:00:00,0,0\n2024-01-01T00:00:01,0,0\n", "not a date or time"),
    ("t,u,y\n0,True,0\n0.01,False,0\n", "'True' is not a number"),
]


@pytest.mark.parametrize("text,words", CSV_ROUND_TWO,
                         ids=[f"csv-r2-{i}" for i in range(len(CSV_ROUND_TWO))])
def test_csv_round_two_refuses(tmp_path, spec, text, words):
    path = _write(tmp_path, "d.csv", text)
    with pytest.raises(E.ModelFileError, match=re.escape(words)):
        read_data(path, spec.layout)


def _parquet(tmp_path, columns, name="d.parquet"):
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    path = tmp_path / name
    pq.write_table(pa.table(columns), path)
    return path


def test_single_parquet_file_is_read(tmp_path, spec, capsys):
    t = np.arange(50) * 0.01
    path = _parquet(tmp_path, {"t": t, "u": np.sin(t), "y": 0.1 * np.cos(t)})
    rec = read_data(path, spec.layout)
    np.testing.assert_array_equal(rec.y.ravel(), 0.1 * np.cos(t))
    model = _write(tmp_path, "m.toml", EXAMPLE_MODEL)
    assert main(["estimate", str(model), str(path), "-o", str(tmp_path / "e.csv"),
                 "--no-progress"]) == 0
    assert "wrote" in capsys.readouterr().out


def test_parquet_timestamp_t_is_seconds(tmp_path, spec):
    t = np.arange(50) * 0.01
    stamps = np.datetime64("2024-05-01T00:00:00", "ns") + (t * 1e9).astype("timedelta64[ns]")
    rec = read_data(_parquet(tmp_path, {"t": stamps, "u": np.sin(t), "y": np.cos(t)}), spec.layout)
    np.testing.assert_allclose(rec.t, t, rtol=0, atol=1e-12)


PARQUET_REFUSED = [
    ("bool y", lambda t: {"t": t, "u": t, "y": t > 0.1}, "column 'y': holds booleans"),
    ("text u", lambda t: {"t": t, "u": [str(v) for v in t], "y": t}, "column 'u': holds text"),
    ("timestamp y", lambda t: {"t": t, "u": t, "y": np.datetime64("2024-01-01", "ns")
                               + np.arange(t.size).astype("timedelta64[s]")}, "holds time stamps"),
    ("one row", lambda t: {"t": t[:1], "u": t[:1], "y": t[:1]}, "at least two samples"),
]


@pytest.mark.parametrize("name,columns,words", PARQUET_REFUSED, ids=[c[0] for c in PARQUET_REFUSED])
def test_parquet_refuses(tmp_path, spec, name, columns, words):
    path = _parquet(tmp_path, columns(np.arange(20) * 0.01))
    with pytest.raises(E.ModelFileError, match=re.escape(words)):
        read_data(path, spec.layout)


# --- brackets in paths are literal when the file exists ----------------------------------------

def test_brackets_in_an_existing_path_are_literal(tmp_path, capsys):
    model = _write(tmp_path, "m.toml", EXAMPLE_MODEL)
    real = _record(tmp_path / "data[1].csv", N=150)
    _record(tmp_path / "data1.csv", N=120)             # what the glob would have matched
    assert not is_glob(real) and fleet_files(str(real)) == [real]
    assert main(["estimate", str(model), str(real), "-o", str(tmp_path / "e.csv"),
                 "--no-progress"]) == 0
    assert "(150 rows)" in capsys.readouterr().out


def test_brackets_glob_when_no_such_file(tmp_path):
    for name in ("data1.csv", "data2.csv"):
        _record(tmp_path / name, N=20)
    pattern = str(tmp_path / "data[12].csv")
    assert is_glob(pattern) and len(fleet_files(pattern)) == 2


# --- the API: typed errors, not bare builtins ----------------------------------------------------

API_ROUND_TWO = [
    ("Box text", lambda: Box(["a"], ["b"]), E.ParameterSetError, "text"),
    ("Box ragged", lambda: Box([[0.0, 1.0], [2.0]], [1.0, 2.0]), E.ParameterSetError,
     "numeric array"),
    ("time_to_within rel<0", lambda: time_to_within([0.0, 1.0], [1.0, 1.0], 1.0, -0.1),
     E.DimensionError, "rel must be > 0"),
    ("estimate_many data=42", lambda: estimate_many(_EXAMPLE_PATH, 42), E.ArgumentTypeError,
     "data must be a folder"),
    ("estimate_many model=42", lambda: estimate_many(42, "."), E.ArgumentTypeError,
     "model must be the path"),
    ("estimate_many list of ints", lambda: estimate_many(_EXAMPLE_PATH, [1, 2]),
     E.ArgumentTypeError, "each record must be a path"),
    ("observer y of text", lambda: _observer().run(np.arange(3.0), np.zeros(3), ["a", "b", "c"]),
     E.DimensionError, "text"),
]


@pytest.fixture(scope="module", autouse=True)
def _example_path(tmp_path_factory):
    global _EXAMPLE_PATH
    _EXAMPLE_PATH = tmp_path_factory.mktemp("example") / "m.toml"
    _EXAMPLE_PATH.write_text(EXAMPLE_MODEL, encoding="utf-8")


_EXAMPLE_PATH: Path = Path("m.toml")


@pytest.mark.parametrize("name,call,error,words", API_ROUND_TWO, ids=[c[0] for c in API_ROUND_TWO])
def test_api_round_two_refuses(name, call, error, words):
    with pytest.raises(error, match=re.escape(words)):
        call()


# --- g undefined on the data, stuck estimates, one-sample summaries ------------------------------

UNDEFINED_G = [
    ("sqrt(y - 10)*theta", [0.0, 2.0], "θ̂(0)"),
    ("y/theta", [0.0, 2.0], "θ = [0.]"),
    ("log(theta)*y", [0.0, 2.0], "θ = [0.]"),
]


@pytest.mark.parametrize("g,bounds,words", UNDEFINED_G, ids=["sqrt", "division", "log"])
def test_undefined_g_is_named_with_its_instant(g, bounds, words):
    pert = parse_perturbation(g, u=[], y=["y"], x=["x"], theta=["theta"])
    system = type("S", (), {"perturbation": pert, "parameter_set": Box(*map(list, zip(bounds))
                                                                            )})()
    msg = undefined_perturbation(system, [0.0, 0.5], None, [[1.0], [2.0]], [0.0], [0.0])
    assert msg is not None and "g is undefined" in msg and "t = 0" in msg and words in msg


def test_cli_names_g_undefined_instead_of_divergence(tmp_path, capsys):
    model = _write(tmp_path, "m.toml", _model('g = "(2 + sin(y))*(theta + theta**3/3)"',
                                              'g = "sqrt(y - 10)*theta"'))
    data = _record(tmp_path / "d.csv")
    assert main(["estimate", str(model), str(data), "-o", str(tmp_path / "e.csv"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "g is undefined (NaN or inf) at t = 0" in err


def test_stuck_estimate_is_reported(tmp_path, capsys):
    """g = sqrt|θ|(2 + sin y) from θ̂(0) = 0: ∂g/∂θ vanishes there, θ̂ never moves."""
    model = _write(tmp_path, "m.toml", _model('g = "(2 + sin(y))*(theta + theta**3/3)"',
                                              'g = "Abs(theta)**0.5*(2 + sin(y))"'))
    data = _record(tmp_path / "d.csv")
    assert main(["estimate", str(model), str(data), "-o", str(tmp_path / "e.csv"),
                 "--no-progress", "--method", "paper"]) == 0              # the law's check
    assert "no information reached the update law for theta" in capsys.readouterr().out


def test_informative_run_is_not_reported_stuck(tmp_path, capsys):
    model = _write(tmp_path, "m.toml", EXAMPLE_MODEL)
    data = _record(tmp_path / "d.csv")
    assert main(["estimate", str(model), str(data), "-o", str(tmp_path / "e.csv"),
                 "--no-progress", "--method", "paper"]) == 0
    assert "no information" not in capsys.readouterr().out


def test_fleet_row_reports_a_stuck_estimate(tmp_path):
    model = _write(tmp_path, "m.toml", _model('g = "(2 + sin(y))*(theta + theta**3/3)"',
                                              'g = "Abs(theta)**0.5*(2 + sin(y))"'))
    d = tmp_path / "f"
    d.mkdir()
    _record(d / "a.csv")
    res = estimate_many(model, d, progress=False, method="paper")
    assert res.n_ok == 1 and "no information" in res.rows[0]["warnings"]


def test_stuck_parameters_direct():
    g = parse_perturbation("Abs(theta)**0.5*(2 + sin(y))", u=[], y=["y"], x=["x"],
                           theta=["theta"])
    system = type("S", (), {"perturbation": g, "parameter_set": Box([-1.0], [3.0])})()
    N = 20
    y = np.linspace(0.0, 1.0, N)[:, None]
    assert stuck_parameters(system, None, y, np.zeros((N, 1)), np.zeros((N, 1)), ["a"])
    assert stuck_parameters(system, None, y, np.zeros((N, 1)), np.ones((N, 1)), ["a"]) is None


def test_one_sample_is_not_settled():
    from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics

    z = np.zeros((1, 1))
    res = EstimateResult(t=np.array([0.0]), x_hat=z, phi_hat=z, theta_hat=np.array([[0.5]]),
                         skipped=np.zeros(1, bool), diagnostics=ObserverDiagnostics())
    text = estimate_summary(res, ["theta"])
    assert "not decided" in text and "settled (within" not in text


def test_cli_y_of_1e30_is_a_one_line_error(tmp_path, capsys):
    """LuGre with y = 1e30: the second observer's implicit step meets a singular matrix; the
    CLI says so with the data's scale (exit 2), not "internal error"."""
    lugre_model = Path(__file__).resolve().parents[1] / "examples" / "lugre.toml"
    t = np.arange(2000) * 1e-3
    data = tmp_path / "y30.csv"
    # y(0) = 0: from the second sample on, not absorbed by the start x̂(0) = C⁺y(0)
    np.savetxt(data, np.c_[t, np.sin(t), np.where(t > 0, 1e30, 0.0)], delimiter=",",
               header="t,u,y", comments="")
    out = tmp_path / "e.csv"
    assert main(["estimate", str(lugre_model), str(data), "-o", str(out), "--no-progress",
                 "--method", "paper"]) == 2
    err = capsys.readouterr().err
    assert "|y| = 1e+30" in err and "internal error" not in err and not out.exists()


@pytest.mark.parametrize("stage1", [None, "paper", 42])
def test_guarded_estimator_refuses_a_stage1_that_is_not_an_estimator(stage1):
    from thetahat import GuardedEstimator
    with pytest.raises(E.ArgumentTypeError, match="stage1 must be an estimator"):
        GuardedEstimator(stage1=stage1)


def test_generate_c_refuses_a_name_that_is_not_a_string():
    from thetahat import generate_c
    from thetahat.models import lugre
    with pytest.raises(E.ArgumentTypeError, match="name must be a string"):
        generate_c(lugre.observer(), dt=0.01, name=None)


@pytest.mark.parametrize("kind", ["pole", "nan", "branch"])
def test_theta_star_check_in_blocks_names_the_same_instants(kind, monkeypatch):
    """check_theta_star evaluates a long record a block of EVAL_BLOCK samples at a time; a
    failure spread over several blocks gives the message of one block: the same first
    instants and the same count of the rest (a pole between two blocks included)."""
    import thetahat.estimation.observer.checks as checks
    t = np.linspace(0.0, 1.0, 1_001)
    if kind == "pole":              # θ* = log(φ + 1)/y: y = cos crosses 0 ten times
        g, Theta, y = _pert("exp(theta*y) - 1"), Box([0.5], [2.0]), np.cos(30 * t)
        law = algebraic_from_perturbation(g, Gamma=1.0, parameter_set=Theta)
        theta_star = law.theta_star
    else:
        g, y = _pert("theta*y"), 1.0 + t
        Theta = Box([1.0], [2.0]) if kind == "nan" else Box([-2.0], [-1.0])

        def theta_star(v, x, phi):
            if kind == "nan":       # NaN where y < 1.5: half the record
                return np.log(v[..., :1] - 1.5) * 0 + phi / v[..., :1]
            return np.abs(phi / v[..., :1])                    # a branch that misses Θ < 0

    def message() -> str:
        with pytest.raises(E.UpdateLawError) as err:
            check_theta_star(theta_star, g, Theta, [[1.0]], t, None, y)
        return str(err.value)

    whole = message()
    monkeypatch.setattr(checks, "EVAL_BLOCK", 7)
    assert message() == whole and " more" in whole
