"""The seven groups of issue 11, reproduced as they were reported, and long input.

1 silent divergence, 2 code execution, 3 hangs, 4 silently wrong estimates, 5 raw tracebacks
and untyped errors, 6 real-world files, 7 ill-conditioned is not "not left-invertible".
"""

from __future__ import annotations

import io
import os
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
import sympy as sp

from thetahat import errors as E
from thetahat import limits
from thetahat.cli import main
from thetahat.io.datafile import read_data
from thetahat.design.gains import modified_high_gain
from thetahat.estimation.observer.laws import GradientInversion, algebraic_from_perturbation
from thetahat.model.paramset import Box
from thetahat.model.parse import parse_perturbation
from thetahat.model.perturbation import SymbolicPerturbation
from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model, run_estimator
from thetahat.progress import reporter
from thetahat.structure.scb import scb
from thetahat.structure.scb_symbolic import scb_symbolic
from thetahat.structure.zeros import invariant_zeros, is_left_invertible

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PROP3 = (EXAMPLES / "prop3.toml").read_text(encoding="utf-8")
#: Hostile input must fail fast; generous against a loaded 2-core machine.
FAST_SECONDS = 10.0


def _prop3(E_row: str, tmp_path: Path) -> Path:
    text = PROP3.replace("E = [[0.0], [1.0]]", f"E = {E_row}")
    assert text != PROP3
    path = tmp_path / "model.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _csv(tmp_path: Path, N: int = 200, *, dropouts: bool = False, bom: bool = False,
         crlf: bool = False) -> Path:
    t = np.arange(N) * 0.01
    rows = [f"{ti:.17g},{np.sin(ti):.17g},{0.1 * np.cos(ti):.17g}" for ti in t]
    if dropouts:
        rows[5] = rows[5].rsplit(",", 1)[0] + ","          # empty y cell
        rows[9] = rows[9].rsplit(",", 1)[0] + ",NaN"
    nl = "\r\n" if crlf else "\n"
    text = ("\ufeff" if bom else "") + "t,u,y" + nl + nl.join(rows) + nl
    path = tmp_path / "data.csv"
    path.write_bytes(text.encode("utf-8"))
    return path


# --- 1. silent divergence -------------------------------------------------------------------

@pytest.mark.parametrize("E_row,zero", [("[[1.0], [-5.0]]", 4.5), ("[[1.0], [-0.5]]", 0.0)],
                         ids=["rhp-zero", "zero-at-origin"])
def test_group1_nonminimum_phase_is_refused_everywhere(tmp_path, capsys, E_row, zero):
    """Y/Φ = (e1 s + 0.5 e1 + e2)/(s² + 0.5 s + 1): the zero is at −0.5 − e2/e1."""
    model = _prop3(E_row, tmp_path)
    spec = loads_model(model.read_text(), source=str(model))
    with pytest.raises(E.NotMinimumPhaseError) as info:
        modified_high_gain(spec.system.A, spec.system.E, spec.system.C, eps=0.5)
    # the zero is simple; rtol: its computed value is exact to ~1e-15 (margin 1e6)
    np.testing.assert_allclose(info.value.zeros.real, [zero], atol=1e-9)
    with pytest.raises(E.NotMinimumPhaseError, match="Assumption 1 fails"):
        build_observer(spec)
    out = tmp_path / "est.csv"
    assert main(["estimate", str(model), str(_csv(tmp_path)), "-o", str(out)]) == 1
    assert not out.exists()                          # nothing written, no x̂ ≈ −2.5e36
    assert "not minimum-phase" in capsys.readouterr().err
    assert main(["analyze", str(model)]) == 1
    captured = capsys.readouterr()
    assert "Assumption 1 (Grip, Saberi & Johansen): FAILS" in captured.out
    assert "check failed" in captured.err


def test_group1_opt_out_is_explicit(tmp_path, capsys):
    model = _prop3("[[1.0], [-5.0]]", tmp_path)
    text = model.read_text().replace("eps = 0.5", "eps = 0.5\nallow_nonminimum_phase = true")
    spec = loads_model(text)
    obs = build_observer(spec)                      # designs, as asked
    assert obs.K_x.shape == (2, 1)


def test_group1_analyze_exit_0_when_all_holds(capsys):
    assert main(["analyze", str(EXAMPLES / "prop3.toml")]) == 0
    assert main(["analyze", str(EXAMPLES / "lugre.toml")]) == 0


def test_group1_unstable_design_system_is_refused(tmp_path, capsys):
    """A design system far from the true one: the gain destabilises the true error system."""
    text = PROP3.replace("eps = 0.5", "eps = 1.0\nA_design = [[0.0, 1.0], [-1.0, -0.5]]")
    text = text.replace("A = [[0.0, 1.0], [-1.0, -0.5]]", "A = [[0.0, 1.0], [60.0, 20.0]]")
    spec = loads_model(text)
    with pytest.raises(E.UnstableDesignError, match="unstable"):
        build_observer(spec)
    path = tmp_path / "m.toml"
    path.write_text(text, encoding="utf-8")
    assert main(["analyze", str(path)]) == 1
    assert "stable on the true system: False" in capsys.readouterr().out


# --- 2. code execution -----------------------------------------------------------------------

def test_group2_scb_symbolic_never_runs_strings(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    payload = "__import__('os').system('touch pwned') or 1"
    with pytest.raises(E.ModelFileError, match="not allowed"):
        scb_symbolic([[payload, "0"], ["0", "0"]], [[0], [1]], [[1, 0]])
    assert not (tmp_path / "pwned").exists()


def test_group2_string_entries_still_work():
    """The safe parser keeps the useful part: formulas in symbols, as in Sec. VIII."""
    res = scb_symbolic([["-(a2 + s1)/J", "-s0/J", "s1/J"], [1, 0, -1], [0, 0, 0]],
                       [[0], [0], [1]], [[1, 0, 0]])
    s0, s1 = sp.Symbol("s0"), sp.Symbol("s1")
    assert res.chain_lengths == (2,) and sp.simplify(res.A_a[0, 0] + s0 / s1) == 0


# --- 3. hangs --------------------------------------------------------------------------------

@pytest.mark.parametrize("g", ["9**9**9**9", "y**y**y**y**y", "(theta + y)**1000"])
def test_group3_hostile_g_fails_fast_in_a_model_file(tmp_path, capsys, g):
    text = PROP3.replace('g = "(2 + sin(y))*(theta + theta**3/3)"', f'g = "{g}"')
    path = tmp_path / "m.toml"
    path.write_text(text, encoding="utf-8")
    start = time.perf_counter()
    assert main(["analyze", str(path)]) == 2
    assert time.perf_counter() - start < FAST_SECONDS
    assert "[perturbation] g" in capsys.readouterr().err


def _sleep_forever() -> None:
    time.sleep(3600)


def test_group3_time_budget_kills_the_worker():
    start = time.perf_counter()
    with pytest.raises(E.SymbolicTimeoutError, match="time budget of 0.5 s") as info:
        limits.run_with_time_budget(_sleep_forever, seconds=0.5, what="a test")
    assert time.perf_counter() - start < FAST_SECONDS
    assert info.value.seconds == 0.5
    assert isinstance(info.value, TimeoutError)


def test_group3_solve_for_theta_star_runs_under_the_budget(monkeypatch):
    """g = (θ + y)**1000 through the API (no parser limit): SymPy's solve is stopped."""
    monkeypatch.setattr(limits, "SYMBOLIC_TIME_BUDGET", 1.0)
    y, x, th = sp.symbols("y x theta", real=True)
    g = SymbolicPerturbation.from_sympy((th + y) ** 1000, u=[], y=[y], x=[x], theta=[th])
    start = time.perf_counter()
    with pytest.raises(E.SymbolicTimeoutError, match="solve"):
        algebraic_from_perturbation(g, Gamma=1.0, parameter_set=Box([0.5], [2.0]))
    assert time.perf_counter() - start < FAST_SECONDS


def test_group3_budget_returns_results_and_reraises_errors():
    z = sp.Symbol("z")
    assert limits.run_with_time_budget(sp.solve, z**2 - 4, z, seconds=30.0) == [-2, 2]
    with pytest.raises(E.UnsupportedError, match="exact"):
        limits.run_with_time_budget(_raise_unsupported, seconds=30.0)


def _raise_unsupported() -> None:
    raise E.UnsupportedError("exact algebra is not available here")


# --- 4. silently wrong estimates -------------------------------------------------------------

EXP_MODEL = """
[system]
A = [[-1.0]]
B = [[1.0]]
C = [[1.0]]
E = [[1.0]]
[perturbation]
g = "exp(theta*y) - 1"
u = ["u"]
y = ["y"]
x = ["x"]
theta = ["theta"]
[parameter_set]
lower = [0.5]
upper = [2.0]
[estimator]
law = "algebraic"
"""


def test_group4_singular_theta_star_is_reported_before_estimation():
    """θ* = log(φ + 1)/y is singular at y = 0: data crossing 0 are refused, with the times."""
    spec = loads_model(EXP_MODEL)
    t = np.arange(0.0, 2.0, 0.01)
    y = np.sin(3.0 * t + 0.1)                   # crosses 0 near t = π/3 − 0.033 = 1.014
    calls = []
    with pytest.raises(E.UpdateLawError, match=r"singular on the data.*t = \[1\.01\]"):
        run_estimator(spec, t, np.zeros_like(t), y, progress=lambda d, n: calls.append(d))
    assert calls == []                          # refused before the run started
    res = run_estimator(spec, t, np.zeros_like(t), 1.0 + 0.5 * np.sin(t))   # y > 0: fine
    assert np.all(np.isfinite(res.theta_hat))


def test_group4_g_without_theta_is_refused(capsys, tmp_path):
    g = parse_perturbation("y**2 + 0*theta", u=[], y=["y"], x=["x"], theta=["theta"])
    with pytest.raises(E.UpdateLawError, match="does not depend on θ"):
        GradientInversion(g, 1.0, Box([0.0], [1.0]))
    path = tmp_path / "m.toml"
    path.write_text(PROP3.replace('g = "(2 + sin(y))*(theta + theta**3/3)"', 'g = "sin(y)"'),
                    encoding="utf-8")
    assert main(["analyze", str(path)]) == 2
    assert "does not depend on θ" in capsys.readouterr().err


def test_group4_complex_y_is_refused():
    obs = build_observer(loads_model(EXAMPLE_MODEL))
    t = np.arange(10) * 0.01
    with pytest.raises(E.DimensionError, match="y must be real"):
        obs.run(t, np.zeros(10), np.exp(1j * t))


# --- 5. raw tracebacks and untyped errors ----------------------------------------------------

def test_group5_deep_nesting_and_towers_are_typed():
    with pytest.raises(E.InputLimitError, match="nested deeper"):
        loads_model("x = " + "[" * 50_000 + "]" * 50_000)
    with pytest.raises(E.InputLimitError, match="nested deeper"):
        loads_model('{"a":' * 50_000 + "1" + "}" * 50_000, syntax="json")
    with pytest.raises(E.ThetahatError):
        parse_perturbation("y" + "**y" * 5000, u=[], y=["y"], x=["x"], theta=["theta"])


def test_group5_cli_sweep_huge_t_end(capsys):
    assert main(["sweep", "--t-end", "1e9"]) == 2
    err = capsys.readouterr().err
    assert "GB of memory" in err and "Traceback" not in err


def test_group5_tiny_eps_is_a_design_error():
    with pytest.raises(E.DesignError, match="too small"):
        modified_high_gain([[0.0, 1.0], [-1.0, -0.5]], [[0.0], [1.0]], [[1.0, 0.0]],
                           eps=1e-300)


def test_group5_cli_internal_error_has_no_traceback(monkeypatch, capsys, tmp_path):
    import thetahat.modelfile as mf

    def broken(path):
        raise ZeroDivisionError("boom")

    monkeypatch.setattr(mf, "load_model", broken)
    assert main(["analyze", str(tmp_path / "m.toml")]) == 3
    err = capsys.readouterr().err
    assert "internal error" in err and "--debug" in err and "Traceback" not in err


# --- 6. real-world files ---------------------------------------------------------------------

def test_group6_bom_crlf_and_dropouts(tmp_path, capsys):
    spec = loads_model(EXAMPLE_MODEL)
    rec = read_data(_csv(tmp_path, bom=True, crlf=True), spec.layout)
    assert rec.t.size == 200 and rec.columns == ("t", "u", "y")
    path = _csv(tmp_path, dropouts=True, bom=True, crlf=True)
    with pytest.raises(E.ModelFileError, match="--nan-policy skip"):
        read_data(path, spec.layout)
    rec = read_data(path, spec.layout, nan_policy="skip")
    assert np.flatnonzero(np.isnan(rec.y[:, 0])).tolist() == [5, 9]
    model = tmp_path / "m.toml"
    model.write_text(EXAMPLE_MODEL, encoding="utf-8")
    out = tmp_path / "est.csv"
    assert main(["estimate", str(model), str(path), "-o", str(out), "--nan-policy", "skip",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "skipped samples (dropouts): 2" in text and "final theta_hat: theta = " in text
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    assert table.shape[0] == 200 and np.all(np.isfinite(table))
    assert np.all(np.abs(table[:, 4]) <= 2.0)     # θ̂ ∈ Θ = [−2, 2] at every sample


def test_group6_output_path_checked_before_work(tmp_path, capsys):
    model = tmp_path / "m.toml"
    model.write_text(EXAMPLE_MODEL, encoding="utf-8")
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    # the data file does not exist: the output path must be refused first
    assert main(["estimate", str(model), str(tmp_path / "missing.csv"), "-o",
                 str(blocker / "out.csv")]) == 2
    err = capsys.readouterr().err
    assert "cannot write" in err and "missing.csv" not in err


# --- 7. ill-conditioned is not "not left-invertible" ------------------------------------------

def _controllable(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(s − 20)/s^k in controllable form."""
    A = np.diag(np.ones(k - 1), 1)
    B = np.zeros((k, 1))
    B[-1] = 1.0
    C = np.zeros((1, k))
    C[0, :2] = [-20.0, 1.0]
    return A, B, C


@pytest.mark.parametrize("k", [9, 15])
def test_group7_ill_conditioned_is_its_own_error(k):
    A, B, C = _controllable(k)
    assert is_left_invertible(A, B, C)
    np.testing.assert_allclose(invariant_zeros(A, B, C), [20.0], rtol=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", E.IllConditionedWarning)
        with pytest.raises(E.IllConditionedError, match="left-invertible .*but too ill-"
                                                        "conditioned") as info:
            scb(A, B, C)
    assert not isinstance(info.value, E.NotLeftInvertibleError)
    assert info.value.condition > 1.0 / info.value.tol       # why the rank test failed
    if info.value.suggested_tol is not None:                  # the suggestion works
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", E.IllConditionedWarning)
            res = scb(A, B, C, tol=info.value.suggested_tol)
        np.testing.assert_allclose(res.invariant_zeros.real, [20.0], rtol=1e-3)


def test_group7_k9_gets_a_working_tolerance():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", E.IllConditionedWarning)
        with pytest.raises(E.IllConditionedError, match=r"tol=1e-12\) succeeds"):
            scb(*_controllable(9))


def test_group7_redundant_outputs_named():
    A = [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]]
    C = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2.0, 1.0, 0.0]]     # row 2 = 2·row 0 + row 1
    with pytest.raises(E.DimensionError, match=r"C has rank 2 < 3 rows: outputs \[\d\] are "
                                               r"linear combinations"):
        scb(A, [[0.0], [0.0], [1.0]], C)


def test_group7_not_left_invertible_still_is():
    with pytest.raises(E.NotLeftInvertibleError, match="Normal rank of the Rosenbrock matrix 3 < n"):
        scb([[0.0, 1.0], [0.0, 0.0]], [[0.0, 0.0], [1.0, 1.0]], [[1.0, 0.0]])


# --- long input --------------------------------------------------------------------------------

def test_long_input_progress_lines_without_tqdm():
    out = io.StringIO()
    progress = reporter("estimate", stream=out, use_tqdm=False)
    obs = build_observer(loads_model(EXAMPLE_MODEL))
    N = 2_500
    t = np.arange(N) * 1e-3
    calls = []

    def both(done, total):
        calls.append((done, total))
        progress(done, total)

    obs.with_run_options(progress=both).run(t, np.sin(t), 0.1 * np.cos(t))
    assert calls[0] == (0, N - 1) and calls[-1] == (N - 1, N - 1)
    assert len(calls) >= N // 1_000                              # PROGRESS_EVERY = 1000
    assert out.getvalue().splitlines()[-1].startswith(f"thetahat: estimate: {N - 1}/{N - 1}")


def test_long_input_memory_is_linear_in_the_output():
    """Peak memory of a run is a small multiple of its output (no per-sample Python objects)."""
    obs = build_observer(loads_model(EXAMPLE_MODEL))
    N = 2_000
    t = np.arange(N) * 1e-3
    tracemalloc.start()
    try:
        res = obs.run(t, np.sin(t), 0.1 * np.cos(t))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    out = sum(a.nbytes for a in (res.t, res.x_hat, res.phi_hat, res.theta_hat,
                                 res.x_hat_refined))
    # the state history, the outputs and one evaluation of g over the record: a handful of
    # copies of the output; 8x leaves margin, a per-sample Python list would be ~30x
    assert peak < 8 * out + 2_000_000, (peak, out)


@pytest.mark.slow
def test_long_input_csv_of_a_million_rows(tmp_path):
    """A 10⁶-row CSV reads in O(N) memory (float64 columns, no list of rows)."""
    N = 1_000_000
    t = np.arange(N) * 1e-3
    path = tmp_path / "big.csv"
    np.savetxt(path, np.column_stack([t, np.sin(t), np.cos(t)]), delimiter=",",
               header="t,u,y", comments="", fmt="%.10g")
    spec = loads_model(EXAMPLE_MODEL)
    tracemalloc.start()
    try:
        rec = read_data(path, spec.layout)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert rec.t.size == N
    assert peak < 6 * 3 * 8 * N, peak            # a few copies of the 24 MB of columns


@pytest.mark.needs_speed
def test_cli_estimate_prints_a_summary(tmp_path, capsys):
    model = tmp_path / "m.toml"
    model.write_text(EXAMPLE_MODEL, encoding="utf-8")
    out = tmp_path / "est.csv"
    assert main(["estimate", str(model), str(_csv(tmp_path, N=1_500)), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "final theta_hat: theta = " in captured.out
    assert ("settled (within 1 % of the final value) at t = " in captured.out
            or "NOT settled: θ̂ stays within 1 % of its final value only from t = "
            in captured.out)                              # either verdict, with its time
    assert "warnings: " in captured.out
    assert "estimate" in captured.err                        # progress went to stderr
    assert os.path.getsize(out) > 0
