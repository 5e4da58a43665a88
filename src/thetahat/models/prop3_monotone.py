"""Proposition 3 example: φ = (2 + sin y)(θ + θ³/3), a monotone perturbation.

Plant: the damped oscillator ẋ₁ = x₂, ẋ₂ = -x₁ - 0.5 x₂ + u + φ, y = x₁, with
θ ∈ Θ = [-2, 2] (true value 1.2).

Why Proposition 3 applies: ∂g/∂θ = (2 + sin y)(1 + θ²) >= 1 for all (v, x, θ), so with the
constant M = 1 condition (13) holds with P = 1:
M ∂g/∂θ(θ₂) + ∂g/∂θ(θ₂)ᵀ Mᵀ = 2(2 + sin y)(1 + θ₂²) >= 2. The gradient-type law
θ̂̇ = Proj(Γ(φ̂ - g(v, x̂, θ̂))) then gives V̇ <= -‖θ̃‖² for V = ½θ̃ᵀΓ⁻¹θ̃, i.e. ‖θ̃‖ decays at
least like e^(-Γ t) with perfect x̂ and φ̂, without solving the cubic for θ. (The cubic can
be inverted too — ``algebraic_from_perturbation`` finds its real Cardano branch —
but the gradient law needs no inverse at all, which is the point of Proposition 3.) Check
(13) with :func:`~thetahat.estimation.observer.checks.check_monotonicity`.

Examples
--------
>>> import numpy as np
>>> from thetahat.models import prop3_monotone
>>> law = prop3_monotone.update_law(Gamma=1.0)
>>> v, x = np.array([0.0, 0.0]), np.zeros(2)
>>> phi = prop3_monotone.system().perturbation.g(v, x, prop3_monotone.THETA)
>>> bool(law.rate(v, x, phi, np.array([0.0]))[0] > 0)    # θ̂ = 0 < θ: pushed up
True
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from ..estimation.observer.laws import GradientInversion
from ..model.paramset import Box
from ..model.perturbation import Perturbation
from ..model.system import PerturbedLinearSystem
from ._oscillator import oscillator, y

FloatArray = NDArray[np.float64]

if TYPE_CHECKING:
    from ..simulation.simulate import PlantTrajectory

__all__ = ["THETA", "PARAMETER_SET", "system", "input_signal", "M", "simulate", "update_law"]

#: The true parameter used by the examples and tests.
THETA = np.array([1.2])
#: Θ, a little larger than the assumed parameter range.
PARAMETER_SET = Box([-2.0], [2.0])

_theta = sp.Symbol("theta", real=True)


def system() -> PerturbedLinearSystem:
    """The oscillator with φ = g(v, x, θ) = (2 + sin y)(θ + θ³/3) and Θ = [-2, 2].

    Returns
    -------
    PerturbedLinearSystem
        With its perturbation g and Θ.
    """
    return oscillator((2 + sp.sin(y)) * (_theta + _theta**3 / 3), [_theta], PARAMETER_SET)


def input_signal(t: ArrayLike) -> FloatArray:
    """u(t) = sin 0.8t, shape (..., 1).

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
    return np.sin(0.8 * t_)[..., None]


def M(v: ArrayLike, x: ArrayLike, theta: ArrayLike) -> FloatArray:
    """The constant M = 1, shape (..., 1, 1).

    Parameters
    ----------
    v : array_like, shape (..., m + r)
        col(u, y).
    x : array_like, shape (..., n)
        The state (estimate).
    theta : array_like, shape (..., p)
        The parameter (estimate).

    Returns
    -------
    ndarray, shape (..., 1, 1)
        M = 1.
    """
    th = np.asarray(theta, dtype=np.float64)
    return np.ones(th.shape[:-1] + (1, 1))


def update_law(Gamma: ArrayLike = 2.0) -> GradientInversion:
    """The Proposition 3 law θ̂̇ = Proj(Γ M (φ̂ - g(v, x̂, θ̂))) with M = 1.

    Parameters
    ----------
    Gamma : float or array_like, shape (p, p), optional
        Adaptation gain Γ (default 2).

    Returns
    -------
    GradientInversion
    """
    sys = system()
    return GradientInversion(cast(Perturbation, sys.perturbation), Gamma, PARAMETER_SET, M=M)


def simulate(seed: int = 0, *, theta: ArrayLike = THETA, t_end: float = 20.0, fs: float = 50.0,
             noise_std: float = 0.01) -> "PlantTrajectory":
    """The oscillator driven by :func:`input_signal`, sampled at ``fs`` with seeded noise on y.

    The plant's φ is the model's g (no Remark 4 distinction here: g depends on y = x₁ only
    through sin, and the plant uses the true x₁). Used to generate fleets of records.

    Parameters
    ----------
    seed : int
        Noise seed.
    theta : array_like, shape (1,)
        The true θ (default :data:`THETA`).
    t_end, fs : float
        Duration (s) and sampling frequency (Hz).
    noise_std : float
        Standard deviation of the white noise on y (0: none).

    Returns
    -------
    PlantTrajectory

    Examples
    --------
    >>> from thetahat.models import prop3_monotone
    >>> prop3_monotone.simulate(seed=1, t_end=1.0).y.shape
    (51, 1)
    """
    from ..simulation.noise import WhiteNoise
    from ..simulation.simulate import simulate_plant

    sys_ = system()
    g = cast(Perturbation, sys_.perturbation)          # system() always attaches g

    def phi(t: Any, x: FloatArray, u: FloatArray, th: FloatArray) -> FloatArray:
        v = np.concatenate([np.atleast_2d(u), np.atleast_2d(x)[..., :1]], axis=-1)
        return np.asarray(g.g(v, np.atleast_2d(x), th), dtype=np.float64).reshape(
            np.shape(x)[:-1] + (1,))

    return simulate_plant(sys_, phi=phi, u=lambda t: input_signal(t), t_end=t_end, fs=fs,
                          x0=np.zeros(2), theta=np.atleast_1d(theta), seed=seed,
                          noise=WhiteNoise(noise_std) if noise_std > 0 else None,
                          method="RK45", rtol=1e-8, atol=1e-10)
