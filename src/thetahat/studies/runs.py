"""The metrics of one study run, shared by ε sweeps and the (ε, Γ) search.

A study run builds an observer, runs it on one simulated record and measures it against the
truth (:mod:`.metrics`); a run that diverges is recorded, not raised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import NonFiniteError, SimulationError, UpdateLawError
from ..estimation.protocol import EstimateResult
from .metrics import divergence_reason, rmse, time_to_within

__all__ = ["DIVERGENCE_ERRORS", "SETTLING_BAND", "RunMetrics", "failed_run", "format_number",
           "run_metrics"]

FloatArray = NDArray[np.float64]

#: Relative band of the settling time recorded as ``t_1pct``: |θ̂ − θ| <= 1 % |θ| for good.
SETTLING_BAND = 0.01

#: Errors of ``observer.run`` that mean "this run diverged" rather than "the set-up is wrong":
#: the observer's own non-finite-state check, a failed integration, and floating-point or
#: linear-algebra failures caused by an exploding state (an update law whose θ* overflows).
DIVERGENCE_ERRORS: tuple[type[BaseException], ...] = (
    NonFiniteError, SimulationError, UpdateLawError, FloatingPointError, OverflowError,
    np.linalg.LinAlgError)


@dataclass(frozen=True, slots=True)
class RunMetrics:
    """Metrics of one study run (one ε, Γ and seed); NaN where a failed run has no value.

    Attributes
    ----------
    diverged : bool
        The run raised one of :data:`DIVERGENCE_ERRORS`, or an estimate left
        ``DIVERGENCE_FACTOR`` times the range of its truth (:func:`~thetahat.studies.metrics.
        diverged`).
    t_1pct : float
        Settling time of θ̂ to within :data:`SETTLING_BAND` of θ (``inf``: not settled).
    theta_max_error : float
        max |θ̂ − θ| over the second half of the record.
    theta_rmse : float
        RMS of ‖θ̂ − θ‖ over the second half.
    x_rmse : ndarray, shape (n,)
        RMSE of each component of x̂ over the second half.
    x_rmse_refined : ndarray, shape (n,), or None
        The same for the second observer's x̂₂.
    error : str or None
        How the run diverged: the error that stopped it, or the estimate that became
        non-finite or left its scale (:func:`~thetahat.studies.metrics.divergence_reason`); None when it did not.
    """

    diverged: bool
    t_1pct: float
    theta_max_error: float
    theta_rmse: float
    x_rmse: FloatArray
    x_rmse_refined: FloatArray | None
    error: str | None


def failed_run(n: int, exc: BaseException) -> RunMetrics:
    """The metrics of a run stopped by ``exc``: diverged, every value NaN.

    Parameters
    ----------
    n : int
        Number of states.
    exc : BaseException
        The error that stopped the run (recorded as ``"Type: message"``).

    Returns
    -------
    RunMetrics

    Examples
    --------
    >>> from thetahat.studies.runs import failed_run
    >>> failed_run(2, OverflowError("boom")).error
    'OverflowError: boom'
    """
    return RunMetrics(diverged=True, t_1pct=math.nan, theta_max_error=math.nan,
                      theta_rmse=math.nan, x_rmse=np.full(n, np.nan), x_rmse_refined=None,
                      error=f"{type(exc).__name__}: {exc}")


def _scale(truth: ArrayLike) -> float:
    """Range of a true signal for the divergence test (1 when it is identically zero)."""
    tr = np.asarray(truth)
    s = float(np.max(np.abs(tr))) if tr.size else 0.0
    return s if s > 0 else 1.0


def run_metrics(data: Any, res: EstimateResult) -> RunMetrics:
    """Accuracy and divergence of one observer run against the simulated truth.

    Parameters
    ----------
    data : PlantTrajectory or alike
        With the true ``x (N, n)`` and ``theta (p,)`` (and optionally ``phi (N, k)``).
    res : EstimateResult
        Any estimator's result (``x_hat_refined`` is checked when the observer has one).

    Returns
    -------
    RunMetrics
        Errors over the second half of the record (after the transient); ``t_1pct`` over the
        whole record.

    Examples
    --------
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics
    >>> from thetahat.studies.runs import run_metrics
    >>> t = np.linspace(0.0, 1.0, 11)
    >>> data = SimpleNamespace(x=np.ones((11, 1)), theta=np.array([0.5]))
    >>> res = EstimateResult(t=t, theta_hat=np.full((11, 1), 0.5), x_hat=np.ones((11, 1)),
    ...                      phi_hat=np.zeros((11, 1)), skipped=np.zeros(11, bool),
    ...                      diagnostics=ObserverDiagnostics())
    >>> m = run_metrics(data, res)
    >>> m.diverged, m.t_1pct, m.theta_rmse
    (False, 0.0, 0.0)
    """
    t = np.asarray(res.t, dtype=float)
    half = int(np.searchsorted(t, t[0] + 0.5 * (t[-1] - t[0])))
    theta = np.asarray(data.theta, dtype=float).ravel()
    x = np.asarray(data.x, dtype=float)
    th_hat = np.asarray(res.theta_hat, dtype=float).reshape(t.size, -1)
    x_hat = np.asarray(res.x_hat, dtype=float)
    x2 = None if res.x_hat_refined is None else np.asarray(res.x_hat_refined, dtype=float)
    checks = [("theta_hat", th_hat, theta)] + [
        (f"x_hat[{i}]", x_hat[:, i], x[:, i]) for i in range(x.shape[1])]
    if x2 is not None:
        checks += [(f"x_hat_refined[{i}]", x2[:, i], x[:, i]) for i in range(x.shape[1])]
    phi = getattr(data, "phi", None)
    if phi is not None:
        checks.append(("phi_hat", np.asarray(res.phi_hat, dtype=float),
                       np.asarray(phi, dtype=float)))
    reasons = [divergence_reason(name, est, _scale(tru)) for name, est, tru in checks]
    reason = "; ".join(r for r in reasons if r is not None) or None
    with np.errstate(over="ignore", invalid="ignore"):
        err = th_hat[half:] - theta
        return RunMetrics(diverged=reason is not None,
                          t_1pct=time_to_within(t, th_hat, theta, SETTLING_BAND),
                          theta_max_error=float(np.max(np.abs(err))),
                          theta_rmse=float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))),
                          x_rmse=rmse(x_hat, x, start=half),
                          x_rmse_refined=None if x2 is None else rmse(x2, x, start=half),
                          error=reason)


def format_number(v: float | None, fmt: str) -> str:
    """A table cell: ``-`` for None or NaN, ``inf`` for infinity, else ``format(v, fmt)``.

    Parameters
    ----------
    v : float or None
        The value.
    fmt : str
        A format spec, e.g. ``".2e"``.

    Returns
    -------
    str

    Examples
    --------
    >>> from thetahat.studies.runs import format_number
    >>> format_number(float("nan"), ".2f"), format_number(0.12345, ".2f")
    ('-', '0.12')
    """
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if math.isinf(v):
        return "inf"
    return format(v, fmt)
