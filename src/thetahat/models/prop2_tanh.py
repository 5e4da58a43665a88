"""Proposition 2 example: φ = tanh(θ y), inverted only while the output is informative.

Plant: the damped oscillator ẋ₁ = x₂, ẋ₂ = -x₁ - 0.5 x₂ + u + φ, y = x₁, with
θ ∈ Θ = [0.5, 3] (true value 1.5).

Why Proposition 2 applies (and Proposition 1 does not): θ* = atanh(φ)/y solves
φ = tanh(θ y) uniquely only when y ≠ 0 and |φ| < 1, and it is badly conditioned near y = 0
(φ carries no information about θ there) and near |φ| = 1 (tanh saturates). The excitation
weight

    l(v, x̂, φ̂) = w(|y|; 0.2, 0.5) · (1 - w(|φ̂|; 0.9, 0.98)),

with w the C¹ ramp of :func:`~thetahat.estimation.observer.laws.smooth_ramp`, is positive only
where |y| > 0.2 and |φ̂| < 0.98, where θ* is unique and Lipschitz in φ̂ — so
Proj(lΓ(θ* - θ̂)) also satisfies Assumption 4. The oscillating output passes through the
informative band every half period, which gives ∫_t^(t+T) l dτ >= σ > 0 (check it with
:func:`~thetahat.estimation.observer.checks.excitation_report`).

Examples
--------
>>> import numpy as np
>>> from thetahat.models import prop2_tanh
>>> v = np.array([[0.0, 0.0], [0.0, 0.6]])        # y = 0 carries no information
>>> phi = np.tanh(1.5 * v[:, 1:])
>>> prop2_tanh.excitation_weight(v, np.zeros(2), phi).tolist()
[0.0, 1.0]
"""

from __future__ import annotations

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from ..estimation.observer.laws import IntermittentInversion, smooth_ramp
from ..model.paramset import Box
from ..model.system import PerturbedLinearSystem
from ._oscillator import oscillator, y

FloatArray = NDArray[np.float64]

__all__ = ["THETA", "PARAMETER_SET", "system", "input_signal", "theta_star",
           "excitation_weight", "update_law"]

#: The true parameter used by the examples and tests.
THETA = np.array([1.5])
#: Θ, a little larger than the assumed parameter range.
PARAMETER_SET = Box([0.5], [3.0])

_theta = sp.Symbol("theta", real=True)
_Y_RAMP = smooth_ramp(0.2, 0.5)  # |y| below 0.2: φ says little about θ
_PHI_RAMP = smooth_ramp(0.9, 0.98)  # |φ̂| above 0.98: tanh saturated, atanh ill-conditioned


def system() -> PerturbedLinearSystem:
    """The oscillator with φ = g(v, x, θ) = tanh(θ y) and Θ = [0.5, 3].

    Returns
    -------
    PerturbedLinearSystem
        With its perturbation g and Θ.
    """
    return oscillator(sp.tanh(_theta * y), [_theta], PARAMETER_SET)


def input_signal(t: ArrayLike) -> FloatArray:
    """u(t) = 1.2 sin 0.6t, shape (..., 1).

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
    return (1.2 * np.sin(0.6 * t_))[..., None]


def theta_star(v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike) -> FloatArray:
    """θ* = atanh(φ̂)/y, shape (..., 1); NaN or inf where y = 0 or |φ̂| >= 1 (l = 0 there).

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
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.arctanh(phi[..., :1]) / v_[..., 1:2]


def excitation_weight(v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike) -> FloatArray:
    """l = w(|y|; 0.2, 0.5)(1 - w(|φ̂|; 0.9, 0.98)) in [0, 1], shape (...).

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
    ndarray, shape (...)
        The excitation weight l.
    """
    v_ = np.asarray(v, dtype=np.float64)
    phi = np.asarray(phi_hat, dtype=np.float64)
    return _Y_RAMP.weight(np.abs(v_[..., 1])) * (1.0 - _PHI_RAMP.weight(np.abs(phi[..., 0])))


def update_law(Gamma: ArrayLike = 3.0) -> IntermittentInversion:
    """The Proposition 2 law θ̂̇ = Proj(lΓ(θ* - θ̂)) on Θ.

    Parameters
    ----------
    Gamma : float or array_like, shape (p, p), optional
        Adaptation gain Γ (default 3).

    Returns
    -------
    IntermittentInversion
    """
    return IntermittentInversion(theta_star, excitation_weight, Gamma, PARAMETER_SET)
