"""The conformance matrix: every back end of the observer step agrees with the reference.

Back ends: a loop of ``ModifiedHighGainObserver.step`` (ZOH only), ``run_batch`` (row 0 of a
batch of two records), the numba kernel of ``compile_observer`` (optional extra ``speed``;
a Box or a Ball Θ; every hold and NaN policy) and the generated C of
``thetahat.codegen.generate_c`` (a Box Θ; every law, hold, NaN policy and second observer; all configurations compiled into one
library, skipped without a C compiler); the combinations a back end does not offer are left
out of the matrix, see ``supported``. The reference is
``ModifiedHighGainObserver.run``. The matrix crosses the update law (Propositions 1–4 and a
held θ), the parameter set (Box; Ball, whose projection takes the generic path), the second
observer of Sec. VI (none, g on its estimates, g on y), the hold (ZOH, FOH) and the NaN policy
(clean data with "raise"; a gap of NaN with "skip"), and checks the error behaviour: the same
error type, with the same message, at the same sample, when the data break the NaN policy and
when the observer diverges: by construction (error dynamics unstable by a wide margin, on every
numpy), and at ε = 0.001 at 1 kHz (where the record happens to cross the bound). A back end
that is absent (numba not installed) skips.
"""

from __future__ import annotations

import importlib.util
import itertools
import re
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

from thetahat.errors import NonFiniteError
from thetahat.estimation.observer.batch_run import run_batch
from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.estimation.observer.plan import linear_part
from thetahat.estimation.observer.redesign import SecondObserver
from thetahat.estimation.observer.step import DIVERGENCE_BOUND
from thetahat.estimation.observer.laws import (AlgebraicInversion, ConstantLaw, GradientInversion,
                                             IntermittentInversion, UpdateLaw, smooth_ramp)
from thetahat.model.paramset import Ball, Box
from thetahat.models import lugre

#: Agreement of a back end with the reference, relative to each column's largest |value|. The
#: step loop runs the very same operations as ``run`` (measured: bit-identical); the batch
#: sums the small products in another order and the kernel uses its own LU and scalar g:
#: rounding only, measured below 1e-12 over these 300 steps. 1e-9 leaves a 1000× margin and
#: is what compile_observer promises.
AGREE_RTOL = 1e-9
DT = 1e-3
T_END = 0.3
#: A gap of missing samples (NaN in y) for nan_policy="skip": long enough for the prediction to
#: matter (θ̂ frozen, z constant), short enough for the observer to recover.
GAP = slice(120, 140)
#: ε at which the discretised observer diverges at 1 kHz (K ~ ε⁻³ ~ 1e9; Sec. VIII notes): on
#: the record of seed 1000 the state leaves every bound at t ≈ 2.54 s (the sweep/tune tests'
#: case, where the old ``run`` and ``run_batch`` disagreed).
EPS_DIVERGING = 0.001
DIVERGING_SEED, DIVERGING_T_END = 1000, 2.6
#: Eigenvalues (1/s) placed for L = [[A − K_x C, E], [−K_φ C, 0]], the linear part of the
#: observer's error dynamics: unstable on purpose. With the exact exponential step the linear
#: part alone grows by e^(λ·dt) = e^0.6 … e^1 per 1 ms sample (g, linear in η̂ with a large
#: coefficient σ0|y|/θ̂, adds to it: the norm gains 1.5–2 decades per sample near the end), so
#: the state crosses DIVERGENCE_BOUND about 140 samples into the record with a margin no
#: rounding difference between numpy versions or back ends can bridge (checked below).
UNSTABLE_POLES = (600.0, 800.0, 1000.0)
#: The state before the crossing must lie this far (in decades) below DIVERGENCE_BOUND, and the
#: crossing step jump this far above it: rounding (1e-12 relative at most) moves log10|s| by
#: ~1e-13, so 0.05 decades (12 %) leaves a margin of 10¹¹.
CROSSING_MARGIN_DECADES = 0.05

LAWS = ("constant", "algebraic", "intermittent", "gradient")
SETS = ("box", "ball")
SECONDS = ("none", "estimates", "y")
HOLDS = ("zoh", "foh")
POLICIES = ("raise", "skip")


def parameter_set(kind: str):
    return Box([0.05], [1.0]) if kind == "box" else Ball([0.525], 0.475)


def make_law(kind: str, theta_set):
    ts = lugre.theta_star()
    if kind == "constant":
        return ConstantLaw([0.4], theta_set)
    if kind == "algebraic":
        return AlgebraicInversion(ts, 2.0, theta_set, on_invalid="freeze")
    if kind == "intermittent":
        return IntermittentInversion(ts, smooth_ramp(*lugre.EXCITATION), 2.0, theta_set,
                                     on_invalid="freeze")
    return GradientInversion(lugre.perturbation(), 50.0, theta_set)


def make_observer(law: str, theta_set: str, second: str, policy: str,
                  eps: float = 1.0) -> ModifiedHighGainObserver:
    system = lugre.system()
    d1, d2 = lugre.designs(eps)
    obs2 = None if second == "none" else SecondObserver(
        system=system, K_x=d2.K, g_on_estimates=second == "estimates")
    return ModifiedHighGainObserver(system=system, K_x=d1.K_x, K_phi=d1.K_phi,
                                    update_law=make_law(law, parameter_set(theta_set)),
                                    second=obs2, nan_policy=policy)


@cache
def records(policy: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """t, U (2, N, 1), Y (2, N, 1): two noisy records; with "skip" each has a NaN gap."""
    runs = [lugre.simulate(seed=s, t_end=T_END) for s in (0, 1)]
    U = np.stack([r.u for r in runs])
    Y = np.stack([r.y for r in runs])
    if policy == "skip":
        Y[0, GAP] = np.nan
        Y[1, GAP.start + 7:GAP.stop + 7] = np.nan        # another gap: rows predict apart
    return runs[0].t, U, Y


@cache
def diverging_records() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    run = lugre.simulate(seed=DIVERGING_SEED, t_end=DIVERGING_T_END)
    return run.t, run.u[None], run.y[None]


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    scale = np.maximum(np.max(np.abs(b), axis=0), np.finfo(float).tiny)
    return float(np.max(np.abs(a - b) / scale))


def compiled(obs: ModifiedHighGainObserver):
    pytest.importorskip("numba")
    from thetahat.estimation.observer.compiled import compile_observer
    return compile_observer(obs, dt=DT)


def supported(law: str, theta_set: str, second: str, hold: str, policy: str,
              backend: str) -> bool:
    """The combinations a back end offers: ``step`` is the ZOH; the C needs a Box Θ (it
    refuses the others with UnsupportedError, and the runner takes numba: see
    test_convex_theta.py). g on y is crossed with the Box and the moving laws only (suite
    time)."""
    if second == "y" and (theta_set == "ball" or law == "constant"):
        return False
    if backend == "step":
        return hold == "zoh"
    if backend == "compiled" and theta_set == "ball":
        return law != "constant"     # a held θ̂ never leaves Θ: a kernel compiled for nothing
    if backend == "c":
        return theta_set == "box"
    return True


BACK_ENDS = ("step", "batch", "compiled", "c")
CASES = [case for case in itertools.product(LAWS, SETS, SECONDS, HOLDS, POLICIES, BACK_ENDS)
         if supported(*case)]
#: The generated C's configurations: (law, second, hold, policy), compiled into one library.
C_CONFIGS = sorted({(law, second, hold, policy) for law, _, second, hold, policy, backend
                    in CASES if backend == "c"})


@pytest.fixture(scope="module")
def c_observers(tmp_path_factory):
    """The generated C (thetahat.codegen) of every configuration the matrix runs in C, built
    with the acceptance's flags into one shared library (one compiler run, ≈ 10 s)."""
    from thetahat.codegen import generate_c
    from thetahat.codegen.loader import CObserver, build_many, find_compiler

    if find_compiler() is None:
        pytest.skip("no C compiler (cc or $CC)")
    codes = {config: generate_c(make_observer(config[0], "box", config[1], config[3])
                                .with_run_options(hold=config[2]), dt=DT, name=f"obs{i}")
             for i, config in enumerate(C_CONFIGS)}
    lib = build_many(list(codes.values()), tmp_path_factory.mktemp("c"))
    return {config: CObserver(code, lib) for config, code in codes.items()}


def step_states(obs: ModifiedHighGainObserver, t, U, Y) -> np.ndarray:
    s = obs.init()
    S = [s]
    for i in range(t.size - 1):
        s = obs.step(s, U[i], Y[i], float(t[i + 1] - t[i]))
        S.append(s)
    return np.array(S)


def back_end(name: str, obs, hold: str, policy: str, t, U, Y, c_obs=None):
    """(x̂, θ̂, x̂₂) of record 0 by one back end (``c_obs``: the generated C's)."""
    lay = obs.layout
    if name == "step":
        S = step_states(obs, t, U[0], Y[0])
        return S[:, lay.x], S[:, lay.theta], S[:, lay.x2] if lay.second else None
    if name == "c":
        res = c_obs.run(U[0], Y[0])
        assert res.status == 0, (res.status, res.index)
        return res.x_hat, res.theta_hat, res.x_hat_refined
    if name == "batch":
        res = run_batch(obs, t, U, Y)[0]
    else:
        res = compiled(obs).run(t, U[0], Y[0])
    return res.x_hat, res.theta_hat, res.x_hat_refined


@pytest.mark.parametrize("law, theta_set, second, hold, policy, backend", CASES,
                         ids=["-".join(case) for case in CASES])
def test_back_end_agrees_with_reference(law, theta_set, second, hold, policy, backend,
                                        request):
    obs = make_observer(law, theta_set, second, policy).with_run_options(hold=hold)
    t, U, Y = records(policy)
    ref = obs.run(t, U[0], Y[0])
    c_obs = (request.getfixturevalue("c_observers")[(law, second, hold, policy)]
             if backend == "c" else None)
    x, th, x2 = back_end(backend, obs, hold, policy, t, U, Y, c_obs)
    assert rel_err(x, ref.x_hat) <= AGREE_RTOL
    assert rel_err(th, ref.theta_hat) <= AGREE_RTOL
    assert (x2 is None) == (ref.x_hat_refined is None)
    if x2 is not None:
        assert rel_err(x2, ref.x_hat_refined) <= AGREE_RTOL
    assert parameter_set(theta_set).contains(th, tol=1e-12).all()      # θ̂ never leaves Θ
    if law != "constant":
        assert np.ptp(ref.theta_hat) > 1e-3          # the law moved θ̂: the case tests it


def errors_of_all_back_ends(obs, t, U, Y) -> dict[str, BaseException]:
    """The exception each present back end raises on record 0 (ZOH)."""
    out: dict[str, BaseException] = {}
    calls = {"run": lambda: obs.run(t, U[0], Y[0]),
             "step": lambda: step_states(obs, t, U[0], Y[0]),
             "batch": lambda: run_batch(obs, t, U[:1], Y[:1])}
    try:
        import numba  # noqa: F401
        from thetahat.estimation.observer.compiled import compile_observer
        fast = compile_observer(obs, dt=DT)
        calls["compiled"] = lambda: fast.run(t, U[0], Y[0])
    except (ImportError, NotImplementedError):
        pass
    for name, call in calls.items():
        with pytest.raises(Exception) as info:       # noqa: PT011 - compared below
            call()
        out[name] = info.value
    return out


def unstable_observer() -> ModifiedHighGainObserver:
    """The LuGre observer of the matrix (IntermittentInversion, Box, second observer on its
    estimates), with K_x, K_φ placing the eigenvalues of L at UNSTABLE_POLES: it diverges by
    construction."""
    system = lugre.system()
    A, C, E = system.A, system.C, system.E
    n, k = E.shape
    A_ext = np.block([[A, E], [np.zeros((k, n + k))]])
    C_ext = np.hstack([C, np.zeros((C.shape[0], k))])
    K = scipy.signal.place_poles(A_ext.T, C_ext.T, np.array(UNSTABLE_POLES)).gain_matrix.T
    eig = np.sort(np.linalg.eigvals(linear_part(A, C, E, K[:n], K[n:])).real)
    np.testing.assert_allclose(eig, UNSTABLE_POLES, rtol=1e-6)   # the placement took
    _, d2 = lugre.designs(1.0)
    return ModifiedHighGainObserver(
        system=system, K_x=K[:n], K_phi=K[n:],
        update_law=make_law("intermittent", parameter_set("box")),
        second=SecondObserver(system=system, K_x=d2.K, g_on_estimates=True))


def assert_reported_identically(errs: dict[str, BaseException]) -> int:
    """Every back end raised NonFiniteError naming the same step, in the same words; that step."""
    assert {type(e) for e in errs.values()} == {NonFiniteError}, errs
    where = {name: re.search(r"t\[(\d+)\]", str(e)) for name, e in errs.items()}
    steps = {name: int(m.group(1)) for name, m in where.items() if m}
    assert set(steps) == set(errs) - {"step"}             # step() says "in this step"
    assert len(set(steps.values())) == 1, steps
    messages = {str(e).replace("of run 0 ", "") for name, e in errs.items() if name != "step"}
    assert len(messages) == 1, messages                    # word for word
    assert "diverged" in str(errs["step"])
    return steps["run"]


def test_divergence_by_construction_is_reported_identically():
    """Unstable error dynamics: every back end present raises NonFiniteError at the same
    sample, with the same message, on every numpy; the step loop stops at that sample too."""
    obs = unstable_observer()
    t, U, Y = records("raise")
    errs = errors_of_all_back_ends(obs, t, U, Y)
    if importlib.util.find_spec("numba") is not None:
        assert "compiled" in errs                          # the kernel took this observer
    with pytest.raises(Exception) as info:                 # noqa: PT011 - compared below
        run_batch(obs, t, U[[0, 0]], Y[[0, 0]])            # the batch path proper (B = 2)
    errs["batch of two"] = info.value
    i = assert_reported_identically(errs)
    s = obs.init()
    log_norms = []
    with pytest.raises(NonFiniteError, match="diverged"):
        for j in range(t.size):
            s = obs.step(s, U[0, j], Y[0, j], DT)
            log_norms.append(np.log10(np.linalg.norm(s)))
    assert j == i                                          # the very same step
    # the premise: the crossing is far from a knife-edge (and well inside the record)
    assert np.log10(DIVERGENCE_BOUND) - log_norms[-1] >= CROSSING_MARGIN_DECADES, log_norms[-3:]
    assert log_norms[-1] - log_norms[-2] >= 2 * CROSSING_MARGIN_DECADES   # still growing fast
    assert 10 < i < t.size - 10


def test_generated_c_refuses_the_diverging_step_at_the_same_sample(tmp_path):
    """The generated C reports the divergence by construction as the status ``diverged`` at
    the sample where every Python back end raises, and stops there."""
    from thetahat.codegen import generate_c
    from thetahat.codegen.loader import STATUS, find_compiler, load_c

    if find_compiler() is None:
        pytest.skip("no C compiler (cc or $CC)")
    obs = unstable_observer()
    t, U, Y = records("raise")
    with pytest.raises(NonFiniteError, match=r"t\[(\d+)\]") as info:
        obs.run(t, U[0], Y[0])
    i = int(re.search(r"t\[(\d+)\]", str(info.value)).group(1))
    res = load_c(generate_c(obs, dt=DT, name="unstable"), tmp_path).run(U[0], Y[0])
    assert (res.status, res.index) == (STATUS["diverged"], i)


def require_divergence(obs, t, U, Y) -> None:
    """Skip unless the reference run crosses the divergence bound on this platform.

    Whether ε = 0.001 crosses DIVERGENCE_BOUND within the record depends on the last bits of
    the arithmetic (numpy 2.4: at t[1663]; numpy 1.26: it peaks below the bound), so the
    comparison of the back ends' errors is made only where the reference diverges.
    """
    try:
        obs.run(t, U[0], Y[0])
    except NonFiniteError:
        return
    pytest.skip("the ε = 0.001 record does not reach the divergence bound with this numpy")


def test_divergence_is_reported_identically():
    """ε = 0.001 at 1 kHz: every back end raises NonFiniteError at the same step."""
    obs = make_observer("intermittent", "box", "estimates", "raise", eps=EPS_DIVERGING)
    t, U, Y = diverging_records()
    require_divergence(obs, t, U, Y)
    assert_reported_identically(errors_of_all_back_ends(obs, t, U, Y))


def test_divergence_step_index_agrees_with_the_step_loop():
    obs = make_observer("intermittent", "box", "none", "raise", eps=EPS_DIVERGING)
    t, U, Y = diverging_records()
    require_divergence(obs, t, U, Y)
    with pytest.raises(NonFiniteError, match=r"t\[(\d+)\]") as info:
        obs.run(t, U[0], Y[0])
    i = int(re.search(r"t\[(\d+)\]", str(info.value)).group(1))
    s = obs.init()
    j = 0
    with pytest.raises(NonFiniteError, match="diverged"):
        for j in range(t.size):
            s = obs.step(s, U[0, j], Y[0, j], DT)
    # the same step, up to one: the state grows by orders of magnitude per step near the bound,
    # so only a last-bit difference between the vector and the batch arithmetic (numpy
    # versions differ there) can move the crossing of DIVERGENCE_BOUND by one sample
    assert abs(j - i) <= 1, (i, j)


def test_generated_c_refuses_nan_under_raise_policy_where_python_does(c_observers):
    """The C of a "raise" configuration stops with ERR_MISSING at the first NaN sample, where
    every Python back end raises (and its "skip" twin runs through)."""
    from thetahat.codegen.loader import STATUS

    t, U, Y = records("skip")                                  # holds NaN gaps
    res = c_observers[("intermittent", "estimates", "zoh", "raise")].run(U[0], Y[0])
    assert (res.status, res.index) == (STATUS["missing"], GAP.start)
    assert c_observers[("intermittent", "estimates", "zoh", "skip")].run(U[0], Y[0]).status == 0


def test_nan_under_raise_policy_is_reported_identically():
    obs = make_observer("intermittent", "box", "estimates", "raise")
    t, U, Y = records("skip")                                  # holds NaN gaps
    errs = errors_of_all_back_ends(obs, t, U, Y)
    assert {type(e) for e in errs.values()} == {NonFiniteError}, errs
    for e in errs.values():
        assert "nan_policy='raise'" in str(e)


# --------------------------------------------------------------------------- a law with a state
class HeldTarget(UpdateLaw):
    """θ̂ relaxes at rate γ towards the last valid θ*, which the law holds in its own state."""

    def __init__(self, gamma: float, theta_set) -> None:
        self.gamma, self.theta_set, self.theta_star = gamma, theta_set, lugre.theta_star()

    @property
    def parameter_set(self):
        return self.theta_set

    @property
    def state_size(self) -> int:
        return 1

    def init_state(self, theta_hat0):
        return np.array(theta_hat0, dtype=float)

    def rate(self, v, x_hat, phi_hat, theta_hat):
        raise NotImplementedError("defined by its discrete step only")

    def advance(self, v, x_hat, phi_hat, theta_hat, state, dt, *, Gamma=None):
        ts = self.theta_star(v, x_hat, phi_hat)
        valid = np.isfinite(ts).all(axis=-1, keepdims=True) & (np.abs(phi_hat) >= 1.0)
        held = np.where(valid, np.clip(ts, -10.0, 10.0), state)
        nxt = held + np.exp(-self.gamma * dt) * (theta_hat - held)
        return self.theta_set.nearest(nxt), held


def test_law_state_lives_in_the_observer_state_and_every_back_end_propagates_it():
    system = lugre.system()
    d1, _ = lugre.designs()
    obs = ModifiedHighGainObserver(system=system, K_x=d1.K_x, K_phi=d1.K_phi,
                                   update_law=HeldTarget(2.0, Box([0.05], [1.0])))
    lay = obs.layout
    assert lay.law_size == 1 and obs.state_size == lay.law.stop == 5
    t, U, Y = records("raise")
    s0 = obs.init(theta_hat0=[0.5])
    assert s0[lay.law].tolist() == [0.5]                   # init_state(θ̂₀)
    S_step = step_states(obs, t, U[0], Y[0])
    held = S_step[:, lay.law]
    assert np.ptp(held) > 0.05                            # the state moves (θ* was valid)
    res = obs.run(t, U[0], Y[0])
    assert rel_err(res.theta_hat, S_step[:, lay.theta]) == 0.0
    batch = run_batch(obs, t, U, Y)[0]
    assert rel_err(batch.theta_hat, res.theta_hat) <= AGREE_RTOL
    pytest.importorskip("numba")
    from thetahat.estimation.observer.compiled import compile_observer
    with pytest.raises(NotImplementedError, match="law with a state"):
        compile_observer(obs, dt=DT)


#: float C against the double reference, relative to each column's largest |value|: measured
#: 1.2e-6 in θ̂ over the matrix's 300 steps (single precision: ε = 6e-8, the observer
#: contracts); the C tests' bound, with a margin of 80.
C_FLOAT_RTOL = 1e-4


@pytest.mark.slow
def test_generated_c_in_float_follows_the_reference(tmp_path):
    """Every C configuration of the matrix, generated in float (one library, ≈ 20 s)."""
    from thetahat.codegen import generate_c
    from thetahat.codegen.loader import CObserver, build_many, find_compiler

    if find_compiler() is None:
        pytest.skip("no C compiler (cc or $CC)")
    codes = {config: generate_c(make_observer(config[0], "box", config[1], config[3])
                                .with_run_options(hold=config[2]), dt=DT, name=f"f{i}",
                                real="float")
             for i, config in enumerate(C_CONFIGS)}
    lib = build_many(list(codes.values()), tmp_path)
    for (law, second, hold, policy), code in codes.items():
        obs = make_observer(law, "box", second, policy)
        t, U, Y = records(policy)
        ref = obs.with_run_options(hold=hold).run(t, U[0], Y[0])
        res = CObserver(code, lib).run(U[0], Y[0])
        assert res.status == 0
        assert rel_err(res.theta_hat.astype(float), ref.theta_hat) <= C_FLOAT_RTOL
        assert rel_err(res.x_hat.astype(float), ref.x_hat) <= C_FLOAT_RTOL
        assert Box([0.05], [1.0]).contains(res.theta_hat.astype(float), tol=0.0).all()
# --------------------------------------------------------------------------- model files
#: The example model files whose observers the kernel must take: θ* given in the file (lugre,
#: prop1, prop2) and the gradient law of a MIMO file (two_inertia).
MODEL_FILES = ("lugre", "prop1", "prop2", "two_inertia")
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: RK4 substeps per 1 ms sample of the plant simulation of the files without a [scenario]:
#: 0.1 ms resolves their fastest plant mode (two_inertia's shaft, ~82 rad/s) 100-fold.
SUBSTEPS = 10


def _plant_record(spec, t_end: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, u, y) of the file's plant at 1 kHz, θ inside Θ, by RK4 on a 0.1 ms grid."""
    s = spec.system
    rng = np.random.default_rng(seed)
    box = s.parameter_set
    theta = box.lower + 0.7 * (box.upper - box.lower)
    h = 1e-3 / SUBSTEPS

    def u_of(t: float) -> np.ndarray:
        return np.full(s.m, 10.0 * np.sin(2 * np.pi * 1.5 * t) + 5.0 * np.sin(2 * np.pi * 4.1 * t))

    def f(t: float, x: np.ndarray) -> np.ndarray:
        u = u_of(t)
        phi = np.asarray(s.perturbation.g(np.concatenate([u, s.C @ x]), x, theta))
        return s.A @ x + s.B @ u + s.E @ phi

    N = int(round(t_end / 1e-3)) + 1
    x = np.zeros(s.n)
    t = np.arange(N) * 1e-3
    Y = np.empty((N, s.r))
    for i in range(N):
        Y[i] = s.C @ x
        for j in range(SUBSTEPS):
            tt = t[i] + j * h
            k1 = f(tt, x)
            k2 = f(tt + h / 2, x + h / 2 * k1)
            k3 = f(tt + h / 2, x + h / 2 * k2)
            k4 = f(tt + h, x + h * k3)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    U = np.array([u_of(tt) for tt in t])
    return t, U, Y + 1e-3 * rng.standard_normal(Y.shape)


def _user_m_observer() -> ModifiedHighGainObserver:
    """two_inertia's Python model: the gradient law with a user's M (LoadSpeedWeight, which
    carries its SymPy form), nan_policy="skip"."""
    from thetahat.models import two_inertia
    obs = two_inertia.observer()
    return ModifiedHighGainObserver.from_design(obs.system, two_inertia.design(),
                                                obs.update_law, nan_policy="skip")


@cache
def model_file_case(name: str):
    """(spec, observer with nan_policy="skip", t, u, y): the record irregular (a sixth of the
    samples dropped, so steps of 1, 2 and 3 ms) and with a NaN gap."""
    from thetahat.modelfile import build_observer, load_model
    spec = load_model(EXAMPLES / f"{name}.toml")
    if name == "lugre":
        run = lugre.simulate(seed=5, t_end=0.4)
        t, u, y = run.t, run.u.reshape(run.t.size, -1), run.y.reshape(run.t.size, -1)
    else:
        t, u, y = _plant_record(spec, 0.4, seed=5)
    keep = np.random.default_rng(6).uniform(size=t.size) > 1 / 6
    keep[[0, -1]] = True
    t, u, y = t[keep], u[keep], y[keep].copy()
    y[t.size // 2:t.size // 2 + 15] = np.nan
    return spec, build_observer(spec, nan_policy="skip"), t, u, y


@pytest.mark.parametrize("hold", HOLDS)
def test_kernel_source_runs_a_user_m(hold):
    """The gradient law with a user's M (two_inertia's LoadSpeedWeight, printed from its
    SymPy form): the kernel's text, run as Python, equals the Python run."""
    spec, _, t, u, y = model_file_case("two_inertia")
    obs = _user_m_observer()
    s0 = obs.init(theta_hat0=spec.estimator.theta_hat0)
    ref = obs.with_run_options(hold=hold).run(t, u, y, state0=s0)
    S = _emitted_run(obs, t, u, y, hold, s0)
    lay = obs.layout
    assert rel_err(S[:, lay.x], ref.x_hat) <= AGREE_RTOL
    assert rel_err(S[:, lay.theta], ref.theta_hat) <= AGREE_RTOL
    assert np.ptp(ref.theta_hat, axis=0).min() > 1e-3    # both parameters moved


def _emitted_run(obs: ModifiedHighGainObserver, t, u, y, hold: str, s0) -> np.ndarray:
    """The states of the kernel's source run as plain Python (no numba: the kernel's text,
    with every argument the compiled observer passes)."""
    from thetahat.estimation.observer.kernel_data import (kernel_arrays, kernel_parts,
                                                          kernel_work, phi_table)
    from thetahat.estimation.kernels.kernel_cache import load_module
    from thetahat.estimation.observer.kernel_source import LAWS, kernel_source
    parts = kernel_parts(obs)
    ts = parts.theta_star
    source = kernel_source(parts.perturbation, None if ts is None else ts.expr,
                           None if ts is None else ts.arguments, LAWS[parts.code], numba=False,
                           M=parts.M, ellipsoid=parts.ellipsoid)
    kernel = load_module(source, "thetahat_kernel_test")    # the printed text, no numba
    t_, dts, U3, Y3, ok3 = obs.check_records(t, u, y)
    plan = obs.plan(float(dts[0]))
    P, P2, LP, flags = kernel_arrays(parts, plan)
    W, rows = kernel_work(plan.layout)
    plan_of, PH = phi_table(obs, dts, ok3[0, :-1])
    S, PHI = np.empty((t_.size, obs.state_size)), np.empty((t_.size, plan.layout.k))
    with np.errstate(all="ignore"):     # numba's error_model='numpy': NaN, not a warning
        status, _ = kernel.kernel_run(s0, U3[0], Y3[0], dts, ok3[0], plan_of, PH, P, P2, LP,
                                      *flags, hold == "foh", W, rows, S, PHI)
    assert status == 0
    return S


@pytest.mark.parametrize("hold", HOLDS)
@pytest.mark.parametrize("name", MODEL_FILES)
def test_kernel_source_runs_model_file_observers(name, hold):
    """The kernel's text, run as Python, on each example file's observer: θ* from the file,
    irregular steps and a gap of missing samples, both holds — equal to the Python run."""
    spec, obs, t, u, y = model_file_case(name)
    s0 = obs.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    ref = obs.with_run_options(hold=hold).run(t, u, y, state0=s0)
    S = _emitted_run(obs, t, u, y, hold, s0)
    lay = obs.layout
    assert rel_err(S[:, lay.x], ref.x_hat) <= AGREE_RTOL
    assert rel_err(S[:, lay.theta], ref.theta_hat) <= AGREE_RTOL
    assert spec.system.parameter_set.contains(S[:, lay.theta], tol=1e-12).all()
    assert np.ptp(ref.theta_hat, axis=0).max() > 1e-3    # the law moved θ̂: the case tests it


@pytest.mark.slow
@pytest.mark.parametrize("name", MODEL_FILES)
def test_run_estimator_compiled_agrees_on_model_files(name):
    """``run_estimator`` on the numba kernel equals its Python run (each file's first
    compilation: 20–40 s, hence slow), both holds, irregular steps and a gap."""
    pytest.importorskip("numba")
    from thetahat.modelfile import run_estimator
    spec, _, t, u, y = model_file_case(name)
    for hold in HOLDS:
        fast, ref = (run_estimator(spec, t, u, y, hold=hold, nan_policy="skip", compiled=c)
                     for c in (True, False))
        for field in ("x_hat", "phi_hat", "theta_hat"):
            assert rel_err(getattr(fast, field), getattr(ref, field)) <= AGREE_RTOL, field
        assert np.array_equal(fast.skipped, ref.skipped)


@pytest.mark.slow
def test_compiled_user_m_agrees():
    """The numba kernel with a user's M (its first compilation: slow) equals the Python run."""
    spec, _, t, u, y = model_file_case("two_inertia")
    for hold in HOLDS:
        obs = _user_m_observer().with_run_options(hold=hold)
        ref = obs.run(t, u, y)
        res = compiled(obs).run(t, u, y)
        assert rel_err(res.x_hat, ref.x_hat) <= AGREE_RTOL
        assert rel_err(res.theta_hat, ref.theta_hat) <= AGREE_RTOL
