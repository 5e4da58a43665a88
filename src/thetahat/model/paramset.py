"""Compact convex parameter sets Θ and their projection (Krstić et al. 1995, App. E)."""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class ParameterSet(ABC):
    """Abstract compact convex Θ ⊂ R^p.

    Concrete classes are final frozen dataclasses (``Box``, ``Ball``, ``Ellipsoid``, ...).
    """

    @property
    @abstractmethod
    def dim(self) -> int:
        """p, the number of parameters."""

    @abstractmethod
    def contains(self, theta: FloatArray, *, tol: float = 0.0) -> bool | NDArray[np.bool_]:
        """Membership θ ∈ Θ (batch over leading axes)."""

    @abstractmethod
    def nearest(self, theta: FloatArray) -> FloatArray:
        """Euclidean projection of θ onto Θ (batch); identity inside Θ."""
