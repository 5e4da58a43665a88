"""The second observer of Sec. VI: state estimates refined with the parameter estimate θ̂.

    x̂₂̇ = A x̂₂ + B u + E g(v̄, x̂₂, θ̂) + K_x2 (y − C x̂₂),

with θ̂ taken from the modified high-gain observer (3). By default ``v̄ = v = col(u, y)``, as
in Sec. VI; with ``g_on_estimates=True`` the output inside g is replaced by the estimate,
``v̄ = col(u, C x̂₂)``, which is what Sec. VIII recommends for a noisy y ("implement
g(v, x̂, θ̂) in the second observer using only the state estimates, and not the noisy
output y"). Only a Lipschitz-like condition on g (not on d) is needed for this observer.

What lives here: :class:`SecondObserver` (its plan per step length, its step and its
right-hand side). What it may import: the plan and the step of this room, the model and the
package's helpers; never the observer (3), which attaches it.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import as_matrix, as_vector, positive_scalar
from ...errors import DimensionError
from ...model.system import PerturbedLinearSystem
from .discretize import PLAN_CACHE_SIZE
from .plan import SecondPlan, dt_key
from .step import second_advance, second_forcing

__all__ = ["SecondObserver"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class SecondObserver:
    """Second observer of Sec. VI, driven by an external parameter estimate θ̂.

    Parameters
    ----------
    system : PerturbedLinearSystem
        The plant (1); its perturbation g is required.
    K_x : array_like, shape (n, r)
        Output-injection gain, designed for the error dynamics ẋ̃ = A x̃ + E g̃ − K_x ỹ
        (Sec. VI), for instance by the high-gain method with poles of H at −1, −2.
    g_on_estimates : bool, default False
        Evaluate g with the estimated output ``C x̂₂`` in place of the measured y (Sec. VIII).

    Raises
    ------
    DimensionError
        ``K_x`` has the wrong shape or the system has no perturbation.
    NonFiniteError
        ``K_x`` holds NaN or inf.

    Notes
    -----
    Attach it to :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver` through its
    ``second`` keyword: the composite state is ``col(x̂, z, θ̂, x̂₂)`` and ``step``/``run``
    advance both observers, the second with the first's θ̂ at the start of each step (the
    cascade of Sec. VI). Used alone, ``rhs`` and ``step`` take θ̂ explicitly and raise
    :class:`~thetahat.errors.NonFiniteError` on NaN; attached, the first observer's
    ``nan_policy`` governs, and during a skipped sample the second observer predicts too
    (y is replaced by ``C x̂₂``, no output injection, exact linear part ``A``).

    The discretisation is that of :mod:`thetahat.estimation.observer.discretize` with
    ``L = A − K_x C`` and ``N = E ∂g/∂x`` (plus ``E ∂g/∂y C`` with ``g_on_estimates``), which
    here is the exact Jacobian, so the step is second order for held or interpolated samples.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.model.perturbation import CallablePerturbation
    >>> zero = CallablePerturbation(g=lambda v, x, th: 0 * x[..., :1], n=2, m=1, r=1, p=1, k=1)
    >>> plant = PerturbedLinearSystem(A=[[0, 1], [-1, -1]], B=[[0], [1]], C=[[1, 0]],
    ...                               E=[[0], [1]], perturbation=zero)
    >>> obs2 = SecondObserver(system=plant, K_x=[[3.0], [2.0]])
    >>> x2 = obs2.step(np.zeros(2), u=[0.0], y=[1.0], theta_hat=[0.3], dt=1e-3)
    >>> x2.shape
    (2,)
    """

    system: PerturbedLinearSystem
    K_x: FloatArray
    g_on_estimates: bool
    _plans: OrderedDict[tuple[float | None, bool], SecondPlan]

    def __init__(self, *, system: PerturbedLinearSystem, K_x: Any,
                 g_on_estimates: bool = False) -> None:
        if not isinstance(system, PerturbedLinearSystem):
            raise DimensionError("system must be a PerturbedLinearSystem; got "
                                 f"{type(system).__name__}.")
        system.require_perturbation("SecondObserver")
        K = np.array(as_matrix("K_x", K_x, (system.n, system.r)), copy=True)
        K.setflags(write=False)
        for name, val in (("system", system), ("K_x", K),
                          ("g_on_estimates", bool(g_on_estimates)), ("_plans", OrderedDict())):
            object.__setattr__(self, name, val)

    @classmethod
    def from_design(cls, system: PerturbedLinearSystem, design: Any, *,
                    g_on_estimates: bool = False) -> SecondObserver:
        """Build from a gain design on the non-extended system (reads ``design.K``, (n, r)).

        Parameters
        ----------
        system : PerturbedLinearSystem
            The plant (1).
        design : GainDesign
            Any object with an attribute ``K`` of shape (n, r).
        g_on_estimates : bool, default False
            As for the constructor.

        Returns
        -------
        SecondObserver

        Examples
        --------
        >>> from types import SimpleNamespace
        >>> from thetahat.model.system import PerturbedLinearSystem
        >>> from thetahat.model.perturbation import CallablePerturbation
        >>> zero = CallablePerturbation(g=lambda v, x, th: 0 * x, n=1, m=1, r=1, p=1, k=1)
        >>> plant = PerturbedLinearSystem(A=[[-1]], B=[[1]], C=[[1]], E=[[1]],
        ...                               perturbation=zero)
        >>> SecondObserver.from_design(plant, SimpleNamespace(K=[[2.0]])).K_x
        array([[2.]])
        """
        return cls(system=system, K_x=design.K, g_on_estimates=g_on_estimates)

    def plan(self, dt: float | None, *, predict: bool = False) -> SecondPlan:
        """The :class:`~thetahat.estimation.observer.plan.SecondPlan` for step length dt (cached).

        Parameters
        ----------
        dt : float or None
            Step length > 0; None: the continuous-time plan (no φ-matrices) that ``rhs`` reads.
        predict : bool
            Include the φ-matrices of the prediction over missing samples.

        Returns
        -------
        SecondPlan
        """
        key = None if dt is None else dt_key(dt)
        plan = self._plans.get((key, predict))
        if plan is None:
            sysm = self.system
            plan = SecondPlan.build(A=sysm.A, B=sysm.B, C=sysm.C, E=sysm.E, K_x=self.K_x,
                                    dt=key, g_on_estimates=self.g_on_estimates,
                                    predict=predict)
            self._plans[(key, predict)] = plan
            if len(self._plans) > PLAN_CACHE_SIZE:
                self._plans.popitem(last=False)
        return plan

    def _check_samples(self, u: ArrayLike | None, y: ArrayLike) -> tuple[FloatArray, FloatArray]:
        sysm = self.system
        u_ = as_vector("u", np.zeros(0) if u is None else u, sysm.m)
        y_ = as_vector("y", y, sysm.r)
        return u_, y_

    # ------------------------------------------------------------------ public API
    def rhs(self, t: float, x_hat2: ArrayLike, v: ArrayLike, theta_hat: ArrayLike) -> FloatArray:
        """Time derivative x̂₂̇ for ODE integrators.

        Parameters
        ----------
        t : float
            Time (unused: the observer is time-invariant given v).
        x_hat2 : array_like, shape (n,)
        v : array_like, shape (m + r,)
            col(u, y) at time t.
        theta_hat : array_like, shape (p,)

        Returns
        -------
        ndarray, shape (n,)

        Raises
        ------
        NonFiniteError
            NaN or inf in v, the state or θ̂.
        """
        sysm = self.system
        v_ = as_vector("v", v, sysm.m + sysm.r, finite=False)
        u, y = self._check_samples(v_[:sysm.m], v_[sysm.m:])
        x2 = as_vector("x_hat2", x_hat2, sysm.n)
        th = as_vector("theta_hat", theta_hat, sysm.p)
        F, _ = second_forcing(self.plan(None), sysm.require_perturbation("SecondObserver"), x2,
                              u, y, th, True)
        return F

    def step(self, x_hat2: ArrayLike, u: ArrayLike | None, y: ArrayLike,
             theta_hat: ArrayLike, dt: float) -> FloatArray:
        """Advance x̂₂ by ``dt`` holding the current samples (zero-order hold).

        Parameters
        ----------
        x_hat2 : array_like, shape (n,)
        u : array_like, shape (m,)
        y : array_like, shape (r,)
        theta_hat : array_like, shape (p,)
        dt : float
            Step length > 0.

        Returns
        -------
        ndarray, shape (n,)

        Raises
        ------
        NonFiniteError
            NaN or inf in the samples, the state or θ̂.
        """
        sysm = self.system
        u_, y_ = self._check_samples(u, y)
        x2 = as_vector("x_hat2", x_hat2, sysm.n)
        th = as_vector("theta_hat", theta_hat, sysm.p)
        h = positive_scalar("dt", dt)
        return second_advance(self.plan(h), sysm.require_perturbation("SecondObserver"), x2,
                              u_, y_, th, h, True)

    def __repr__(self) -> str:
        return (f"SecondObserver(n={self.system.n}, r={self.system.r}, "
                f"g_on_estimates={self.g_on_estimates})")
