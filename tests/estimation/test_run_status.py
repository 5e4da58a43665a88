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
  estimator reports stage 1's failure, whatever stage 1 is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thetahat import GuardedEstimator, JointEKF, MapEstimator
from thetahat.errors import NonFiniteError
from thetahat.estimation.statistical.ekf_kernels import NIS_MODEL_ERROR
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
                                         ("spring_friction", "the EKF diverged"),
                                         ("two_inertia", "process-noise likelihood")])
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


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater"])
def test_the_guarded_estimator_raises_stage1s_error_as_stage1_does(name):
    """The guarded run raises stage 1's error — or, where its own output overflows first (the
    heater's φ̂ = g(v, x̂, θ̂) at y × 1e100 from the first sample), that earlier failure: the
    same exception type, and the message of the earliest failing sample."""
    spec, t, U, Y = _record(name)
    obs = build_observer(spec)
    est = GuardedEstimator(stage1=obs, system=spec.system)
    kw = dict(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        with pytest.raises(NonFiniteError) as alone:
            obs.run(t, U, Y * HUGE_SCALE, state0=obs.init(**kw))
        with pytest.raises(NonFiniteError) as guarded:
            est.run(t, U, Y * HUGE_SCALE, state0=est.init(**kw))
        first = obs.run(t, U, Y * HUGE_SCALE, state0=obs.init(**kw), throw=False).failed_at
        mine = est.run(t, U, Y * HUGE_SCALE, state0=est.init(**kw), throw=False).failed_at
    assert type(guarded.value) is type(alone.value)
    assert mine <= first
    if mine == first:
        assert str(guarded.value) == str(alone.value)
    else:
        assert "not finite" in str(guarded.value) and "rescale" in str(guarded.value)


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater"])
def test_the_guarded_estimator_returns_stage1s_failure(name):
    """With ``throw=False`` the guarded run carries stage 1's status and message; stage 2 and
    the guard ran over the rows stage 1 gave (a stage 1 that reports its failure: here the
    joint EKF, which diverges with the tiny noise level)."""
    spec, t, U, Y = _record(name)
    stage1 = JointEKF(system=spec.system, noise_std=TINY_SIGMA, substeps=COARSE)
    est = GuardedEstimator(stage1=stage1, system=spec.system, use_fits=False)
    kw = dict(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        alone = stage1.run(t, U, Y, state0=stage1.init(**kw), throw=False)
        res = est.run(t, U, Y, state0=est.init(**kw), throw=False)
        k = _stopped_as_said(res, alone.status)
        _raises_the_same(lambda: est.run(t, U, Y, state0=est.init(**kw)), res)
    assert (k, res.message) == (alone.failed_at, alone.message)
    np.testing.assert_array_equal(res.diagnostics.theta_stage1[:k], alone.theta_hat[:k])
    assert np.all(np.abs(res.theta_hat[:k] - res.diagnostics.theta_stage1[:k])
                  <= res.diagnostics.band[:k] + 1e-12)          # the guard held there


@pytest.mark.parametrize("name", ["prop3", "actuator", "heater"])
def test_the_guarded_estimator_returns_the_observers_failure(name):
    spec, t, U, Y = _record(name)
    obs = build_observer(spec)
    est = GuardedEstimator(stage1=obs, system=spec.system)
    kw = dict(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    with _np_quiet():
        res = est.run(t, U, Y * HUGE_SCALE, state0=est.init(**kw), throw=False)
        _stopped_as_said(res, Status.DIVERGED)
        _raises_the_same(lambda: est.run(t, U, Y * HUGE_SCALE, state0=est.init(**kw)), res)


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
