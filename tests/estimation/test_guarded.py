"""The guarded estimator: the guarantee it states, tested where stage 2 is broken or stage 1 slow.

Stage 1 is either the paper's observer or a stand-in with the observer's public interface
whose θ̂_G converges exponentially at a chosen rate (what Theorem 1 guarantees, at a rate we
control), so that "stage 1 slow" and "stage 1 converged" are exact, cheap scenarios.
Everything runs on the numpy fallback (compiled=False) to keep the suite fast.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics
from thetahat.estimation.statistical.guarded import GuardedEstimator
from thetahat.estimation.statistical.mle import MapEstimator
from thetahat.estimation.statistical.noise_level import MIN_SAMPLES, estimate_noise_std
from thetahat.models import lugre

P = lugre.LuGreParameters()
THETA = P.alpha0
LO, HI = P.theta_lower, P.theta_upper
#: Rounding slack of the guarantee |θ̂ − θ̂_G| ≤ δ (clip and Θ-projection in float64).
ROUND = 1e-12


class ExponentialStage1:
    """Stand-in for stage 1: θ̂_G(t) = θ + (θ̂₀ − θ) e^{−t/τ}; x̂ = (y, 0)."""

    def __init__(self, tau: float, theta: float = THETA) -> None:
        self.tau, self.theta, self.system = tau, theta, lugre.system()

    def init(self, x_hat0=None, theta_hat0=None):
        return np.array([0.0, float(np.ravel(theta_hat0)[0])])   # (t, θ̂₀)

    def _theta(self, t, th0):
        return self.theta + (th0 - self.theta) * np.exp(-t / self.tau)

    def run(self, t, u, y, state0, throw=True):
        th = self._theta(np.asarray(t) - t[0], state0[1])[:, None]
        x = np.column_stack([np.asarray(y).reshape(-1), np.zeros(len(t))])
        return EstimateResult(t=np.asarray(t), x_hat=x, theta_hat=th,
                              phi_hat=np.zeros((len(t), 1)), skipped=np.zeros(len(t), bool),
                              diagnostics=ObserverDiagnostics())

    def estimate(self, state, u, y):
        return SimpleNamespace(theta_hat=np.array([self._theta(state[0], state[1])]),
                               x_hat=np.array([float(np.ravel(y)[0]), 0.0]),
                               x_hat_refined=None)

    def step(self, state, u, y, dt):
        return np.array([state[0] + dt, state[1]])


@pytest.fixture(scope="module")
def data():
    return lugre.simulate(seed=4, t_end=1.5)


def _guarantee_holds(res):
    d = res.diagnostics
    assert np.all(np.abs(res.theta_hat - d.theta_stage1) <= d.band + ROUND)
    assert np.all((res.theta_hat >= LO) & (res.theta_hat <= HI))


def test_slow_stage1_does_not_bias_a_correct_stage2(data):
    # stage 1 still 10 % off at the end (τ = 5 s): a band shrinking at a fixed rate would pull
    # stage 2 towards it; the evidence-based band sees no contraction and stays open.
    est = GuardedEstimator(stage1=ExponentialStage1(tau=5.0), system=lugre.system(),
                           compiled=False)
    res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    _guarantee_holds(res)
    assert abs(res.diagnostics.theta_stage1[-1, 0] - THETA) > 0.1 * THETA
    d = res.diagnostics
    assert d.clipped_fraction == 0.0 and d.resets == 0
    assert abs(res.theta_hat[-1, 0] - THETA) < 4 * d.theta_sd[-1, 0]


def test_settling_stage1_narrows_the_band_without_clipping_a_correct_stage2(data):
    # τ = 0.15 s: stage 1 has contracted visibly by the end, so the band shrinks, but only to
    # what stage 1's own progress supports; a correct stage 2 stays inside it.
    est = GuardedEstimator(stage1=ExponentialStage1(tau=0.15), system=lugre.system(),
                           compiled=False)
    res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[1.0]))
    _guarantee_holds(res)
    assert res.diagnostics.band[-1, 0] < 0.1 * (HI - LO)
    late = data.t > 0.5
    assert not res.diagnostics.clipped[late].any()
    assert abs(res.theta_hat[-1, 0] - THETA) < 0.01 * THETA


def test_broken_stage2_cannot_take_the_output_away_from_stage1(data):
    # stage 2's model is wrong (viscous α2 50 % off): alone it settles far from θ; the output
    # keeps stage 1's convergence within the band, and the band closes as stage 1 settles.
    wrong = lugre.system(dataclasses.replace(P, alpha2=1.5 * P.alpha2))
    est = GuardedEstimator(stage1=ExponentialStage1(tau=0.1), system=wrong, compiled=False,
                           use_fits=False)
    res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    _guarantee_holds(res)
    stage2_alone = GuardedEstimator(stage1=ExponentialStage1(tau=1e9), system=wrong,
                                    compiled=False, use_fits=False).run(
        data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    assert abs(stage2_alone.theta_hat[-1, 0] - THETA) > 0.05 * THETA      # it is broken
    err_out = abs(res.theta_hat[-1, 0] - THETA)
    d = res.diagnostics
    assert err_out <= abs(d.theta_stage1[-1, 0] - THETA) + d.band[-1, 0] + ROUND
    assert err_out < 0.01 * THETA
    assert d.clipped[-100:].all()                     # the disagreement alarm is raised


def test_nan_injected_into_stage2_resets_it_and_the_output_stays_finite(data):
    est = GuardedEstimator(stage1=ExponentialStage1(tau=0.1), system=lugre.system(),
                           compiled=False, use_fits=False)
    st = est.init(theta_hat0=[0.5])
    out = []
    for k in range(400):
        st = est.step(st, data.u[k], data.y[k], 1e-3)
        if k == 250:
            st.stream.s[:] = np.nan                # stage 2's state is corrupted
        out.append((st.theta_hat[0], st.reset, st.theta_stage1[0], st.band[0]))
    th, reset, thG, band = map(np.array, zip(*out))
    assert np.all(np.isfinite(th)) and reset[251] and reset.sum() == 1
    assert np.all(np.abs(th - thG) <= band + ROUND)
    assert abs(th[-1] - THETA) < 0.01 * THETA          # stage 2 recovered after the reset


def test_streaming_step_reproduces_run_without_fits(data):
    est = GuardedEstimator(stage1=lugre.observer(eps=1.0, Gamma=10.0), system=lugre.system(),
                           compiled=False, use_fits=False)
    st0 = est.init(theta_hat0=[LO])
    n = 300
    res = est.run(data.t[:n], data.u[:n], data.y[:n], state0=st0)
    st, th = st0, []
    for k in range(n):
        st = est.step(st, data.u[k], data.y[k], 1e-3)
        th.append(st.theta_hat[0])
    assert np.max(np.abs(np.array(th) - res.theta_hat[:, 0])) < 1e-9
    _guarantee_holds(res)


def test_paper_stage1_guarded_from_the_edge_of_theta(data):
    est = lugre.estimator("guarded", Gamma=10.0, compiled=False)
    res = est.run(data.t[:600], data.u[:600], data.y[:600], state0=est.init(theta_hat0=[HI]))
    _guarantee_holds(res)
    assert abs(res.theta_hat[-1, 0] - THETA) < 0.01 * THETA
    # the fits follow the information schedule (sample counts), the last on all but one sample
    ks = MapEstimator(system=lugre.system(), compiled=False).fit_samples(data.t[:599])
    assert list(res.diagnostics.fit_samples + 1) == [k for k in ks if MIN_SAMPLES <= k < 600]
    assert np.all(np.abs(res.diagnostics.fit_cost - 1) < 0.5)


def test_noise_level_estimate_matches_the_simulated_noise(data):
    # 1500 second differences: the MAD's relative sd is ~1.7/√1500 ≈ 4 %; 12 % is 3 sd
    assert estimate_noise_std(data.y)[0] == pytest.approx(0.02, rel=0.12)


def test_failed_and_inconsistent_fits_are_counted_not_applied(data, monkeypatch):
    """A fit that raises or comes back non-finite is ignored with a warning, one that fails its
    consistency checks is kept out of stage 2; the diagnostics count both and the output keeps
    its guarantee."""
    from thetahat.errors import NonFiniteError, ThetahatWarning
    from thetahat.estimation.statistical import guarded as guarded_module
    real = guarded_module.fit_record
    calls = []

    def flaky(*args, **kwargs):
        calls.append(args[4])                                  # k1
        fit = real(*args, **kwargs)
        if len(calls) == 3:
            raise NonFiniteError("injected")
        if len(calls) == 4:
            return dataclasses.replace(fit, theta=np.full_like(fit.theta, np.nan))
        if len(calls) == 5:                                    # far off and says so
            bad = dataclasses.replace(fit, theta=np.full_like(fit.theta, LO), cost=50.0,
                                      process_noise=0.0)
            assert not bad.consistent
            return bad
        return fit

    monkeypatch.setattr(guarded_module, "fit_record", flaky)
    est = GuardedEstimator(stage1=ExponentialStage1(tau=0.1), system=lugre.system(),
                           compiled=False)
    with pytest.warns(ThetahatWarning, match="stage-2 fit was ignored") as rec:
        res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    assert len([w for w in rec if "stage-2 fit was ignored" in str(w.message)]) == 2
    d = res.diagnostics
    assert d.fits_failed == 2 and len(d.fits) == len(calls) - 2
    assert d.fits_rejected == 1 and "fits_rejected=1, fits_failed=2" in repr(d)
    k_bad = calls[4] - 1                                       # where the bad fit came back
    assert abs(d.theta_stage2[k_bad, 0] - LO) > 0.1 * (HI - LO)   # stage 2 did not take it
    _guarantee_holds(res)
    assert np.all(np.isfinite(res.theta_hat))
    assert abs(res.theta_hat[-1, 0] - THETA) < 0.01 * THETA


def test_a_last_fit_that_did_not_converge_is_not_applied_and_said(data, monkeypatch):
    """The final fit comes back 5 standard errors short of its optimum (and with θ on Θ's
    lower face): it is rejected as not converged, the run warns that its last fit was not
    applied, stage 2 does not take its θ, and the output keeps its guarantee and stays near
    the truth (the EKF carried on from the last fit applied)."""
    from thetahat.errors import ThetahatWarning
    from thetahat.estimation.statistical import guarded as guarded_module
    real = guarded_module.fit_record

    def short(*args, **kwargs):
        fit = real(*args, **kwargs)
        if kwargs.get("final"):
            return dataclasses.replace(fit, theta=np.full_like(fit.theta, LO), step_se=5.0)
        return fit

    monkeypatch.setattr(guarded_module, "fit_record", short)
    est = GuardedEstimator(stage1=ExponentialStage1(tau=0.1), system=lugre.system(),
                           compiled=False)
    with pytest.warns(ThetahatWarning, match="last stage-2 fit was not applied") as rec:
        res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[0.5]))
    msg = next(str(w.message) for w in rec if "last stage-2 fit" in str(w.message))
    assert "5 standard errors short" in msg and "did not converge" in msg
    d = res.diagnostics
    assert d.fits[-1].step_se == 5.0 and d.fits_rejected >= 1
    assert abs(d.theta_stage2[-1, 0] - LO) > 0.1 * (HI - LO)
    _guarantee_holds(res)
    assert abs(res.theta_hat[-1, 0] - THETA) < 0.02 * THETA
