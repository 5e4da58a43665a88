"""Estimates as tables: an :class:`~thetahat.estimation.protocol.EstimateResult` as a pandas
DataFrame or an xarray Dataset (both optional; imported lazily).

Columns (and Dataset variables) follow the names of ``thetahat estimate``'s CSV:
``x_hat_<state>``, ``phi_hat_<i>``, ``theta_hat_<parameter>``, ``x_hat_refined_<state>``
and ``skipped``, indexed by ``t``. The names of the states and parameters are the ones given,
else the result's own (``result.names``, which :func:`thetahat.modelfile.run_estimator` sets
from the model file), else ``1``, ``2``, ….
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import DimensionError, MissingExtraError

__all__ = ["result_columns", "result_names", "result_to_dataframe", "result_to_xarray"]


def result_names(result: Any, *, state_names: Sequence[str] | None = None,
                 parameter_names: Sequence[str] | None = None
                 ) -> tuple[list[str], list[str]]:
    """The names of a result's states and parameters: given, else its own, else 1, 2, ….

    Parameters
    ----------
    result : EstimateResult
        Reads ``x_hat (N, n)``, ``theta_hat (N, p)`` and ``names`` (a
        :class:`~thetahat.estimation.protocol.SignalNames` or None).
    state_names : sequence of str, optional
        n names of the states x, in place of the result's.
    parameter_names : sequence of str, optional
        p names of the parameters θ, in place of the result's.

    Returns
    -------
    states : list of str
        n names.
    parameters : list of str
        p names.

    Raises
    ------
    DimensionError
        A list of names has the wrong length.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.protocol import EstimateResult, ObserverDiagnostics, SignalNames
    >>> z = np.zeros((3, 2))
    >>> res = EstimateResult(t=np.arange(3.0), x_hat=z, phi_hat=z[:, :1], theta_hat=z[:, :1],
    ...                      skipped=np.zeros(3, bool), diagnostics=ObserverDiagnostics(),
    ...                      names=SignalNames(states=("omega", "eta"), parameters=("alpha0",),
    ...                                        inputs=("u",), outputs=("y",)))
    >>> result_names(res)
    (['omega', 'eta'], ['alpha0'])
    >>> result_names(res, parameter_names=["theta"])
    (['omega', 'eta'], ['theta'])
    """
    own = getattr(result, "names", None)
    out = []
    for given, attr, what, count in (
            (state_names, "states", "state", result.x_hat.shape[1]),
            (parameter_names, "parameters", "parameter", result.theta_hat.shape[1])):
        names = given if given is not None else (None if own is None else getattr(own, attr))
        names = [str(i + 1) for i in range(count)] if names is None else list(names)
        if len(names) != count:
            raise DimensionError(f"{len(names)} {what} names for {count} {what}s: give one "
                                 f"name per {what}; got {names}.")
        out.append(names)
    return out[0], out[1]


def result_columns(result: Any, *, state_names: Sequence[str] | None = None,
                   parameter_names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """``{column: values (N,)}`` of a result, in the CSV's order (without ``t``).

    Parameters
    ----------
    result : EstimateResult
        The estimates: ``t (N,)``, ``x_hat (N, n)``, ``phi_hat (N, k)``, ``theta_hat (N, p)``,
        ``x_hat_refined (N, n)`` or None, and ``skipped (N,)``.
    state_names, parameter_names : sequence of str, optional
        The n names of the states x and the p names of the parameters θ (default: the
        result's own, else ``"1"``, ``"2"``, …; :func:`result_names`).

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
    k = result.phi_hat.shape[1]
    sn, pn = result_names(result, state_names=state_names, parameter_names=parameter_names)
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
    state_names, parameter_names : sequence of str, optional
        The n names of the states x and the p names of the parameters θ (default: the
        result's own, else ``"1"``, ``"2"``, …; :func:`result_names`).

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
    state_names, parameter_names : sequence of str, optional
        The n names of the states x and the p names of the parameters θ (default: the
        result's own, else ``"1"``, ``"2"``, …; :func:`result_names`).

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
    k = result.phi_hat.shape[1]
    sn, pn = result_names(result, state_names=state_names, parameter_names=parameter_names)
    data = {"x_hat": (("t", "state"), np.asarray(result.x_hat)),
            "phi_hat": (("t", "channel"), np.asarray(result.phi_hat)),
            "theta_hat": (("t", "parameter"), np.asarray(result.theta_hat)),
            "skipped": (("t",), np.asarray(result.skipped))}
    if result.x_hat_refined is not None:
        data["x_hat_refined"] = (("t", "state"), np.asarray(result.x_hat_refined))
    coords = {"t": np.asarray(result.t), "state": sn, "channel": np.arange(1, k + 1),
              "parameter": pn}
    return xr.Dataset(data, coords=coords)
