"""The guarded estimator on three shipped models besides LuGre: θ̂ ∈ Θ and the guard's
inequality at every sample, and the RMSE over the last half at the Cramér–Rao bound."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import thetahat
from thetahat.estimation.statistical.guarded import GuardedEstimator
from thetahat.modelfile import build_observer, load_model, simulate_model

pytest.importorskip("numba", reason="24 guarded runs take minutes without the compiled "
                    "kernels (extra speed)")
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SEEDS = 6
#: RMSE over the last half of SEEDS runs ÷ √(mean CRLB over the last half, x(0) unknown): the
#: target is 1.5; the RMSE of 6 runs (correlated samples within a run) has a relative standard
#: deviation of ≈ 30 %, so 2.0 is the target plus 1.7 of those.
EFFICIENCY_BOUND = 2.0
#: Rounding allowance of the guard's inequality (relative to Θ's width).
ROUND = 1e-9


def _guarded_run(name: str, seed: int, t_end: float | None = None, var=None):
    """One guarded run of a model file's scenario from the file's start values: asserts θ̂
    finite and in Θ and the guard's inequality at every sample; returns θ̂ − θ over the last
    half and the mean Cramér–Rao bound there (x(0) unknown; ``var`` if given: the bound
    depends on the input and the sampling, the same in every seed)."""
    spec = load_model(EXAMPLES / f"{name}.toml")
    sc = spec.scenario
    lo, hi = spec.system.parameter_set.lower, spec.system.parameter_set.upper
    est = GuardedEstimator(stage1=build_observer(spec), system=spec.system)
    d = simulate_model(spec, seed, t_end=t_end)
    U, Y = np.asarray(d.u), np.asarray(d.y)
    N = d.t.size
    if var is None:
        b = thetahat.crlb(spec.system, d.t, U, theta=sc.theta, noise_std=sc.noise_std,
                          x0=sc.x0, x0_known=False)
        var = np.mean(np.diagonal(np.asarray(b.cov), axis1=-2, axis2=-1)[N // 2:], axis=0)
    res = est.run(d.t, U, Y, state0=est.init(x_hat0=spec.estimator.x_hat0,
                                             theta_hat0=spec.estimator.theta_hat0))
    th = res.theta_hat
    assert np.all(np.isfinite(th)) and np.all((th >= lo) & (th <= hi))
    # |θ̂ − θ| ≤ |θ̂_G − θ| + δ at every sample, whatever stage 2 did
    d2 = res.diagnostics
    assert np.all(np.abs(th - sc.theta) <= np.abs(d2.theta_stage1 - sc.theta) + d2.band
                  + ROUND * (hi - lo))
    return th[N // 2:] - sc.theta, var


@pytest.mark.parametrize("name", ["prop1", "prop2", "prop3"])
def test_guarded_is_guaranteed_and_efficient(name):
    err, var = _guarded_run(name, 0)
    runs = [(err, var)] + [_guarded_run(name, seed, var=var) for seed in range(1, SEEDS)]
    ratio = np.sqrt(np.mean(np.concatenate([e for e, _ in runs]) ** 2, axis=0) / var)
    assert np.all(ratio <= EFFICIENCY_BOUND), ratio


def _one_guarded_run(name: str, seed: int, t_end: float | None) -> None:
    """One guarded run (the invariants of :func:`_guarded_run`) with RMSE over the last half
    ≤ 1.5 × 2.6 √CRLB: one run is about one Gaussian draw per parameter over its last half,
    and 2.6 sd is its 99 % two-sided quantile."""
    err, var = _guarded_run(name, seed, t_end)
    ratio = np.sqrt(np.mean(err ** 2, axis=0) / var)
    assert np.all(ratio <= 1.5 * 2.6), ratio


@pytest.mark.parametrize("name, t_end", [("heater", None), ("actuator", None),
                                          ("spring_friction", 10.0)])
def test_guarded_in_minutes_milliseconds_and_p3(name, t_end):
    """The heater's whole scenario (20 min at 10 Hz), the actuator's (0.5 s at 10 kHz), 10 s of
    the spring with p = 3 and a parameter inside tanh. Before the guard took a consistent fit
    as evidence on stage 1's error, a slow stage 1 that looked settled clipped stage 2: the
    output was 76-110 × √CRLB on the heater and 260-2000 × on the spring."""
    _one_guarded_run(name, 1, t_end)
