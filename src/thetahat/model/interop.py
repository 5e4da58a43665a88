"""Adapters between :class:`PerturbedLinearSystem` and python-control / scipy.signal.

Both libraries are imported lazily, inside the functions: python-control is an optional
dependency (``pip install thetahat[interop]``).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from ..errors import DimensionError, MissingExtraError
from .paramset import ParameterSet
from .perturbation import Perturbation
from .system import PerturbedLinearSystem

__all__ = ["from_state_space", "to_state_space"]


def _is_control_object(sys: Any) -> bool:
    return type(sys).__module__.split(".")[0] == "control"


def _from_control(sys: Any) -> tuple[Any, Any, Any, Any]:
    import control

    if not isinstance(sys, control.StateSpace):
        raise DimensionError(
            f"from_state_space needs a state-space realization, because E is given in its "
            f"state coordinates; got a python-control {type(sys).__name__}. Convert it with "
            f"control.ss(sys) and build E for that realization.")
    if sys.isdtime(strict=True):
        raise DimensionError(
            f"the system is discrete-time (dt={sys.dt}); thetahat's observer (3) is "
            f"continuous-time. Pass a continuous-time system (dt=0), e.g. from "
            f"control.d2c or the physical model.")
    return sys.A, sys.B, sys.C, sys.D


def _from_scipy(sys: Any) -> tuple[Any, Any, Any, Any]:
    from scipy import signal

    if isinstance(sys, signal.dlti):
        raise DimensionError(
            f"the system is discrete-time (dt={sys.dt}); thetahat's observer (3) is "
            f"continuous-time. Pass a continuous-time scipy.signal.StateSpace (no dt).")
    if not isinstance(sys, signal.StateSpace):
        raise DimensionError(
            f"from_state_space needs a state-space realization, because E is given in its "
            f"state coordinates; got scipy.signal.{type(sys).__name__}. Convert it with "
            f"sys.to_ss() and build E for that realization.")
    return sys.A, sys.B, sys.C, sys.D


def from_state_space(sys: Any, *, E: ArrayLike, perturbation: Perturbation | None = None,
                     parameter_set: ParameterSet | None = None) -> PerturbedLinearSystem:
    """Build the model (1) from the linear part of a python-control or scipy system.

    Parameters
    ----------
    sys : control.StateSpace or scipy.signal.StateSpace (lti)
        Continuous-time realization of ẋ = A x + B u, y = C x + D u, with D = 0.
    E : array_like, shape (n, k)
        Where φ enters, in the state coordinates of ``sys``.
    perturbation : Perturbation, optional
        φ = g(v, x, θ) with v = col(u, y).
    parameter_set : ParameterSet, optional
        Θ.

    Returns
    -------
    PerturbedLinearSystem

    Raises
    ------
    DimensionError
        ``sys`` is not a state-space object of either library, is discrete-time, has a
        nonzero D, or E / the perturbation do not fit (see :class:`PerturbedLinearSystem`).

    Notes
    -----
    The paper's output equation is y = C x (1b), so the direct feedthrough D must be
    exactly zero. With a feedthrough, the known signal y - D u satisfies (1b): subtract
    D u from the measurements and pass the system with D = 0.

    Examples
    --------
    >>> from scipy import signal
    >>> from thetahat.model.interop import from_state_space
    >>> lin = signal.StateSpace([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]])
    >>> from_state_space(lin, E=[[0.0], [1.0]]).A
    array([[0., 1.],
           [0., 0.]])
    """
    if _is_control_object(sys):
        A, B, C, D = _from_control(sys)
    elif type(sys).__module__.split(".")[0] == "scipy":
        A, B, C, D = _from_scipy(sys)
    else:
        raise DimensionError(
            f"sys must be a python-control StateSpace or a scipy.signal.StateSpace; got "
            f"{type(sys).__name__}. For plain matrices use PerturbedLinearSystem(A=..., B=..., "
            f"C=..., E=...).")
    D = np.asarray(D, dtype=np.float64)
    if D.size and np.any(D != 0):
        raise DimensionError(
            f"D must be zero because the paper's output equation is y = C x (1b); got D with "
            f"shape {D.shape} and max |D| = {np.max(np.abs(D)):.3g}. Subtract D u from the "
            f"measurement (y - D u is known) and pass the system with D = 0.")
    return PerturbedLinearSystem(A=A, B=B, C=C, E=E, perturbation=perturbation,
                                 parameter_set=parameter_set)


def to_state_space(system: PerturbedLinearSystem, *,
                   library: Literal["scipy", "control"] = "scipy") -> Any:
    """The linear part of (1) with φ as an extra input: (A, [B E], C, 0).

    Parameters
    ----------
    system : PerturbedLinearSystem
    library : {"scipy", "control"}, optional
        Return a ``scipy.signal.StateSpace`` (default) or a ``control.StateSpace`` (whose
        inputs are named u[i] and phi[j], outputs y[i], states x[i]).

    Returns
    -------
    scipy.signal.StateSpace or control.StateSpace
        Continuous-time, with inputs col(u, φ) of size m + k and outputs y of size r.

    Raises
    ------
    DimensionError
        ``system`` is not a PerturbedLinearSystem or ``library`` is unknown.
    ImportError
        python-control is not installed (``pip install thetahat[interop]``).

    Examples
    --------
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.model.interop import to_state_space
    >>> sys = PerturbedLinearSystem(A=[[0, 1], [0, 0]], B=[[0], [1]], C=[[1, 0]], E=[[0], [1]])
    >>> to_state_space(sys).B
    array([[0., 0.],
           [1., 1.]])
    """
    if not isinstance(system, PerturbedLinearSystem):
        raise DimensionError(f"system must be a PerturbedLinearSystem; got "
                             f"{type(system).__name__}.")
    B_full = np.hstack([system.B, system.E])
    D = np.zeros((system.r, system.m + system.k))
    if library == "scipy":
        from scipy import signal

        return signal.StateSpace(system.A.copy(), B_full, system.C.copy(), D)
    if library == "control":
        try:
            import control
        except ImportError as exc:
            raise MissingExtraError("to_state_space(..., library='control') needs python-control: "
                              "pip install thetahat[interop].") from exc
        inputs = [f"u[{i}]" for i in range(system.m)] + [f"phi[{j}]" for j in range(system.k)]
        return control.ss(system.A.copy(), B_full, system.C.copy(), D, inputs=inputs,
                          outputs=[f"y[{i}]" for i in range(system.r)],
                          states=[f"x[{i}]" for i in range(system.n)])
    raise DimensionError(f"library must be 'scipy' or 'control'; got {library!r}.")
