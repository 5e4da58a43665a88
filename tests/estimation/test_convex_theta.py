"""Stage 2 (JointEKF, MAP fits, guarded estimator, trust report) and the paper's observer on
a ball or ellipsoid Θ.

Three shipped models besides LuGre (examples/prop3, prop4, two_inertia), each given a ball or
an ellipsoid Θ through the model file: θ̂ ∈ Θ at every sample; near the truth when it lies
inside Θ; on Θ's boundary, and reported there, when it lies outside. The paper's observer runs
such a file on its compiled kernel (one per model, Θ as data) and agrees with its NumPy run.
"""

from __future__ import annotations

import dataclasses
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import ModelFileError, ThetahatWarning, UnsupportedError
from thetahat.estimation.statistical.ekf import JointEKF
from thetahat.estimation.statistical.stage2_set import (BOUNDARY_RTOL, ELLIPSOID_MARGIN, on_boundary, project_kernel,
                                            project_theta, stage2_set, theta_bounds)
from thetahat.model.paramset import Ball, Box, ConvexSet, Ellipsoid
from thetahat.modelfile import build_observer, loads_model, run_estimator, simulate_model

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

#: The kernel's bisection on λ against Ellipsoid.nearest's secular-equation solve (an
#: independent method): both are accurate to ~1e-12 relative; the kernel also ends
#: ELLIPSOID_MARGIN (1e-12 in P, 5e-13 in distance) inside. 1e-8 leaves a wide margin.
PROJECTION_ATOL = 1e-8
#: With the truth inside Θ (and off its boundary) an estimate that ignores Θ's shape ends
#: within a few Cramér–Rao standard deviations of it: measured 0.02–1.2 σ for the MAP fit and
#: the EKF on these records (seed 0); 4 σ leaves room for another noise draw.
NEAR_TRUTH_SD = 4.0

#: name: (the file's box, a Θ containing the truth, a Θ that excludes it, the truth)
CASES = {
    "prop3": ("lower = [-2.0]\nupper = [2.0]", "center = [1.0]\nradius = 0.6",
              "center = [0.0]\nradius = 0.8", [1.2]),
    "prop4": ("lower = [-2.0, -2.0]\nupper = [2.0, 2.0]",
              "center = [0.5, 0.5]\nshape = [[1.0, 0.0], [0.0, 0.444]]",
              "center = [0.0, 0.0]\nshape = [[1.0, 0.0], [0.0, 4.0]]", [1.0, 1.0]),
    "two_inertia": ("lower = [0.05, 0.05]\nupper = [1.0, 1.0]",
                    "center = [0.4, 0.45]\nradius = 0.3",
                    "center = [0.7, 0.7]\nradius = 0.2", [0.3, 0.5]),
}


def _spec(name: str, theta_set: str, truth: list[float] | None = None,
          gamma: str | None = None):
    """examples/<name>.toml with [parameter_set] replaced, θ̂(0) at Θ's centre, the
    scenario's θ set to ``truth`` (removed when None) and Γ set to ``gamma`` (TOML)."""
    return loads_model(_spec_text(name, theta_set, truth, gamma),
                       source=f"{name}-convex.toml")


def _spec_text(name: str, theta_set: str, truth: list[float] | None = None,
               gamma: str | None = None) -> str:
    """The text of :func:`_spec`'s model file."""
    text = (EXAMPLES / f"{name}.toml").read_text()
    if gamma is not None:
        text = re.sub(r"\nGamma = .*\n", f"\nGamma = {gamma}\n", text)
    text = re.sub(r"\[parameter_set\]\n(?:[a-z]+ = .*\n)+",
                  "[parameter_set]\n" + theta_set + "\n", text)
    text = re.sub(r"\ntheta_hat0 = .*\n", "\n", text)
    if "\n[scenario]\n" in text:
        head, tail = text.split("\n[scenario]\n")
        line = "\n" if truth is None else f"\ntheta = {truth}\n"
        text = head + "\n[scenario]\n" + re.sub(r"\ntheta = .*\n", line, tail)
    elif truth is not None:
        text += f"\n[scenario]\ntheta = {truth}\n"
    return text


@pytest.fixture(scope="module")
def records():
    out = {}
    for name, (box, _, _, truth) in CASES.items():
        out[name] = simulate_model(_spec(name, box, truth), 0)
    return out


def _check_in_theta(theta_set, theta_hat):
    assert np.all(np.isfinite(theta_hat))
    assert np.all(theta_set.contains(theta_hat)), "θ̂ left Θ"


# ------------------------------------------------------------------ the projection itself
@pytest.mark.parametrize("theta_set", [
    Ball([0.5, -1.0], 0.7),
    Ellipsoid([1.0, 2.0, 0.0], np.array([[2.0, 0.3, 0.0], [0.3, 0.5, 0.1], [0.0, 0.1, 9.0]])),
])
def test_the_kernel_is_the_weighted_projection(theta_set, rng):
    p = theta_set.dim
    st = stage2_set(theta_set)
    for _ in range(20):
        z = theta_set.interior_point + 3.0 * rng.standard_normal(p)
        A = rng.standard_normal((p, p))
        M = A @ A.T + 0.1 * np.eye(p)            # a covariance
        th = z.copy()
        project_kernel(th, M, st.lo, st.hi, st.ell)
        ref = theta_set.nearest(z, metric=np.linalg.inv(M))
        assert bool(theta_set.contains(th))
        if not bool(theta_set.contains(z)):
            np.testing.assert_allclose(th, ref, atol=PROJECTION_ATOL)
        else:
            np.testing.assert_array_equal(th, z)


def test_a_singular_covariance_falls_back_to_a_point_of_theta():
    ball = Ball([0.0, 0.0], 1.0)
    st = stage2_set(ball)
    th = np.array([3.0, 0.0])
    project_kernel(th, np.zeros((2, 2)), st.lo, st.hi, st.ell)   # no λ reaches ∂Θ
    np.testing.assert_allclose(th, [1.0, 0.0], atol=PROJECTION_ATOL)
    assert th @ th <= 1.0 - ELLIPSOID_MARGIN


def test_the_compiled_kernel_agrees_with_python(rng):
    pytest.importorskip("numba")
    from thetahat.estimation.statistical.plant_kernel import printed_kernels
    mod, (name,) = printed_kernels("thetahat_test_projection", "The projection compiled "
                                   "alone (tests).", [project_kernel], {}, True)
    fast = getattr(mod, name)
    ell = Ellipsoid([0.0, 1.0], np.array([[4.0, 1.0], [1.0, 1.0]]))
    st = stage2_set(ell)
    for _ in range(10):
        z = 4.0 * rng.standard_normal(2)
        M = np.diag(rng.uniform(0.1, 3.0, 2))
        a, b = z.copy(), z.copy()
        project_kernel(a, M, st.lo, st.hi, st.ell)
        fast(b, M, st.lo, st.hi, st.ell)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)


def test_bounds_and_boundary_of_each_set():
    lo, hi = theta_bounds(Ellipsoid([1.0, 0.0], np.diag([1 / 4, 1 / 9])))
    np.testing.assert_allclose(lo, [-1.0, -3.0])
    np.testing.assert_allclose(hi, [3.0, 3.0])
    disk = ConvexSet(P=lambda t: np.sum(t**2, axis=-1) - 1.0, grad_P=lambda t: 2 * t,
                     interior_point=[0.0, 0.0])
    lo, hi = theta_bounds(disk)                  # SLSQP's support function: ±1 to 1e-6
    np.testing.assert_allclose(lo, [-1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(hi, [1.0, 1.0], atol=1e-6)
    assert on_boundary(disk, [0.0, 1.0]).tolist() == [False, True]
    assert on_boundary(Ball([0.0, 0.0], 1.0), [0.5, 0.5]).tolist() == [False, False]
    assert on_boundary(Box([0.0, 0.0], [1.0, 1.0]), [1.0, 0.5]).tolist() == [True, False]


# ------------------------------------------------------------------ model files
def test_model_files_declare_a_ball_or_an_ellipsoid():
    assert isinstance(_spec("prop3", "center = [1.0]\nradius = 0.6").system.parameter_set,
                      Ball)
    spec = _spec("prop4", CASES["prop4"][1])
    assert isinstance(spec.system.parameter_set, Ellipsoid)
    # the scenario's default truth lies inside the ellipsoid
    assert bool(spec.system.parameter_set.contains(spec.scenario.theta))
    with pytest.raises(ModelFileError, match="radius"):
        _spec("prop3", "center = [1.0]")
    with pytest.raises(ModelFileError, match="unknown key"):
        _spec("prop3", "center = [1.0]\nradius = 0.6\nlower = [0.0]")
    with pytest.raises(ModelFileError, match="radius must be finite and > 0|positive"):
        _spec("prop3", "center = [1.0]\nradius = -1.0")


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("method", ["mle", "ekf"])
@pytest.mark.needs_speed
def test_truth_inside_theta_is_found(records, name, method):
    _, inside, _, truth = CASES[name]
    spec = _spec(name, inside)
    d = records[name]
    res = run_estimator(spec, d.t, d.u, d.y, method=method)
    _check_in_theta(spec.system.parameter_set, res.theta_hat)
    assert res.trust.on_boundary == ()
    err = np.abs(res.theta_hat[-1] - truth)
    assert np.all(err <= NEAR_TRUTH_SD * res.trust.crlb_sd)


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("method", ["mle", "ekf"])
@pytest.mark.needs_speed
def test_truth_outside_theta_ends_on_the_boundary_and_is_reported(records, name, method):
    _, _, outside, truth = CASES[name]
    spec = _spec(name, outside)
    ps = spec.system.parameter_set
    d = records[name]
    with pytest.warns(Warning, match="boundary"):
        res = run_estimator(spec, d.t, d.u, d.y, method=method)
    _check_in_theta(ps, res.theta_hat)
    assert not bool(ps.contains(truth))
    # on ∂Θ, to the trust report's tolerance (an EKF update may step a hair inside after the
    # last projection: measured P = −3e-5)
    assert float(ps.constraint(res.theta_hat[-1])[0]) >= -2 * BOUNDARY_RTOL
    assert res.trust.on_boundary == tuple(spec.parameter_names)


def _guarded(records, name, which):
    _, inside, outside, truth = CASES[name]
    spec = _spec(name, inside if which == "inside" else outside)
    d = records[name]
    if which == "inside":
        res = run_estimator(spec, d.t, d.u, d.y, method="guarded")
    else:
        with pytest.warns(Warning, match="boundary"):
            res = run_estimator(spec, d.t, d.u, d.y, method="guarded")
    ps = spec.system.parameter_set
    _check_in_theta(ps, res.theta_hat)
    _check_in_theta(ps, res.diagnostics.theta_stage2)
    if which == "inside":
        assert np.all(np.abs(res.theta_hat[-1] - truth) <= NEAR_TRUTH_SD * res.trust.crlb_sd)
        assert res.trust.on_boundary == ()
    else:
        assert res.trust.on_boundary == tuple(spec.parameter_names)


@pytest.mark.parametrize("which", ["inside", "outside"])
def test_guarded_on_a_ball(records, which):
    _guarded(records, "prop3", which)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["prop4", "two_inertia"])
@pytest.mark.parametrize("which", ["inside", "outside"])
def test_guarded_on_a_ball_or_ellipsoid_slow(records, name, which):
    _guarded(records, name, which)


# ------------------------------------------------------------------ API only: ConvexSet
def test_joint_ekf_on_a_general_convex_set(records):
    spec = _spec("two_inertia", CASES["two_inertia"][0], CASES["two_inertia"][3])
    # a superellipse |θ − c|⁴ ≤ r⁴ (not an ellipsoid) around (0.7, 0.7): the truth is outside
    c, r = np.array([0.7, 0.7]), 0.2
    theta_set = ConvexSet(P=lambda t: np.sum(((t - c) / r) ** 4, axis=-1) - 1.0,
                          grad_P=lambda t: 4 * (t - c) ** 3 / r ** 4, interior_point=c)
    system = dataclasses.replace(spec.system, parameter_set=theta_set)
    d = records["two_inertia"]
    N = 400                                      # the Python path: a short record
    res = JointEKF(system=system).run(d.t[:N], d.u[:N], d.y[:N])
    _check_in_theta(theta_set, res.theta_hat)
    with pytest.raises(UnsupportedError, match="compiled projection"):
        JointEKF(system=system, compiled=True).kernels


def test_project_theta_in_a_covariance_metric_moves_the_uncertain_component():
    ell = Ellipsoid([0.0, 0.0], np.eye(2))
    th = project_theta(ell, [1.0, 1.0], cov=np.diag([1.0, 1e-4]))
    assert bool(ell.contains(th))
    assert abs(1.0 - th[1]) < 1e-2 < abs(1.0 - th[0])      # θ₂ is pinned, θ₁ gives way


def test_joint_ekf_compiled_and_python_agree_on_a_ball(records):
    pytest.importorskip("numba")
    _, _, outside, _ = CASES["two_inertia"]
    system = _spec("two_inertia", outside).system      # the truth outside: projections act
    d = records["two_inertia"]
    N = 600
    runs = [JointEKF(system=system, compiled=c).run(d.t[:N], d.u[:N], d.y[:N])
            for c in (False, True)]
    for res in runs:
        _check_in_theta(system.parameter_set, res.theta_hat)
    # the same arithmetic in both (numba's and Python's float64), rounding only
    np.testing.assert_allclose(runs[0].theta_hat, runs[1].theta_hat, rtol=1e-9, atol=1e-12)
    assert bool(np.any(on_boundary(system.parameter_set, runs[1].theta_hat[-1])))


# ------------------------------------------------------------------ the paper's observer
#: name: (a ball Θ, an ellipsoid Θ, Γ), both sets excluding CASES' truth, so that the law
#: drives θ̂ onto ∂Θ and the projection acts; prop4's Γ is not diagonal (the Γ⁻¹-weighted
#: projection is then not the Euclidean one).
OBSERVER_SETS = {
    "prop3": ("center = [0.0]\nradius = 0.8", "center = [0.0]\nshape = [[2.0]]", None),
    "prop4": ("center = [0.0, 0.0]\nradius = 0.6", CASES["prop4"][2],
              "[[4.0, 1.5], [1.5, 3.0]]"),
    "two_inertia": (CASES["two_inertia"][2],
                    "center = [0.7, 0.7]\nshape = [[25.0, 5.0], [5.0, 16.0]]", None),
}
#: The kernel and the NumPy path project by different methods (bisection on the multiplier
#: with a 5e-13 margin inside, the secular equation): 1e-12 apart per projection, and the
#: observer is contracting, so the runs agree to rounding. 1e-9 is what compile_observer
#: promises (the same tolerance as tests/estimation/test_compiled.py).
AGREE_RTOL = 1e-9
#: Distance by which the NumPy path's θ̂ may read outside Θ (rounding of its point on ∂Θ).
NUMPY_BOUNDARY_TOL = 1e-12
#: θ̂ counts as on ∂Θ from P(θ̂) >= -1e-9 on (the kernel ends 1e-12 inside in P).
ON_BOUNDARY_P = -1e-9


def _observer_spec(name: str, kind: str):
    ball, ellipsoid, gamma = OBSERVER_SETS[name]
    return _spec(name, ball if kind == "ball" else ellipsoid, gamma=gamma)


@pytest.fixture(scope="module")
def observer_runs(records):
    """(spec, NumPy run, compiled run) of the paper's method per (model, Θ kind): one numba
    kernel per model, shared by its ball and its ellipsoid (Θ is data)."""
    pytest.importorskip("numba")
    out = {}
    for name in OBSERVER_SETS:
        d = records[name]
        for kind in ("ball", "ellipsoid"):
            spec = _observer_spec(name, kind)
            ref, fast = (run_estimator(spec, d.t, d.u, d.y, method="paper", compiled=c,
                                       diagnose=False) for c in (False, True))
            out[name, kind] = spec, ref, fast
    return out


@pytest.mark.parametrize("kind", ["ball", "ellipsoid"])
@pytest.mark.parametrize("name", list(OBSERVER_SETS))
def test_compiled_observer_agrees_with_numpy_on_a_ball_or_ellipsoid(observer_runs, name, kind):
    spec, ref, fast = observer_runs[name, kind]
    ps = spec.system.parameter_set
    assert isinstance(ps, Ball if kind == "ball" else Ellipsoid)
    for field in ("x_hat", "phi_hat", "theta_hat"):
        a, b = getattr(fast, field), getattr(ref, field)
        scale = np.maximum(np.max(np.abs(b), axis=0), np.finfo(float).tiny)
        assert float(np.max(np.abs(a - b) / scale)) <= AGREE_RTOL, field
    _check_in_theta(ps, fast.theta_hat)          # the kernel ends ELLIPSOID_MARGIN inside
    # NumPy's nearest point lies on ∂Θ to rounding: P evaluated on the whole record (another
    # summation order) reads up to 1 ulp above 0 (measured 2.2e-16 on two_inertia)
    assert np.all(ps.contains(ref.theta_hat, tol=NUMPY_BOUNDARY_TOL))
    # the projection acted: θ̂ sat on ∂Θ for a good part of the record
    on = ps.constraint(fast.theta_hat)[:, 0] >= ON_BOUNDARY_P
    assert on.mean() > 0.2


def test_the_runner_compiles_a_ball_theta_with_numba_where_c_refuses(observer_runs,
                                                                     monkeypatch):
    """The C generator refuses Θ ≠ Box with a reason; the runner then takes the numba kernel
    (no Python-fallback note), also where a C compiler is found."""
    from thetahat.codegen import generate_c
    from thetahat.codegen import native
    from thetahat.codegen.generate import supports_c
    from thetahat.estimation.drive import COMPILE_MIN_SAMPLES, runner
    from thetahat.estimation.observer.compiled import CompiledObserver
    obs = build_observer(_observer_spec("two_inertia", "ellipsoid"))
    assert not supports_c(obs)
    with pytest.raises(UnsupportedError, match="Θ must be a Box.*numba"):
        generate_c(obs, dt=1e-3)
    monkeypatch.setattr(native, "native_enabled", lambda: True)
    t = np.arange(COMPILE_MIN_SAMPLES) * 1e-3
    with warnings.catch_warnings():
        warnings.simplefilter("error", ThetahatWarning)
        fast = runner(obs, t)
    assert isinstance(fast, CompiledObserver)


def test_estimate_on_an_ellipsoid_file_runs_compiled_without_a_fallback_note(
        observer_runs, records, tmp_path, capsys):
    """``thetahat estimate`` on a model file with an ellipsoid Θ and a record long enough for
    the compiled path: no "runs in Python" note (the kernel is the one observer_runs built)."""
    from thetahat.cli import main
    from thetahat.estimation.drive import COMPILE_MIN_SAMPLES
    _, ellipsoid, _ = OBSERVER_SETS["two_inertia"]
    model = tmp_path / "ellipsoid.toml"
    model.write_text(_spec_text("two_inertia", ellipsoid))
    d = records["two_inertia"]
    reps = -(-COMPILE_MIN_SAMPLES // d.t.size)       # the record repeated: long enough
    N = reps * d.t.size
    t = np.arange(N) * (d.t[1] - d.t[0])
    data = tmp_path / "data.csv"
    np.savetxt(data, np.c_[t, np.tile(d.u, (reps, 1)), np.tile(d.y, (reps, 1))],
               delimiter=",", header="t,u,y1,y2", comments="")
    assert main(["estimate", str(model), str(data), "-o", str(tmp_path / "e.csv"),
                 "--method", "paper", "--no-progress"]) == 0
    out = capsys.readouterr()
    assert "wrote" in out.out + out.err
    assert "runs in Python" not in out.out + out.err
