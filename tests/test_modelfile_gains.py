"""The ε and Γ a model file's observer runs with (thetahat.modelfile.resolve_gains): ``Gamma =
"auto"`` is chosen on a record in one place, ``thetahat estimate`` prints it, and ``thetahat
codegen`` takes it (``--gamma``) or chooses it on the same log (``--data``).

Models with Gamma = "auto": the shipped EMPS file (the least-squares law's default), and
copies of prop3, prop4 and the heater with their Γ replaced by "auto" (gradient laws).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.codegen.loader import find_compiler
from thetahat.errors import ModelFileError, ThetahatError, ThetahatWarning, UpdateLawError
from thetahat.io.datafile import read_data
from thetahat.modelfile import (auto_gamma, build_observer, generate_c_from_model, load_model,
                                resolve_gains, run_estimator, start_x_hat)
from thetahat.modelfile.study import simulate_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
EMPS = EXAMPLES / "emps.toml"
#: The gradient-law files made "auto", and how long a record of each is simulated (s): a few
#: hundred samples, enough for the information gain to see every parameter move.
AUTO_COPIES = {"prop3": 3.0, "prop4": 3.0, "heater": 60.0}
#: The estimate's back end against the plain NumPy observer: they evaluate the same formulas
#: in another order of floating-point operations (8.7e-13 relative measured on LuGre, see
#: tests/test_cli.py); three orders of magnitude of margin.
BACKEND_RTOL = 1e-9
#: A printed gain has 6 significant digits: |printed − Γ| ≤ 5e-6 |Γ| (half a unit of the
#: sixth digit of a value whose first is 1), bound with a margin of 2.
PRINTED_RTOL = 1e-5
#: EMPS: the first 3 s of the measured record (3000 samples) keep the Python least-squares
#: law's run to about a second.
EMPS_SAMPLES = 3000


def auto_copy(name: str, folder: Path) -> Path:
    """examples/NAME.toml with its [estimator] Gamma replaced by "auto"."""
    text = (EXAMPLES / f"{name}.toml").read_text(encoding="utf-8")
    new, count = re.subn(r"(?m)^Gamma = .*$", 'Gamma = "auto"', text)
    assert count == 1, name
    path = folder / f"{name}.toml"
    path.write_text(new, encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def auto_models(tmp_path_factory) -> dict[str, tuple[Path, tuple[np.ndarray, ...]]]:
    """Each model with Gamma = "auto" and a record for it: its path and (t, u, y)."""
    folder = tmp_path_factory.mktemp("auto")
    out = {}
    for name, t_end in AUTO_COPIES.items():
        path = auto_copy(name, folder)
        rec = simulate_model(load_model(path), seed=0, t_end=t_end)
        out[name] = path, (rec.t, rec.u, rec.y)
    spec = load_model(EMPS)
    rec = read_data(EXAMPLES / "data" / "emps" / "DATA_EMPS.mat", spec.layout)
    out["emps"] = EMPS, (rec.t[:EMPS_SAMPLES], rec.u[:EMPS_SAMPLES], rec.y[:EMPS_SAMPLES])
    return out


@pytest.mark.parametrize("name", [*AUTO_COPIES, "emps"])
def test_auto_is_chosen_once_and_is_what_the_estimate_runs(auto_models, name):
    """resolve_gains chooses "auto" as auto_gamma does; the estimate runs with that Γ: the
    observer built with it (what codegen prints as C) gives the estimate's θ̂."""
    path, (t, u, y) = auto_models[name]
    spec = load_model(path)
    assert spec.estimator.gamma_auto
    gains = resolve_gains(spec, t, u, y)
    assert gains.source == "auto" and gains.eps == spec.estimator.eps
    np.testing.assert_array_equal(gains.Gamma, auto_gamma(spec, t, u, y))
    assert np.all(np.diag(gains.Gamma) > 0) and not gains.Gamma.flags.writeable
    res = run_estimator(spec, t, u, y, method="paper", diagnose=False)
    obs = build_observer(spec, Gamma=gains.Gamma)
    ref = obs.run(t, u, y, state0=obs.init(x_hat0=start_x_hat(spec, y),
                                           theta_hat0=spec.estimator.theta_hat0))
    np.testing.assert_allclose(res.theta_hat, ref.theta_hat, rtol=BACKEND_RTOL)
    # and with that Γ given, run_estimator does not choose again: the same run
    again = run_estimator(spec, t, u, y, method="paper", diagnose=False, Gamma=gains.Gamma)
    np.testing.assert_array_equal(again.theta_hat, res.theta_hat)


@pytest.mark.parametrize("name", [*AUTO_COPIES, "emps"])
def test_without_a_record_auto_is_refused_with_the_ways_to_give_it(auto_models, name):
    path, _ = auto_models[name]
    spec = load_model(path)
    for call in (lambda: resolve_gains(spec), lambda: build_observer(spec),
                 lambda: generate_c_from_model(path, dt=0.01)):
        with pytest.raises(ModelFileError, match=r"Gamma = 'auto'.*codegen --data LOG.*"
                                                 r"thetahat estimate printed.*--gamma"):
            call()


def test_a_given_gamma_is_a_number_a_diagonal_or_a_matrix():
    spec = load_model(EXAMPLES / "prop4.toml")                     # p = 2, Gamma = 4.0
    file = resolve_gains(spec)
    assert file.source == "file" and file.eps == 0.5
    np.testing.assert_array_equal(file.Gamma, 4.0 * np.eye(2))
    for given, want in ((3.0, 3.0 * np.eye(2)), ([3.0], 3.0 * np.eye(2)),
                        ([1.0, 5.0], np.diag([1.0, 5.0])),
                        ([[2.0, 0.5], [0.5, 1.0]], [[2.0, 0.5], [0.5, 1.0]])):
        gains = resolve_gains(spec, Gamma=given, eps=0.2)
        assert (gains.source, gains.eps) == ("given", 0.2)
        np.testing.assert_array_equal(gains.Gamma, want)
    with pytest.raises(UpdateLawError, match="positive definite"):
        resolve_gains(spec, Gamma=[1.0, -1.0])
    with pytest.raises(UpdateLawError, match=r"\(2, 2\) matrix for p = 2"):
        resolve_gains(spec, Gamma=[1.0, 2.0, 3.0])


def _csv(path: Path, t, u, y) -> Path:
    header = "t," + ",".join(f"u{i + 1}" for i in range(u.shape[1])) + "," + ",".join(
        f"y{i + 1}" for i in range(y.shape[1]))
    np.savetxt(path, np.column_stack([t, u, y]), delimiter=",", header=header, comments="",
               fmt="%.17g")
    return path


def _printed_gamma(out: str) -> np.ndarray:
    """Γ's diagonal from the line `thetahat estimate` prints."""
    line = next(x for x in out.splitlines() if x.startswith("observer gains:"))
    text = re.search(r"Gamma = (diag\(([^)]*)\)|[^ ]+) ", line)
    assert text is not None, line
    return np.array([float(v) for v in (text.group(2) or text.group(1)).split(",")])


@pytest.mark.parametrize("name", list(AUTO_COPIES))
def test_estimate_prints_the_gains_and_codegen_takes_them(auto_models, name, tmp_path, capsys):
    """The issue: codegen refused "auto" ('give Gamma'), estimate never printed the Γ it chose.
    Now estimate prints ε and Γ; codegen --data LOG generates the observer with exactly that Γ,
    and codegen --gamma with the printed one."""
    path, (t, u, y) = auto_models[name]
    spec = load_model(path)
    log = _csv(tmp_path / "log.csv", t, u, y)
    gains = resolve_gains(spec, t, u, y)
    assert main(["estimate", str(path), str(log), "-o", str(tmp_path / "est.csv"),
                 "--no-progress", "--method", "paper"]) == 0
    out = capsys.readouterr().out
    assert f"observer gains: eps = {spec.estimator.eps:g}, Gamma = " in out
    assert '("auto", chosen on this record; for C: thetahat codegen MODEL --eps' in out
    printed = _printed_gamma(out)
    np.testing.assert_allclose(printed, np.diag(gains.Gamma), rtol=PRINTED_RTOL)

    assert main(["codegen", str(path), "--dt", "0.01", "-o", str(tmp_path / "c0")]) == 2
    assert "codegen --data LOG" in capsys.readouterr().err
    assert main(["codegen", str(path), "--dt", "0.01", "-o", str(tmp_path / "c1"),
                 "--data", str(log)]) == 0
    assert "observer gains:" in capsys.readouterr().out
    exact = generate_c_from_model(path, dt=0.01, Gamma=gains.Gamma)
    assert (tmp_path / "c1" / f"{name}.c").read_text() == exact.source
    assert main(["codegen", str(path), "--dt", "0.01", "-o", str(tmp_path / "c2"),
                 "--gamma", *(f"{g:.6g}" for g in printed)]) == 0
    typed = generate_c_from_model(path, dt=0.01, Gamma=np.diag(printed))
    assert (tmp_path / "c2" / f"{name}.c").read_text() == typed.source
    assert main(["codegen", str(path), "--dt", "0.01", "-o", str(tmp_path / "c3"),
                 "--data", str(log), "--gamma", "1"]) == 2
    assert "give one of them" in capsys.readouterr().err


def test_mle_runs_no_observer_and_prints_no_gains(auto_models, tmp_path, capsys):
    path, (t, u, y) = auto_models["prop3"]
    log = _csv(tmp_path / "log.csv", t, u, y)
    assert main(["estimate", str(path), str(log), "-o", str(tmp_path / "est.csv"),
                 "--no-progress", "--method", "mle"]) == 0
    assert "observer gains" not in capsys.readouterr().out


@pytest.mark.skipif(find_compiler() is None or shutil.which("make") is None,
                    reason="no C compiler (cc or $CC) or no make")
def test_the_c_from_the_log_reproduces_the_estimate(auto_models, tmp_path, capsys):
    """`thetahat estimate MODEL LOG` and the harness of `thetahat codegen MODEL --data LOG`,
    on the same log: the same estimates to rounding (the bound of
    tests/codegen/test_codegen.py, DOUBLE_RTOL = 1e-9 of each column's largest value)."""
    path, (t, u, y) = auto_models["prop4"]
    log = _csv(tmp_path / "log.csv", t, u, y)
    assert main(["estimate", str(path), str(log), "-o", str(tmp_path / "est.csv"),
                 "--no-progress", "--method", "paper"]) == 0
    out = tmp_path / "c"
    assert main(["codegen", str(path), "--dt", repr(float(t[1] - t[0])), "-o", str(out),
                 "--data", str(log)]) == 0
    capsys.readouterr()
    make = subprocess.run(["make", "-s", "-C", str(out)], capture_output=True, text=True,
                          timeout=300)
    assert make.returncode == 0, make.stderr
    done = subprocess.run([str(out / path.stem), str(log)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    c = np.loadtxt(done.stdout.splitlines()[1:], delimiter=",", ndmin=2)
    py = np.loadtxt(tmp_path / "est.csv", delimiter=",", skiprows=1, ndmin=2)
    assert c.shape == py.shape
    scale = np.maximum(np.max(np.abs(py), axis=0), np.finfo(float).tiny)
    assert np.max(np.abs(c - py) / scale) <= BACKEND_RTOL


#: Missing outputs in the test below: 1 % of the samples, in short gaps (a logger's dropouts).
MISSING_FRACTION = 0.01


@pytest.mark.parametrize("name", sorted(AUTO_COPIES) + ["emps"])
def test_auto_gamma_with_missing_samples(tmp_path, name):
    """``nan_policy="skip"`` with ``Gamma = "auto"``: the first pass predicts over the gaps and
    Γ is the record's information without them. Γ is κ/T over the mean of |∂g/∂θ|² along the
    record; dropping 1 % of the rows moves a mean of positive terms by about that fraction,
    and the first pass's x̂ re-converges within a few samples of each gap: Γ within 10 × the
    missing fraction of the complete record's (a margin of 10 for the x̂ transients)."""
    if name == "emps":
        spec = load_model(EMPS)
        rec = read_data(EMPS.parent / "data" / "emps" / "DATA_EMPS.mat", spec.layout)
        t, u, y = rec.t[:EMPS_SAMPLES], rec.u[:EMPS_SAMPLES], rec.y[:EMPS_SAMPLES].copy()
    else:
        spec = load_model(auto_copy(name, tmp_path))
        d = simulate_model(spec, 0, t_end=AUTO_COPIES[name])
        t, u, y = d.t, d.u, np.array(d.y, dtype=float, copy=True)
    full = resolve_gains(spec, t, u, y).Gamma
    y = y.reshape(t.size, -1)
    rng = np.random.default_rng(7)
    starts = rng.choice(np.arange(20, t.size - 20), size=max(1, int(MISSING_FRACTION * t.size
                                                                    / 3)), replace=False)
    for k in starts:
        y[k:k + 3] = np.nan
    with pytest.raises(ThetahatError):           # refused unless the user says skip
        resolve_gains(spec, t, u, y)
    gappy = resolve_gains(spec, t, u, y, nan_policy="skip").Gamma
    assert np.all(np.isfinite(gappy))
    np.testing.assert_allclose(np.diag(gappy), np.diag(full), rtol=10 * MISSING_FRACTION)
    res = run_estimator(spec, t, u, y, nan_policy="skip", method="paper", diagnose=False)
    assert int(res.skipped.sum()) == int(np.isnan(y).any(axis=1).sum())
    assert np.all(np.isfinite(res.theta_hat))


#: The output scale that overflows the first pass's observer from the sample it starts at.
OVERFLOWING_SCALE = 1e100


@pytest.mark.parametrize("name", sorted(AUTO_COPIES))
def test_auto_gamma_from_a_first_pass_that_stops(auto_models, name):
    """The first pass (θ̂ held at θ̂₀) stops where the outputs jump to 1e100 × their size: Γ is
    the information of the samples it gave — the same arithmetic as on the record cut there,
    so the same Γ to rounding — with a warning that names the sample; a pass that stops within
    its first two samples has no information to give, and its error is raised."""
    path, (t, u, y) = auto_models[name]
    spec = load_model(path)
    y = np.array(y, dtype=float).reshape(t.size, -1)
    half = t.size // 2
    y[half:] *= OVERFLOWING_SCALE
    with np.errstate(all="ignore"):
        with pytest.warns(ThetahatWarning, match=r"the first pass .* stopped at t\[") as rec:
            G = auto_gamma(spec, t, u, y)
        F = int(re.search(r"stopped at t\[(\d+)\]", str(rec[0].message)).group(1))
        assert half < F <= t.size - 1
        cut = auto_gamma(spec, t[:F], np.asarray(u).reshape(t.size, -1)[:F], y[:F])
        np.testing.assert_allclose(G, cut, rtol=1e-12, atol=0.0)
        assert np.all(np.isfinite(G)) and np.all(np.diag(G) > 0)


def test_auto_gamma_from_a_first_pass_that_stops_at_once(auto_models):
    """The heater's first pass at outputs × 1e100 from the first sample stops in its first
    step: no information to give, so its error is raised (with the data's scale)."""
    path, (t, u, y) = auto_models["heater"]
    with np.errstate(all="ignore"), pytest.raises(ThetahatError, match="diverged"):
        auto_gamma(load_model(path), t, u, np.asarray(y, dtype=float) * OVERFLOWING_SCALE)
