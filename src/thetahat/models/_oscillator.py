"""The damped oscillator shared by the Proposition 1–4 examples.

ẋ₁ = x₂, ẋ₂ = -x₁ - 0.5 x₂ + u + φ, y = x₁: (C, A, E) has relative degree 2 and no
invariant zeros, so it is left-invertible and minimum-phase (Assumption 1).
"""

from __future__ import annotations

import numpy as np
import sympy as sp
from numpy.typing import NDArray

from ..model.paramset import ParameterSet
from ..model.perturbation import SymbolicPerturbation
from ..model.system import PerturbedLinearSystem

FloatArray = NDArray[np.float64]

A = np.array([[0.0, 1.0], [-1.0, -0.5]])
B = np.array([[0.0], [1.0]])
C = np.array([[1.0, 0.0]])
E = np.array([[0.0], [1.0]])

#: The symbols every example uses: u, y = x₁ (measured), the states x₁, x₂.
u, y, x1, x2 = sp.symbols("u y x1 x2", real=True)


def oscillator(expr: sp.Expr, theta: list[sp.Symbol],
               parameter_set: ParameterSet) -> PerturbedLinearSystem:
    """The oscillator with φ = expr(u, y, x₁, x₂, θ)."""
    g = SymbolicPerturbation.from_sympy(expr, u=[u], y=[y], x=[x1, x2], theta=theta)
    return PerturbedLinearSystem(A=A, B=B, C=C, E=E, perturbation=g,
                                 parameter_set=parameter_set)
