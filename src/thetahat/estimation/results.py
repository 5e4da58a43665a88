"""What the observer returns: estimates over a record (:class:`ObserverResult`) and from one
streaming state (:class:`ObserverEstimate`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from .trust import TrustReport

__all__ = ["ObserverEstimate", "ObserverResult"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class ObserverResult:
    """Estimates over a sampled record, returned by :meth:`ModifiedHighGainObserver.run`.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sampling instants.
    x_hat : ndarray, shape (N, n)
        State estimate x̂ of (3a).
    phi_hat : ndarray, shape (N, k)
        Perturbation estimate φ̂ = g(v, x̂, θ̂) + z of (3c).
    theta_hat : ndarray, shape (N, p)
        Parameter estimate θ̂ of (8).
    x_hat_refined : ndarray, shape (N, n), or None
        x̂₂ of the second observer of Sec. VI (None when none is attached).
    skipped : ndarray of bool, shape (N,)
        Samples whose y held NaN and were used without output correction
        (``nan_policy="skip"``).
    trust : TrustReport or None
        What the estimate says about itself (:func:`~thetahat.estimation.trust.trust_report`:
        identifiability, Θ's boundary, the guard, the model error), when it was checked
        (:func:`~thetahat.modelfile.run_estimator` checks by default).
    """

    t: FloatArray
    x_hat: FloatArray
    phi_hat: FloatArray
    theta_hat: FloatArray
    x_hat_refined: FloatArray | None
    skipped: NDArray[np.bool_]
    trust: TrustReport | None = None

    def __repr__(self) -> str:
        N = self.t.shape[0]
        span = f"[{self.t[0]:.6g}, {self.t[-1]:.6g}]" if N else "[]"
        refined = "None" if self.x_hat_refined is None else f"{self.x_hat_refined.shape}"
        return (f"ObserverResult(N={N}, t={span}, x_hat={self.x_hat.shape}, "
                f"phi_hat={self.phi_hat.shape}, theta_hat={self.theta_hat.shape}, "
                f"x_hat_refined={refined}, skipped={int(self.skipped.sum())})")

    def to_dataframe(self, *, state_names: Any = None, parameter_names: Any = None) -> Any:
        """A :class:`pandas.DataFrame` indexed by t (:func:`thetahat.tables.result_to_dataframe`).

        Parameters
        ----------
        state_names, parameter_names : sequence of str, optional
            Column suffixes (default 1, 2, …).
        """
        from ..tables import result_to_dataframe
        return result_to_dataframe(self, state_names=state_names,
                                   parameter_names=parameter_names)

    def to_xarray(self, *, state_names: Any = None, parameter_names: Any = None) -> Any:
        """An :class:`xarray.Dataset` over t (:func:`thetahat.tables.result_to_xarray`).

        Parameters
        ----------
        state_names, parameter_names : sequence of str, optional
            Coordinate labels (default 1, 2, …).
        """
        from ..tables import result_to_xarray
        return result_to_xarray(self, state_names=state_names,
                                parameter_names=parameter_names)


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
