"""Accuracy metrics of an estimate against the truth: settling times, RMSE, divergence."""

from __future__ import annotations

import warnings as _warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_vector, positive_scalar
from ..errors import DimensionError
from ..estimation.protocol import EstimateResult
from ..estimation.statistical.trust import SETTLE_TAIL
from ..tables import result_names

__all__ = ["DIVERGENCE_FACTOR", "diverged", "divergence_reason", "estimate_record",
           "estimate_summary", "rmse", "settling", "time_to_within"]

FloatArray = NDArray[np.float64]

#: An estimate counts as diverged when it is non-finite or this many times the truth's range.
DIVERGENCE_FACTOR = 1e3


def time_to_within(t: ArrayLike, estimate: ArrayLike, truth: ArrayLike, rel: float) -> float:
    """First time after which ``|estimate − truth| ≤ rel·|truth|`` holds for good.

    Parameters
    ----------
    t : array_like, shape (N,)
    estimate : array_like, shape (N,) or (N, p)
    truth : array_like, shape (p,) or scalar (a constant parameter)
    rel : float
        Relative band >= 0, e.g. 0.01 for 1 %. For p > 1, every component must be within.

    Returns
    -------
    float
        The settling time, or ``inf`` if the estimate is outside the band at the last sample.

    Examples
    --------
    >>> from thetahat.studies.metrics import time_to_within
    >>> time_to_within([0, 1, 2, 3], [2.0, 1.2, 1.005, 1.0], 1.0, 0.01)
    2.0
    """
    t = as_vector("t", t)
    band = positive_scalar("rel", rel) if rel != 0 else 0.0      # a band is >= 0
    est = np.asarray(estimate, dtype=float)
    if est.shape[0] != t.size:
        raise DimensionError(f"estimate has {est.shape[0]} samples but t has {t.size}.")
    est = est.reshape(t.size, -1)
    tru = np.broadcast_to(np.asarray(truth, dtype=float).ravel(), (est.shape[1],))
    inside = np.all(np.abs(est - tru) <= band * np.abs(tru), axis=1)
    if not inside[-1]:
        return float("inf")
    outside = np.flatnonzero(~inside)
    return float(t[0] if outside.size == 0 else t[outside[-1] + 1])


def rmse(estimate: ArrayLike, truth: ArrayLike, *, start: int = 0) -> FloatArray:
    """Root-mean-square error per component over samples ``start:``; shape (p,).

    Parameters
    ----------
    estimate : array_like, shape (N,) or (N, p)
    truth : array_like, shape (N,) or (N, p)
    start : int
        First sample included (e.g. ``N // 2`` for the second half).

    Returns
    -------
    ndarray, shape (p,)
        The RMSE of each component.

    Examples
    --------
    >>> from thetahat.studies.metrics import rmse
    >>> rmse([[1.0], [3.0]], [[0.0], [0.0]]).tolist()
    [2.23606797749979]
    """
    e = np.asarray(estimate, dtype=float)
    tr = np.asarray(truth, dtype=float)
    if e.ndim not in (1, 2) or e.shape[0] == 0:
        raise DimensionError(f"estimate must have shape (N,) or (N, p) with N >= 1; got "
                             f"{e.shape}.")
    e = e.reshape(e.shape[0], -1)
    if tr.ndim:
        if tr.shape[0] != e.shape[0] or tr.ndim > 2 or tr.reshape(tr.shape[0], -1).shape[1] \
                not in (1, e.shape[1]):
            raise DimensionError(f"truth has shape {tr.shape} but estimate has {e.shape}; "
                                 f"give the truth per sample, (N,) or (N, p), or a scalar.")
        tr = tr.reshape(tr.shape[0], -1)
    tr = np.broadcast_to(tr, e.shape)
    if not 0 <= int(start) < e.shape[0]:
        raise DimensionError(f"start must be in [0, {e.shape[0]}); got {start}.")
    return np.sqrt(np.mean((e[start:] - tr[start:]) ** 2, axis=0))


def diverged(estimate: ArrayLike, scale: float) -> bool:
    """True when the estimate is non-finite or exceeds ``DIVERGENCE_FACTOR·scale`` anywhere.

    Parameters
    ----------
    estimate : array_like
        The estimate, any shape.
    scale : float
        The range of the truth.

    Returns
    -------
    bool
    """
    e = np.asarray(estimate, dtype=float)
    return bool(not np.all(np.isfinite(e)) or np.max(np.abs(e)) > DIVERGENCE_FACTOR * scale)


def divergence_reason(name: str, estimate: ArrayLike, scale: float) -> str | None:
    """Why an estimate counts as diverged (non-finite, or beyond ``DIVERGENCE_FACTOR·scale``).

    Parameters
    ----------
    name : str
        The estimate's name, used in the reason.
    estimate : array_like
    scale : float
        The magnitude of the truth it estimates.

    Returns
    -------
    str or None
        None when it did not diverge.

    Examples
    --------
    >>> divergence_reason("theta_hat", [0.3, float("nan")], 1.0)
    'theta_hat is not finite (first at sample 1)'
    >>> divergence_reason("theta_hat", [0.3, 0.2], 1.0) is None
    True
    """
    if not diverged(estimate, scale):
        return None
    e = np.asarray(estimate, dtype=float).reshape(np.shape(estimate)[0] if np.ndim(estimate)
                                                  else 1, -1)
    finite = np.isfinite(e).all(axis=1)
    if not finite.all():
        return f"{name} is not finite (first at sample {int(np.argmin(finite))})"
    peak = float(np.max(np.abs(e)))
    return (f"{name} reached {peak:.3g}, beyond {DIVERGENCE_FACTOR:g} × the truth's scale "
            f"{scale:.3g}")


#: Band of :func:`estimate_summary`'s settling time: θ̂ within 1 % of its final value.
SETTLE_REL = 0.01
# θ̂ has settled only if it stayed in that band over at least the last SETTLE_TAIL of the
# record (the trust report's tail): a θ̂ that enters the band at t = 29.99 of a 30 s record
# has not settled, it has stopped.


def estimate_summary(result: EstimateResult, parameter_names: Sequence[str] | None = None, *,
                     warnings: Sequence[str | _warnings.WarningMessage] = ()) -> str:
    """A few lines on an estimate: final θ̂, when it settled, skipped samples, warnings.

    Parameters
    ----------
    result : EstimateResult
        From any estimator's ``run`` (reads ``t``, ``theta_hat``, ``skipped``, ``trust`` and
        ``names``).
    parameter_names : sequence of str, optional
        Names of the p parameters (default: the result's own, as
        :func:`~thetahat.modelfile.run_estimator` sets them; else 1, 2, …).
    warnings : sequence of str or warnings.WarningMessage
        Warnings raised during the run: sentences, or as ``warnings.catch_warnings(record=True)``
        records them (shown as ``Category: message``).

    Returns
    -------
    str
        The summary ``thetahat estimate`` prints. The settling time is the first time after
        which every θ̂ component stays within ``SETTLE_REL`` (1 %) of its final value (an
        absolute band of 1e-12 for a final value 0); when that leaves less than the last
        ``SETTLE_TAIL`` of the record, the summary says "NOT settled". The trust report's
        findings (``result.trust.warnings``) are listed with the warnings even when they
        were not caught.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics
    >>> from thetahat.studies.metrics import estimate_summary
    >>> z = np.zeros((3, 1))
    >>> res = EstimateResult(t=np.array([0.0, 1.0, 2.0]), x_hat=z, phi_hat=z,
    ...                      theta_hat=np.array([[0.0], [1.0], [1.0]]),
    ...                      skipped=np.zeros(3, bool), diagnostics=ObserverDiagnostics())
    >>> print(estimate_summary(res, ["theta"]))
    final theta_hat: theta = 1
    settled (within 1 % of the final value) at t = 1 of [0, 2]
    skipped samples (dropouts): 0
    warnings: none
    """
    t = np.asarray(result.t, dtype=float)
    final = np.asarray(result.theta_hat, dtype=float).reshape(t.size, -1)[-1]
    settle, late = settling(result)
    names = result_names(result, parameter_names=parameter_names)[1]
    values = ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, final))
    if t.size <= 1:
        settled = "settled: not decided (a single sample has no course to settle)"
    elif late:
        settled = (f"NOT settled: θ̂ stays within {SETTLE_REL * 100:g} % of its final value "
                   f"only from t = {settle:.6g} of [{t[0]:.6g}, {t[-1]:.6g}], less than the "
                   f"last {100 * SETTLE_TAIL:g} % of the record")
    else:
        settled = (f"settled (within {SETTLE_REL * 100:g} % of the final value) at t = "
                   f"{settle:.6g} of [{t[0]:.6g}, {t[-1]:.6g}]")
    lines = [f"final theta_hat: {values}", settled,
             f"skipped samples (dropouts): {int(np.sum(result.skipped))}"]
    if result.trust is not None:                 # checked by run_estimator
        lines += result.trust.lines()
    notes = _notes(result, warnings)
    lines.append("warnings: " + ("none" if not notes else "; ".join(notes)))
    return "\n".join(lines)


def settling(result: EstimateResult) -> tuple[float, bool]:
    """When θ̂ settled: the first time after which every component stays within
    :data:`SETTLE_REL` of its final value, and whether that leaves less than the last
    :data:`~thetahat.estimation.statistical.trust.SETTLE_TAIL` of the record.

    Parameters
    ----------
    result : EstimateResult
        Reads ``t`` and ``theta_hat``.

    Returns
    -------
    (float, bool)
        The settling time, and True when it is too late to call θ̂ settled.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics
    >>> from thetahat.studies.metrics import settling
    >>> z = np.zeros((5, 1))
    >>> res = EstimateResult(t=np.arange(5.0), x_hat=z, phi_hat=z,
    ...                      theta_hat=np.array([[0.0], [1.0], [1.0], [1.0], [1.0]]),
    ...                      skipped=np.zeros(5, bool), diagnostics=ObserverDiagnostics())
    >>> settling(res)
    (1.0, False)
    """
    t = np.asarray(result.t, dtype=float)
    th = np.asarray(result.theta_hat, dtype=float).reshape(t.size, -1)
    final = th[-1]
    band = np.maximum(SETTLE_REL * np.abs(final), 1e-12)
    inside = np.all(np.abs(th - final) <= band, axis=1)
    outside = np.flatnonzero(~inside)
    settle = t[0] if outside.size == 0 else t[min(outside[-1] + 1, t.size - 1)]
    late = bool(t.size > 1 and settle > t[-1] - SETTLE_TAIL * (t[-1] - t[0]))
    return float(settle), late


def _notes(result: EstimateResult,
           warnings: Sequence[str | _warnings.WarningMessage]) -> list[str]:
    """The run's warnings and the trust report's findings, each once, in order."""
    notes = [w if isinstance(w, str) else f"{w.category.__name__}: {w.message}"
             for w in warnings]
    if result.trust is not None:                 # its findings, whether caught or not
        shown = " ".join(notes)
        notes += [f"ThetahatWarning: {w}" for w in result.trust.warnings if w not in shown]
    return list(dict.fromkeys(notes))


def _number(v: float) -> float | str:
    """A float for JSON: inf and NaN as the strings "inf", "-inf", "nan" (JSON has none)."""
    v = float(v)
    return v if np.isfinite(v) else ("nan" if np.isnan(v) else ("inf" if v > 0 else "-inf"))


def estimate_record(result: EstimateResult, parameter_names: Sequence[str] | None = None, *,
                    warnings: Sequence[str | _warnings.WarningMessage] = (),
                    context: dict[str, Any] | None = None) -> dict[str, Any]:
    """The summary of :func:`estimate_summary` as data: what ``thetahat estimate --summary``
    writes as JSON, for a script, a report or ``thetahat codegen --gamma``.

    Parameters
    ----------
    result : EstimateResult
        From any estimator's ``run``.
    parameter_names : sequence of str, optional
        As for :func:`estimate_summary`.
    warnings : sequence of str or warnings.WarningMessage
        As for :func:`estimate_summary`.
    context : dict, optional
        Entries put first (the CLI's: model and data files, method, hold, ε and Γ).

    Returns
    -------
    dict
        JSON-ready: ``theta_hat`` (name → final value), ``crlb_sd`` (name → Cramér–Rao sd, when
        the result has a trust report), ``settled_at``, ``settled`` (False: "NOT settled"),
        ``samples``, ``skipped``, ``status``, ``trust`` (the report's lines), ``warnings``; inf
        and NaN as strings.

    Examples
    --------
    >>> import json
    >>> import numpy as np
    >>> from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics
    >>> from thetahat.studies.metrics import estimate_record
    >>> z = np.zeros((3, 1))
    >>> res = EstimateResult(t=np.array([0.0, 1.0, 2.0]), x_hat=z, phi_hat=z,
    ...                      theta_hat=np.array([[0.0], [1.0], [1.0]]),
    ...                      skipped=np.zeros(3, bool), diagnostics=ObserverDiagnostics())
    >>> rec = estimate_record(res, ["theta"])
    >>> rec["theta_hat"], rec["settled"], json.loads(json.dumps(rec))["warnings"]
    ({'theta': 1.0}, True, [])
    """
    t = np.asarray(result.t, dtype=float)
    final = np.asarray(result.theta_hat, dtype=float).reshape(t.size, -1)[-1]
    names = result_names(result, parameter_names=parameter_names)[1]
    settle, late = settling(result)
    out: dict[str, Any] = dict(context or {})
    out["theta_hat"] = {n: _number(v) for n, v in zip(names, final)}
    if result.trust is not None:
        out["crlb_sd"] = {n: _number(v) for n, v in zip(names, result.trust.crlb_sd)}
    out.update(settled_at=_number(settle), settled=bool(t.size > 1 and not late),
               samples=int(t.size), skipped=int(np.sum(result.skipped)),
               status=result.status.name,
               trust=[] if result.trust is None else list(result.trust.lines()),
               warnings=_notes(result, warnings))
    return out
