"""``window`` through the front doors (issues 32, 33): ``run_estimator``, ``build_estimator``,
``estimate_many`` and ``thetahat estimate --window`` give the bounded fits to the fitting
methods (guarded, mle), and a bad value is refused with one line before any work. (The
windowed fits' efficiency and bounded cost: tests/estimation/test_window.py.)"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import OptionError
from thetahat.fleet import estimate_many
from thetahat.modelfile import build_estimator, load_model, run_estimator
from thetahat.studies.free_run import simulate_output

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


@pytest.mark.parametrize("name", ["prop1", "heater", "actuator", "spring_friction"])
def test_the_window_reaches_the_fitting_methods(name):
    spec = load_model(EXAMPLES / f"{name}.toml")
    gamma = np.eye(spec.system.p) if spec.estimator.gamma_auto else None
    for method in ("guarded", "mle"):
        assert build_estimator(spec, method=method, window="auto", Gamma=gamma).window == "auto"
        assert build_estimator(spec, method=method, Gamma=gamma).window is None
    assert not hasattr(build_estimator(spec, method="ekf", window="auto"), "window")


def _record(name: str, N: int):
    spec = load_model(EXAMPLES / f"{name}.toml")
    sc = spec.scenario
    t = np.arange(N) / sc.fs
    amps, freqs = np.atleast_2d(sc.u_amplitudes), np.atleast_2d(sc.u_frequencies)
    u = np.column_stack([sum(a * np.sin(2 * np.pi * f * t) for a, f in zip(amps[i], freqs[i]))
                         for i in range(spec.system.m)])
    y = simulate_output(spec.system, np.asarray(sc.theta, dtype=float), t, u,
                        x0=np.zeros(spec.system.n), hold="foh")
    y = y + 0.01 * np.std(y, axis=0) * np.random.default_rng(2).standard_normal(y.shape)
    return spec, t, u, y


def test_run_estimator_with_a_window_is_the_windowed_estimator():
    """The run's θ̂ path is the one of ``MapEstimator(window=W)`` built by hand, and differs
    from the fits of all the data (the window was used, not dropped)."""
    spec, t, u, y = _record("prop1", 3000)
    res = run_estimator(spec, t, u, y, method="mle", window=300)
    est = build_estimator(spec, method="mle", window=300)
    own = est.run(t, u, y, state0=est.init(x_hat0=res.x_hat[0],
                                            theta_hat0=spec.estimator.theta_hat0))
    assert np.array_equal(own.theta_hat, res.theta_hat)
    full = run_estimator(spec, t, u, y, method="mle")
    assert not np.array_equal(full.theta_hat, res.theta_hat)
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    assert np.all((res.theta_hat >= lo) & (res.theta_hat <= hi))


def test_a_bad_window_is_refused_in_one_line(tmp_path):
    spec, t, u, y = _record("prop1", 200)
    data = tmp_path / "rec.csv"
    np.savetxt(data, np.column_stack([t, u, y]), delimiter=",", comments="",
               header=",".join(["t", *spec.signal_names.inputs, *spec.signal_names.outputs]))
    for bad in ("x12", "1e3", "-5"):
        out = subprocess.run([sys.executable, "-m", "thetahat", "estimate",
                              str(EXAMPLES / "prop1.toml"), str(data), "--method", "mle",
                              "--window", bad, "-o", str(tmp_path / "e.csv"), "--quiet"],
                             capture_output=True, text=True, timeout=300,
                             env={"PYTHONPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin"})
        assert out.returncode == 2, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "--window" in lines[0] and "Traceback" not in out.stderr
        assert not (tmp_path / "e.csv").exists()
    with pytest.raises(OptionError):
        estimate_many(EXAMPLES / "prop1.toml", [data], method="mle", window="wide")
