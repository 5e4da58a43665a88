"""The perturbation φ = g(v, x, θ) and its Jacobians ∂g/∂v, ∂g/∂x, ∂g/∂θ (Sec. II).

Batch convention used throughout thetahat: arguments carry any leading batch shape,
``v (..., m + r)``, ``x (..., n)``, ``theta (..., p)``; results are ``g (..., k)``,
``dg_dv (..., k, m + r)``, ``dg_dx (..., k, n)``, ``dg_dtheta (..., k, p)``. Leading shapes
broadcast against each other.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class Perturbation(ABC):
    """Abstract φ = g(v, x, θ) with v = col(u, y).

    Concrete classes are final: combine them, do not subclass them.
    """

    @property
    @abstractmethod
    def dims(self) -> tuple[int, int, int, int, int]:
        """(n, m, r, p, k): states, inputs, outputs, parameters, perturbation size."""

    @abstractmethod
    def g(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """φ = g(v, x, θ); shape (..., k)."""

    @abstractmethod
    def dg_dv(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂v; shape (..., k, m + r)."""

    @abstractmethod
    def dg_dx(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂x; shape (..., k, n)."""

    @abstractmethod
    def dg_dtheta(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂θ; shape (..., k, p)."""
