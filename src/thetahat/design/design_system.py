"""Gains designed on a simplified "design system" and applied to the true one (Sec. VII–VIII).

A small parameter that lowers the relative degree (the DC motor's σ1) makes the SCB of the
true system ill-conditioned and its gains large. The paper designs on the system with the
parameter set to zero and checks that the resulting K stabilises the true error dynamics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .._validate import as_triple
from ..errors import DimensionError, UnstableDesignError
from .gains import GainDesign, extended_system


@dataclass(frozen=True, slots=True, repr=False)
class DesignSystemReport:
    """Spectra of a design on its design system and on the true system.

    Attributes
    ----------
    design : GainDesign
    eig_design : ndarray of complex
        eig(A_d − K C) of the design system (the extended one for a modified design).
    eig_true : ndarray of complex
        eig(A − K C) of the true system.
    stable : bool
        All true eigenvalues in the open left half-plane.
    """

    design: GainDesign
    eig_design: NDArray[np.complex128]
    eig_true: NDArray[np.complex128]
    stable: bool

    def __repr__(self) -> str:
        def fmt(z):
            return "[" + ", ".join(f"{complex(v):.4g}" for v in z) + "]"
        return (f"DesignSystemReport(stable={self.stable},\n  design: {fmt(self.eig_design)},\n"
                f"  true:   {fmt(self.eig_true)})")


def apply_design(design: GainDesign, A, E, C, *, allow_unstable: bool = False
                 ) -> DesignSystemReport:
    """Apply a gain designed on a simplified system to the true linear part (A, E, C).

    For a modified high-gain design (``design.K_phi`` set) the spectrum is that of the
    extended error system (4); otherwise of ż = (A − K C) z.

    Parameters
    ----------
    design : GainDesign
    A, E, C : array_like
        The true linear part, shapes (n, n), (n, k), (r, n).
    allow_unstable : bool, default False
        Return the report even when the true spectrum is unstable (for analysis reports).

    Returns
    -------
    DesignSystemReport

    Raises
    ------
    UnstableDesignError
        The gain leaves the true error system unstable (unless ``allow_unstable``); the
        message and ``.eigenvalues`` name the unstable eigenvalues.

    Examples
    --------
    The paper's DC motor: design on σ1 = 0, apply to σ1 = 0.6.

    >>> from thetahat import modified_high_gain, apply_design
    >>> J, s0, s1, a2 = 0.0023, 260.0, 0.6, 0.176
    >>> d = modified_high_gain([[-a2 / J, -s0 / J], [1, 0]], [[0], [-1]], [[1, 0]], eps=1.0)
    >>> apply_design(d, [[-(a2 + s1) / J, -s0 / J], [1, 0]], [[s1 / J], [-1]], [[1, 0]]).stable
    True
    """
    A, E, C = as_triple(A, E, C, names=("A", "E", "C"))
    if design.K_phi is not None:
        A_, _, C_ = extended_system(A, E, C)
    else:
        A_, C_ = A, C
    if design.K.shape != (A_.shape[0], C_.shape[0]):
        raise DimensionError(f"design.K has shape {design.K.shape} but the true system needs "
                             f"({A_.shape[0]}, {C_.shape[0]}).")
    eig_true = np.sort_complex(np.linalg.eigvals(A_ - design.K @ C_))
    stable = bool(np.all(eig_true.real < 0))
    if not stable and not allow_unstable:
        bad = eig_true[eig_true.real >= 0]
        raise UnstableDesignError(
            f"the gain designed on the design system (eps = {design.eps:g}) leaves the true "
            f"error system unstable: eigenvalue(s) "
            f"{', '.join(f'{complex(z):.4g}' for z in bad)} with Re >= 0. Decrease eps "
            "(Sec. VII), or design on a system closer to the true one.", eigenvalues=bad)
    return DesignSystemReport(design=design, eig_design=design.eigenvalues, eig_true=eig_true,
                              stable=stable)
