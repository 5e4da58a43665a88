"""Proposition 4 example: φ = θ₁ sin y + θ₂ tanh u, identifiable only over time.

Plant: the damped oscillator ẋ₁ = x₂, ẋ₂ = -x₁ - 0.5 x₂ + u + φ, y = x₁, driven by the
multisine u(t) = sin 0.7t + 0.8 sin(1.9t + 1) + 0.6 sin(3.1t + 2), with
θ ∈ Θ = [-2, 2]² (true value (1, -0.7)).

Why Proposition 4 applies (and Proposition 3 does not): one scalar φ cannot determine two
parameters at any instant. With ψ(v) = col(sin y, tanh u), ∂g/∂θ = ψᵀ and the default
M = (∂g/∂θ)ᵀ = ψ, the matrix of (14) is 2ψψᵀ = 2S(v) with S = ψψᵀ positive semidefinite
but singular. The multisine makes ψ(t) persistently exciting, ∫_t^(t+T) S dτ >= σI with
σ > 0 (check with :func:`~thetahat.estimation.observer.checks.excitation_report`), and
‖g(θ) - g(θ̂)‖ = |ψᵀθ̃| = (θ̃ᵀSθ̃)^(1/2) gives L_g = 1, so the gradient law
θ̂̇ = Proj(Γψ(φ̂ - g(v, x̂, θ̂))) satisfies Assumption 3.

Examples
--------
>>> import numpy as np
>>> from thetahat.models import prop4_pe
>>> v = np.array([0.3, 0.5])
>>> np.allclose(prop4_pe.S(v, np.zeros(2)), np.outer([np.sin(0.5), np.tanh(0.3)],
...                                                   [np.sin(0.5), np.tanh(0.3)]))
True
"""

from __future__ import annotations

from typing import cast

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from ..estimation.observer.laws import GradientInversion
from ..model.paramset import Box
from ..model.perturbation import Perturbation
from ..model.system import PerturbedLinearSystem
from ._oscillator import oscillator, u, y

FloatArray = NDArray[np.float64]

__all__ = ["THETA", "PARAMETER_SET", "system", "input_signal", "S", "update_law"]

#: The true parameter used by the examples and tests.
THETA = np.array([1.0, -0.7])
#: Θ, a little larger than the assumed parameter range.
PARAMETER_SET = Box([-2.0, -2.0], [2.0, 2.0])

_theta = sp.symbols("theta1 theta2", real=True)


def system() -> PerturbedLinearSystem:
    """The oscillator with φ = g(v, x, θ) = θ₁ sin y + θ₂ tanh u and Θ = [-2, 2]².

    Returns
    -------
    PerturbedLinearSystem
        With its perturbation g and Θ.
    """
    return oscillator(_theta[0] * sp.sin(y) + _theta[1] * sp.tanh(u), list(_theta),
                      PARAMETER_SET)


def input_signal(t: ArrayLike) -> FloatArray:
    """The multisine u(t) = sin 0.7t + 0.8 sin(1.9t + 1) + 0.6 sin(3.1t + 2), shape (..., 1).

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
    return (np.sin(0.7 * t_) + 0.8 * np.sin(1.9 * t_ + 1.0)
            + 0.6 * np.sin(3.1 * t_ + 2.0))[..., None]


def S(v: ArrayLike, x: ArrayLike) -> FloatArray:
    """S(v, x) = ψψᵀ with ψ = col(sin y, tanh u), shape (..., 2, 2).

    Parameters
    ----------
    v : array_like, shape (..., m + r)
        col(u, y).
    x : array_like, shape (..., n)
        The state (estimate).

    Returns
    -------
    ndarray, shape (..., 2, 2)
        S(v, x).
    """
    v_ = np.asarray(v, dtype=np.float64)
    psi = np.stack([np.sin(v_[..., 1]), np.tanh(v_[..., 0])], axis=-1)
    return psi[..., :, None] * psi[..., None, :]


def update_law(Gamma: ArrayLike = 4.0) -> GradientInversion:
    """The Proposition 4 law θ̂̇ = Proj(Γ(∂g/∂θ)ᵀ(φ̂ - g(v, x̂, θ̂))) on Θ.

    Parameters
    ----------
    Gamma : float or array_like, shape (p, p), optional
        Adaptation gain Γ (default 4).

    Returns
    -------
    GradientInversion
    """
    return GradientInversion(cast(Perturbation, system().perturbation), Gamma, PARAMETER_SET)
