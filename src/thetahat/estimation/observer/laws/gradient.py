"""Propositions 3 and 4: the gradient law θ̂̇ = Proj(Γ M (φ̂ − g(v, x̂, θ̂))), stepped by the
exponential (Rosenbrock) Euler method."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...._validate import positive_scalar
from ....errors import DimensionError, UpdateLawError
from ....model.jacobian_check import require_theta_dependence
from ....model.paramset import ParameterSet
from ....model.perturbation import Perturbation
from .base import (FAR, UpdateLaw, apply_saturation, as_batch, broadcast_rows,
                       check_law_options, project_rows, law_binding)
from ...kernels.kernel_args import LawArrays
from .projection import Projection, Saturation, as_gain
from ...status import status_constants

__all__ = ["GradientInversion"]

FloatArray = NDArray[np.float64]


@final
@dataclass(frozen=True, slots=True, eq=False)
class GradientInversion(UpdateLaw):
    r"""Propositions 3 and 4: θ̂̇ = Proj(Γ M(v, x̂, θ̂)(φ̂ - g(v, x̂, θ̂))).

    $$
    \dot{\hat\theta} = \operatorname{Proj}\bigl(\Gamma\,M(v, \hat x, \hat\theta)\,
      (\hat\phi - g(v, \hat x, \hat\theta))\bigr)
    $$

    Parameters
    ----------
    perturbation : Perturbation
        g and ∂g/∂θ.
    Gamma : float or array_like, shape (p, p)
        Symmetric positive-definite gain Γ.
    parameter_set : ParameterSet
        Θ; its dimension must equal the perturbation's p.
    M : callable, optional
        ``M(v, x, theta)`` of shape (..., p, k). Default (∂g/∂θ)ᵀ(v, x, θ̂) (gradient descent
        on ½‖φ̂ - g‖²).
    saturation : Saturation, optional
        Saturation of x̂ and φ̂ before use (Remark 3).
    layer : float, optional
        Boundary layer of the projection (0 = hard projection, the default).

    Raises
    ------
    UpdateLawError
        Γ not symmetric positive definite; M returns the wrong shape.
    DimensionError
        Θ and the perturbation disagree on p.

    Notes
    -----
    Proposition 3 needs M(v, x, θ₁)∂g/∂θ(v, x, θ₂) + (…)ᵀ >= 2P > 0 on Θ × Θ (13); then
    V = ½θ̃ᵀΓ⁻¹θ̃ decays with V̇ <= -θ̃ᵀPθ̃ and ‖θ̃‖ at rate >= λ_min(P)λ_min(Γ). Proposition 4
    only needs >= 2S(v, x) >= 0 (14) with ∫ S persistently exciting. Check both with
    :func:`thetahat.estimation.observer.checks.check_monotonicity` and
    :func:`~thetahat.estimation.observer.checks.excitation_report`.

    ``step`` uses the exponential (Rosenbrock) Euler method: with K = ΓM∂g/∂θ and
    f = ΓM(φ̂ - g) at θ̂, it integrates the linearisation θ̇ = f - K(θ - θ̂) exactly over dt
    (one (p+1)×(p+1) matrix exponential), then applies the Γ⁻¹-weighted projection. Under (13)
    the eigenvalues of K have positive real parts, so the step is stable for every dt (for a
    huge dt it becomes a Newton step on φ̂ = g(θ)); plain Euler would oscillate once
    ‖K‖dt > 2.

    Examples
    --------
    A perturbation linear in θ, g = θ y (p = k = 1):

    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.model.perturbation import Perturbation
    >>> class Lin(Perturbation):
    ...     dims = (1, 1, 1, 1, 1)
    ...     def g(self, v, x, th): return th * v[..., 1:]
    ...     def dg_dv(self, v, x, th): raise NotImplementedError
    ...     def dg_dx(self, v, x, th): raise NotImplementedError
    ...     def dg_dtheta(self, v, x, th): return v[..., 1:, None] + 0 * th[..., None]
    >>> from thetahat.estimation.observer.laws import GradientInversion
    >>> law = GradientInversion(Lin(), 1.0, Box([-5.0], [5.0]))
    >>> law.rate([0.0, 2.0], [0.0], [2.0], [0.0]).tolist()  # Γ y (φ - θ̂ y)
    [4.0]
    """

    perturbation: Perturbation
    Gamma: FloatArray
    parameter_set: ParameterSet
    M: Callable[[FloatArray, FloatArray, FloatArray], Any] | None = None
    saturation: Saturation | None = None
    layer: float = 0.0
    _proj: Projection = field(init=False, repr=False)

    def __init__(self, perturbation: Perturbation, Gamma: ArrayLike,
                 parameter_set: ParameterSet, *,
                 M: Callable[[FloatArray, FloatArray, FloatArray], Any] | None = None,
                 saturation: Saturation | None = None, layer: float = 0.0) -> None:
        check_law_options("GradientInversion", parameter_set, "raise", saturation)
        if not isinstance(perturbation, Perturbation):
            raise DimensionError(f"perturbation must be a thetahat Perturbation; got "
                                 f"{type(perturbation).__name__}.")
        if perturbation.dims[3] != parameter_set.dim:
            raise DimensionError(f"parameter_set has dimension {parameter_set.dim} but the "
                                 f"perturbation has p = {perturbation.dims[3]} parameters.")
        require_theta_dependence(perturbation, parameter_set, owner="GradientInversion")
        if M is not None and not callable(M):
            raise UpdateLawError("GradientInversion: M must be a callable M(v, x, theta) -> "
                                 "(..., p, k), or None for (∂g/∂θ)ᵀ.")
        proj = Projection(parameter_set, as_gain("Gamma", Gamma, parameter_set.dim),
                          layer=layer)
        object.__setattr__(self, "perturbation", perturbation)
        object.__setattr__(self, "Gamma", proj.Gamma)
        object.__setattr__(self, "parameter_set", parameter_set)
        object.__setattr__(self, "M", M)
        object.__setattr__(self, "saturation", saturation)
        object.__setattr__(self, "layer", proj.layer)
        object.__setattr__(self, "_proj", proj)

    def _inputs(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, tuple[int, ...]]:
        """(v, x̂, φ̂, θ̂, batch shape), checked, with x̂ and φ̂ saturated."""
        n, m, r, p, k = self.perturbation.dims
        v_, x, phi, th, batch = as_batch(v, x_hat, phi_hat, theta_hat, p)
        for name, arr, size in (("v", v_, m + r), ("x_hat", x, n), ("phi_hat", phi, k)):
            if arr.shape[-1] != size:
                raise DimensionError(f"{name} must have shape (..., {size}); got {arr.shape}.")
        x, phi = apply_saturation(self.saturation, x, phi)
        return v_, x, phi, th, batch

    def _jacobian(self, v: FloatArray, x: FloatArray, th: FloatArray, batch: tuple[int, ...]
                  ) -> FloatArray:
        """∂g/∂θ broadcast to the batch, shape (..., k, p)."""
        _, _, _, p, k = self.perturbation.dims
        with np.errstate(over="ignore", invalid="ignore"):
            J = np.asarray(self.perturbation.dg_dtheta(v, x, th), dtype=np.float64)
        return np.broadcast_to(J, batch + (k, p))

    def _terms(self, v_: FloatArray, x: FloatArray, phi: FloatArray, th: FloatArray,
               batch: tuple[int, ...], J: FloatArray | None, Gamma: FloatArray | None = None
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(f = ΓM(φ̂ - g), ΓM, θ̂) broadcast to the batch; J: ∂g/∂θ if already evaluated."""
        _, _, _, p, k = self.perturbation.dims
        with np.errstate(over="ignore", invalid="ignore"):
            resid = phi - np.asarray(self.perturbation.g(v_, x, th), dtype=np.float64)
            if self.M is None:
                Mm = np.swapaxes(self._jacobian(v_, x, th, batch) if J is None else J, -1, -2)
            else:
                Mm = np.asarray(self.M(v_, x, th), dtype=np.float64)
                if Mm.shape[-2:] != (p, k):
                    raise UpdateLawError(f"GradientInversion: M must return shape (..., {p}, "
                                         f"{k}); got {Mm.shape}.")
            G = self.Gamma if Gamma is None else Gamma
            GM = np.broadcast_to(G @ Mm, batch + (p, k))
            f = np.einsum("...pk,...k->...p", GM, np.broadcast_to(resid, batch + (k,)))
        return f, GM, np.broadcast_to(th, batch + (p,))

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """θ̂̇ = Proj(ΓM(φ̂ - g(v, x̂, θ̂))); shape (..., p)."""
        v_, x, phi, th_in, batch = self._inputs(v, x_hat, phi_hat, theta_hat)
        f, _, th = self._terms(v_, x, phi, th_in, batch, None)
        if not np.all(np.isfinite(f)):
            raise UpdateLawError("GradientInversion: the rate overflowed (φ̂ - g or Γ too "
                                 "large); saturate φ̂ and x̂ (Saturation) or reduce Γ.")
        return self._proj.proj(f, th)

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float, *, Gamma: ArrayLike | None = None) -> FloatArray:
        """Exponential-Euler step of the linearised law, then the Γ⁻¹ projection; in Θ.

        :func:`~thetahat.estimation.observer.laws.formulas.gradient_law` on NumPy arrays. ``Gamma``
        (shape (..., p, p)) gives one Γ per batch row in place of the law's own.
        """
        dt = positive_scalar("dt", dt)
        G = None if Gamma is None else np.asarray(Gamma, dtype=np.float64)
        v_, x, phi, th, batch = self._inputs(v, x_hat, phi_hat, theta_hat)
        _, _, _, p, k = self.perturbation.dims
        args = broadcast_rows(batch, v_, x, phi, th)
        LP = LawArrays(Gamma=self.Gamma if G is None else G, g=np.empty(batch + (k,)),
                       J=np.empty(batch + (k, p)), Mt=np.empty(batch + (p, k)),
                       GM=np.empty(batch + (p, k)), f=np.empty(batch + (p,)),
                       K=np.empty(batch + (p, p)), Z=np.empty(batch + (p + 1, p + 1)),
                       Ex=np.empty(batch + (p + 1, p + 1)), Gamma_rows=G)
        thn = np.empty(batch + (p,))
        env = law_binding(self, None, ("gradient_law",), batch == (),
                          lambda: _gradient_names(self))
        with np.errstate(over="ignore", invalid="ignore"):
            env["gradient_law"](LP, args[0], args[1], args[2], args[3], dt, thn, None)
        return thn


def _gradient_names(law: GradientInversion) -> dict[str, Any]:
    """The hooks of :func:`law_formulas.gradient_law` for one law."""
    pert = law.perturbation
    _, _, _, p, k = pert.dims

    def g_val(v: FloatArray, x: FloatArray, th: FloatArray, g: FloatArray) -> None:
        g[...] = pert.g(v, x, th)

    def dg_dtheta(v: FloatArray, x: FloatArray, th: FloatArray, J: FloatArray) -> None:
        J[...] = pert.dg_dtheta(v, x, th)

    M = law.M if law.M is not None else (            # only called with a user's M
        lambda v, x, th: np.swapaxes(pert.dg_dtheta(v, x, th), -1, -2))

    def m_matrix(v: FloatArray, x: FloatArray, th: FloatArray, Mt: FloatArray) -> None:
        Mm = np.asarray(M(v, x, th), dtype=np.float64)
        if Mm.shape[-2:] != (p, k):
            raise UpdateLawError(f"GradientInversion: M must return shape (..., {p}, {k}); "
                                 f"got {Mm.shape}.")
        Mt[...] = Mm

    def project(LP: LawArrays, thn: FloatArray) -> int:
        thn[...] = project_rows(law._proj, thn, LP.Gamma_rows)
        return 0

    return {"g_val": g_val, "dg_dtheta": dg_dtheta, "m_matrix": m_matrix,
            "project": project, "NP": p, "NK": k, "USER_M": law.M is not None, "FAR": FAR,
            **status_constants()}
