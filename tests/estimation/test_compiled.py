"""Tests of the compiled fast path (``thetahat.estimation.observer.compiled``, optional extra ``speed``).

The compiled kernel must compute what the Python observer computes: every test that compiles
compares with ``ModifiedHighGainObserver.run``/``step`` on the same data. Kernels are cached on
disk by numba, so only the first session pays the JIT compilation (three kernels: the DC motor
with the paper's θ*, and a MIMO toy model (k = p = r = 2) with and without a SymPy-derived
θ*); observers that differ only in gains, Γ, the law or the second observer share a kernel.
"""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
import sympy as sp

from thetahat.errors import (DimensionError, MissingExtraError, NonFiniteError, OptionError,
                             UpdateLawError)
from thetahat.estimation.observer.compiled import CompiledObserver, compile_observer
from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.estimation.observer.redesign import SecondObserver
from thetahat.estimation.observer.laws import (AlgebraicInversion, ConstantLaw, GradientInversion,
                                             IntermittentInversion, algebraic_from_perturbation,
                                             smooth_ramp)
from thetahat.model.paramset import Ball, Box, ConvexSet
from thetahat.model.perturbation import CallablePerturbation, SymbolicPerturbation
from thetahat.model.system import PerturbedLinearSystem
from thetahat.models import lugre

#: Agreement of the compiled and the Python run, relative to each column's largest |value|.
#: The kernel performs the same operations up to the summation order of the small products, a
#: hand-written pivoted LU in place of LAPACK's and scalar code for g: rounding only, measured
#: below 1e-12 on the DC motor over 20 s. 1e-9 is the agreement compile_observer promises.
AGREE_RTOL = 1e-9
DT = 1e-3


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    """Largest |a − b| relative to the largest |b| of the same column."""
    scale = np.maximum(np.max(np.abs(b), axis=0), np.finfo(float).tiny)
    return float(np.max(np.abs(a - b) / scale))


def assert_agree(fast_res, ref) -> None:
    for name in ("x_hat", "phi_hat", "theta_hat", "x_hat_refined"):
        a, b = getattr(fast_res, name), getattr(ref, name)
        if b is None:
            assert a is None
            continue
        assert rel_err(a, b) <= AGREE_RTOL, name


@pytest.fixture(scope="module")
def motor():
    """The paper's estimator (Sec. VIII-A, second observer attached), its data and kernel."""
    pytest.importorskip("numba")
    data = lugre.simulate(seed=3, t_end=2.0)
    obs = lugre.observer()
    fast = compile_observer(obs, dt=DT)
    return data, obs, fast


# --------------------------------------------------------------------------- a MIMO toy model
U_, Y1, Y2, X1, X2, T1, T2 = sp.symbols("u y1 y2 x1 x2 theta1 theta2", real=True)
TOY_G = SymbolicPerturbation.from_sympy(
    [T1 * sp.tanh(X1) + U_ / 10, T2 * X2 / (1 + X2**2) + Y1 * Y2 / 20],
    u=[U_], y=[Y1, Y2], x=[X1, X2], theta=[T1, T2])
TOY_BOX = Box([0.2, 0.1], [2.0, 3.0])
TOY = PerturbedLinearSystem(A=[[0.0, 1.0], [-1.0, -0.5]], B=[[0.0], [1.0]], C=np.eye(2),
                            E=np.eye(2), perturbation=TOY_G, parameter_set=TOY_BOX)


def toy_data(N: int = 2000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    t = np.arange(N) * DT
    y = np.c_[np.sin(2 * t), 1.5 * np.cos(t)] + 0.01 * rng.standard_normal((N, 2))
    return t, np.sin(3 * t)[:, None], y


def toy_observer(law, *, second: str | None = None) -> ModifiedHighGainObserver:
    obs2 = None if second is None else SecondObserver(
        system=TOY, K_x=3 * np.eye(2), g_on_estimates=second == "estimates")
    return ModifiedHighGainObserver(system=TOY, K_x=4 * np.eye(2), K_phi=4 * np.eye(2),
                                    update_law=law, second=obs2)


TOY_LAWS = {
    "gradient+second": (lambda: GradientInversion(TOY_G, np.diag([0.5, 2.0]), TOY_BOX), "y"),
    "constant+second_on_estimates": (lambda: ConstantLaw([1.0, 2.0], TOY_BOX), "estimates"),
    "algebraic_sympy": (lambda: algebraic_from_perturbation(
        TOY_G, Gamma=np.diag([1.0, 3.0]), parameter_set=TOY_BOX, on_invalid="freeze"), None),
    "intermittent_sympy+second": (lambda: IntermittentInversion.from_perturbation(
        TOY_G, smooth_ramp(0.3, 0.6), Gamma=np.diag([2.0, 1.0]), parameter_set=TOY_BOX,
        on_invalid="freeze"), "y"),
}


# --------------------------------------------------------------------------- agreement
def test_motor_run_matches_python_run(motor):
    data, obs, fast = motor
    res = fast.run(data.t, data.u, data.y)
    assert_agree(res, obs.run(data.t, data.u, data.y))
    assert not res.skipped.any()


def test_motor_theta_hat_moves_and_stays_in_theta(motor):
    data, _, fast = motor
    th = fast.run(data.t, data.u, data.y).theta_hat[:, 0]
    assert th.min() >= 0.05 and th.max() <= 1.0
    assert np.ptp(th) > 0.05          # the law is active: θ̂ leaves its start 0.525


def test_motor_step_matches_python_step(motor):
    data, obs, fast = motor
    s_py = s_c = obs.init()
    for i in range(400):
        s_py = obs.step(s_py, data.u[i], data.y[i], DT)
        s_c = fast.step(s_c, data.u[i], data.y[i], DT)
        assert np.allclose(s_c, s_py, rtol=AGREE_RTOL, atol=AGREE_RTOL * 1e-3), i
    assert isinstance(s_c, np.ndarray) and s_c.shape == (obs.state_size,)


def test_step_with_missing_samples_matches_python_step(motor):
    """Gaps (NaN in y under nan_policy="skip") between present samples: the compiled step's
    two φ-tables for a step of dt (sample present, sample missing: made once each and kept)
    give the Python step's states at every sample, in whatever order they alternate."""
    data, obs, _ = motor
    skip = ModifiedHighGainObserver(system=obs.system, K_x=obs.K_x, K_phi=obs.K_phi,
                                    update_law=obs.update_law, second=obs.second,
                                    nan_policy="skip")
    fast = compile_observer(skip, dt=DT)
    y = np.array(data.y, dtype=float)
    y[50:60] = np.nan                           # a gap, then single missing samples
    y[100:300:7] = np.nan
    s_py = s_c = skip.init()
    for i in range(400):
        s_py = skip.step(s_py, data.u[i], y[i], DT)
        s_c = fast.step(s_c, data.u[i], y[i], DT)
        assert np.allclose(s_c, s_py, rtol=AGREE_RTOL, atol=AGREE_RTOL * 1e-3), i


def test_gains_and_gamma_are_data_not_code(motor):
    _, _, fast = motor
    other = compile_observer(lugre.observer(eps=0.5, Gamma=3.0, second=False), dt=5e-4)
    kernel = repr(fast).rsplit("kernel=", 1)[1]
    assert repr(other).endswith(f"kernel={kernel}")  # one kernel per model: no recompilation
    assert isinstance(other, CompiledObserver) and other.dt == 5e-4


@pytest.mark.parametrize("case", sorted(TOY_LAWS))
def test_mimo_toy_run_matches_python(case):
    pytest.importorskip("numba")
    make_law, second = TOY_LAWS[case]
    obs = toy_observer(make_law(), second=second)
    t, u, y = toy_data()
    fast = compile_observer(obs, dt=DT)
    res = fast.run(t, u, y)
    assert_agree(res, obs.run(t, u, y))
    assert TOY_BOX.contains(res.theta_hat).all()


def test_inversion_law_on_a_ball_with_a_full_gamma_matches_python():
    """The inversion law (Γ = V diag(Λ) Vᵀ not diagonal) on a ball Θ: the kernel's
    Γ⁻¹-weighted projection (kernels/set_projection) agrees with the NumPy path's, and θ̂
    rides on ∂Θ for part of the record (the projection acts)."""
    pytest.importorskip("numba")
    ball = Ball([1.1, 1.5], 0.3)
    law = IntermittentInversion.from_perturbation(
        TOY_G, smooth_ramp(0.3, 0.6), Gamma=[[2.0, 0.7], [0.7, 1.0]], parameter_set=ball,
        on_invalid="freeze")
    obs = toy_observer(law)
    t, u, y = toy_data()
    res = compile_observer(obs, dt=DT).run(t, u, y)
    assert_agree(res, obs.run(t, u, y))
    assert ball.contains(res.theta_hat).all()
    assert (ball.constraint(res.theta_hat)[:, 0] >= -1e-9).mean() > 0.1


def test_invalid_theta_star_raises_like_python(motor):
    data, _, _ = motor
    sys_ = lugre.system()
    law = AlgebraicInversion(lugre.theta_star(), 1.0, sys_.parameter_set, on_invalid="raise")
    obs = ModifiedHighGainObserver.from_design(sys_, lugre.designs()[0], law)
    fast = compile_observer(obs, dt=DT)
    # at the start φ̂ = g(v, 0, θ̂) = 0, so θ* = σ0 η |y| / φ̂ is 0/0 while the weight is 1
    with pytest.raises(UpdateLawError, match="theta_star is NaN"):
        obs.run(data.t[:20], data.u[:20], data.y[:20])
    with pytest.raises(UpdateLawError, match="theta_star is NaN"):
        fast.run(data.t[:20], data.u[:20], data.y[:20])


# --------------------------------------------------------------------------- input errors
def test_run_takes_the_records_own_spacing(motor):
    """Another dt (every other sample: 2 ms) and irregular steps (a third of the samples
    dropped at random): each step uses the φ-matrices of its own length, as the Python run."""
    data, obs, fast = motor
    keep = np.random.default_rng(0).uniform(size=data.t.size) > 1 / 3
    keep[0] = True
    for sel in (slice(None, None, 2), keep):
        t, u, y = data.t[sel], data.u[sel], data.y[sel]
        assert_agree(fast.run(t, u, y), obs.run(t, u, y))


def test_foh_matches_python_run(motor):
    data, obs, _ = motor
    foh = obs.with_run_options(hold="foh")
    assert_agree(compile_observer(foh, dt=DT).run(data.t, data.u, data.y),
                 foh.run(data.t, data.u, data.y))


def test_progress_is_reported_to_the_end(motor):
    data, obs, _ = motor
    seen: list[tuple[int, int]] = []
    reporting = obs.with_run_options(progress=lambda done, total: seen.append((done, total)))
    compile_observer(reporting, dt=DT).run(data.t, data.u, data.y)
    N = data.t.size
    assert seen[0] == (0, N - 1) and seen[-1] == (N - 1, N - 1)
    assert [d for d, _ in seen] == sorted(d for d, _ in seen)


def test_run_rejects_nan_under_raise_and_bad_input(motor):
    data, _, fast = motor
    y = data.y[:50].copy()
    y[10] = np.nan
    with pytest.raises(NonFiniteError, match="NaN"):       # the observer's own NaN policy
        fast.run(data.t[:50], data.u[:50], y)
    with pytest.raises(NonFiniteError, match="NaN"):
        fast.step(fast.init(), [0.0], [np.nan], DT)
    with pytest.raises(NonFiniteError, match="state"):
        fast.step(np.full(fast.state_size, np.nan), [0.0], [1.0], DT)
    with pytest.raises(DimensionError):
        fast.step(fast.init(), [0.0], [1.0, 2.0], DT)
    with pytest.raises(DimensionError, match="compiled observer steps dt"):
        fast.step(fast.init(), [0.0], [1.0], 2 * DT)
    with pytest.raises(TypeError):
        fast.step(fast.init(), [0.0], [1.0])              # dt is required, as everywhere
    with pytest.raises(TypeError):
        fast.init([0.0, 0.0])                             # init takes keywords only


def _callable_observer() -> ModifiedHighGainObserver:
    pert = CallablePerturbation(g=lambda v, x, th: th * x[..., :1], n=2, m=1, r=1, p=1, k=1)
    plant = PerturbedLinearSystem(A=np.zeros((2, 2)), B=[[0.0], [1.0]], C=[[1.0, 0.0]],
                                  E=[[0.0], [1.0]], perturbation=pert)
    return ModifiedHighGainObserver(system=plant, K_x=[[3.0], [2.0]], K_phi=[[1.0]],
                                    update_law=ConstantLaw([0.5], Box([0.0], [1.0])),
                                    allow_nonminimum_phase=True)   # a toy, not left-invertible


def _law_observer(law) -> ModifiedHighGainObserver:
    sys_ = lugre.system()
    return ModifiedHighGainObserver.from_design(sys_, lugre.designs()[0], law)


#: Θ = [0.1, 0.9] as a general convex set (its P a Python callable: no compiled projection).
DISK = ConvexSet(P=lambda t: (t[..., 0] - 0.5) ** 2 / 0.16 - 1.0,
                 grad_P=lambda t: 2.0 * (t - 0.5) / 0.16, interior_point=[0.5])

UNSUPPORTED = {
    "callable_g": (_callable_observer, "SymbolicPerturbation"),
    "convex_set": (lambda: _law_observer(ConstantLaw([0.5], DISK)),
                   "must be a Box, Ball or Ellipsoid"),
    "python_theta_star": (lambda: _law_observer(IntermittentInversion(
        lambda v, x, phi: phi, smooth_ramp(0.5, 1.0), 1.0, Box([0.05], [1.0]))), "ThetaStar"),
    "user_M": (lambda: _law_observer(GradientInversion(
        lugre.perturbation(), 1.0, Box([0.05], [1.0]), M=lambda v, x, th: np.ones((1, 1)))),
               "user M"),
    "other_weight": (lambda: _law_observer(IntermittentInversion(
        lugre.theta_star(), lambda v, x, phi: np.ones(np.shape(phi)[:-1]), 1.0,
        Box([0.05], [1.0]))), "smooth_ramp"),
}


@pytest.mark.parametrize("case", sorted(UNSUPPORTED))
def test_unsupported_parts_are_named(case):
    pytest.importorskip("numba")
    make, what = UNSUPPORTED[case]
    with pytest.raises(NotImplementedError, match=what):
        compile_observer(make(), dt=DT)


def test_non_diagonal_gamma_is_unsupported():
    pytest.importorskip("numba")
    law = GradientInversion(TOY_G, [[1.0, 0.2], [0.2, 1.0]], TOY_BOX)
    with pytest.raises(NotImplementedError, match="non-diagonal"):
        compile_observer(toy_observer(law), dt=DT)


def test_missing_numba_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "numba", None)       # `import numba` now fails
    with pytest.raises(MissingExtraError, match=r"pip install 'thetahat\[speed\]'"):
        compile_observer(lugre.observer(), dt=DT)


# --------------------------------------------------------------------------- θ* by SymPy
def test_from_perturbation_inverts_the_lugre_g():
    """SymPy writes θ* with exp(ω²/ω0²)·exp(−ω²/ω0²), NaN beyond |ω| ≈ 0.27 rad/s; the
    expanded form that update_laws now keeps is finite and equals the paper's θ*."""
    law = algebraic_from_perturbation(lugre.perturbation(), Gamma=1.0,
                                      parameter_set=Box([0.05], [1.0]))
    rng = np.random.default_rng(0)
    v = np.c_[rng.standard_normal(200), 4 * rng.standard_normal(200)]
    x = np.c_[4 * rng.standard_normal(200), 1e-3 * rng.standard_normal(200)]
    phi = lugre.perturbation().g(v, x, [0.28])
    est = law.theta_star(v, x, phi)
    assert np.all(np.isfinite(est))
    assert np.allclose(est, lugre.theta_star()(v, x, phi), rtol=1e-10, atol=1e-12)
    assert np.allclose(est, 0.28, rtol=1e-9)


# --------------------------------------------------------------------------- named arguments
def test_kernel_arrays_are_the_named_tuples_every_binding_uses():
    """P, P2, LP of the kernel are kernel_args' named tuples, each field the plan's or the
    law's array of that name (the NumPy binding builds the same tuples by keyword)."""
    from thetahat.estimation.observer.kernel_data import kernel_arrays, kernel_parts
    from thetahat.estimation.kernels.kernel_args import LawArrays, PlanArrays, SecondArrays
    obs = lugre.observer()
    plan = obs.plan(DT)
    P, P2, LP, flags = kernel_arrays(kernel_parts(obs), plan)
    assert (type(P), type(P2), type(LP)) == (PlanArrays, SecondArrays, LawArrays)
    for name in ("L", "Bv", "K_x", "KxC", "Phi1", "Phi2"):
        np.testing.assert_array_equal(getattr(P, name), getattr(plan, name)[0])
    for name in ("A", "B", "C", "E"):
        np.testing.assert_array_equal(getattr(P, name), getattr(plan, name))
    np.testing.assert_array_equal(P2.K_x, plan.second.K_x[0])
    np.testing.assert_array_equal(P2.Phi1, plan.second.Phi1[0])
    box = obs.update_law.parameter_set
    np.testing.assert_array_equal(LP.lower, box.lower)
    np.testing.assert_array_equal(LP.upper, box.upper)
    np.testing.assert_array_equal(LP.lam, np.diagonal(plan.Gamma[0]))   # Γ = V diag(λ) Vᵀ
    assert LP.Gamma is None and flags == (True, True)


# --------------------------------------------------------------------------- the default path
def test_runner_keeps_short_records_off_numba(monkeypatch):
    """numba's first compilation is slow: a record below its min_samples stays in Python when
    the C back end is off; compiled=False keeps every record there."""
    from thetahat.estimation.drive import COMPILE_MIN_SAMPLES, runner
    monkeypatch.setenv("THETAHAT_C", "0")
    obs = lugre.observer()
    assert runner(obs, np.arange(COMPILE_MIN_SAMPLES - 1) * DT) is obs
    assert runner(obs, np.arange(10 * COMPILE_MIN_SAMPLES) * DT, compiled=False) is obs


def test_runner_falls_back_with_a_one_line_note(monkeypatch):
    """An unsupported part, or numba missing: the observer itself, and a ThetahatWarning of
    one line naming why."""
    from thetahat.errors import ThetahatWarning
    from thetahat.estimation.drive import runner
    monkeypatch.setenv("THETAHAT_C", "0")     # the numba path (the C one: tests/codegen)
    t = np.arange(100) * DT
    obs = UNSUPPORTED["convex_set"][0]()
    # the reason named is the first that applies: numba missing (test-core), else the part
    why = ("must be a Box, Ball or Ellipsoid" if importlib.util.find_spec("numba")
           else "numba is not installed")
    with pytest.warns(ThetahatWarning, match=f"runs in Python: .*{why}") as rec:
        assert runner(obs, t, compiled=True) is obs
    assert "\n" not in str(rec[0].message)
    monkeypatch.setitem(sys.modules, "numba", None)       # `import numba` now fails
    obs = lugre.observer()
    with pytest.warns(ThetahatWarning, match=r"numba is not installed .*thetahat\[speed\]"):
        assert runner(obs, t, compiled=True) is obs


def test_an_observer_built_compiled_runs_on_the_kernel(motor, monkeypatch):
    """``compiled=True`` on the observer: its ``run`` goes through the one driver to numba's
    kernel (the C back end off), with the observer's hold, and agrees with the NumPy run."""
    from thetahat.estimation.observer import compiled as compiled_module
    data, obs, _ = motor
    monkeypatch.setenv("THETAHAT_C", "0")
    calls: list[str] = []
    kernel_run = compiled_module.CompiledObserver.run

    def spy(self, *args, **kwargs):
        calls.append(self.observer.hold)
        return kernel_run(self, *args, **kwargs)

    monkeypatch.setattr(compiled_module.CompiledObserver, "run", spy)
    fast = obs.with_run_options(hold="foh", compiled=True)
    assert_agree(fast.run(data.t, data.u, data.y),
                 obs.with_run_options(hold="foh").run(data.t, data.u, data.y))
    assert calls == ["foh"]
    with pytest.raises(OptionError, match="compiled"):
        obs.with_run_options(compiled="yes")


def test_row_blocks_give_the_whole_runs_numbers(motor, monkeypatch):
    """The kernel run a block of state rows at a time (ROW_BLOCK, their columns copied out
    by RecordRows) computes the one-block run's numbers bit for bit: each block starts from
    the state its predecessor ended with."""
    import thetahat.estimation.observer.compiled as compiled
    data, obs, fast = motor
    whole = fast.run(data.t, data.u, data.y)
    monkeypatch.setattr(compiled, "ROW_BLOCK", 97)
    cut = fast.run(data.t, data.u, data.y)
    for name in ("x_hat", "theta_hat", "phi_hat"):
        assert np.array_equal(getattr(cut, name), getattr(whole, name)), name
    assert np.array_equal(cut.diagnostics.x_hat_refined, whole.diagnostics.x_hat_refined)
    assert whole.diagnostics.x_hat_refined is not None and data.t.size > 10 * 97
