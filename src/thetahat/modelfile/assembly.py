"""Model-file assembly: the estimator a :class:`~thetahat.modelfile.schema.ModelSpec` describes.

From a spec read by :func:`~thetahat.modelfile.schema.load_model`: the gain designs on the design
system, the observer (3) with its update law and second observer, and a run on sampled data.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from collections.abc import Callable

from ..design.design_system import apply_design
from ..design.gains import GainDesign, high_gain, modified_high_gain
from ..errors import ModelFileError, NotMinimumPhaseError, ThetahatError, UnstableDesignError
from ..estimation.checks import check_theta_star
from ..estimation.observer import ModifiedHighGainObserver, ObserverResult
from ..estimation.redesign import SecondObserver
from ..structure.assumptions import check_assumption_1
from .schema import ModelSpec

__all__ = ["build_observer", "design_gains", "design_matrices", "run_estimator"]

FloatArray = NDArray[np.float64]

def design_matrices(spec: ModelSpec) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(A, E, C) of the system the gains are designed on: the design system if the file has one.

    Parameters
    ----------
    spec : ModelSpec

    Returns
    -------
    A, E, C : ndarray
        Shapes (n, n), (n, k), (r, n).
    """
    s, est = spec.system, spec.estimator
    return (s.A if est.A_design is None else est.A_design,
            s.E if est.E_design is None else est.E_design, s.C)


def design_gains(spec: ModelSpec, eps: float | None) -> tuple[GainDesign, GainDesign | None]:
    """K(ε) of the modified high-gain observer and, if any, the second observer's gain.

    Parameters
    ----------
    spec : ModelSpec
    eps : float or None
        Overrides ``spec.estimator.eps``.

    Returns
    -------
    design, design2 : GainDesign, GainDesign or None

    Raises
    ------
    NotMinimumPhaseError
        Assumption 1 fails on the system the gains are designed on (unless the file sets
        ``allow_nonminimum_phase = true``); the message names the file and the zeros.
    ModelFileError
        Another design failure; the message names the keys.
    """
    est = spec.estimator
    A_d, E_d, C = design_matrices(spec)
    where = "the design system (A_design, E_design)" if (
        est.A_design is not None or est.E_design is not None) else "(A, E, C)"
    allow = est.allow_nonminimum_phase
    try:
        d1 = modified_high_gain(A_d, E_d, C, est.eps if eps is None else eps,
                                est.chain_poles, est.b_poles, allow_nonminimum_phase=allow)
    except NotMinimumPhaseError as exc:
        raise NotMinimumPhaseError(f"model file {spec.source}: Assumption 1 fails on {where}: "
                                   f"{exc} (or set allow_nonminimum_phase = true in "
                                   f"[estimator] to design anyway).", zeros=exc.zeros) from exc
    except ThetahatError as exc:
        raise ModelFileError(f"model file {spec.source}: [estimator] eps/chain_poles/b_poles: "
                             f"the modified high-gain design on {where} failed: {exc}") from exc
    d2 = None
    if est.second is not None:
        try:
            d2 = high_gain(A_d, E_d, C, est.second.eps2, est.second.chain_poles,
                           est.second.b_poles, allow_nonminimum_phase=allow)
        except ThetahatError as exc:
            raise ModelFileError(f"model file {spec.source}: [estimator.second]: the "
                                 f"high-gain design on {where} failed: {exc}") from exc
    return d1, d2


def build_observer(spec: ModelSpec, *, eps: float | None = None) -> ModifiedHighGainObserver:
    """The estimator of a model file: observer (3) with the file's update law (8).

    The gains K(ε) = [K_x; K_φ] are designed by
    :func:`~thetahat.design.gains.modified_high_gain` on the design system (or the true one),
    and the second observer, if any, by :func:`~thetahat.design.gains.high_gain`.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`load_model`.
    eps : float, optional
        Overrides ``spec.estimator.eps`` (for ε sweeps).

    Returns
    -------
    ModifiedHighGainObserver
        Start it with ``init(x_hat0=spec.estimator.x_hat0,
        theta_hat0=spec.estimator.theta_hat0)``, or use :func:`run_estimator`.

    Raises
    ------
    NotMinimumPhaseError
        Assumption 1 fails on the true or the design system (unless the file opts out
        with ``allow_nonminimum_phase = true``).
    UnstableDesignError
        The gain designed on the design system leaves the true error system unstable.
    ModelFileError
        The gains cannot be designed (e.g. a wrong number of chain poles); the message names
        the keys.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, build_observer, loads_model
    >>> obs = build_observer(loads_model(EXAMPLE_MODEL))
    >>> obs.K_x.shape, obs.K_phi.shape
    ((2, 1), (1, 1))
    """
    est, s = spec.estimator, spec.system
    if not est.allow_nonminimum_phase:
        try:
            check_assumption_1(s.A, s.E, s.C, strict=True)
        except NotMinimumPhaseError as exc:
            raise NotMinimumPhaseError(
                f"model file {spec.source}: Assumption 1 fails on the true system: {exc} (or "
                f"set allow_nonminimum_phase = true in [estimator] to run anyway).",
                zeros=exc.zeros) from exc
    d1, d2 = design_gains(spec, eps)
    if est.A_design is not None or est.E_design is not None:
        for name, d in (("[estimator]", d1), ("[estimator.second]", d2)):
            try:
                if d is not None:
                    apply_design(d, s.A, s.E, s.C, allow_unstable=est.allow_nonminimum_phase)
            except UnstableDesignError as exc:
                raise UnstableDesignError(f"model file {spec.source}: {name}: {exc}",
                                          eigenvalues=exc.eigenvalues) from exc
    second = None
    if d2 is not None:
        second = SecondObserver(system=spec.system, K_x=d2.K,
                                g_on_estimates=spec.estimator.second.g_on_estimates)
    return ModifiedHighGainObserver.from_design(spec.system, d1, spec.estimator.update_law,
                                                second=second,
                                                allow_nonminimum_phase=est.allow_nonminimum_phase)


def run_estimator(spec: ModelSpec, t: ArrayLike, u: ArrayLike | None, y: ArrayLike, *,
                  hold: str = "zoh", nan_policy: str = "raise",
                  progress: Callable[[int, int], None] | None = None) -> ObserverResult:
    """Run the file's estimator on sampled data, from the file's initial values.

    Parameters
    ----------
    spec : ModelSpec
    t : array_like, shape (N,)
        Strictly increasing sampling instants.
    u : array_like, shape (N, m), or None when m = 0
    y : array_like, shape (N, r)
    hold : {"zoh", "foh"}
        Sample hold (see :meth:`~thetahat.estimation.observer.ModifiedHighGainObserver.run`).
    nan_policy : {"raise", "skip"}
        What NaN in y (measurement dropouts) does: refuse the data, or predict over the
        missing samples without output correction.
    progress : callable, optional
        ``progress(done, total)`` is called during the run (see
        :meth:`~thetahat.estimation.observer.ModifiedHighGainObserver.run`).

    Returns
    -------
    ObserverResult

    Raises
    ------
    UpdateLawError
        The law's θ* fails on the data (singular or on a branch that misses Θ); checked by
        :func:`~thetahat.estimation.checks.check_theta_star` before estimation starts.
    NotMinimumPhaseError, UnstableDesignError, ModelFileError
        As for :func:`build_observer`.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model, run_estimator
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 1.0, 0.01)
    >>> res = run_estimator(spec, t, np.sin(t)[:, None], np.zeros((t.size, 1)))
    >>> res.theta_hat.shape
    (100, 1)
    """
    obs = build_observer(spec)
    if nan_policy != "raise":
        obs = ModifiedHighGainObserver(
            system=obs.system, K_x=obs.K_x, K_phi=obs.K_phi, update_law=obs.update_law,
            second=obs.second, nan_policy=nan_policy,
            allow_nonminimum_phase=spec.estimator.allow_nonminimum_phase)
    s = spec.system
    theta_star = getattr(spec.estimator.update_law, "theta_star", None)
    if theta_star is not None:
        check_theta_star(theta_star, s.perturbation, s.parameter_set, s.C, t, u, y)
    state0 = obs.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
    return obs.run(t, u, y, hold=hold, state0=state0, progress=progress)
