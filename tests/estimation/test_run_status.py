"""One failure behaviour for the statistical estimators (thetahat.estimation.status).

A run that cannot go on stops with a Status: ``throw=True`` raises
``status_error(status, message)``; ``throw=False`` returns the result with that status, the
same message, ``failed_at``, NaN rows from ``failed_at`` on and the run's own finite rows
before. Checked on shipped models besides LuGre (examples/*.toml), each failure provoked by an
absurd input:

* a noise level of 1e-12 where the record's is 1e-2 … 1e-4: the filter trusts every sample
  beyond what the model can follow and its state overflows within a few samples (the EKF), or
  the filter between two fits does, or the process-noise fit's filter is not finite (mle);
* a noise level of 1e-300: 1/σ² overflows, so the first fit's information matrix is not a
  number and cannot be decomposed (SINGULAR);
* outputs scaled by 1e100: stage 1's (the paper's observer's) state overflows — the guarded
  estimator says so and goes on with stage 2 alone (the paper's guarantee gone), whatever
  stage 1 is, unless its own estimates overflow too.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from thetahat import GuardedEstimator, JointEKF, MapEstimator
from thetahat.errors import NonFiniteError, ThetahatWarning
from thetahat.estimation.statistical.ekf_kernels import NIS_MODEL_ERROR
from thetahat.estimation.statistical.stage2_set import stage2_set
from thetahat.estimation.status import Status
from thetahat.modelfile import build_observer, load_model, simulate_model

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: Samples of each record: every provoked failure below happens within its first 50.
N = 200
#: The absurd noise levels (see the module docstring).
TINY_SIGMA = 1e-12
#: The stage-2 filters' sub-steps in the divergence cases: one per sample (plus the stability
#: choice), the sampled-data map these records' divergences were provoked with. With the
#: sub-steps chosen for accuracy at σ = 1e-12 (64: the model exact to a tenth of a standard
#: error) the prop3 and actuator filters stay finite — inconsistent (mean NIS 1e20), not
#: diverged — and the cases would provoke nothing.
COARSE = 1
UNDERFLOWING_SIGMA = 1e-300
#: The absurd output scale that overflows the observer's state.
HUGE_SCALE = 1e100


def _record(name: str):
    spec = load_model(EXAMPLES / f"{name}.toml")
    d = simulate_model(spec, 0, t_end=(N - 1) / spec.scenario.fs)
    return spec, d.t[:N], np.asarray(d.u)[:N], np.asarray(d.y)[:N]


def _stopped_as_said(res, status: Status) -> int:
    """The result of a run that stopped: its status, a message, NaN rows from failed_at on in
    every estimate and per-sample diagnostic; finite estimates before (a standard deviation
    may be inf there: a direction the data so far do not determine); returns failed_at."""
    k = res.failed_at
    assert res.status == status and not res.ok and res.message
    assert isinstance(k, int) and 0 <= k < res.t.shape[0]      # 0: the data overflow g at once
    diagnostics = [getattr(res.diagnostics, f) for f in ("theta_sd", "theta_stage2", "band")
                   if hasattr(res.diagnostics, f)]
    for a in [res.theta_hat, res.x_hat, res.phi_hat] + diagnostics:
        assert np.all(np.isnan(a[k:])), "a row from failed_at on is not NaN"
        assert not np.any(np.isnan(a[:k])), "a row before failed_at is not the run's"
    for a in [res.theta_hat, res.x_hat, res.phi_hat]:
        assert np.all(np.isfinite(a[:k])), "an estimate before failed_at is not finite"
    with pytest.raises(NonFiniteError) as err:
        res.raise_for_status()
    assert str(err.value) == res.message
    return k


def _raises_the_same(run, res) -> None:
    """``throw=True`` raises the type and message that ``throw=False`` reported."""
    with pytest.raises(NonFiniteError) as err:
        run()
    assert str(err.value) == res.message


def _np_quiet():
    # the provoked overflows are the point; the numpy fallback would also warn about them
    return np.errstate(over="ignore", invalid="ignore", divide="ignore")


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater", "two_inertia"])
def test_a_diverging_ekf_reports_where_and_why(name):
    spec, t, U, Y = _record(name)
    ekf = JointEKF(system=spec.system, noise_std=TINY_SIGMA, substeps=COARSE)
    st0 = ekf.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        res = ekf.run(t, U, Y, state0=st0, throw=False)
        k = _stopped_as_said(res, Status.DIVERGED)
        _raises_the_same(lambda: ekf.run(t, U, Y, state0=st0), res)
    assert res.message.startswith(f"the EKF diverged at t[{k}] = {t[k]:.6g}")
    assert np.all(np.isnan(res.diagnostics.nis[k:]))
    # the model-error sentence exactly when the innovations before were far above their size
    nis = res.diagnostics.nis[:k]
    too_big = np.median(nis[np.isfinite(nis)]) / spec.system.r > NIS_MODEL_ERROR
    assert too_big == ("does not fit this record; give a process noise q_x > 0, or use method "
                       "'guarded' or 'mle'" in res.message)


@pytest.mark.parametrize("name, where", [("actuator", "the EKF diverged"),
                                         ("heater", "the EKF diverged"),
                                         ("two_inertia", "process-noise likelihood")])
@pytest.mark.needs_speed
def test_a_failing_map_estimator_reports_where_and_why(name, where):
    """Between fits (the EKF from the latest fit) or in a fit (the process-noise fit's filter):
    the run stops there; the fits before are kept in the diagnostics."""
    spec, t, U, Y = _record(name)
    est = MapEstimator(system=spec.system, noise_std=TINY_SIGMA, substeps=COARSE)
    st0 = est.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        res = est.run(t, U, Y, state0=st0, throw=False)
        k = _stopped_as_said(res, Status.DIVERGED)
        _raises_the_same(lambda: est.run(t, U, Y, state0=st0), res)
    assert where in res.message
    assert all(e < k for e in res.diagnostics.fit_samples)


@pytest.mark.parametrize("compiled", [True, False])
def test_g_undefined_at_the_start_is_said_alike_on_every_back_end(compiled):
    """The wheel's g divides by the speed V; x̂(0) = 0 puts it at a pole. The compiled
    kernels follow NumPy's arithmetic there (inf, then the run's own finiteness check), so both
    back ends stop at t[0] with the same NonFiniteError naming x_hat0 — the compiled one used
    to raise a bare ZeroDivisionError from inside the kernel."""
    if compiled:
        pytest.importorskip("numba")
    spec, t, U, Y = _record("wheel")
    est = MapEstimator(system=spec.system, compiled=compiled)
    st0 = est.init(x_hat0=np.zeros(spec.system.n), theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        res = est.run(t, U, Y, state0=st0, throw=False)
        assert _stopped_as_said(res, Status.DIVERGED) == 0
        _raises_the_same(lambda: est.run(t, U, Y, state0=st0), res)
    assert res.message.startswith("φ̂ = g(v, x̂, θ̂) is not finite at t[0]")
    assert "x_hat0" in res.message


@pytest.mark.parametrize("name", ["prop3", "heater", "actuator"])
def test_a_map_fit_whose_information_is_not_a_number_is_singular(name):
    """1/σ² overflows: the first fit's information cannot be decomposed. SINGULAR at the fit's
    last sample, raised as a NonFiniteError that says so (numpy's LinAlgError never leaves)."""
    spec, t, U, Y = _record(name)
    est = MapEstimator(system=spec.system, noise_std=UNDERFLOWING_SIGMA)
    st0 = est.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        res = est.run(t, U, Y, state0=st0, throw=False)
        k = _stopped_as_said(res, Status.SINGULAR)
        _raises_the_same(lambda: est.run(t, U, Y, state0=st0), res)
    first = est.fit_samples(t)[0]
    assert k == first - 1 and f"the MAP fit of samples 0…{first - 1}" in res.message
    assert res.diagnostics.fits == ()


def _past_stage1(res, alone, lo, hi) -> int:
    """A guarded run whose stage 1 stopped at F (``alone``: stage 1's own run): it says so in
    its diagnostics; θ̂_G is stage 1's before F and NaN from F; and, where the run itself did
    not stop, from F on the band is Θ's full width, nothing is clipped and θ̂ — finite and in
    Θ at every sample — is stage 2's θ̂₂. Returns F."""
    F = alone.failed_at
    d = res.diagnostics
    assert (d.stage1_failed_at, d.stage1_message) == (F, alone.message)
    assert f"stage1_failed_at={F}" in repr(d)
    rows = res.t.shape[0] if res.ok else res.failed_at
    np.testing.assert_array_equal(d.theta_stage1[:min(F, rows)], alone.theta_hat[:min(F, rows)])
    assert np.all(np.isnan(d.theta_stage1[F:]))
    th = res.theta_hat[:rows]
    assert np.all(np.isfinite(th)) and np.all((lo <= th) & (th <= hi))
    if F < rows:
        np.testing.assert_array_equal(d.band[F:rows], np.broadcast_to(hi - lo, d.band[F:rows].shape))
        assert not d.clipped[F:rows].any()
        np.testing.assert_allclose(th[F:], d.theta_stage2[F:rows], rtol=1e-12, atol=0.0)
    return F


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater"])
def test_the_guarded_estimator_goes_on_past_the_observers_failure(name):
    """Outputs × 1e100 overflow stage 1 (the paper's observer). The guarded run does not stop
    there: a ThetahatWarning names the sample and stage 1's message, and stage 2 goes on with
    the band at Θ's width — unless the run's own estimates overflow (the heater's φ̂ =
    g(v, x̂, θ̂) at y × 1e100), which stops it as any run stops (status, NaN rows, the same
    error raised with ``throw=True``)."""
    spec, t, U, Y = _record(name)
    obs = build_observer(spec)
    est = GuardedEstimator(stage1=obs, system=spec.system)
    ts = stage2_set(spec.system.parameter_set)
    kw = dict(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        alone = obs.run(t, U, Y * HUGE_SCALE, state0=obs.init(**kw), throw=False)
        assert alone.status == Status.DIVERGED
        with pytest.warns(ThetahatWarning, match=rf"stage 1 stopped at t\[{alone.failed_at}\]"):
            res = est.run(t, U, Y * HUGE_SCALE, state0=est.init(**kw), throw=False)
        _past_stage1(res, alone, ts.lo, ts.hi)
        if not res.ok:
            _stopped_as_said(res, Status.DIVERGED)
            _raises_the_same(lambda: est.run(t, U, Y * HUGE_SCALE, state0=est.init(**kw)), res)
        else:
            again = est.run(t, U, Y * HUGE_SCALE, state0=est.init(**kw))      # nothing raised
            np.testing.assert_array_equal(again.theta_hat, res.theta_hat)


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater"])
def test_before_stage1s_failure_the_guarded_run_is_the_one_on_the_record_that_far(name):
    """A stage 1 that stops (the joint EKF with the tiny noise level diverges): the guarded
    run's rows before that sample are, bit for bit, those of a run on the record cut there
    (nothing after the failure reaches back), and after it stage 2 runs on, within Θ, to the
    end with status OK."""
    spec, t, U, Y = _record(name)
    stage1 = JointEKF(system=spec.system, noise_std=TINY_SIGMA, substeps=COARSE)
    sigma = 0.01 * np.std(Y, axis=0)          # given, so that σ̂ does not depend on the length
    est = GuardedEstimator(stage1=stage1, system=spec.system, use_fits=False,
                           noise_std=sigma, substeps=COARSE)
    ts = stage2_set(spec.system.parameter_set)
    kw = dict(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        alone = stage1.run(t, U, Y, state0=stage1.init(**kw), throw=False)
        F = alone.failed_at
        assert alone.status == Status.DIVERGED and 1 < F < N - 10
        with pytest.warns(ThetahatWarning, match="without the paper's guarantee"):
            res = est.run(t, U, Y, state0=est.init(**kw), throw=False)
        cut = est.run(t[:F], U[:F], Y[:F], state0=est.init(**kw))
    assert res.ok and _past_stage1(res, alone, ts.lo, ts.hi) == F
    for a, b in [(res.theta_hat, cut.theta_hat), (res.x_hat, cut.x_hat),
                 (res.diagnostics.band, cut.diagnostics.band),
                 (res.diagnostics.theta_stage2, cut.diagnostics.theta_stage2)]:
        np.testing.assert_array_equal(a[:F], b)


@pytest.mark.parametrize("method", ["ekf", "mle", "guarded"])
def test_a_run_that_ends_well_says_so(method):
    spec, t, U, Y = _record("prop3")
    est = {"ekf": lambda: JointEKF(system=spec.system),
           "mle": lambda: MapEstimator(system=spec.system),
           "guarded": lambda: GuardedEstimator(stage1=build_observer(spec),
                                               system=spec.system)}[method]()
    for throw in (True, False):       # (a stage 1 without throw is run with its default)
        res = est.run(t, U, Y, state0=est.init(theta_hat0=spec.estimator.theta_hat0),
                      throw=throw)
        assert (res.status, res.message, res.failed_at, res.ok) == (Status.OK, "", None, True)
        assert np.all(np.isfinite(res.theta_hat)) and res.raise_for_status() is res


#: A guarded stream against its run: the same compiled loop on the same samples, stage 1
#: stepped instead of run (the observer's step and run evaluate the same formulas in another
#: order: 1e-12 relative measured on LuGre in tests/estimation/test_guarded.py's 1e-9); the
#: guarded θ̂ to 1e-9 of Θ's width.
STREAM_RTOL = 1e-9


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater"])
def test_a_guarded_stream_goes_on_past_stage1s_failure_as_its_run_does(name):
    """Step by step, the observer at outputs × 1e100 is lost at the sample the run loses it:
    a warning, then θ̂_G NaN, the band Θ's width, and the guarded θ̂ that of the run (over
    the rows the run gave: the heater's own φ̂ overflows and stops the run, not the stream)."""
    spec, t, U, Y = _record(name)
    stage1, Y = build_observer(spec), Y * HUGE_SCALE
    est = GuardedEstimator(stage1=stage1, system=spec.system, use_fits=False,
                           noise_std=0.01 * np.std(Y, axis=0), substeps=COARSE)
    ts = stage2_set(spec.system.parameter_set)
    kw = dict(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet(), warnings.catch_warnings():
        warnings.simplefilter("ignore", ThetahatWarning)
        res = est.run(t, U, Y, state0=est.init(**kw), throw=False)
    F = res.diagnostics.stage1_failed_at
    assert F is not None
    rows = res.t.shape[0] if res.ok else res.failed_at
    st, th, band, th1 = est.init(**kw), [], [], []
    dt = np.append(np.diff(t), t[1] - t[0])
    with _np_quiet(), pytest.warns(ThetahatWarning, match=rf"stage 1 stopped at sample {F} "):
        for k in range(t.shape[0]):
            st = est.step(st, U[k], Y[k], dt[k])
            th.append(st.theta_hat), band.append(st.band), th1.append(st.theta_stage1)
    assert est.stream_diagnostics(st).stage1_failed_at == F
    assert f"stage1_failed_at={F}" in repr(est.stream_diagnostics(st))
    width = ts.hi - ts.lo
    np.testing.assert_allclose(np.array(th)[:rows] / width, res.theta_hat[:rows] / width,
                               rtol=0.0, atol=STREAM_RTOL)
    np.testing.assert_allclose(np.array(band)[:rows], res.diagnostics.band[:rows],
                               rtol=STREAM_RTOL)
    assert np.all(np.isnan(np.array(th1)[F:])) and np.all(np.isfinite(np.array(th1)[:F]))
    np.testing.assert_array_equal(np.array(band)[F:], np.broadcast_to(width, (len(band) - F,
                                                                               width.size)))


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater", "two_inertia"])
def test_stage1_reads_its_estimates_without_phi_as_estimate_does(name):
    """``read_estimates`` (what the guarded stream reads from stage 1) is ``estimate``'s x̂,
    θ̂ and x̂₂ bit for bit, at states along a run (the C and numba back ends hand it to this
    observer's); a sample
    stage 1 refuses (NaN in y under nan_policy="raise") is refused the same way, so the
    guarded stream raises it (the caller's error), and does not count it as stage 1 lost."""
    spec, t, U, Y = _record(name)
    obs = build_observer(spec)
    states = [obs.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)]
    for k in range(20):
        states.append(obs.step(states[-1], U[k], Y[k], t[k + 1] - t[k]))
    for s, u, y in zip(states, U, Y):
        e = obs.estimate(s, u, y)
        x, th, x2 = obs.read_estimates(s, u, y)
        np.testing.assert_array_equal(x, e.x_hat)
        np.testing.assert_array_equal(th, e.theta_hat)
        assert (x2 is None) == (e.x_hat_refined is None)
        if x2 is not None:
            np.testing.assert_array_equal(x2, e.x_hat_refined)
    y_nan = np.full(spec.system.r, np.nan)
    with pytest.raises(NonFiniteError) as by_estimate:
        obs.estimate(states[0], U[0], y_nan)
    with pytest.raises(NonFiniteError) as by_read:
        obs.read_estimates(states[0], U[0], y_nan)
    assert str(by_read.value) == str(by_estimate.value)
    est = GuardedEstimator(stage1=obs, system=spec.system, use_fits=False)
    st = est.step(est.init(), U[0], Y[0], t[1] - t[0])
    with pytest.raises(NonFiniteError, match="nan_policy"):
        est.step(st, U[1], y_nan, t[2] - t[1])
    assert est.stream_diagnostics(st).stage1_failed_at is None


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater", "two_inertia"])
def test_read_and_step_is_read_estimates_then_step_on_every_back_end(name):
    """``read_and_step`` (the guarded stream's one call to stage 1 per sample): bit for bit
    ``read_estimates`` and ``step`` of the same state and samples, on the observer itself and
    on its compiled back end (the C one: tests/codegen/test_native.py), and a sample the two
    refuse refused with the same message."""
    from thetahat.estimation.observer.compiled import compile_observer
    spec, t, U, Y = _record(name)
    built = build_observer(spec)
    plain = getattr(built, "observer", built)           # the NumPy observer
    h = float(t[1] - t[0])
    backs = [plain, built]
    try:
        backs.append(compile_observer(plain, dt=h))
    except ImportError:                                 # numba absent (the core suite)
        pass
    y_nan = np.full(spec.system.r, np.nan)
    for obs in backs:
        s = obs.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
        for k in range(20):
            x, th, x2, nxt = obs.read_and_step(s, U[k], Y[k], h)
            rx, rth, rx2 = obs.read_estimates(s, U[k], Y[k])
            np.testing.assert_array_equal(x, rx)
            np.testing.assert_array_equal(th, rth)
            assert (x2 is None) == (rx2 is None) and (x2 is None or np.array_equal(x2, rx2))
            np.testing.assert_array_equal(nxt, obs.step(s, U[k], Y[k], h))
            s = nxt
        with pytest.raises(NonFiniteError) as by_step:
            obs.step(s, U[0], y_nan, h)
        with pytest.raises(NonFiniteError) as by_both:
            obs.read_and_step(s, U[0], y_nan, h)
        assert str(by_both.value) == str(by_step.value)
