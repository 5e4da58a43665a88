"""Issue 19's acceptance on the measured EMPS record: the shipped model file, no tuning.

Each method ends within 3 % of the published IDIM-LS M, Fv and Fc and within 0.5 N of the
offset (Janot, Gautier, Brunot 2019, section 3.4), θ̂ stays in Θ, and the summary names the
model error (the machine's friction is asymmetric, section 4.2).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from thetahat.io.datafile import read_data
from thetahat.errors import ThetahatWarning
from thetahat.modelfile import load_model, run_estimator
from thetahat.models import emps

pytest.importorskip("numba", reason="the EMPS record's fits take minutes without the "
                    "compiled kernels (extra speed)")
ROOT = Path(__file__).resolve().parents[2]
#: The issue's acceptance: 3 % on M, Fv, Fc; 0.5 N on the offset.
REL_TOL = 0.03
OFFSET_TOL = 0.5
#: Records that begin in motion: DATA_EMPS from these samples on, t restarted at 0; q(0) is
#: 0.24 m and 0.23 m from x̂₀ = 0, so the estimators start at x̂₀ + C⁺(y(0) − C x̂₀)
#: (x_hat0_from_y). Two stretches of the trajectory with their own information: a q searched
#: on a short early window must not decide the later fits (map_fit.Q_SEARCH_GROWTH).
CUTS = (3000, 9000)

@pytest.fixture(scope="module")
def record():
    spec = load_model(ROOT / "examples" / "emps.toml")
    data = read_data(ROOT / "examples" / "data" / "emps" / "DATA_EMPS.mat", spec.layout)
    return spec, data


def assert_published(th):
    pub = emps.PUBLISHED.value
    assert np.all(np.abs(th[:3] / pub[:3] - 1) < REL_TOL), th
    assert abs(th[3] - pub[3]) < OFFSET_TOL, th


def assert_final_fit_applies(res, N):
    """mle and guarded: the whole record's fit is consistent — its innovations' Gaussian core,
    not their mean square, which a few unmodelled force bursts lift above the χ² bound (on
    the cut record 1.28 against 1.07) — so stage 2 takes it. (guarded's last fit is of the
    samples before the last: a fit scheduled at sample k sees 0 … k − 1.)"""
    fits = getattr(res.diagnostics, "fits", None)
    if fits is not None:
        assert fits[-1].k1 >= N - 1 and fits[-1].consistent, fits[-1]


@pytest.mark.slow
@pytest.mark.parametrize("cut", CUTS)
@pytest.mark.parametrize("method", ["mle", "guarded", "paper"])
def test_record_that_begins_in_motion(record, method, cut):
    spec, data = record
    t, u, y = data.t[cut:] - data.t[cut], data.u[cut:], data.y[cut:]
    assert abs(y[0, 0]) > 0.1                                       # m, far from C x̂₀ = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_estimator(spec, t, u, y, method=method, diagnose=False)
    assert_published(res.theta_hat[-1])
    assert_final_fit_applies(res, t.size)
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    assert np.all((res.theta_hat >= lo) & (res.theta_hat <= hi))


@pytest.mark.parametrize("method", ["mle", "guarded", "paper"])
def test_method_reproduces_the_published_table(record, method):
    spec, data = record
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run_estimator(spec, data.t, data.u, data.y, method=method)
    assert_published(res.theta_hat[-1])
    assert_final_fit_applies(res, data.t.size)
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    assert np.all((res.theta_hat >= lo) & (res.theta_hat <= hi))
    texts = [str(w.message) for w in caught if issubclass(w.category, ThetahatWarning)]
    assert any("model error" in w for w in texts)
    assert res.trust is not None and res.trust.unpinned == ()
    if method != "paper":
        # their final fit converged and was applied: θ̂ is where the data put it (the score
        # test at θ̂ passes; with a fit applied 2.4 standard errors short it was χ²₄ = 50
        # against 18.5) — the paper's θ̂ (χ²₄ ≈ 20) is flagged, which test_trust covers
        assert res.trust.consistent, res.trust



def test_the_published_theta_is_recovered_from_its_closed_loop_simulation(record):
    # The closed loop simulated with the published θ along DATA_EMPS's reference and the
    # encoder's quantisation: the truth is known and the model file inexact as on the machine
    # (sharp sign friction that sticks at q̇ = 0, smoothed as tanh(q̇/v_s) in the file).
    spec, data = record
    rec = emps.load(ROOT / "examples" / "data" / "emps" / "DATA_EMPS.mat")
    pub = emps.PUBLISHED.value
    q, nu = emps.simulate_closed_loop(pub, rec)
    dy = np.diff(data.y[:, 0])
    step = np.min(np.abs(dy[dy != 0]))                  # the encoder's resolution on the record
    y = (np.round(q / step) * step)[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ThetahatWarning)
        res = run_estimator(spec, rec.t, emps.G_TAU * nu[:, None], y, method="mle")
    th = res.theta_hat[-1]
    assert np.all(np.abs(th[:3] / pub[:3] - 1) < REL_TOL), th
    assert abs(th[3] - pub[3]) < OFFSET_TOL, th


def test_a_constant_disturbance_is_an_offset():
    # simulate_closed_loop's disturbance acts on the load like the model's offset, with the
    # opposite sign: the two closed loops are one (the plant is integrated exactly)
    rec = emps.load(ROOT / "examples" / "data" / "emps" / "DATA_EMPS.mat")
    pub = emps.PUBLISHED.value
    shifted = pub + np.array([0.0, 0.0, 0.0, 2.0])
    q1, nu1 = emps.simulate_closed_loop(shifted, rec)
    q2, nu2 = emps.simulate_closed_loop(pub, rec, disturbance=np.full(rec.t.size, -2.0))
    np.testing.assert_allclose(q2, q1, rtol=0, atol=1e-12)    # m; round-off of a 0.3 m stroke
    np.testing.assert_allclose(nu2, nu1, rtol=0, atol=1e-6)   # V; KP·KV·1e-12 m, amplified


def test_joint_ekf_taken_as_exact_says_the_model_does_not_fit(record):
    """The bare joint EKF (q_x = 0, the model taken as exact) on the measured record: its
    innovations grow to ~10⁴ times their predicted size and it diverges at 7.7 s. The error
    says that the model does not fit and what to do; with a process noise q_x > 0, as it
    says, the same filter runs through with θ̂ in Θ (bench_emps.py prints both)."""
    import thetahat
    from thetahat.errors import NonFiniteError
    spec, data = record
    U, Y = np.asarray(data.u), np.asarray(data.y)
    th0 = spec.estimator.theta_hat0
    exact = thetahat.JointEKF(system=spec.system)
    with pytest.raises(NonFiniteError, match="does not fit this record.*q_x > 0"):
        exact.run(data.t, U, Y, state0=exact.init(theta_hat0=th0))
    noisy = thetahat.JointEKF(system=spec.system, q_x=1e-8)
    th = np.asarray(noisy.run(data.t, U, Y, state0=noisy.init(theta_hat0=th0)).theta_hat)
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    assert np.all(np.isfinite(th)) and np.all((th >= lo) & (th <= hi))
