"""Checks of the benchmark helpers: metrics, the peers' discretised model, the CRLB sensitivity."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("filterpy")

import crlb  # noqa: E402
import metrics  # noqa: E402
import peers  # noqa: E402

from thetahat.models import lugre  # noqa: E402

#: Central differences of the 1 ms RK4 map with step 1e-6 are exact to ~1e-9 (round-off of
#: the map ~1e-16 / 1e-6 ≈ 1e-10, truncation O(step²) smaller); 1e-7 leaves margin.
JACOBIAN_TOL = 1e-7
#: Open-loop 2 s run of the filters' RK4 model against the plant's LSODA solution: measured
#: max |Δω| 2.9e-4 rad/s over 20 s (at velocity reversals); 1e-3 is 20x below the noise σ.
OPEN_LOOP_OMEGA_TOL = 1e-3
#: The bound's sensitivities (the sampled map's, RK4 sub-steps chosen for accuracy at the
#: noise level, u linear between samples) against central differences (step 1e-4 θ) of the
#: LSODA simulation on 2 s: measured RMS gap 0.27 % of the RMS sensitivity — the gap sits at
#: the two velocity reversals (t ≈ 1.0 and 1.74 s, up to 7 % of max |S| at one sample), where
#: g's |ω| has a kink that a fixed sub-step straddles; 1 % leaves margin.
SENSITIVITY_RMS_TOL = 0.01
#: What the bound is for: √CRLB from S against √CRLB from S_fd: measured 6e-5 relative;
#: 1e-3 leaves margin and is far below any efficiency ratio we report (two digits).
SENSITIVITY_SD_TOL = 1e-3
#: √(P_θθ / CRLB) of the exact-model EKF: measured 0.997 at 2 s and 0.9998 at 20 s (the gap is
#: the early linearisation along the estimate rather than the truth); 1 % leaves margin.
EKF_CRLB_TOL = 0.01

P = lugre.LuGreParameters()
PM = peers.model_params(P)


def test_settling_time_cases():
    t = np.arange(5.0)
    assert metrics.settling_time(t, [0.28] * 5, 0.28, 0.01) == 0.0
    assert metrics.settling_time(t, [0.5, 0.5, 0.28, 0.281, 0.28], 0.28, 0.01) == 2.0
    assert metrics.settling_time(t, [0.28, 0.28, 0.28, 0.28, 0.5], 0.28, 0.01) == math.inf
    assert metrics.settling_time(t, [np.nan, 0.28, 0.28, 0.28, 0.28], 0.28, 0.01) == 1.0


def test_divergence_rule():
    base = dict(t_5pct=0.1, t_1pct=0.2, theta_mse=1e-8, theta_bias=0.0, omega_mse=0.02 ** 2,
                eta_mse=1e-12, omega_ref_ms=2.0 ** 2, theta_final_err=0.001, per_step_us=10.0,
                ok=True)
    assert not metrics.is_diverged(metrics.RunMetrics(**base), 0.28)
    assert not metrics.is_diverged(metrics.RunMetrics(**{**base, "omega_mse": 0.4 ** 2}), 0.28)
    assert metrics.is_diverged(metrics.RunMetrics(**{**base, "ok": False}), 0.28)
    assert metrics.is_diverged(metrics.RunMetrics(**{**base, "omega_mse": 0.6 ** 2}), 0.28)
    assert metrics.is_diverged(metrics.RunMetrics(**{**base, "theta_final_err": 0.2}), 0.28)
    assert metrics.is_diverged(metrics.RunMetrics(**{**base, "omega_mse": np.nan}), 0.28)


def test_pooled_rmse_is_root_mean_of_mse():
    runs = [metrics.RunMetrics(0.1, 0.2, 1e-8, 1e-4, 4e-4, 1e-12, 4.0, 0.0, 10.0, True),
            metrics.RunMetrics(0.3, 0.4, 3e-8, -1e-4, 4e-4, 1e-12, 4.0, 0.0, 20.0, True),
            metrics.RunMetrics(9.0, 9.0, 1.0, 1.0, 1.0, 1.0, 4.0, 1.0, 1.0, False)]
    agg = metrics.pooled(runs)
    assert agg["theta_rmse"] == pytest.approx(math.sqrt(2e-8))
    assert agg["theta_bias"] == pytest.approx(0.0, abs=1e-15)
    assert agg["t_1pct"] == pytest.approx(0.3)
    assert agg["n_ok"] == 2


@pytest.mark.parametrize("s", [[1.3, 0.2, 0.3], [-0.004, -0.31, 0.06], [0.0, 0.1, 1.0]])
def test_rk4_jacobian_matches_finite_differences(s):
    s = np.array(s)
    _, F = peers.propagate_jacobian(s, 0.5, 0.51, 1e-3, PM)
    Ffd = np.empty((3, 3))
    for j in range(3):
        d = np.zeros(3)
        d[j] = 1e-6
        Ffd[:, j] = (peers.propagate(s + d, 0.5, 0.51, 1e-3, PM)
                     - peers.propagate(s - d, 0.5, 0.51, 1e-3, PM)) / 2e-6
    # the kink of |ω| at ω = 0 and the clip at θ = 1 are one-sided: skip points astride them
    if s[0] == 0.0 or s[2] == 1.0:
        Ffd[:, [0, 2]] = F[:, [0, 2]]
    assert np.max(np.abs(F - Ffd)) < JACOBIAN_TOL


def test_substeps_keep_rk4_stable_at_the_stiff_end():
    # θ at the lower end of Θ and ω beyond the scenario's range: σ0|ω|/ζ ≈ 2.1e4 s⁻¹
    n = peers._substeps(4.0, 0.0, P.theta_lower, 1e-3, PM)
    rho = P.sigma0 * 4.0 / P.theta_lower
    assert 1e-3 * rho / n <= peers.RK4_H_RHO * 1.05


def test_open_loop_model_tracks_the_plant():
    traj = lugre.simulate(0, t_end=2.0, noise_std=0.0)
    u = traj.u[:, 0]
    s = np.array([0.0, 0.0, P.alpha0])
    err = 0.0
    for k in range(traj.t.size - 1):
        s = peers.propagate(s, u[k], u[k + 1], 1e-3, PM)
        err = max(err, abs(s[0] - traj.x[k + 1, 0]))
    assert err < OPEN_LOOP_OMEGA_TOL


@pytest.mark.parametrize("run", [peers.run_ekf, peers.run_ukf], ids=["ekf", "ukf"])
def test_peer_filters_converge_and_keep_theta_in_Theta(run):
    traj = lugre.simulate(7, t_end=2.0)
    res = run(traj.t, traj.u, traj.y, theta_hat0=P.theta_upper)
    assert res.ok
    assert np.all((res.theta_hat >= P.theta_lower) & (res.theta_hat <= P.theta_upper))
    assert abs(res.theta_hat[-1] - P.alpha0) < 0.01 * P.alpha0


def test_crlb_sensitivity_matches_finite_differences_and_bound_decreases():
    sc = lugre.Scenario(t_end=2.0)
    S, s_fd = crlb.sensitivity_pair(sc)
    assert np.sqrt(np.mean((S - s_fd) ** 2)) < SENSITIVITY_RMS_TOL * np.sqrt(np.mean(s_fd ** 2))
    assert np.sqrt(np.sum(S ** 2) / np.sum(s_fd ** 2)) == pytest.approx(1.0,
                                                                       abs=SENSITIVITY_SD_TOL)
    res = crlb.crlb(sc)
    finite = np.isfinite(res.var_t)
    assert np.all(np.diff(res.var_t[finite]) <= 0)
    assert res.var == pytest.approx(res.var_t[-1])
    assert res.var_x0_unknown >= res.var * (1 - 1e-9)


def test_crlb_equals_the_covariance_of_an_exact_ekf():
    # Independent check of the bound: an EKF with the exact model, no process noise, x(0)
    # known and θ at its true value propagates P_θθ(t) = 1 / I(t) of the linearised problem.
    traj = lugre.simulate(0, t_end=2.0)
    ekf = peers._LuGreEKF(PM)
    ekf.x = np.array([0.0, 0.0, P.alpha0])
    ekf.P = np.diag([1e-12, 1e-12, 0.3 ** 2])
    ekf.Q = np.zeros((3, 3))
    ekf.R = np.array([[0.02 ** 2]])
    u, y = traj.u[:, 0], traj.y[:, 0]
    for k in range(traj.t.size):
        if k:
            ekf._u = (u[k - 1], u[k], 1e-3)
            ekf.predict()
        ekf.update(np.array([y[k]]), peers._hjac, peers._hx)
    bound = crlb.crlb(lugre.Scenario(t_end=2.0)).var
    assert math.sqrt(ekf.P[2, 2] / bound) == pytest.approx(1.0, abs=EKF_CRLB_TOL)


def test_bench_adapters_return_estimates_in_Theta():
    import bench_lugre

    traj = lugre.simulate(3, t_end=0.5)
    for name in bench_lugre.ESTIMATORS:
        spec = bench_lugre.ESTIMATORS[name]
        # the two-stage estimators compile numba kernels for ~1 min: they are tested on the
        # numpy path in tests/estimation/test_guarded.py and compiled in the slow study
        if not spec.available() or name in bench_lugre.TWO_STAGE:
            continue
        est = spec.run(traj, theta_hat0=P.theta_upper)
        assert est.ok, name
        assert est.theta_hat.shape == (traj.t.size,) and est.x_hat.shape == (traj.t.size, 2)
        assert np.all((est.theta_hat >= P.theta_lower) & (est.theta_hat <= P.theta_upper))


def test_jsonable_maps_non_finite_to_null():
    out = metrics.jsonable({"a": np.float64(np.inf), "b": [np.int64(3), float("nan")]})
    assert out == {"a": None, "b": [3, None]}
