"""Assumption 1 in one call: is (C, A, E) left-invertible and minimum-phase?"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_triple
from ..errors import NotLeftInvertibleError, NotMinimumPhaseError
from .subspaces import rank
from .zeros import MINIMUM_PHASE_RTOL, invariant_zeros, normal_rank, unstable_zeros


@dataclass(frozen=True, slots=True, repr=False)
class AssumptionReport:
    """The outcome of :func:`check_assumption_1`.

    Attributes
    ----------
    left_invertible : bool
        Normal rank of the Rosenbrock matrix equals n + k.
    normal_rank : int
    rank_E : int
    zeros : ndarray of complex
        All invariant zeros (Rosenbrock definition: decoupling zeros count).
    minimum_phase : bool
        All zeros in the open left half-plane, with margin ``rtol·max(1, ‖A‖)``.
    offending_zeros : ndarray of complex
        The zeros that break minimum phase.
    n, k : int
    """

    left_invertible: bool
    normal_rank: int
    rank_E: int
    zeros: NDArray[np.complex128]
    minimum_phase: bool
    offending_zeros: NDArray[np.complex128]
    n: int
    k: int

    @property
    def holds(self) -> bool:
        """True when Assumption 1 holds."""
        return self.left_invertible and self.minimum_phase

    def __str__(self) -> str:
        z = ", ".join(f"{complex(v):.6g}" for v in self.zeros) or "none"
        lines = [
            f"Assumption 1 (Grip, Saberi & Johansen): {'holds' if self.holds else 'FAILS'}",
            f"  left-invertible : {self.left_invertible} (normal rank {self.normal_rank} of "
            f"n + k = {self.n + self.k}; rank E = {self.rank_E})",
            f"  invariant zeros : {z}",
            f"  minimum-phase   : {self.minimum_phase}",
        ]
        if self.offending_zeros.size:
            bad = ", ".join(f"{complex(v):.6g}" for v in self.offending_zeros)
            lines.append(f"  offending zeros : {bad} (closed right half-plane)")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"AssumptionReport(holds={self.holds}, left_invertible={self.left_invertible}, "
                f"minimum_phase={self.minimum_phase}, zeros={np.round(self.zeros, 6).tolist()})")


def check_assumption_1(A: ArrayLike, E: ArrayLike, C: ArrayLike, *, strict: bool = False, tol: float | None = None,
                       rtol: float = MINIMUM_PHASE_RTOL) -> AssumptionReport:
    """Check Assumption 1: the triple (C, A, E) is left-invertible and minimum-phase.

    Parameters
    ----------
    A : array_like, shape (n, n)
    E : array_like, shape (n, k)
    C : array_like, shape (r, n)
    strict : bool
        Raise instead of reporting when the assumption fails.
    tol : float, optional
        Rank tolerance of the zero computation.
    rtol : float
        Minimum-phase margin (see ``unstable_zeros``).

    Returns
    -------
    AssumptionReport

    Raises
    ------
    NotLeftInvertibleError
        With ``strict=True``, when (C, A, E) is not left-invertible.
    NotMinimumPhaseError
        With ``strict=True``, when a zero lies in the closed right half-plane; the message and
        ``.zeros`` name the offending zeros.

    Examples
    --------
    >>> from thetahat import check_assumption_1
    >>> rep = check_assumption_1([[-1.0, 0], [1, -2]], [[1.0], [0]], [[0, 1.0]])
    >>> rep.holds, rep.zeros.size
    (True, 0)
    """
    A, E, C = as_triple(A, E, C, names=("A", "E", "C"))
    n, k = E.shape
    nr = normal_rank(A, E, C, tol=tol)
    left = nr == n + k
    zeros = invariant_zeros(A, E, C, tol=tol)
    scale = max(1.0, float(np.linalg.norm(A, 2)))
    bad = unstable_zeros(zeros, scale=scale, rtol=rtol)
    rE = rank(E / max(float(np.linalg.norm(E, 2)), 1e-300), 1e-10)
    rep = AssumptionReport(left_invertible=bool(left), normal_rank=int(nr), rank_E=int(rE),
                           zeros=zeros, minimum_phase=bad.size == 0, offending_zeros=bad,
                           n=n, k=k)
    if strict and not left:
        raise NotLeftInvertibleError(
            f"(C, A, E) is not left-invertible: the Rosenbrock matrix has normal rank {nr} < "
            f"n + k = {n + k} (rank E = {rE}). Add outputs that see the perturbation or reduce "
            "E to the directions the outputs can distinguish.", rank_B=rE, normal_rank=nr)
    if strict and bad.size:
        zs = ", ".join(f"{complex(v):.6g}" for v in bad)
        raise NotMinimumPhaseError(
            f"(C, A, E) is not minimum-phase: invariant zero(s) {zs} in the closed right "
            "half-plane. The observer error would not converge (A_a of (5)/(6) is not "
            "Hurwitz); change the measured outputs or the model of where φ enters.", zeros=bad)
    return rep
