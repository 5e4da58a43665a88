"""The ``thetahat`` command: wiring to the public API, exit codes and error messages."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.io.datafile import estimate_columns
from thetahat.modelfile import build_observer, load_model, run_estimator, start_x_hat
from thetahat.models import lugre

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
LUGRE = EXAMPLES / "lugre.toml"

#: The compiled back ends against NumPy on 1 s of LuGre: 8.7e-13 relative, 1.3e-15 absolute
#: (measured); the bounds leave three orders of magnitude.
BACKEND_RTOL = 1e-9
BACKEND_ATOL = 1e-12


def test_python_dash_m_help():
    proc = subprocess.run([sys.executable, "-m", "thetahat", "--help"], capture_output=True,
                          text=True, timeout=120, check=False)
    assert proc.returncode == 0
    for command in ("demo", "sweep", "analyze", "estimate"):
        assert command in proc.stdout


def test_analyze_prints_the_lugre_zero_and_gain(capsys):
    assert main(["analyze", str(LUGRE)]) == 0
    out = capsys.readouterr().out
    assert "Assumption 1 (Grip, Saberi & Johansen): holds" in out
    assert "-433.333" in out                                   # −σ0/σ1, Sec. VIII-A
    assert "K(eps = 1) = [K_x; K_phi] = [6, -0.00415885, 6.0075]" in out
    assert "second observer: K(eps2 = 1) = [3, -0.00204846]" in out
    assert "stable on the true system: True" in out


@pytest.fixture(scope="module")
def lugre_csv(tmp_path_factory) -> tuple[Path, lugre.PlantTrajectory]:
    data = lugre.simulate(seed=2, t_end=1.0)
    path = tmp_path_factory.mktemp("data") / "motor.csv"
    table = np.column_stack([data.t, data.u, data.y])
    np.savetxt(path, table, delimiter=",", header="t,u,y", comments="", fmt="%.17g")
    return path, data


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_estimate_round_trips_with_the_api(tmp_path, lugre_csv, hold, capsys):
    csv_path, data = lugre_csv
    out = tmp_path / "est.csv"
    assert main(["estimate", str(LUGRE), str(csv_path), "-o", str(out), "--hold", hold,
                 "--method", "paper"]) == 0
    assert f"wrote {out} ({data.t.size} rows)" in capsys.readouterr().out
    header = out.read_text().splitlines()[0].split(",")
    spec = load_model(LUGRE)
    assert tuple(header) == estimate_columns(spec.layout, refined=True)
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    # the same arrays through the API (the CSV holds 17 significant digits: exact floats)
    t, u, y = (np.loadtxt(csv_path, delimiter=",", skiprows=1)[:, i] for i in range(3))
    np.testing.assert_array_equal(t, data.t)
    api = run_estimator(spec, t, u, y, hold=hold, diagnose=False,    # what the command runs
                        method="paper")
    np.testing.assert_array_equal(table, _columns(api))
    # and the plain NumPy observer: the command may run a compiled back end, which evaluates
    # the same formulas in another order of floating-point operations (8.7e-13 relative,
    # measured), hence a tolerance instead of equality
    obs = build_observer(spec).with_run_options(hold=hold)
    res = obs.run(t, u, y, state0=obs.init(x_hat0=start_x_hat(spec, y),
                                           theta_hat0=spec.estimator.theta_hat0))
    np.testing.assert_allclose(table, _columns(res), rtol=BACKEND_RTOL, atol=BACKEND_ATOL)


def _columns(res) -> np.ndarray:
    return np.column_stack([res.t, res.x_hat, res.phi_hat, res.theta_hat, res.x_hat_refined])


def _error(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_bad_model_file_exits_2_with_the_message(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(LUGRE.read_text().replace('law = "intermittent"', 'law = "kalman"'))
    assert main(["analyze", str(bad)]) == 2
    err = _error(capsys)
    assert err.startswith("thetahat: error: model file")
    assert "[estimator] law: unknown law 'kalman'" in err


def test_code_in_the_perturbation_is_refused(tmp_path, capsys):
    bad = tmp_path / "evil.toml"
    text = LUGRE.read_text()
    start = text.index('g = "')
    end = text.index("\n", start)
    bad.write_text(text[:start] + 'g = "__import__(\'os\').system(\'true\')"' + text[end:])
    assert main(["estimate", str(bad), "whatever.csv"]) == 2
    err = _error(capsys)
    assert "[perturbation] g" in err and "__import__" in err and "not allowed" in err


def test_bad_data_file_exits_2_with_the_line(tmp_path, capsys):
    data = tmp_path / "data.csv"
    data.write_text("t,u,y\n0,0,0\n0.001,0,oops\n")
    assert main(["estimate", str(LUGRE), str(data), "-o", str(tmp_path / "e.csv")]) == 2
    err = _error(capsys)
    assert "line 3, column 'y': 'oops' is not a number" in err
    assert not (tmp_path / "e.csv").exists()


def test_missing_data_column_exits_2(tmp_path, capsys):
    data = tmp_path / "data.csv"
    data.write_text("t,y\n0,0\n")
    assert main(["estimate", str(LUGRE), str(data)]) == 2
    assert "missing column 'u' or 'u1'" in _error(capsys)


def test_usage_errors_exit_2(capsys):
    assert main(["estimate", str(LUGRE)]) == 2                 # DATA missing
    assert "DATA is missing (MODEL DATA): after the model file" in capsys.readouterr().err
    assert main(["sweep", "--eps", "0.5", "0.3"]) == 2         # Sec. VII: start at 1
    assert "start at 1 and decrease" in _error(capsys)


def test_sweep_writes_table_json_and_figure(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["sweep", "--eps", "1", "0.5", "--seeds", "1", "--t-end", "1",
                 "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "omega RMSE" in captured.out and "1/1" in captured.out
    summary = json.loads((out / "sweep.json").read_text())
    assert summary["eps"] == [1.0, 0.5] and summary["first_unstable"] is None
    if importlib.util.find_spec("matplotlib") is None:        # the plot extra is optional
        assert "sweep.png not written" in captured.err
        assert not (out / "sweep.png").exists()
    else:
        assert (out / "sweep.png").stat().st_size > 0


def test_demo_calls_the_lugre_report(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr("thetahat.models.lugre_report.report",
                        lambda **kw: calls.append(kw) or {})
    assert main(["demo", "lugre", "--out", "somewhere", "--eps", "0.5", "--seed", "3"]) == 0
    assert calls == [{"out": "somewhere", "eps": 0.5, "seed": 3, "show": False}]


def test_estimate_method_guarded_writes_the_guarded_theta(tmp_path, lugre_csv, capsys,
                                                          monkeypatch):
    # numpy kernels (no numba compilation in the default suite); same numbers as compiled
    import thetahat.estimation.statistical.plant_kernel as mk
    monkeypatch.setattr(mk, "have_numba", lambda: False)
    csv_path, data = lugre_csv
    out = tmp_path / "est.csv"
    assert main(["estimate", str(LUGRE), str(csv_path), "-o", str(out),
                 "--method", "guarded"]) == 0
    spec = load_model(LUGRE)
    header = out.read_text().splitlines()[0].split(",")
    assert tuple(header) == estimate_columns(spec.layout, refined=False)
    theta = np.loadtxt(out, delimiter=",", skiprows=1)[:, header.index("theta_hat_theta")]
    assert np.all((theta >= 0.05) & (theta <= 1.0))
    assert abs(theta[-1] - 0.28) < 0.01 * 0.28          # the paper's stage 1 alone: ~0.45
    assert main(["estimate", str(LUGRE), str(csv_path), "--method", "ukf"]) == 2
    assert "invalid choice: 'ukf'" in capsys.readouterr().err


# --- progress, --quiet, and what an estimate imports -----------------------------------------

@pytest.mark.parametrize("flags,lines", [([], 1), (["--no-progress"], 1), (["--quiet"], 0),
                                         (["-q"], 0)])
def test_estimate_off_a_terminal_writes_the_final_line_or_nothing(tmp_path, lugre_csv, capsys,
                                                                  flags, lines):
    csv_path, data = lugre_csv
    out = tmp_path / "est.csv"
    assert main(["estimate", str(LUGRE), str(csv_path), "-o", str(out), *flags]) == 0
    captured = capsys.readouterr()
    err = [line for line in captured.err.splitlines() if line]
    assert len(err) == lines and "\r" not in captured.err
    if lines:
        assert err[0].startswith("thetahat: done in ")
        for name in ("load model", "read", "estimate", "trust report", "write"):
            assert f" {name} " in err[0]
    assert f"wrote {out} ({data.t.size} rows)" in captured.out


def test_the_parser_loads_no_numerical_library_and_an_estimate_no_signal_processing(
        tmp_path, lugre_csv):
    """The command's first line is drawn once the parser is built, so building it loads
    neither SymPy nor SciPy; a whole estimate never loads scipy.signal or scipy.stats (1.4 s
    of imports on a loaded machine, for coloured noise the estimate never draws)."""
    csv_path, _ = lugre_csv
    code = f"""if True:
        import json, sys
        import thetahat.cli as cli
        cli._parser()
        before = sorted(m for m in ("sympy", "scipy") if m in sys.modules)
        code = cli.main(["estimate", {str(LUGRE)!r}, {str(csv_path)!r}, "-o",
                         {str(tmp_path / "est.csv")!r}, "--quiet"])
        after = sorted({{m.split(".")[1] for m in sys.modules
                        if m.startswith(("scipy.signal", "scipy.stats"))}})
        print(json.dumps([code, before, after, "sympy" in sys.modules]))
    """
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, check=True)
    code_, before, after, sympy_loaded = json.loads(proc.stdout.strip().splitlines()[-1])
    assert code_ == 0 and sympy_loaded              # the estimate ran (and parsed its model)
    assert before == [] and after == []


EMPS_MAT = EXAMPLES / "data" / "emps" / "DATA_EMPS.mat"


@pytest.mark.parametrize("argv, says", [
    # the model file forgotten: a lone record is named as the record, the model asked first
    ([str(EMPS_MAT)], "give the model file first (MODEL DATA): " + str(EMPS_MAT)),
    ([str(EXAMPLES / "data" / "emps")], "give the model file first"),      # a fleet's folder
    ([str(EMPS_MAT), str(EXAMPLES / "emps.toml")],
     f"the model file comes first (MODEL DATA): thetahat estimate {EXAMPLES / 'emps.toml'} "
     f"{EMPS_MAT}"),
    ([], "give the model file (.toml or .json), then the record"),
])
def test_estimate_says_which_argument_is_which(argv, says, capsys):
    """What argparse alone said for each ("the following arguments are required: data") did
    not say that the one file given was the record; exit 2 with the usage line."""
    assert main(["estimate", *argv]) == 2
    err = capsys.readouterr().err
    assert says in err and "usage: thetahat estimate MODEL DATA" in err
    assert "required" not in err


def _closed_early(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """Run ``thetahat ARGV`` with its stdout a pipe whose reader is gone before the first write
    (what ``| head`` does once it has its lines; closing first makes it certain)."""
    proc = subprocess.Popen([sys.executable, "-m", "thetahat", *argv], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    _, err = proc.communicate(timeout=600)
    return subprocess.CompletedProcess(proc.args, proc.returncode, None, err.decode())


def test_a_closed_pipe_exits_quietly_with_141(tmp_path, lugre_csv):
    """``thetahat … | head``: no message, no traceback, and the shell's status for coreutils
    killed by SIGPIPE (128 + 13; `seq 1 1000000 | head -1` gives 141 in PIPESTATUS), not 2,
    the bad-input code. The estimates were written before the summary's print met the pipe."""
    from thetahat.cli import EXIT_PIPE
    assert EXIT_PIPE == 128 + 13
    done = _closed_early(["analyze", str(LUGRE)], tmp_path)
    assert (done.returncode, done.stderr) == (EXIT_PIPE, "")
    csv_path, data = lugre_csv
    done = _closed_early(["estimate", str(LUGRE), str(csv_path), "-o", "est.csv",
                          "--quiet"], tmp_path)
    assert (done.returncode, done.stderr) == (EXIT_PIPE, "")
    assert len((tmp_path / "est.csv").read_text().splitlines()) == data.t.size + 1


def test_a_broken_pipe_that_is_not_the_output_is_an_error(monkeypatch, capsys):
    """EPIPE from another pipe (a worker's) is not the reader going away: exit 2 with it."""
    def broken(args):
        raise BrokenPipeError(32, "Broken pipe")
    monkeypatch.setattr("thetahat.cli._analyze", broken)
    assert main(["analyze", str(LUGRE)]) == 2
    assert "Broken pipe" in _error(capsys)
