"""The joint EKF as C (``thetahat.codegen.ekf_c``, ``thetahat codegen --method ekf``), compiled by
the system C compiler and run on the records the Python ``JointEKF`` filters.

Every comparison runs the Python EKF (``run``, and ``step`` for the stream) and the generated
harness on the same samples, with NaN outputs in them (both predict over them). Tests skip only
when no C compiler is present.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from thetahat.cli import main
from thetahat.codegen.ekf_c import generate_ekf_c
from thetahat.codegen.harness import C_FLAGS
from thetahat.codegen.loader import find_compiler
from thetahat.errors import NonFiniteError, OptionError, ThetahatError, UnsupportedError
from thetahat.estimation.statistical.ekf import JointEKF
from thetahat.modelfile import generate_ekf_c_from_model, load_model, simulate_model

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler (cc or $CC)")

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: LuGre and every shipped model the EKF runs on (a symbolic g and a box Θ).
MODELS = ("lugre", "prop1", "prop2", "prop3", "prop4", "two_inertia", "heater", "actuator",
          "spring_friction", "emps")
#: Samples per record: enough for every θ̂ to move off its start (the EKF's transient is a
#: few tens of samples), few enough for the plain-Python reference without numba.
N_SAMPLES = 2000
#: C against Python, relative to each column's largest |value| (the observer's C promises the
#: same, tests/codegen/test_codegen.py). The C performs the kernels' operations in their order
#: on the same SymPy forms; what differs is rounding: SymPy's C printer groups the common
#: subexpressions of f, ∂f/∂x, ∂f/∂θ afresh and writes x² as pow(x, 2), and libm's pow and
#: exp may differ from Python's ** by an ulp. The filter then amplifies an ulp most where a
#: parameter is weakly identified (its gain divides by a small innovation variance): measured
#: 8e-15 on LuGre, ≤ 2e-14 on the propositions, two-inertia, actuator and EMPS, 6.7e-13 on the
#: heater and 1.2e-12 on the spring with friction (3,000 samples); the bound leaves ~800×.
EKF_RTOL = 1e-9
HEAP = re.compile(r"\b(malloc|calloc|realloc|free)\s*\(")
#: The sanitizers of the observer's C tests (tests/codegen/test_codegen.py).
SANITIZE = "-fsanitize=address,undefined,float-cast-overflow"


def rel_err(a, b) -> float:
    """Largest |a − b| relative to the largest |b| of the same column."""
    scale = np.maximum(np.max(np.abs(b), axis=0), np.finfo(float).tiny)
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b)) / scale))


def record(name: str):
    """The model file's scenario (seed 0), its first N_SAMPLES, outputs NaN at rows 10 and
    50–52 (predicted over)."""
    spec = load_model(EXAMPLES / f"{name}.toml")
    d = simulate_model(spec, 0)
    N = min(N_SAMPLES, len(d.t))
    t = np.asarray(d.t, dtype=np.float64)[:N]
    u = np.asarray(d.u, dtype=np.float64).reshape(len(d.t), -1)[:N]
    y = np.asarray(d.y, dtype=np.float64).reshape(len(d.t), -1)[:N].copy()
    y[10] = np.nan
    y[50:53] = np.nan
    return spec, t, u, y


def build(code, out: Path, flags=C_FLAGS) -> Path:
    code.write(out)
    name = code.name
    res = subprocess.run([find_compiler(), *flags, "-o", name, f"{name}_main.c", f"{name}.c",
                          "-lm"], cwd=out, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and not res.stderr.strip(), res.stderr
    return out / name


def run_harness(exe: Path, path: Path, t, u, y) -> tuple[int, np.ndarray, str]:
    np.savetxt(path, np.c_[t, u, y], delimiter=",", header="t,u,y", comments="", fmt="%.17g")
    out = subprocess.run([str(exe), str(path)], capture_output=True, text=True, timeout=300)
    rows = out.stdout.splitlines()[1:]
    table = np.loadtxt(rows, delimiter=",", ndmin=2) if rows else np.zeros((0, 1))
    return out.returncode, table, out.stderr


def reference(spec, t, u, y, hold="zoh"):
    """The Python EKF's run (sub-steps chosen on the record) and the EKF it ran."""
    ekf = JointEKF(system=spec.system, noise_std=spec.scenario.noise_std, hold=hold)
    st = ekf.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    res = ekf.run(t, u, y, state0=st)
    ekf = JointEKF(system=spec.system, noise_std=spec.scenario.noise_std, hold=hold,
                   substeps=res.diagnostics.substeps)
    return res, ekf


@pytest.mark.parametrize("name", MODELS)
def test_c_ekf_agrees_with_python_and_keeps_theta_in_set(tmp_path, name):
    spec, t, u, y = record(name)
    res, ekf = reference(spec, t, u, y)
    code = generate_ekf_c(ekf, dt=float(t[1] - t[0]), name=f"{name}_ekf",
                          x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    assert not HEAP.search(code.source)
    assert re.findall(r"#include <(\w+)\.h>", code.source) == ["math"]
    rc, table, err = run_harness(build(code, tmp_path), tmp_path / "d.csv", t, u, y)
    assert rc == 0, err
    n, p = spec.system.n, spec.system.p
    assert table.shape == (t.size, 1 + n + p)
    assert rel_err(table[:, 1:1 + n], res.x_hat) <= EKF_RTOL
    assert rel_err(table[:, 1 + n:], res.theta_hat) <= EKF_RTOL
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    theta = table[:, 1 + n:]
    assert np.all(np.isfinite(theta)) and np.all((theta >= lo) & (theta <= hi))
    assert np.ptp(res.theta_hat, axis=0).max() > 0.0          # the filter did estimate


#: LuGre and three more models under the linear holds (the zero-order one: all of MODELS).
FOH_MODELS = ("lugre", "two_inertia", "actuator", "emps")


@pytest.mark.parametrize("hold", ("foh", "smooth"))
@pytest.mark.parametrize("name", FOH_MODELS)
def test_c_ekf_with_the_linear_hold_agrees_with_python(tmp_path, name, hold):
    """hold="foh": u on the line from the previous sample to the current one, which the
    C's step has (its state keeps the previous u), as the Python EKF's run reads them;
    hold="smooth": the line through the corrected samples ũ, which the C computes with the
    printed smooth_step from the history in its state, as the run computes them a block at
    a time. Each hold is used: the estimates under the hold before it (zoh, foh) differ by
    more than 100× the tolerance (the least: EMPS's slow input, whose correction moves its
    estimates by 2.4e-7)."""
    spec, t, u, y = record(name)
    res, ekf = reference(spec, t, u, y, hold=hold)
    code = generate_ekf_c(ekf, dt=float(t[1] - t[0]), name=f"{name}_{hold}",
                          x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    assert code.sizes["hold"] == hold and f"hold {hold}" in code.source
    assert ("f_smooth_step" in code.source) == (hold == "smooth")
    rc, table, err = run_harness(build(code, tmp_path), tmp_path / "d.csv", t, u, y)
    assert rc == 0, err
    estimates = np.c_[res.x_hat, res.theta_hat]
    assert rel_err(table[:, 1:], estimates) <= EKF_RTOL
    other, _ = reference(spec, t, u, y, hold="zoh" if hold == "foh" else "foh")
    assert rel_err(np.c_[other.x_hat, other.theta_hat], estimates) > 100 * EKF_RTOL


@pytest.mark.parametrize("hold", ("zoh", "foh", "smooth"))
def test_c_ekf_is_the_stream_of_step(tmp_path, hold):
    """The C's step is JointEKF.step: 300 LuGre samples, one step call each."""
    spec, t, u, y = record("lugre")
    t, u, y = t[:300], u[:300], y[:300]
    ekf = JointEKF(system=spec.system, noise_std=spec.scenario.noise_std, hold=hold)
    st = ekf.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    dt = float(t[1] - t[0])
    rows = []
    for k in range(t.size):
        st = ekf.step(st, u[k], y[k], dt)
        rows.append(np.concatenate([st.x_hat, st.theta_hat]))
    code = generate_ekf_c(ekf, dt=dt, name="lugre_stream", x_hat0=spec.estimator.x_hat0,
                          theta_hat0=spec.estimator.theta_hat0)
    rc, table, err = run_harness(build(code, tmp_path), tmp_path / "d.csv", t, u, y)
    assert rc == 0, err
    assert rel_err(table[:, 1:], np.array(rows)) <= EKF_RTOL


def test_c_ekf_refuses_a_nonfinite_input_as_step_does(tmp_path):
    spec, t, u, y = record("prop4")
    t, u, y = t[:40], u[:40].copy(), y[:40]
    u[20] = np.nan
    ekf = JointEKF(system=spec.system, noise_std=spec.scenario.noise_std, hold="zoh")
    st = ekf.init()
    for k in range(20):
        st = ekf.step(st, u[k], y[k], 0.01)
    with pytest.raises(NonFiniteError):
        ekf.step(st, u[20], y[20], 0.01)
    rc, table, err = run_harness(build(generate_ekf_c(ekf, dt=0.01, name="e"), tmp_path),
                                 tmp_path / "d.csv", t, u, y)
    assert rc == 2 and "data row 21" in err and table.shape[0] == 20


@pytest.mark.parametrize("name", ["lugre", "two_inertia"])
def test_c_ekf_under_sanitizers(tmp_path, name):
    probe = tmp_path / "probe.c"
    probe.write_text("int main(void) { return 0; }\n")
    ok = subprocess.run([find_compiler(), SANITIZE, "-o", str(tmp_path / "probe"), str(probe)],
                        capture_output=True).returncode == 0
    if not ok or subprocess.run([str(tmp_path / "probe")]).returncode != 0:
        pytest.skip("the C compiler cannot build with the sanitizers here")
    spec, t, u, y = record(name)
    t, u, y = t[:500], u[:500], y[:500]
    res, ekf = reference(spec, t, u, y)
    code = generate_ekf_c(ekf, dt=float(t[1] - t[0]), name="san",
                          x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    exe = build(code, tmp_path, flags=(*C_FLAGS, "-g", SANITIZE, "-fno-sanitize-recover=all"))
    rc, table, err = run_harness(exe, tmp_path / "d.csv", t, u, y)
    assert rc == 0 and "runtime error" not in err and "Sanitizer" not in err, err
    assert rel_err(table[:, 1:], np.c_[res.x_hat, res.theta_hat]) <= EKF_RTOL


def test_cli_codegen_method_ekf_builds_with_make(tmp_path, capsys):
    spec, t, u, y = record("prop3")
    data = tmp_path / "d.csv"
    np.savetxt(data, np.c_[t, u, y], delimiter=",", header="t,u,y", comments="", fmt="%.17g")
    out = tmp_path / "c"
    assert main(["codegen", str(EXAMPLES / "prop3.toml"), "--method", "ekf", "--dt", "0.01",
                 "--data", str(data), "--nan-policy", "skip", "-o", str(out), "--name", "p3"]) == 0
    assert "joint EKF" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["Makefile", "p3.c", "p3.h", "p3_main.c"]
    if subprocess.run(["make", "--version"], capture_output=True).returncode == 0:
        res = subprocess.run(["make", "-C", str(out)], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
    # the record fixed σ and the sub-steps, as JointEKF.run chooses them
    ref, _ = reference(spec, t, u, y)
    code = generate_ekf_c_from_model(EXAMPLES / "prop3.toml", dt=0.01, record=(t, u, y))
    assert code.sizes["substeps"] == ref.diagnostics.substeps


@pytest.mark.parametrize("hold", ("foh", "smooth"))
def test_cli_codegen_method_ekf_takes_the_linear_holds(tmp_path, capsys, hold):
    out = tmp_path / "c"
    assert main(["codegen", str(EXAMPLES / "lugre.toml"), "--method", "ekf", "--dt", "1e-3",
                 "--noise-std", "0.02", "--hold", hold, "-o", str(out), "--name", "lf"]) == 0
    capsys.readouterr()
    assert f"hold {hold}," in (out / "lf.c").read_text()


def test_cli_codegen_paper_refuses_the_smooth_hold_in_one_line(tmp_path, capsys):
    """"smooth" corrects stage 2's samples; the paper's observer has no such hold."""
    assert main(["codegen", str(EXAMPLES / "lugre.toml"), "--dt", "1e-3", "--hold", "smooth",
                 "-o", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "--method ekf or guarded" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("args, match", [
    (["--eps", "0.1"], "--eps"),
    (["--real", "float"], "--real float"),
    ([], "noise"),
])
def test_cli_codegen_method_ekf_refuses(tmp_path, capsys, args, match):
    assert main(["codegen", str(EXAMPLES / "lugre.toml"), "--method", "ekf", "--dt", "1e-3",
                 "-o", str(tmp_path / "c"), *args]) == 2
    err = capsys.readouterr().err
    assert match in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()


def test_generate_ekf_c_refusals():
    spec = load_model(EXAMPLES / "lugre.toml")
    with pytest.raises(UnsupportedError, match="'bandlimited' reads later samples"):
        generate_ekf_c(JointEKF(system=spec.system, noise_std=0.01, hold="bandlimited"),
                       dt=1e-3)
    with pytest.raises(OptionError, match="noise"):
        generate_ekf_c(JointEKF(system=spec.system, hold="zoh"), dt=1e-3)
    ekf = JointEKF(system=spec.system, noise_std=0.01, hold="zoh")
    for dt in (0.0, -1.0, float("nan")):
        with pytest.raises(OptionError, match="dt"):
            generate_ekf_c(ekf, dt=dt)
    with pytest.raises(ThetahatError):
        generate_ekf_c(ekf, dt=1e-3, name="x */ int evil; /*")
    with pytest.raises(UnsupportedError, match="JointEKF"):
        generate_ekf_c(spec, dt=1e-3)   # type: ignore[arg-type]


def test_model_title_cannot_leave_its_comment():
    spec = load_model(EXAMPLES / "lugre.toml")
    ekf = JointEKF(system=spec.system, noise_std=0.01, hold="zoh")
    code = generate_ekf_c(ekf, dt=1e-3, title="demo */ int injected = 1; /*")
    assert "int injected" not in code.source.split("*/", 1)[1]
