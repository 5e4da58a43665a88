"""Parameter update laws u_θ(v, x̂, φ̂, θ̂) of Sec. IV (Propositions 1–4, and the least-squares
law on the filtered regressor).

Every law has two entry points over one formula: ``rate`` returns θ̂̇ = u_θ(v, x̂, φ̂, θ̂) (8),
projection included, for ODE integrators and for the observer's (3b); ``step`` advances θ̂ over
a time step and always returns a point of Θ, whatever the data and the step length.

Batch convention: ``v (..., m + r)``, ``x_hat (..., n)``, ``phi_hat (..., k)``,
``theta_hat (..., p)``; leading shapes broadcast, results have shape ``(..., p)``.
"""

from __future__ import annotations

from .gradient import GradientInversion
from .inversion import (WEIGHT_TOL, AlgebraicInversion, IntermittentInversion, SmoothRamp,
                        algebraic_from_perturbation, invalid_theta_star_error, smooth_ramp)
from .base import FAR, INIT_RTOL, ConstantLaw, UpdateLaw
from .least_squares import FilteredLeastSquares

__all__ = ["UpdateLaw", "ConstantLaw", "AlgebraicInversion", "algebraic_from_perturbation",
           "IntermittentInversion",
           "GradientInversion", "FilteredLeastSquares", "SmoothRamp", "invalid_theta_star_error", "smooth_ramp",
           "FAR", "INIT_RTOL", "WEIGHT_TOL"]
