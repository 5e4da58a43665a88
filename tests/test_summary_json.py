"""``thetahat estimate --summary RUN.json``: the printed summary as data.

The JSON a script reads must say what the run said: θ̂ equal to the last row of the estimates
file the same run wrote (an independent path: the CSV writer), the Cramér–Rao sd of the trust
report, the ε and Γ the observer ran with — those ``thetahat codegen --eps/--gamma`` takes, the
same as :func:`thetahat.modelfile.resolve_gains` resolves on the record — and the settling
verdict of the printed summary. Run on LuGre and three more shipped models (short parts of
their scenarios), for the paper's observer and the default (guarded) method.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.methods import get_method
from thetahat.modelfile import load_model, resolve_gains, simulate_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
#: Short parts of each scenario (s): enough samples for the trust report, within seconds.
T_END = {"lugre": 2.0, "prop3": 10.0, "heater": None, "spring_friction": 5.0}


def _record(tmp_path: Path, name: str) -> tuple[Path, Path]:
    model = EXAMPLES / f"{name}.toml"
    spec = load_model(model)
    t_end = T_END[name] or spec.scenario.t_end / 10
    d = simulate_model(spec, 1, t_end=t_end)
    lay = spec.layout
    header = ",".join(("t",) + tuple(lay.input_names) + tuple(lay.output_names))
    u = np.asarray(d.u, dtype=float).reshape(d.t.size, -1)
    y = np.asarray(d.y, dtype=float).reshape(d.t.size, -1)
    path = tmp_path / f"{name}.csv"
    np.savetxt(path, np.column_stack([d.t, u, y]), delimiter=",", header=header, comments="",
               fmt="%.17g")
    return model, path


@pytest.mark.parametrize("method", ["paper", None])
@pytest.mark.parametrize("name", sorted(T_END))
@pytest.mark.needs_speed
def test_the_summary_says_what_the_run_wrote(tmp_path, name, method, capsys):
    model, data = _record(tmp_path, name)
    out, summary = tmp_path / "est.csv", tmp_path / "run.json"
    argv = ["estimate", str(model), str(data), "-o", str(out), "--summary", str(summary), "-q"]
    assert main(argv + ([] if method is None else ["--method", method])) == 0
    printed = capsys.readouterr().out
    rec = json.loads(summary.read_text(encoding="utf-8"))
    spec = load_model(model)
    assert rec["method"] == (method or spec.estimator.method)
    table = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
    header = out.read_text(encoding="utf-8").splitlines()[0].split(",")
    cols = [header.index(f"theta_hat_{n}") for n in spec.parameter_names]
    assert list(rec["theta_hat"]) == list(spec.parameter_names)
    # θ̂ in the JSON is the estimates file's last row, to the CSV's round trip (17 digits)
    np.testing.assert_allclose(list(rec["theta_hat"].values()), table[-1, cols], rtol=1e-15,
                               atol=0)
    sd = np.array([float(v) for v in rec["crlb_sd"].values()])
    assert np.all(sd > 0)
    assert rec["samples"] == table.shape[0] and rec["status"] == "OK"
    assert rec["settled"] == ("NOT settled" not in printed)
    assert rec["warnings"] == [] or "warnings: none" not in printed
    if get_method(rec["method"]).runs_observer:     # paper, guarded's stage 1: the gains
        # codegen takes are those the run resolved
        d = np.loadtxt(data, delimiter=",", skiprows=1, ndmin=2)
        m = len(spec.layout.input_names)
        gains = resolve_gains(spec, d[:, 0], d[:, 1:1 + m], d[:, 1 + m:])
        assert rec["eps"] == pytest.approx(gains.eps, rel=1e-15)
        np.testing.assert_allclose(np.asarray(rec["Gamma"]), np.asarray(gains.Gamma),
                                   rtol=1e-12)
    else:
        assert "eps" not in rec                     # no observer: no observer gains


@pytest.mark.parametrize("bad, why", [
    (lambda d: ["--summary", str(d / "est.json"), "-o", str(d / "est.json")], "suffix"),
    (lambda d: ["--summary", str(d / "run.txt")], ".json"),
])
def test_a_summary_over_another_output_is_refused_before_work(tmp_path, bad, why, capsys):
    model, data = _record(tmp_path, "prop3")
    argv = ["estimate", str(model), str(data), "-o", str(tmp_path / "est.csv"), "-q"]
    assert main(argv + bad(tmp_path)) == 2
    err = capsys.readouterr().err
    assert why in err and "Traceback" not in err
    assert not (tmp_path / "est.csv").exists()                        # before any work


def test_a_fleet_has_no_summary(tmp_path, capsys):
    _record(tmp_path, "prop3")
    assert main(["estimate", str(EXAMPLES / "prop3.toml"), str(tmp_path), "--summary",
                 str(tmp_path / "run.json"), "-q"]) == 2
    assert "one row per record" in capsys.readouterr().err
