"""Streaming fits never make ``GuardedEstimator.step`` wait, and a bad fit is ignored.

The properties are asserted by ordering, never by absolute times: a fit held back by an
Event (an executor passed as ``fit_executor`` whose jobs wait for the test's signal) must
leave every ``step`` free to return while it is blocked, and its result must be applied at the
first ``step`` after it finishes. Stage 1 is the exponential stand-in of ``test_guarded`` and
stage 2 runs on the numpy fallback (compiled=False), with an early, short first fit (20 ms of
data, 3 Gauss–Newton iterations) so that the real fit code runs in a fraction of a second.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import threading
import time

import numpy as np
import pytest

from test_guarded import HI, LO, THETA, ExponentialStage1
from thetahat.errors import ThetahatWarning
from thetahat.estimation.statistical import fit_worker
from thetahat.estimation.statistical.guarded import GuardedEstimator
from thetahat.estimation.statistical.map_fit import FitSchedule, doubling_schedule
from thetahat.models import lugre

#: Upper bound on waiting for a released fit (never reached unless the fit is broken).
PATIENCE = 120.0
#: Sample after which the first fit is due (t = 0.02 s at 1 kHz).
K_FIT = 20


@pytest.fixture(scope="module")
def data():
    return lugre.simulate(seed=4, t_end=0.4)


def _estimator(executor, *, max_iter: int = 3) -> GuardedEstimator:
    sys_ = lugre.system()
    sched = FitSchedule(system=sys_, times=doubling_schedule(0.02), first_max_iter=max_iter,
                        max_iter=max_iter, compiled=False)
    return GuardedEstimator(stage1=ExponentialStage1(tau=0.1), system=sys_, schedule=sched,
                            noise_std=0.02, compiled=False, fit_executor=executor)


class GatedExecutor(concurrent.futures.Executor):
    """A one-thread executor whose fits wait for ``gate`` and then pass their result through
    ``transform``; other jobs (the worker's warm-up) run at once in the caller."""

    def __init__(self, transform=None) -> None:
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
        self.gate = threading.Event()
        self.transform = transform
        self.fits: list[concurrent.futures.Future] = []

    def submit(self, fn, /, *args, **kwargs):
        if fn is not fit_worker.run_fit:
            done = concurrent.futures.Future()
            done.set_result(fn(*args, **kwargs))
            return done

        def gated():
            if not self.gate.wait(PATIENCE):
                raise TimeoutError("the test never released the fit")
            out = fn(*args, **kwargs)
            return self.transform(out) if self.transform else out

        fut = self.pool.submit(gated)
        self.fits.append(fut)
        return fut

    def shutdown(self, wait=True, *, cancel_futures=False):
        self.gate.set()
        self.pool.shutdown(wait=wait, cancel_futures=cancel_futures)


def _steps(est, st, data, ks):
    for k in ks:
        st = est.step(st, data.u[k], data.y[k], 1e-3)
    return st


def test_step_never_waits_for_a_blocked_fit_and_applies_it_right_after(data):
    ex = GatedExecutor()
    try:
        est = _estimator(ex)
        st = _steps(est, est.init(theta_hat0=[0.5]), data, range(200))
        # the fit due after sample 20 was handed over and is still blocked: 180 steps returned
        # meanwhile (had a step waited for it, it would have been applied by now)
        assert len(ex.fits) == 1 and not ex.fits[0].done()
        assert st.fits == 0 and est.stream_diagnostics(st).pending
        ex.gate.set()
        ex.fits[0].result(timeout=PATIENCE)
        st = _steps(est, st, data, [200])
        diag = est.stream_diagnostics(st)
        assert st.fits == 1 and diag.failures == ()
        assert diag.fit_samples.tolist() == [[K_FIT, 200]]    # window end, applied at
        fit = diag.fits[0]
        assert (fit.k0, fit.k1) == (0, K_FIT + 1)
        assert fit.consistent and LO <= fit.theta[0] <= HI
        assert diag.fit_seconds[0] > 0.0
    finally:
        ex.shutdown()


def test_a_crashed_fit_is_ignored_with_a_warning(data):
    def crash(_):
        raise RuntimeError("solver exploded")

    ex = GatedExecutor(transform=crash)
    ex.gate.set()
    try:
        est = _estimator(ex)
        st = est.init(theta_hat0=[0.5])
        with pytest.warns(ThetahatWarning, match="RuntimeError: solver exploded"):
            st = _steps(est, st, data, range(60))
            ex.fits[0].exception(timeout=PATIENCE)
            st = _steps(est, st, data, range(60, 300))
        diag = est.stream_diagnostics(st)
        assert st.fits == 0 and st.fits_failed == len(diag.failures) >= 1
        assert len(ex.fits) >= 2                      # the stream went on submitting fits
        assert LO <= st.theta_hat[0] <= HI
        assert abs(st.theta_hat[0] - THETA) < 0.05 * THETA   # stage 1 (τ = 0.1 s) carries on
    finally:
        ex.shutdown()


def test_a_non_finite_fit_is_ignored_and_stage2_keeps_its_estimate(data):
    def poison(timed):
        return dataclasses.replace(timed, fit=dataclasses.replace(
            timed.fit, theta=np.full_like(timed.fit.theta, np.nan)))

    ex = GatedExecutor(transform=poison)
    try:
        est = _estimator(ex)
        st = _steps(est, est.init(theta_hat0=[0.5]), data, range(100))
        ex.gate.set()
        ex.fits[0].result(timeout=PATIENCE)
        with pytest.warns(ThetahatWarning, match="non-finite"):
            st = _steps(est, st, data, [100])
        assert st.fits == 0 and st.fits_failed == 1
        assert np.isfinite(st.theta_stage2[0]) and np.isfinite(st.theta_hat[0])
        assert LO <= st.theta_hat[0] <= HI
    finally:
        ex.shutdown()


def test_fits_in_the_worker_process_equal_the_offline_fits(data):
    # the default executor: a spawned worker process with the real fit code; the stream's
    # first fit sees exactly the samples the offline run's first fit sees (0 … 20), so they
    # agree up to the time stamps (the stream sums dt, the record has t = k·dt: ~1e-16 s)
    # propagated through 3 Gauss–Newton iterations; 1e-9 of θ leaves a wide margin.
    est = _estimator(None)
    st = _steps(est, est.init(theta_hat0=[0.5]), data, range(K_FIT + 1))
    deadline = time.monotonic() + PATIENCE
    k = K_FIT + 1
    N = data.t.shape[0]
    while st.fits == 0 and st.fits_failed == 0 and time.monotonic() < deadline and k < N:
        # a sensor loop between samples, its pace spread so that the record's remaining
        # samples last until the deadline (a cold worker compiles for tens of seconds)
        time.sleep(max(0.01, (deadline - time.monotonic()) / (N - k)))
        st = _steps(est, st, data, [k])
        k += 1
    diag = est.stream_diagnostics(st)
    assert diag.failures == () and len(diag.fits) == 1
    assert diag.fit_samples[0, 0] == K_FIT and diag.fit_samples[0, 1] == k - 1
    res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    assert res.diagnostics.fit_samples[0] == K_FIT
    fit = res.diagnostics.fits[0]
    np.testing.assert_allclose(diag.fits[0].theta, fit.theta, rtol=0, atol=1e-9)
    assert diag.fits[0].iterations == fit.iterations


def test_default_stream_fits_all_the_data_at_the_information_schedule(data):
    """Without given times the stream fits at the sample counts of the information schedule
    (never seconds), every fit of all the data so far (k0 = 0), as the offline run does."""
    ex = GatedExecutor()
    ex.gate.set()
    try:
        sys_ = lugre.system()
        est = GuardedEstimator(stage1=ExponentialStage1(tau=0.1), system=sys_, noise_std=0.02,
                               compiled=False, fit_executor=ex)
        st = est.init(theta_hat0=[0.5])
        for k in range(120):
            st = est.step(st, data.u[k], data.y[k], 1e-3)
            if ex.fits:                         # let each fit finish before the next sample
                ex.fits[-1].result(timeout=PATIENCE)
        diag = est.stream_diagnostics(st)
        at = est.fit_schedule.sample_counts()
        expected = [at(j) for j in range(20) if at(j) < 120]
        assert [f.k1 for f in diag.fits] == expected
        assert all(f.k0 == 0 for f in diag.fits)
        assert diag.failures == ()
    finally:
        ex.shutdown()
