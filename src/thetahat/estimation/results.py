"""What the observer returns: estimates over a record (an
:class:`~thetahat.estimation.protocol.EstimateResult`, also named :data:`ObserverResult`) and
from one streaming state (:class:`ObserverEstimate`)."""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np
from numpy.typing import NDArray

from .protocol import EstimateResult

__all__ = ["ObserverEstimate", "ObserverResult"]

FloatArray = NDArray[np.float64]


#: The observer's name for :class:`~thetahat.estimation.protocol.EstimateResult` (kept so that
#: ``thetahat.ObserverResult`` stays importable; every estimator returns that one type).
ObserverResult = EstimateResult


@dataclass(frozen=True, slots=True, eq=False)
class ObserverEstimate:
    """Estimates read from one streaming state (:meth:`ModifiedHighGainObserver.estimate`).

    Attributes
    ----------
    x_hat : ndarray, shape (n,)
    phi_hat : ndarray, shape (k,)
    theta_hat : ndarray, shape (p,)
    x_hat_refined : ndarray, shape (n,), or None
    """

    x_hat: FloatArray
    phi_hat: FloatArray
    theta_hat: FloatArray
    x_hat_refined: FloatArray | None
