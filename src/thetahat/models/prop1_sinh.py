"""Proposition 1 example: φ = (1 + y²) sinh θ, inverted algebraically.

Plant: the damped oscillator ẋ₁ = x₂, ẋ₂ = -x₁ - 0.5 x₂ + u + φ, y = x₁, with
θ ∈ Θ = [-0.5, 0.5] (true value 0.25). Θ is small on purpose: φ grows like y², and for
|sinh θ| > 1/2 the forced oscillator has no equilibrium and escapes to infinity; with
θ = 0.25 and the small input below the state stays near the stable equilibrium y ≈ 0.27.

Why Proposition 1 applies: for every (v, x, φ) the equation φ = (1 + y²) sinh θ has the
unique solution θ* = asinh(φ / (1 + y²)), because sinh is a bijection of R and 1 + y² >= 1.
The law θ̂̇ = Proj(Γ(θ* - θ̂)) therefore satisfies Assumption 3 with V = ½θ̃ᵀΓ⁻¹θ̃, and
‖θ̃‖ decays at least like e^(-λ_min(Γ) t) when x̂ = x and φ̂ = φ. It also satisfies
Assumption 4 without saturation: |∂θ*/∂φ| = 1/√((1 + y²)² + φ²) <= 1 and θ* does not
depend on x̂.

Examples
--------
>>> import numpy as np
>>> from thetahat.models import prop1_sinh
>>> sys = prop1_sinh.system()
>>> law = prop1_sinh.update_law()
>>> v = np.array([0.0, 1.5])                      # col(u, y)
>>> phi = sys.perturbation.g(v, np.zeros(2), prop1_sinh.THETA)
>>> round(float(prop1_sinh.theta_star(v, np.zeros(2), phi)[0]), 12)
0.25
"""

from __future__ import annotations

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from ..estimation.observer.laws import AlgebraicInversion, IntermittentInversion
from ..model.paramset import Box
from ..model.system import PerturbedLinearSystem
from ._oscillator import oscillator, y

FloatArray = NDArray[np.float64]

__all__ = ["THETA", "PARAMETER_SET", "system", "input_signal", "theta_star", "update_law"]

#: The true parameter used by the examples and tests.
THETA = np.array([0.25])
#: Θ, a little larger than the assumed parameter range.
PARAMETER_SET = Box([-0.5], [0.5])

_theta = sp.Symbol("theta", real=True)


def system() -> PerturbedLinearSystem:
    """The oscillator with φ = g(v, x, θ) = (1 + y²) sinh θ and Θ = [-0.5, 0.5].

    Returns
    -------
    PerturbedLinearSystem
        With its perturbation g and Θ.
    """
    return oscillator((1 + y**2) * sp.sinh(_theta), [_theta], PARAMETER_SET)


def input_signal(t: ArrayLike) -> FloatArray:
    """u(t) = 0.3 sin t + 0.2 sin 2.3t, shape (..., 1).

    Parameters
    ----------
    t : array_like, shape (...)
        Times (s).

    Returns
    -------
    ndarray, shape (..., 1)
        The input.
    """
    t_ = np.asarray(t, dtype=np.float64)
    return (0.3 * np.sin(t_) + 0.2 * np.sin(2.3 * t_))[..., None]


def theta_star(v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike) -> FloatArray:
    """θ* = asinh(φ̂ / (1 + y²)), shape (..., 1); v = col(u, y).

    Parameters
    ----------
    v : array_like, shape (..., m + r)
        col(u, y).
    x_hat : array_like, shape (..., n)
        The state estimate.
    phi_hat : array_like, shape (..., k)
        The perturbation estimate.

    Returns
    -------
    ndarray, shape (..., 1)
        θ*.
    """
    v_ = np.asarray(v, dtype=np.float64)
    phi = np.asarray(phi_hat, dtype=np.float64)
    return np.arcsinh(phi[..., :1] / (1.0 + v_[..., 1:2] ** 2))


def update_law(Gamma: ArrayLike = 2.0) -> IntermittentInversion:
    """The Proposition 1 law θ̂̇ = Proj(Γ(θ* - θ̂)) on Θ.

    Parameters
    ----------
    Gamma : float or array_like, shape (p, p), optional
        Adaptation gain Γ (default 2).

    Returns
    -------
    IntermittentInversion
        ``AlgebraicInversion(...)``: the intermittent law with l ≡ 1.
    """
    return AlgebraicInversion(theta_star, Gamma, PARAMETER_SET)
