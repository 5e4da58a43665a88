"""Parameter update laws u_θ(v, x̂, φ̂, θ̂) of Sec. IV (Propositions 1–4)."""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import NDArray

from ..model.paramset import ParameterSet

FloatArray = NDArray[np.float64]


class UpdateLaw(ABC):
    """Abstract update law (8): θ̂̇ = u_θ(v, x̂, φ̂, θ̂), projection included.

    Concrete laws are final frozen dataclasses. Two entry points over one law:
    ``rate`` for continuous time (the observer's (3b) uses it as θ̂̇) and ``step`` for
    discrete time, which must return a point of Θ whatever the data.
    """

    @property
    @abstractmethod
    def parameter_set(self) -> ParameterSet:
        """Θ, where θ̂ stays."""

    @abstractmethod
    def rate(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
             theta_hat: FloatArray) -> FloatArray:
        """θ̂̇ = u_θ(v, x̂, φ̂, θ̂) (8); shape (..., p)."""

    def step(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
             theta_hat: FloatArray, dt: float) -> FloatArray:
        """θ̂ after a step of length dt, guaranteed in Θ (default: Euler, then ``nearest``)."""
        nxt = theta_hat + dt * self.rate(v, x_hat, phi_hat, theta_hat)
        return self.parameter_set.nearest(nxt)
