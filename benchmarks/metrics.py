"""Accuracy metrics of the LuGre benchmark: settling times, last-half errors, divergence rule.

Definitions (quoted by bench_lugre.py and the README):

* ``t_5pct`` / ``t_1pct``: the time after which θ̂ stays within 5 % / 1 % of the true θ for the
  rest of the record (0 if it never leaves the band, inf if it is outside at the last sample).
* last half: samples with t ≥ t_end / 2; ``theta_rmse``, ``theta_bias`` (mean θ̂ − θ),
  ``omega_rmse`` and ``eta_rmse`` are taken there.
* diverged (failed): the estimator raised or produced non-finite values, or its ω̂ RMSE over
  the last half exceeds :data:`DIVERGED_OMEGA_REL` times the RMS of the true ω there (the
  state estimate is lost), or the mean |θ̂ − θ| over the last second exceeds
  :data:`DIVERGED_THETA_REL` · θ (no usable parameter estimate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["settling_time", "RunMetrics", "run_metrics", "pooled", "is_diverged",
           "DIVERGED_OMEGA_REL", "DIVERGED_THETA_REL"]

#: An ω̂ error of a quarter of the signal (0.5 rad/s on the scenario, 25 noise σ) means the state
#: estimate has lost the plant; working estimators sit at or below σ = 0.02 rad/s after their
#: transient, and an estimator whose state estimate leans on a still-converging θ̂ may exceed
#: a few σ for a while without having diverged.
DIVERGED_OMEGA_REL = 0.25
#: A final θ̂ more than 50 % off is no estimate at all; the ±20 % model-mismatch cases may bias
#: θ̂ by tens of percent without counting as diverged.
DIVERGED_THETA_REL = 0.5


def settling_time(t: np.ndarray, est: np.ndarray, true: float, rel: float) -> float:
    """First time after which |est − true| ≤ rel·|true| holds up to the end of the record."""
    t = np.asarray(t, float)
    est = np.asarray(est, float).reshape(-1)
    outside = ~(np.abs(est - true) <= rel * abs(true))          # NaN counts as outside
    if not outside.any():
        return 0.0
    last = int(np.flatnonzero(outside)[-1])
    return float(t[last + 1]) if last + 1 < t.size else float("inf")


@dataclass(frozen=True, slots=True)
class RunMetrics:
    """Metrics of one estimator on one record (squared errors kept for pooling over seeds)."""

    t_5pct: float
    t_1pct: float
    theta_mse: float
    theta_bias: float
    omega_mse: float
    eta_mse: float
    omega_ref_ms: float
    theta_final_err: float
    per_step_us: float
    ok: bool


def run_metrics(t, theta_hat, x_hat, x_true, theta: float, wall_s: float, ok: bool) -> RunMetrics:
    """Metrics of one run; ``x_hat``, ``x_true`` (N, 2) = (ω, η) with η in rad."""
    t = np.asarray(t, float)
    th = np.asarray(theta_hat, float).reshape(-1)
    xh = np.asarray(x_hat, float)
    xt = np.asarray(x_true, float)
    half = t >= t[-1] / 2
    last_second = t >= t[-1] - 1.0
    e = th - theta
    return RunMetrics(
        t_5pct=settling_time(t, th, theta, 0.05), t_1pct=settling_time(t, th, theta, 0.01),
        theta_mse=float(np.mean(e[half] ** 2)), theta_bias=float(np.mean(e[half])),
        omega_mse=float(np.mean((xh[half, 0] - xt[half, 0]) ** 2)),
        eta_mse=float(np.mean((xh[half, 1] - xt[half, 1]) ** 2)),
        omega_ref_ms=float(np.mean(xt[half, 0] ** 2)),
        theta_final_err=float(np.mean(np.abs(e[last_second]))),
        per_step_us=1e6 * wall_s / t.size, ok=ok and bool(np.isfinite(th).all()
                                                        and np.isfinite(xh).all()))


def is_diverged(m: RunMetrics, theta: float) -> bool:
    """The divergence rule of the module docstring."""
    if not m.ok:
        return True
    if not m.omega_mse <= DIVERGED_OMEGA_REL ** 2 * m.omega_ref_ms:
        return True
    return not m.theta_final_err <= DIVERGED_THETA_REL * abs(theta)


def pooled(runs: list[RunMetrics]) -> dict:
    """Aggregate over seeds: median settling times and per-step time, RMSEs pooled over all
    last-half samples of all runs (equal lengths), mean bias. Failed runs are excluded from the
    errors (they are counted by ``diverged``); all-failed gives NaN."""
    good = [m for m in runs if m.ok]
    if not good:
        nan = float("nan")
        return dict(t_5pct=nan, t_1pct=nan, theta_rmse=nan, theta_bias=nan, omega_rmse=nan,
                    eta_rmse=nan, per_step_us=nan, theta_mse=nan, theta_rmse_rel_se=nan,
                    n_runs=len(runs), n_ok=0)
    mse = np.array([m.theta_mse for m in good])
    # standard error of the pooled RMSE relative to it (delta method: half that of the mean
    # MSE); the last-half errors of one run are strongly correlated, so seeds are the samples
    rel_se = (0.5 * float(np.std(mse, ddof=1)) / math.sqrt(mse.size) / float(np.mean(mse))
              if mse.size > 1 and np.mean(mse) > 0 else float("nan"))
    return dict(
        t_5pct=float(np.median([m.t_5pct for m in good])),
        t_1pct=float(np.median([m.t_1pct for m in good])),
        theta_rmse=float(np.sqrt(np.mean([m.theta_mse for m in good]))),
        theta_bias=float(np.mean([m.theta_bias for m in good])),
        omega_rmse=float(np.sqrt(np.mean([m.omega_mse for m in good]))),
        eta_rmse=float(np.sqrt(np.mean([m.eta_mse for m in good]))),
        per_step_us=float(np.median([m.per_step_us for m in good])),
        theta_mse=float(np.mean(mse)), theta_rmse_rel_se=rel_se, n_runs=len(runs),
        n_ok=len(good))

def jsonable(o):
    """Plain JSON: numpy scalars to Python, non-finite floats (never settled, failed) to null."""
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o
