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
from thetahat.datafile import check_writable, read_data
from thetahat.design.design_system import apply_design
from thetahat.design.gains import high_gain, modified_high_gain
from thetahat.estimation.checks import check_theta_star
from thetahat.estimation.update_laws import AlgebraicInversion, GradientInversion
from thetahat.model.paramset import Box
from thetahat.model.parse import parse_expression, parse_perturbation
from thetahat.model.perturbation import SymbolicPerturbation
from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
from thetahat.simulation.metrics import rmse, time_to_within
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
        read_data(path, spec)


def test_csv_not_utf8(tmp_path, spec):
    path = tmp_path / "data.csv"
    path.write_bytes(b"t,u,y\n0,0,\xff\xfe\n")
    with pytest.raises(E.ModelFileError, match="cannot read data file"):
        read_data(path, spec)


def test_csv_missing_file(tmp_path, spec):
    with pytest.raises(E.ModelFileError, match="cannot read data file"):
        read_data(tmp_path / "nope.csv", spec)


def test_csv_unknown_nan_policy(tmp_path, spec):
    with pytest.raises(E.OptionError, match="nan_policy must be one of"):
        read_data(tmp_path / "x.csv", spec, nan_policy="drop")


def test_csv_input_dropout_is_refused_even_with_skip(tmp_path, spec):
    path = tmp_path / "data.csv"
    path.write_text("t,u,y\n0,,0\n", encoding="utf-8")
    with pytest.raises(E.ModelFileError, match="is not a number"):
        read_data(path, spec, nan_policy="skip")


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
        AlgebraicInversion.from_perturbation(_pert("sin(y)"), Gamma=1.0,
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
        obs.run(np.arange(3.0), np.zeros(3), np.zeros(3), hold="cubic")


def test_compiled_observer_refuses_complex_y():
    pytest.importorskip("numba")
    from thetahat.estimation.compiled import compile_observer

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
    from thetahat.estimation.batch_run import run_batch

    obs = _observer()
    t = np.arange(5) * 0.01
    with pytest.raises(E.DimensionError, match="Y must be real"):
        run_batch(obs, t, np.zeros((2, 5)), np.zeros((2, 5)) + 1j)
