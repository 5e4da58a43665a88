"""The estimator protocol: the five estimators behind one ``init``/``step``/``run`` and one result.

Every estimator is checked for the same properties: it is an ``Estimator``; ``run`` is a loop
of ``step`` (each estimator's alignment of states with rows is documented on its ``step``);
a state can be handed to ``run`` as ``state0`` where the estimator supports continuing a
stream; θ̂ stays in Θ and the result's arrays are finite and read-only. The statistical
estimators run on the numpy kernels (``compiled=False``) so that no numba compilation enters
the default suite; the compiled observer is skipped without numba.
"""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

from thetahat import (EKFDiagnostics, EstimateResult, Estimator, GuardedDiagnostics,
                      MapDiagnostics, ObserverDiagnostics)
from thetahat.errors import OptionError
from thetahat.estimation.statistical.ekf import JointEKF
from thetahat.estimation.statistical.guarded import GuardedEstimator
from thetahat.estimation.statistical.mle import MapEstimator
from thetahat.models import lugre

P = lugre.LuGreParameters()
LO, HI = P.theta_lower, P.theta_upper
TH0 = 0.5
DT = 1e-3
#: σ handed to the statistical estimators: the same R in ``run`` and ``step`` (estimating σ
#: from the whole record in ``run`` and from the first samples in ``step`` differ by design).
SIGMA = 0.02
#: run vs a loop of step where both execute the same operations in the same order: only
#: the order of a few reductions may differ (observer, EKF, guarded without fits).
SAME_OPS = 1e-12
#: The MAP fits see the sample times as t − t₀ in ``run`` and as sums of dt in ``step``
#: (equal here, t₀ = 0: the measured difference is 0; for t₀ ≠ 0 spacings may differ in the
#: last bit); 1e-9 still catches a wrong fit window: one sample more in the window of the
#: fit at 51 samples moves θ̂ by 1.0e-2 on this record (measured).
MAP_TOL = 1e-9


def _compiled():
    pytest.importorskip("numba")
    from thetahat.estimation.observer.compiled import compile_observer
    return compile_observer(lugre.observer(), dt=DT)


FACTORIES = {
    "paper": lambda: lugre.observer(),
    "compiled": _compiled,
    "guarded": lambda: GuardedEstimator(stage1=lugre.observer(), system=lugre.system(),
                                        noise_std=SIGMA, use_fits=False, compiled=False),
    "mle": lambda: MapEstimator(system=lugre.system(), noise_std=SIGMA, compiled=False),
    "ekf": lambda: JointEKF(system=lugre.system(), noise_std=SIGMA, compiled=False),
}
DIAGNOSTICS = {"paper": ObserverDiagnostics, "compiled": ObserverDiagnostics,
               "guarded": GuardedDiagnostics, "mle": MapDiagnostics, "ekf": EKFDiagnostics}


@pytest.fixture(scope="module")
def data():
    return lugre.simulate(seed=1, t_end=0.25)


@pytest.fixture(scope="module", params=list(FACTORIES))
def case(request, data):
    est = FACTORIES[request.param]()
    res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[TH0]))
    return request.param, est, res


def _theta(name, est, state):
    """θ̂ read from a state (the observers' states are arrays laid out by ``layout``)."""
    if name in ("paper", "compiled"):
        obs = est if name == "paper" else est.observer
        return np.asarray(state)[obs.layout.theta]
    return state.theta_hat


def test_every_estimator_is_an_estimator(case):
    name, est, res = case
    assert isinstance(est, Estimator)
    assert isinstance(res, EstimateResult) and isinstance(res.diagnostics, DIAGNOSTICS[name])
    assert "EstimateResult(" in repr(res) and type(res.diagnostics).__name__ in repr(res)


def test_result_invariants(case, data):
    name, est, res = case
    N = data.t.size
    assert res.t.shape == (N,) and res.theta_hat.shape == (N, 1)
    assert res.x_hat.shape == (N, 2) and res.phi_hat.shape == (N, 1)
    assert res.skipped.shape == (N,) and not res.skipped.any()
    assert np.all((res.theta_hat >= LO) & (res.theta_hat <= HI))        # θ̂ ∈ Θ
    for a in (res.x_hat, res.theta_hat, res.phi_hat):
        assert np.all(np.isfinite(a)) and not a.flags.writeable
    # every method starts at θ̂₀: the observers' row 0 is the initial state, and the EKF's
    # first update leaves θ alone (its prior has no x–θ correlation)
    assert res.theta_hat[0, 0] == pytest.approx(TH0, abs=SAME_OPS)
    refined = res.x_hat_refined
    assert (refined is not None) == (name in ("paper", "compiled"))    # lugre has x̂₂


def test_run_is_a_loop_of_step(case, data):
    name, est, res = case
    n = 120 if name == "mle" else data.t.size - 1          # the MAP step refits: keep it short
    st = est.init(theta_hat0=[TH0])
    got = []
    for k in range(n):
        st = est.step(st, data.u[k], data.y[k], data.t[k + 1] - data.t[k])
        got.append(_theta(name, est, st)[0])
    got = np.array(got)
    # observers: the state after k + 1 steps is row k + 1 (the state at t[k + 1]); the
    # statistical estimators: the state after sample k is row k
    want = res.theta_hat[1:n + 1, 0] if name in ("paper", "compiled") else res.theta_hat[:n, 0]
    tol = MAP_TOL if name == "mle" else SAME_OPS
    np.testing.assert_allclose(got, want, rtol=0, atol=tol)
    if name == "mle":
        assert len(st.fits) >= 3                             # the window crossed several fits
        np.testing.assert_allclose(st.x_hat, res.x_hat[n - 1], rtol=0, atol=1e-7)


@pytest.mark.parametrize("name", ["paper", "compiled", "ekf"])
def test_a_stepped_state_continues_in_run(name, data):
    """state0 round trip: step the first M samples, run the rest from that state; the rows
    equal the whole record's."""
    est = FACTORIES[name]()
    full = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[TH0]))
    M = 100
    st = est.init(theta_hat0=[TH0])
    for k in range(M):
        st = est.step(st, data.u[k], data.y[k], data.t[k + 1] - data.t[k])
    rest = est.run(data.t[M:], data.u[M:], data.y[M:], state0=st)
    np.testing.assert_allclose(rest.theta_hat, full.theta_hat[M:], rtol=0, atol=SAME_OPS)
    np.testing.assert_allclose(rest.x_hat, full.x_hat[M:], rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["guarded", "mle"])
def test_run_refuses_a_stepped_state(name, data):
    """The fitting estimators' run starts an experiment; a stream continues with step."""
    est = FACTORIES[name]()
    st = est.step(est.init(theta_hat0=[TH0]), data.u[0], data.y[0], DT)
    with pytest.raises(OptionError, match="continue its stream with step"):
        est.run(data.t, data.u, data.y, state0=st)


@pytest.mark.parametrize("method", ["guarded", "mle", "ekf"])
def test_statistical_estimators_keep_the_protocol_strictly(method):
    """``run(t, u, y, *, state0, throw)`` and ``init(*, x_hat0, theta_hat0)``: the start of a
    run is its state, nothing beside it, and init's arguments are named. The estimators that
    fit (guarded, mle) also take ``fit_progress``, keyword-only and None by default: a report
    on the run, not an input of it."""
    est = FACTORIES[method]()
    run = inspect.signature(est.run).parameters
    extra = ["fit_progress"] if method in ("guarded", "mle") else []
    assert list(run) == ["t", "u", "y", "state0", "throw"] + extra
    kinds = [p.kind for p in run.values()][3:]
    assert kinds == [inspect.Parameter.KEYWORD_ONLY] * (2 + len(extra))
    assert all(run[n].default is None for n in extra)
    init = inspect.signature(est.init).parameters
    assert {n: p.kind for n, p in init.items()} == {
        "x_hat0": inspect.Parameter.KEYWORD_ONLY, "theta_hat0": inspect.Parameter.KEYWORD_ONLY}


def test_ekf_runs_from_a_state_of_ones_own(data):
    """A prior covariance of one's own is a state of one's own: θ's prior variance 1e-18
    keeps θ̂ at θ̂₀ (its update is ≤ 1e-9 × |θ̂₀| over the record), the default prior lets the
    data move it by more than 0.1."""
    ekf = FACTORIES["ekf"]()
    st = ekf.init(theta_hat0=[TH0])
    P0 = st.P.copy()
    P0[2, 2] = 1e-18
    held = ekf.run(data.t, data.u, data.y, state0=dataclasses.replace(st, P=P0))
    free = ekf.run(data.t, data.u, data.y, state0=st)
    assert np.max(np.abs(held.theta_hat[:, 0] - TH0)) < 1e-9 * TH0
    assert abs(free.theta_hat[-1, 0] - TH0) > 0.1


def test_ekf_step_waits_for_sigma_without_noise_std(data):
    """Without σ the streaming EKF makes no update before MIN_SAMPLES outputs (θ̂ stays θ̂₀),
    then updates with σ estimated from them."""
    from thetahat.estimation.statistical.noise_level import MIN_SAMPLES
    ekf = JointEKF(system=lugre.system(), compiled=False)
    st = ekf.init(theta_hat0=[TH0])
    for k in range(MIN_SAMPLES - 1):
        st = ekf.step(st, data.u[k], data.y[k], DT)
        assert st.noise_std is None and np.isnan(st.nis) and st.theta_hat[0] == TH0
    st = ekf.step(st, data.u[MIN_SAMPLES - 1], data.y[MIN_SAMPLES - 1], DT)
    assert st.noise_std is not None and np.isfinite(st.nis)


def test_compiled_step_refuses_another_dt(data):
    fast = _compiled()
    from thetahat.errors import DimensionError
    with pytest.raises(DimensionError, match="compiled observer steps dt"):
        fast.step(fast.init(theta_hat0=[TH0]), data.u[0], data.y[0], 2 * DT)


@pytest.mark.parametrize("method", ["paper", "guarded", "mle", "ekf"])
def test_cli_and_fleet_accept_every_method(method, tmp_path, monkeypatch, capsys):
    """``thetahat estimate --method m`` and ``estimate_many(method=m)`` run each method
    through the protocol and write θ̂ ∈ Θ; both agree with run_estimator."""
    import thetahat.estimation.statistical.plant_kernel as mk
    monkeypatch.setattr(mk, "have_numba", lambda: False)     # numpy kernels: no compilation
    from pathlib import Path

    from thetahat.cli import main
    from thetahat.fleet import estimate_many
    from thetahat.modelfile import load_model, run_estimator

    model = Path(__file__).resolve().parents[2] / "examples" / "lugre.toml"
    data = lugre.simulate(seed=2, t_end=0.2)
    csv = tmp_path / "data" / "m1.csv"
    csv.parent.mkdir()
    np.savetxt(csv, np.column_stack([data.t, data.u, data.y]), delimiter=",",
               header="t,u,y", comments="", fmt="%.17g")
    out = tmp_path / "est.csv"
    assert main(["estimate", str(model), str(csv), "-o", str(out), "--method", method,
                 "--no-progress"]) == 0
    header = out.read_text().splitlines()[0].split(",")
    theta = np.loadtxt(out, delimiter=",", skiprows=1)[:, header.index("theta_hat_theta")]
    spec = load_model(model)
    lo, hi = spec.system.parameter_set.lower[0], spec.system.parameter_set.upper[0]
    assert np.all((theta >= lo) & (theta <= hi))
    ref = run_estimator(spec, data.t, data.u, data.y, method=method)
    assert theta[-1] == pytest.approx(float(ref.theta_hat[-1, 0]), rel=1e-12)
    fleet = estimate_many(model, csv.parent, method=method, progress=False)
    assert fleet.n_ok == 1
    assert fleet.rows[0]["theta_hat_theta"] == pytest.approx(theta[-1], rel=1e-9)
    capsys.readouterr()


def test_the_protocol_page_example_runs(capsys):
    """docs/estimator-protocol.md's example runs as written and prints each method's θ̂."""
    from pathlib import Path
    page = (Path(__file__).resolve().parents[2] / "docs" / "estimator-protocol.md").read_text()
    code = page.split("```python\n", 1)[1].split("```", 1)[0]
    exec(compile(code, "estimator-protocol.md", "exec"), {})
    out = capsys.readouterr().out
    for name in ("paper", "guarded", "mle", "ekf", "EKF streamed"):
        assert name in out
