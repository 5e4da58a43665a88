"""Does information reach the update law? Two checks on a record, for the summaries.

* :func:`stuck_parameters`: ∂g/∂θ evaluated along the run at (v, x̂, θ̂) is zero (or undefined)
  at every sample for some θ component, so the update law never moves it: the final θ̂ is the
  initial guess, not an estimate (``g = sqrt(|θ|)·(2 + sin y)`` started at θ̂(0) = 0).
* :func:`undefined_perturbation`: g is NaN or infinite on the data at a point of Θ that the
  estimate can reach (θ̂(0), the centre, the corners of a box, the point of Θ nearest 0), which
  is the real cause when the observer then diverges (``sqrt(y − 10)·θ``, ``y/θ`` or ``log θ``
  with 0 in Θ).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..model.state_set import (ASSUMPTION_2_REMEDY, GROWTH_DECADES, GROWTH_LIMIT,
                               lipschitz_growth, measured_states, state_scale)

__all__ = ["stuck_parameters", "undefined_perturbation", "VANISH_RTOL"]

FloatArray = NDArray[np.float64]

#: ∂g/∂θ "vanishes" at a sample when it is below this fraction of its largest size over the
#: same data at the centre of Θ: √(machine ε), the level below which a product of it with a
#: bounded error is lost in the rounding of the terms it is added to.
VANISH_RTOL: float = math.sqrt(float(np.finfo(np.float64).eps))


def _v(u: ArrayLike | None, y: ArrayLike, N: int) -> FloatArray:
    y_ = np.asarray(y, dtype=np.float64).reshape(N, -1)
    if u is None:
        return y_
    u_ = np.asarray(u, dtype=np.float64).reshape(N, -1)
    return np.concatenate((u_, y_), axis=1)


def stuck_parameters(system: Any, u: ArrayLike | None, y: ArrayLike, x_hat: ArrayLike,
                     theta_hat: ArrayLike, names: Sequence[str]) -> str | None:
    """A warning when ∂g/∂θ_i vanishes at θ̂ at every sample of a run, else None.

    Parameters
    ----------
    system : PerturbedLinearSystem
        Its ``perturbation`` (g and ∂g/∂θ) and ``parameter_set`` (Θ).
    u : array_like, shape (N, m), or None
        Inputs (None when m = 0).
    y : array_like, shape (N, r)
        Outputs (NaN dropouts are skipped).
    x_hat, theta_hat : array_like, shapes (N, n) and (N, p)
        The run's estimates.
    names : sequence of str
        The p parameter names.

    Returns
    -------
    str or None
        The warning text, naming the parameters and their final value.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.paramset import Box
    >>> from types import SimpleNamespace
    >>> g = parse_perturbation("Abs(theta)**2*(2 + sin(y))", u=[], y=["y"], x=["x"],
    ...                        theta=["theta"])
    >>> sys = SimpleNamespace(perturbation=g, parameter_set=Box([-1.0], [3.0]))
    >>> N = 50
    >>> msg = stuck_parameters(sys, None, np.ones((N, 1)), np.zeros((N, 1)), np.zeros((N, 1)),
    ...                        ["theta"])
    >>> msg.split(":")[0]
    'no information reached the update law for theta (θ̂ = 0)'
    """
    th = np.asarray(theta_hat, dtype=np.float64)
    N = th.shape[0]
    if N == 0:
        return None
    th = th.reshape(N, -1)
    v = _v(u, y, N)
    x = np.asarray(x_hat, dtype=np.float64).reshape(N, -1)
    rows = np.isfinite(v).all(axis=1) & np.isfinite(x).all(axis=1) & np.isfinite(th).all(axis=1)
    if not rows.any():
        return None
    pert = system.perturbation
    with np.errstate(all="ignore"):
        J = np.asarray(pert.dg_dtheta(v[rows], x[rows], th[rows]))          # (N, k, p)
        centre = np.broadcast_to(system.parameter_set.interior_point, th[rows].shape)
        J0 = np.asarray(pert.dg_dtheta(v[rows], x[rows], centre))
    size = np.where(np.isfinite(J), np.abs(J), 0.0).max(axis=1)            # (N, p)
    scale = np.where(np.isfinite(J0), np.abs(J0), 0.0).max(axis=(0, 1))     # (p,)
    stuck = [i for i in range(th.shape[1]) if np.all(size[:, i] <= VANISH_RTOL * scale[i])]
    if not stuck:
        return None
    which = ", ".join(f"{names[i]} (θ̂ = {th[-1, i]:.6g})" for i in stuck)
    return (f"no information reached the update law for {which}: ∂g/∂θ is zero or undefined "
            f"at θ̂ at every sample of the run, so θ̂ stayed where it started and is not an "
            f"estimate; start θ̂(0) elsewhere in Θ (e.g. its centre) or check g.")


def _candidates(system: Any, theta_hat0: ArrayLike | None) -> list[tuple[str, FloatArray]]:
    theta_set = system.parameter_set
    out: list[tuple[str, FloatArray]] = []
    if theta_hat0 is not None:
        out.append(("θ̂(0)", np.asarray(theta_hat0, dtype=np.float64).ravel()))
    centre = np.asarray(theta_set.interior_point, dtype=np.float64)
    out.append(("the centre of Θ", centre))
    lower, upper = getattr(theta_set, "lower", None), getattr(theta_set, "upper", None)
    if lower is not None and upper is not None:
        out += [("the lower corner of Θ", np.asarray(lower, dtype=np.float64)),
                ("the upper corner of Θ", np.asarray(upper, dtype=np.float64))]
    try:
        out.append(("the point of Θ nearest 0", np.asarray(theta_set.nearest(0 * centre))))
    except Exception:  # noqa: BLE001 - a diagnosis only: a set without projection skips it
        pass
    return out


def undefined_perturbation(system: Any, t: ArrayLike, u: ArrayLike | None, y: ArrayLike,
                           x_hat0: ArrayLike, theta_hat0: ArrayLike | None = None
                           ) -> str | None:
    """Where g is NaN or infinite on the data at a point of Θ, else None.

    g is evaluated at every sample with x = x̂(0) and θ at θ̂(0), the centre of Θ, the
    corners of a box and the point of Θ nearest 0; the first failure is reported with its
    instant and the value of v there.

    Parameters
    ----------
    system : PerturbedLinearSystem
    t : array_like, shape (N,)
    u : array_like, shape (N, m), or None
    y : array_like, shape (N, r)
    x_hat0 : array_like, shape (n,)
    theta_hat0 : array_like, shape (p,), optional

    Returns
    -------
    str or None
        A sentence naming θ, the instant and v, or None when g is finite everywhere tried.

    Examples
    --------
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.paramset import Box
    >>> g = parse_perturbation("sqrt(y - 10)*theta", u=[], y=["y"], x=["x"], theta=["theta"])
    >>> sys = SimpleNamespace(perturbation=g, parameter_set=Box([0.0], [2.0]))
    >>> undefined_perturbation(sys, [0.0, 0.1], None, [[11.0], [3.0]], [0.0]).split(",")[0]
    'g is undefined (NaN or inf) at t = 0.1'
    """
    t_ = np.asarray(t, dtype=np.float64).ravel()
    N = t_.size
    if N == 0:
        return None
    v = _v(u, y, N)
    x = np.broadcast_to(np.asarray(x_hat0, dtype=np.float64).ravel(), (N, system.perturbation
                                                                         .dims[0]))
    ok_rows = np.isfinite(v).all(axis=1)
    for label, theta in _candidates(system, theta_hat0):
        with np.errstate(all="ignore"):
            phi = np.asarray(system.perturbation.g(v, x, np.broadcast_to(theta, (N, theta.size))))
        bad = ok_rows & ~np.isfinite(phi).reshape(N, -1).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            return (f"g is undefined (NaN or inf) at t = {t_[i]:.6g}, with v = (u, y) = "
                    f"{np.array2string(v[i], precision=6)} and θ = "
                    f"{np.array2string(theta, precision=6)} ({label}): the observer cannot "
                    f"evaluate φ there; restrict Θ or the data to where g is defined, or "
                    f"rewrite g")
    return None


#: The end of an explained numerical failure: what to check.
_SCALE_ADVICE = "check that they are in the model's units and scale"
_GROWTH_CAUSE = "g is Lipschitz in x only on bounded sets (Assumption 2 fails)"


def _x_growth(system: Any, t: ArrayLike, u: ArrayLike | None, y: ArrayLike,
              x_hat0: ArrayLike, theta_hat0: ArrayLike | None) -> float:
    """The largest :func:`~thetahat.model.state_set.lipschitz_growth` at the first sample and
    x̂(0), on the scale of x̂(0) and of the states the outputs measure over the record, over
    θ̂(0), Θ's centre and corners (θ̂ moves within Θ: a cubic term whose coefficient starts at
    0 grows all the same)."""
    N = np.asarray(t, dtype=np.float64).size
    v = _v(u, y, N)
    rows = np.flatnonzero(np.isfinite(v).all(axis=1))
    if rows.size == 0:
        return math.nan
    x0 = np.asarray(x_hat0, dtype=np.float64).ravel()
    C = getattr(system, "C", None)
    seen = (x0[None, :] if C is None
            else np.vstack([x0[None, :], measured_states(C, np.asarray(y, dtype=np.float64))]))
    scale = state_scale(seen)
    return max(lipschitz_growth(system.perturbation, v[rows[0]], x0, theta, scale)
               for _, theta in _candidates(system, theta_hat0))


def explain_nonfinite(exc: BaseException, system: Any, t: ArrayLike, u: ArrayLike | None,
                      y: ArrayLike, x_hat0: ArrayLike,
                      theta_hat0: ArrayLike | None = None) -> BaseException:
    """The error to report for a run that failed with ``exc``: when g is undefined on the data
    (:func:`undefined_perturbation`), a :class:`~thetahat.errors.NonFiniteError` naming that
    cause; a numerical failure outside thetahat's errors (``LinAlgError``, an overflow)
    becomes a :class:`~thetahat.errors.SimulationError` with the scale of the data; else
    ``exc`` itself. An error it explained already is returned as it is (explaining twice adds
    nothing).

    Parameters
    ----------
    exc : BaseException
        The failure of the run (e.g. "the observer state diverged").
    system : PerturbedLinearSystem
    t, u, y, x_hat0, theta_hat0
        As for :func:`undefined_perturbation`.

    Returns
    -------
    BaseException

    Examples
    --------
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.paramset import Box
    >>> g = parse_perturbation("y/theta", u=[], y=["y"], x=["x"], theta=["theta"])
    >>> sys = SimpleNamespace(perturbation=g, parameter_set=Box([0.0], [2.0]))
    >>> err = explain_nonfinite(ValueError("diverged"), sys, [0.0], None, [[1.0]], [0.0],
    ...                         [0.0])
    >>> type(err).__name__, str(err)[:40]
    ('NonFiniteError', 'g is undefined (NaN or inf) at t = 0, wi')
    >>> explain_nonfinite(err, sys, [0.0], None, [[1.0]], [0.0], [0.0]) is err
    True
    """
    from ..errors import NonFiniteError, SimulationError, ThetahatError

    try:
        cause = undefined_perturbation(system, t, u, y, x_hat0, theta_hat0)
    except Exception:  # noqa: BLE001 - a diagnosis must never hide the original failure
        cause = None
    if cause is not None:
        if cause in str(exc):                  # explained already (run_estimator, then fleet)
            return exc
        return NonFiniteError(f"{cause} (the run then failed: {exc})")
    numeric = isinstance(exc, NonFiniteError)        # a diverged or singular step: a status
    if not numeric and (isinstance(exc, ThetahatError)
                        or not isinstance(exc, (ArithmeticError, ValueError))):
        return exc
    with np.errstate(all="ignore"):
        size = {name: float(np.nanmax(np.abs(a), initial=0.0)) for name, a in
                (("u", np.asarray(u, dtype=np.float64) if u is not None else np.zeros(0)),
                 ("y", np.asarray(y, dtype=np.float64)))}
    if numeric:
        if _SCALE_ADVICE in str(exc) or _GROWTH_CAUSE in str(exc):     # explained already
            return exc
        try:
            growth = _x_growth(system, t, u, y, x_hat0, theta_hat0)
        except Exception:  # noqa: BLE001 - a diagnosis must never hide the original failure
            growth = math.nan
        if growth > GROWTH_LIMIT:
            shown = "without bound" if math.isinf(growth) else f"{growth:.3g}-fold"
            return NonFiniteError(
                f"{str(exc).rstrip('.')}; {_GROWTH_CAUSE} (‖∂g/∂x‖ grows {shown} from "
                f"the states' scale in the data to {10 ** GROWTH_DECADES} times it): a wrong "
                "x̂ or θ̂ meets a g that grows faster than any gain this dt allows can "
                f"dominate; {ASSUMPTION_2_REMEDY}, or use method guarded or mle.")
        return NonFiniteError(f"{str(exc).rstrip('.')}; the data reach |u| = {size['u']:.3g} "
                              f"and |y| = {size['y']:.3g}: {_SCALE_ADVICE}.")
    return SimulationError(f"the run failed numerically ({type(exc).__name__}: {exc}); the "
                           f"data reach |u| = {size['u']:.3g} and |y| = {size['y']:.3g}: "
                           f"check that they are in the model's units and scale (the "
                           f"observer's linear algebra fails once its state overflows).")
