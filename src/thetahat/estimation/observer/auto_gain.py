"""``Gamma = "auto"``: the gradient law's Γ from the information of the record, not from a guess.

The gradient law of Propositions 3–4, θ̂̇ = Proj(Γ (∂g/∂θ)ᵀ (φ̂ − g(v, x̂, θ̂))), linearised
about θ, moves the error θ̃ as θ̃̇ ≈ −Γ H θ̃ with H the information per unit time,

    H = (1/N) Σ_k J_kᵀ J_k,   J_k = ∂g/∂θ(v_k, x̂_k, θ̂₀).

A scalar Γ = 1 is meaningless when the parameters span decades (a mass in kg, a friction in
N s/m, an offset in N): the components then converge at rates that differ by the squares of
their scales. :func:`information_gain` chooses the diagonal

    Γ = (κ / T) diag(H)⁻¹,

which makes every Jacobi-scaled direction converge at a rate κ/T times an eigenvalue of the
scaled H (whose mean is 1): over a record of duration T the law makes κ time constants
(:data:`AUTO_KAPPA`), whatever the units, the sampling rate or the time scale of the process.
A diagonal Γ keeps the Γ⁻¹-weighted projection onto a box a clip (and the compiled path).
x̂ comes from a first pass of the observer with θ̂ held at θ̂₀.

For the least-squares law (:class:`~thetahat.estimation.observer.laws.least_squares.
FilteredLeastSquares`) the same formula gives Γ₀, whose inverse (T/κ) diag(H) is the prior
information on θ̂₀: with κ = :data:`PRIOR_KAPPA` the prior weighs as much as 1/κ of the
record, so the record decides, while the first moments of the run (before the information has
built up) stay near θ̂₀ instead of following the first noisy samples. :func:`auto_kappa`
picks κ by law.

What lives here: :func:`information_gain`, :func:`auto_kappa` and their constants. What it may
import: the model's perturbation and the package's errors only.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...errors import DimensionError, UpdateLawError
from ...model.perturbation import Perturbation

__all__ = ["AUTO_KAPPA", "PRIOR_KAPPA", "auto_kappa", "information_gain"]

FloatArray = NDArray[np.float64]

#: Time constants of the (Jacobi-scaled) gradient law over the record.
AUTO_KAPPA = 10.0
#: The least-squares law's prior is worth 1/PRIOR_KAPPA of the record's information.
PRIOR_KAPPA = 100.0


def auto_kappa(law: object) -> float:
    """κ of ``Gamma = "auto"`` for an update law: :data:`PRIOR_KAPPA` for the least-squares
    law (a prior worth 1/κ of the record), :data:`AUTO_KAPPA` otherwise (κ time constants).

    Parameters
    ----------
    law : UpdateLaw

    Returns
    -------
    float

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.observer.auto_gain import auto_kappa
    >>> auto_kappa(lugre.estimator_spec().law)
    10.0
    """
    from .laws.least_squares import FilteredLeastSquares
    return PRIOR_KAPPA if isinstance(law, FilteredLeastSquares) else AUTO_KAPPA


def information_gain(perturbation: Perturbation, v: FloatArray, x_hat: FloatArray,
                     theta_hat0: FloatArray, duration: float, *,
                     kappa: float = AUTO_KAPPA) -> FloatArray:
    """Γ = (κ / T) diag(H)⁻¹ with H the mean of (∂g/∂θ)ᵀ ∂g/∂θ over the record (module doc).

    Parameters
    ----------
    perturbation : Perturbation
        g with ∂g/∂θ.
    v : ndarray (N, m + r)
        col(u, y) at the samples.
    x_hat : ndarray (N, n)
        State estimate at the samples (a first pass of the observer).
    theta_hat0 : ndarray (p,)
        Where ∂g/∂θ is evaluated.
    duration : float
        T, the record's duration (> 0).
    kappa : float
        κ > 0.

    Returns
    -------
    ndarray (p, p)
        Diagonal and positive definite.

    Raises
    ------
    UpdateLawError
        ∂g/∂θ vanishes on the whole record for some parameter (no information reaches the
        law: the message names it).
    DimensionError
        Non-positive ``duration`` or ``kappa``.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.estimation.observer.auto_gain import information_gain
    >>> g = parse_perturbation("a*y + b", u=[], y=["y"], x=["x"], theta=["a", "b"])
    >>> t = np.linspace(0.0, 10.0, 1001)
    >>> G = information_gain(g, np.sin(t)[:, None], np.zeros((t.size, 1)), np.zeros(2), 10.0)
    >>> np.round(np.diag(G), 2)                 # κ/T / mean(sin²), κ/T / 1
    array([2.1, 1. ])
    """
    if not (np.isfinite(duration) and duration > 0):
        raise DimensionError(f"information_gain: the record's duration must be > 0; got "
                             f"{duration!r}.")
    if not (np.isfinite(kappa) and kappa > 0):
        raise DimensionError(f"information_gain: kappa must be > 0; got {kappa!r}.")
    N = v.shape[0]
    th = np.broadcast_to(np.asarray(theta_hat0, dtype=np.float64), (N, theta_hat0.shape[0]))
    with np.errstate(over="ignore", invalid="ignore"):
        J = np.asarray(perturbation.dg_dtheta(v, x_hat, th), dtype=np.float64)   # (N, k, p)
        sq = np.einsum("nkp,nkp->np", J, J)          # rows whose squares overflow: left out
    ok = np.all(np.isfinite(sq), axis=1)
    h = sq[ok].sum(axis=0) / max(int(ok.sum()), 1)
    dead = np.flatnonzero(~(h > 0))
    if dead.size:
        raise UpdateLawError(f"Gamma = 'auto': ∂g/∂θ vanishes on the whole record for "
                             f"parameter(s) {dead.tolist()} at θ̂₀ = {theta_hat0}: no information "
                             "reaches the law. Give Gamma explicitly or check the model.")
    return np.diag(kappa / duration / h)
