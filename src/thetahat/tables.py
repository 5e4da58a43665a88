"""Estimates as tables: an :class:`~thetahat.estimation.protocol.EstimateResult` as a pandas
DataFrame or an xarray Dataset (both optional; imported lazily).

Columns (and Dataset variables) follow the names of ``thetahat estimate``'s CSV:
``x_hat_<state>``, ``phi_hat_<i>``, ``theta_hat_<parameter>``, ``x_hat_refined_<state>``
and ``skipped``, indexed by ``t``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import MissingExtraError

__all__ = ["result_columns", "result_to_dataframe", "result_to_xarray"]


def _names(names: Sequence[str] | None, count: int) -> list[str]:
    return [str(i + 1) for i in range(count)] if names is None else list(names)


def result_columns(result: Any, *, state_names: Sequence[str] | None = None,
                   parameter_names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """``{column: values (N,)}`` of a result, in the CSV's order (without ``t``).

    Parameters
    ----------
    result : EstimateResult
        The estimates: ``t (N,)``, ``x_hat (N, n)``, ``phi_hat (N, k)``, ``theta_hat (N, p)``,
        ``x_hat_refined (N, n)`` or None, and ``skipped (N,)``.
    state_names : sequence of str, optional
        n names of the states x; default ``"1"``, …, ``"n"``.
    parameter_names : sequence of str, optional
        p names of the parameters θ; default ``"1"``, …, ``"p"``.

    Returns
    -------
    dict of str to ndarray, shape (N,)
        ``x_hat_<state>`` (n), ``phi_hat_<i>`` (k, i from 1), ``theta_hat_<parameter>`` (p),
        ``x_hat_refined_<state>`` (n, when the result has x̂₂) and ``skipped`` (bool).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics
    >>> z = np.zeros((3, 1))
    >>> res = EstimateResult(t=np.arange(3.0), x_hat=z, phi_hat=z, theta_hat=z + 0.5,
    ...                      skipped=np.zeros(3, bool), diagnostics=ObserverDiagnostics())
    >>> list(result_columns(res, parameter_names=["alpha0"]))
    ['x_hat_1', 'phi_hat_1', 'theta_hat_alpha0', 'skipped']
    """
    n, k, p = result.x_hat.shape[1], result.phi_hat.shape[1], result.theta_hat.shape[1]
    sn, pn = _names(state_names, n), _names(parameter_names, p)
    cols: dict[str, np.ndarray] = {}
    cols.update({f"x_hat_{s}": result.x_hat[:, i] for i, s in enumerate(sn)})
    cols.update({f"phi_hat_{i + 1}": result.phi_hat[:, i] for i in range(k)})
    cols.update({f"theta_hat_{s}": result.theta_hat[:, i] for i, s in enumerate(pn)})
    if result.x_hat_refined is not None:
        cols.update({f"x_hat_refined_{s}": result.x_hat_refined[:, i]
                     for i, s in enumerate(sn)})
    cols["skipped"] = np.asarray(result.skipped)
    return cols


def result_to_dataframe(result: Any, *, state_names: Sequence[str] | None = None,
                        parameter_names: Sequence[str] | None = None) -> Any:
    """The result as a :class:`pandas.DataFrame` indexed by ``t`` (needs pandas).

    Parameters
    ----------
    result : EstimateResult
        The estimates: ``t (N,)``, ``x_hat (N, n)``, ``phi_hat (N, k)``, ``theta_hat (N, p)``,
        ``x_hat_refined (N, n)`` or None, and ``skipped (N,)``.
    state_names : sequence of str, optional
        n names of the states x; default ``"1"``, …, ``"n"``.
    parameter_names : sequence of str, optional
        p names of the parameters θ; default ``"1"``, …, ``"p"``.

    Returns
    -------
    pandas.DataFrame
        N rows indexed by ``t``, with the columns of :func:`result_columns`.

    Raises
    ------
    MissingExtraError
        pandas is not installed (``pip install 'thetahat[data]'``).
    """
    try:
        import pandas as pd
    except ImportError as exc:
        raise MissingExtraError("to_dataframe needs pandas: pip install 'thetahat[data]'") from exc
    cols = result_columns(result, state_names=state_names, parameter_names=parameter_names)
    return pd.DataFrame(cols, index=pd.Index(np.asarray(result.t), name="t"))


def result_to_xarray(result: Any, *, state_names: Sequence[str] | None = None,
                     parameter_names: Sequence[str] | None = None) -> Any:
    """The result as an :class:`xarray.Dataset` over ``t`` with variables ``x_hat``
    (t, state), ``phi_hat`` (t, channel), ``theta_hat`` (t, parameter), ``x_hat_refined``
    when present and ``skipped`` (needs xarray).

    Parameters
    ----------
    result : EstimateResult
        The estimates: ``t (N,)``, ``x_hat (N, n)``, ``phi_hat (N, k)``, ``theta_hat (N, p)``,
        ``x_hat_refined (N, n)`` or None, and ``skipped (N,)``.
    state_names : sequence of str, optional
        n names of the states x; default ``"1"``, …, ``"n"``.
    parameter_names : sequence of str, optional
        p names of the parameters θ; default ``"1"``, …, ``"p"``.

    Returns
    -------
    xarray.Dataset
        Coordinates ``t`` (N), ``state`` (the state names), ``channel`` (1 … k) and
        ``parameter`` (the parameter names).

    Raises
    ------
    MissingExtraError
        xarray is not installed (``pip install 'thetahat[data]'``).
    """
    try:
        import xarray as xr
    except ImportError as exc:
        raise MissingExtraError("to_xarray needs xarray: pip install 'thetahat[data]'") from exc
    n, k, p = result.x_hat.shape[1], result.phi_hat.shape[1], result.theta_hat.shape[1]
    data = {"x_hat": (("t", "state"), np.asarray(result.x_hat)),
            "phi_hat": (("t", "channel"), np.asarray(result.phi_hat)),
            "theta_hat": (("t", "parameter"), np.asarray(result.theta_hat)),
            "skipped": (("t",), np.asarray(result.skipped))}
    if result.x_hat_refined is not None:
        data["x_hat_refined"] = (("t", "state"), np.asarray(result.x_hat_refined))
    coords = {"t": np.asarray(result.t), "state": _names(state_names, n),
              "channel": np.arange(1, k + 1), "parameter": _names(parameter_names, p)}
    return xr.Dataset(data, coords=coords)
