"""Model-file studies: the [scenario] table, the simulated plant, ``thetahat sweep/tune MODEL``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from thetahat import ModelFileError
from thetahat.cli import main
from thetahat.modelfile import EXAMPLE_MODEL, load_model, loads_model
from thetahat.modelfile.study import ModelPhi, simulate_model
from thetahat.models import lugre

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

#: lugre.simulate and the model file integrate the same plant with the same LSODA settings
#: (rtol 1e-9) and the same noise; each agrees with a Radau reference to ~1.3e-8 rad/s in ω
#: (thetahat.models.lugre.LUGRE_RTOL), so they agree with each other to a few 1e-8: 1e-6
#: leaves a factor ~30.
PLANT_ATOL = 1e-6
#: ∂φ/∂x by central differences with step 1e-6: truncation ~1e-12·|φ'''|, rounding ~1e-10/1e-6.
FD_RTOL = 1e-5


def test_lugre_file_simulates_the_lugre_plant():
    """examples/lugre.toml's [scenario] is lugre.Scenario(): same records to integrator accuracy."""
    spec = load_model(EXAMPLES / "lugre.toml")
    a = simulate_model(spec, seed=3, t_end=1.0)
    b = lugre.simulate(seed=3, t_end=1.0)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=PLANT_ATOL)
    np.testing.assert_allclose(a.y, b.y, rtol=0, atol=PLANT_ATOL)
    np.testing.assert_allclose(a.u, b.u, rtol=0, atol=1e-12)


def test_model_phi_jacobian_matches_finite_differences(rng):
    spec = loads_model(EXAMPLE_MODEL)
    phi = ModelPhi(perturbation=spec.system.perturbation, C=spec.system.C)
    for _ in range(5):
        x, u, th = rng.normal(size=2), rng.normal(size=1), rng.uniform(-2, 2, size=1)
        J = phi.dphi_dx(0.0, x, u, th)
        h = 1e-6
        fd = np.stack([(phi(0.0, x + h * e, u, th) - phi(0.0, x - h * e, u, th)) / (2 * h)
                       for e in np.eye(2)], axis=-1)
        np.testing.assert_allclose(J, fd, rtol=FD_RTOL, atol=1e-8)


def test_scenario_defaults_and_values():
    spec = loads_model(EXAMPLE_MODEL)
    sc = spec.scenario
    assert sc.theta.tolist() == [1.0]                         # 3/4 of the way across [-2, 2]
    assert (sc.t_end, sc.fs, sc.noise_std, sc.method) == (20.0, 100.0, 0.01, "Radau")
    assert "theta" in sc.defaults and "fs" in sc.defaults
    given = loads_model(EXAMPLE_MODEL + "\n[scenario]\ntheta = [1.5]\nfs = 50.0\n"
                                        "u_amplitudes = [[1.0, 2.0]]\n"
                                        "u_frequencies = [[0.1, 0.2]]\n").scenario
    assert given.theta.tolist() == [1.5] and given.fs == 50.0
    assert given.u_amplitudes.shape == (1, 2) and "theta" not in given.defaults


@pytest.mark.parametrize("table, match", [
    ("theta = [3.0]", r"\[scenario\] theta: the true θ = \[3.0\] lies outside Θ"),
    ("fs = -1.0", r"\[scenario\] fs: expected a finite positive number"),
    ("method = 'Euler'", r"\[scenario\] method: unknown method 'Euler'; expected one of"),
    ("u_amplitudes = [1.0, 2.0]\nu_frequencies = [0.1]", r"u_frequencies: expected the shape"),
    ("noise = 0.1", r"\[scenario\]: unknown key\(s\) \['noise'\]"),
    ("noise_std = -0.1", r"noise_std: expected a finite number >= 0; got -0.1"),
    ("u_hold = 'foh'", r"\[scenario\] u_hold: unknown .*'foh'; expected one of"),
])
def test_bad_scenarios_name_the_key(table, match):
    with pytest.raises(ModelFileError, match=match):
        loads_model(EXAMPLE_MODEL + "\n[scenario]\n" + table + "\n")


def test_sweep_model_file(tmp_path, capsys):
    """Issue 10: ``thetahat sweep examples/prop3.toml`` runs the file's estimator."""
    out = tmp_path / "out"
    assert main(["sweep", str(EXAMPLES / "prop3.toml"), "--eps", "1", "0.5", "--seeds", "1",
                 "--t-end", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "x1 RMSE" in printed and "x2 RMSE" in printed        # the file's state names
    summary = json.loads((out / "sweep.json").read_text())
    assert summary["eps"] == [1.0, 0.5] and summary["first_unstable"] is None


def test_tune_model_file(tmp_path, capsys):
    """Issue 10: ``thetahat tune examples/prop3.toml`` picks (ε, Γ) for the file's law."""
    out = tmp_path / "out"
    # 5 s: θ̂ settles for ε = 0.5 (2 s is too short for any pair, and tune then picks none)
    assert main(["tune", str(EXAMPLES / "prop3.toml"), "--eps", "1", "0.5", "--gamma", "1",
                 "4", "--seeds", "1", "--t-end", "5", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "chosen: eps =" in printed
    summary = json.loads((out / "tune.json").read_text())
    assert summary["best_eps"] in (1.0, 0.5) and summary["best_Gamma"] in (1.0, 4.0)


def test_sweep_of_a_file_without_scenario_notes_the_defaults(tmp_path, capsys):
    model = tmp_path / "m.toml"
    model.write_text(EXAMPLE_MODEL)
    assert main(["sweep", str(model), "--eps", "1", "--seeds", "1", "--t-end", "1",
                 "--out", str(tmp_path / "out")]) == 0
    assert "[scenario] gives no theta, u_amplitudes" in capsys.readouterr().err


#: The file's estimator and lugre.estimator_spec() share gains (same design matrices to 16
#: digits in the file) and θ* (the same formula, parsed vs numpy); on records that agree to
#: ~1e-8 their sweeps agree far inside 1e-4 relative.
SWEEP_RTOL = 1e-4


def test_lugre_file_is_the_lugre_estimator():
    """examples/lugre.toml and thetahat.models.lugre describe one estimator: same K(ε) for every
    ε and the same sweep on the same seeds."""
    from thetahat.modelfile import estimator_spec
    from thetahat.studies.sweep import eps_sweep

    spec = load_model(EXAMPLES / "lugre.toml")
    from_file, built_in = estimator_spec(spec), lugre.estimator_spec()
    for eps in (1.0, 0.2):
        a, b = from_file.designs(eps), built_in.designs(eps)
        np.testing.assert_allclose(a[0].K, b[0].K, rtol=1e-9)
        np.testing.assert_allclose(a[1].K, b[1].K, rtol=1e-9)
    kw = dict(eps_values=[1.0, 0.5], seeds=[0], theta_hat0=[0.5], progress=False)
    ra = eps_sweep(from_file, lambda s: simulate_model(spec, s, t_end=0.5), **kw)
    rb = eps_sweep(built_in, lambda s: lugre.simulate(seed=s, t_end=0.5), **kw)
    np.testing.assert_allclose(ra.theta_rmse, rb.theta_rmse, rtol=SWEEP_RTOL)
    np.testing.assert_allclose(ra.x_rmse, rb.x_rmse, rtol=SWEEP_RTOL)


#: A linear plant through solve_ivp (rtol 1e-10, atol 1e-12, restarted at every sample)
#: against its exact discretisation (the matrix exponential of the plant augmented with the
#: held input): measured 1e-10 apart on states of size ~3; 1e-7 leaves a factor of 1000.
LINEAR_PLANT_ATOL = 1e-7

_LINEAR_MODEL = """
name = "A lightly damped oscillator with a linear perturbation"
[system]
A = [[0.0, 1.0], [-1.0, -0.1]]
B = [[0.0], [1.0]]
C = [[1.0, 0.0]]
E = [[0.0], [1.0]]
[perturbation]
g = "-theta*y"
u = ["u"]
y = ["y"]
x = ["x1", "x2"]
theta = ["theta"]
[parameter_set]
lower = [0.0]
upper = [1.0]
[estimator]
law = "gradient"
Gamma = 1.0
eps = 0.5
[scenario]
theta = [0.5]
t_end = 12.0
fs = 2.0
noise_std = 0.0
u_amplitudes = [1.0, 0.5]
u_frequencies = [0.23, 0.61]
method = "DOP853"
rtol = 1e-10
atol = 1e-12
"""


def _held_flow(A, B, t, u, hold):
    """x(t_k) of ẋ = A x + B u from x = 0 with u zero- or first-order held: the exponential of
    [[A, B, 0], [0, 0, I/h], [0, 0, 0]] over each interval (exact for a linear plant)."""
    from scipy.linalg import expm
    n, m = B.shape
    x, out = np.zeros(n), [np.zeros(n)]
    for k in range(t.size - 1):
        h = t[k + 1] - t[k]
        M = np.zeros((n + 2 * m, n + 2 * m))
        M[:n, :n], M[:n, n:n + m] = A, B
        if hold == "foh":
            M[n:n + m, n + m:] = np.eye(m) / h
        F = expm(M * h)
        slope = (u[k + 1] - u[k]) if hold == "foh" else np.zeros(m)
        x = F[:n, :n] @ x + F[:n, n:n + m] @ u[k] + F[:n, n + m:] @ slope
        out.append(x)
    return np.array(out)


def test_a_dac_held_scenario_input_is_what_the_plant_sees():
    """[scenario] u_hold = "zoh": the plant is driven by the sines' samples held, which the
    exact discretisation of the same linear plant confirms; the continuous sines give another
    trajectory (by far more than the tolerance), so the key is not ignored."""
    spec = loads_model(_LINEAR_MODEL + 'u_hold = "zoh"\n')
    assert spec.scenario.u_hold == "zoh"
    held = simulate_model(spec, seed=0)
    s, th = spec.system, spec.scenario.theta[0]
    exact = _held_flow(s.A - th * s.E @ s.C, s.B, held.t, held.u, "zoh")
    np.testing.assert_allclose(held.x, exact, rtol=0, atol=LINEAR_PLANT_ATOL)
    sines = simulate_model(loads_model(_LINEAR_MODEL), seed=0)
    np.testing.assert_array_equal(sines.u, held.u)       # the same samples ...
    assert np.abs(sines.x - held.x).max() > 100 * LINEAR_PLANT_ATOL   # ... another input


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_a_held_record_integrates_sample_to_sample(hold):
    """simulate_plant restarts at every sample of a held record (jumps of zoh, kinks of foh),
    here 1 200 of them — more than the 1 000 at which it used to step over them: the exact
    discretisation agrees."""
    from thetahat.simulation.signals import FromArray
    from thetahat.simulation.simulate import simulate_plant
    spec = loads_model(_LINEAR_MODEL)
    s, th = spec.system, spec.scenario.theta[0]
    t = np.arange(1201) * 0.05
    u = np.random.default_rng(5).normal(size=(t.size, 1))
    traj = simulate_plant(s, phi=lambda t_, x, u_, q: -q[..., :1] * x[..., :1],
                          u=FromArray(t, u, hold=hold), t_end=float(t[-1]), fs=20.0,
                          x0=[0.0, 0.0], theta=[th], method="DOP853", rtol=1e-10, atol=1e-12)
    assert traj.stats.n_segments == t.size - 1
    exact = _held_flow(s.A - th * s.E @ s.C, s.B, t, u, hold)
    np.testing.assert_allclose(traj.x, exact, rtol=0, atol=LINEAR_PLANT_ATOL)
