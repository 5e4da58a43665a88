"""The argument tuples of the step's formulas, named and with their shapes: one definition.

The formulas (:mod:`~thetahat.estimation.observer.formulas`,
:mod:`~thetahat.estimation.observer.laws.formulas`) take the plan's arrays, the law's arrays and
their work buffers as tuples ``P``, ``P2``, ``LP`` and ``W``. Every back end builds them as the
named tuples below, by keyword — the NumPy binding (:mod:`~thetahat.estimation.observer.step`,
the laws' own steps), the compiled kernel (:mod:`~thetahat.estimation.observer.compiled`; numba
compiles named tuples like tuples, with their field names) and the C printer — so that a field
means the same everywhere: ``LP.Gamma`` is Γ and ``LP.lower`` Θ's lower bound in each, whatever
else a binding fills in. A field a binding does not use is None.

:data:`SHAPES` gives each field's shape for one row, in the dimensions of the formulas (``NX``,
``NU``, ``NY``, ``NK``, ``NP``, ``NV`` = NU + NY, ``NQ`` = NX + NK, ``NP1`` = NP + 1, ``LS1``
= max(LS, 1)): the printers read it to size the blocks of a formula
(:mod:`~thetahat.estimation.kernels.subset`), :func:`work_arrays` to allocate ``W``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

__all__ = ["LawArrays", "PlanArrays", "SHAPES", "SecondArrays", "WorkArrays", "dimensions",
           "work_arrays"]


class PlanArrays(NamedTuple):
    """``P``: the observer's plan arrays for one step (:class:`~thetahat.estimation.observer.plan.StepPlan`).

    Φ₁ and Φ₂ are those of this step: the corrected ones, or the prediction's over a missing
    sample.
    """

    L: Any
    Bv: Any
    E: Any
    C: Any
    A: Any
    B: Any
    K_x: Any
    KxC: Any
    Phi1: Any
    Phi2: Any


class SecondArrays(NamedTuple):
    """``P2``: the second observer's plan arrays (Sec. VI) for one step."""

    A: Any
    B: Any
    C: Any
    E: Any
    K_x: Any
    Phi1: Any
    Phi2: Any


class LawArrays(NamedTuple):
    """``LP``: what an update law's formula and its hooks read, and its scratch.

    ``Gamma`` is Γ (one per row, or None for the law's own); the inversion law (Propositions
    1–2) reads Γ = V diag(lam) Vᵀ as ``lam``, ``V``, ``VT`` with scratch ``ts``, ``err``; the
    gradient law (Propositions 3–4) reads ``Gamma`` with scratch ``g``, ``J``, ``Mt``, ``GM``,
    ``f``, ``K``, ``Z``, ``Ex``, ``T``, ``U``; the compiled kernel's projection onto a box
    reads ``lower``, ``upper``, its projection onto a ball or an ellipsoid
    (:func:`~thetahat.estimation.kernels.set_projection.project_into`) reads ``ell`` ((p + 1,
    p): the centre c, then Q) with the metric ``Gamma`` (Γ; I for the held law) and the
    scratch ``pw`` ((p + 2, p + 1)), and the inversion law's options ``opts`` = (ramp low,
    ramp high, l is the smooth ramp, on_invalid is "freeze"); the NumPy projection reads
    ``Gamma_rows``, Γ per row (None: the law's own); the filtered least-squares law reads
    its error filter's ``H``, ``Lf`` (L) and ``Phi1`` (Φ₁ of the step) with scratch ``g``,
    ``J``, ``w``, ``wn``, ``wb``, ``Wm``, ``WT``, ``Rn`` (R⁺, also the metric of its
    projection), ``Rf``, ``b``, ``e``, ``Ad``, ``Bd``, ``q`` (and ``pw`` for the compiled
    projection onto a box).
    """

    Gamma: Any = None
    lam: Any = None
    V: Any = None
    VT: Any = None
    ts: Any = None
    err: Any = None
    g: Any = None
    J: Any = None
    Mt: Any = None
    GM: Any = None
    f: Any = None
    K: Any = None
    Z: Any = None
    Ex: Any = None
    T: Any = None
    U: Any = None
    lower: Any = None
    upper: Any = None
    opts: Any = None
    Gamma_rows: Any = None
    ell: Any = None
    pw: Any = None
    H: Any = None
    Lf: Any = None
    Phi1: Any = None
    w: Any = None
    wn: Any = None
    wb: Any = None
    Wm: Any = None
    WT: Any = None
    Rn: Any = None
    Rf: Any = None
    b: Any = None
    e: Any = None
    Ad: Any = None
    Bd: Any = None
    q: Any = None


class WorkArrays(NamedTuple):
    """``W``: the work buffers of one step (:func:`~thetahat.estimation.observer.formulas.advance`).

    The observer's v, g, ∂g/∂x, ∂g/∂y, ∂g/∂θ, the forcing F and its rate, N, the implicit
    step's matrix and right-hand side, φ̂, scratch of lengths r and n, z's correction, Δθ̂, θ̂⁺
    and the law state; then the same for the second observer (suffix 2).
    """

    v: Any
    g: Any
    Gx: Any
    Gy: Any
    Gth: Any
    F: Any
    Fd: Any
    Nm: Any
    M: Any
    rhs: Any
    phi: Any
    wr: Any
    wn: Any
    zc: Any
    dth: Any
    thn: Any
    lsn: Any
    v2: Any
    g2: Any
    Gx2: Any
    Gy2: Any
    F2: Any
    Fd2: Any
    N2: Any
    M2: Any
    rhs2: Any
    w2: Any


#: The shape of each field of one row, by tuple type and field (fields a printer never sizes
#: are left out).
SHAPES: Mapping[str, Mapping[str, tuple[str, ...]]] = {
    "PlanArrays": {"L": ("NQ", "NQ"), "Bv": ("NQ", "NV"), "E": ("NX", "NK"), "C": ("NY", "NX"),
                   "A": ("NX", "NX"), "B": ("NX", "NU"), "K_x": ("NX", "NY"),
                   "KxC": ("NX", "NX"), "Phi1": ("NQ", "NQ"), "Phi2": ("NQ", "NQ")},
    "SecondArrays": {"A": ("NX", "NX"), "B": ("NX", "NU"), "C": ("NY", "NX"),
                     "E": ("NX", "NK"), "K_x": ("NX", "NY"), "Phi1": ("NX", "NX"),
                     "Phi2": ("NX", "NX")},
    "LawArrays": {"Gamma": ("NP", "NP"), "lam": ("NP",), "V": ("NP", "NP"),
                  "VT": ("NP", "NP"), "ts": ("NP",), "err": ("NP",), "g": ("NK",),
                  "J": ("NK", "NP"), "Mt": ("NP", "NK"), "GM": ("NP", "NK"), "f": ("NP",),
                  "K": ("NP", "NP"), "Z": ("NP1", "NP1"), "Ex": ("NP1", "NP1"),
                  "T": ("NP1", "NP1"), "U": ("NP1", "NP1"), "lower": ("NP",),
                  "upper": ("NP",), "H": ("NK", "NQ"), "Lf": ("NQ", "NQ"),
                  "Phi1": ("NQ", "NQ"), "w": ("NQ", "NP"), "wn": ("NQ", "NP"), "wb": ("NQ",),
                  "Wm": ("NK", "NP"), "WT": ("NP", "NK"), "Rn": ("NP", "NP"),
                  "Rf": ("NP", "NP"), "b": ("NP",), "e": ("NK",), "Ad": ("NQ", "NQ"),
                  "Bd": ("NQ", "NK"), "q": ("NQ",)},
    "WorkArrays": {"v": ("NV",), "g": ("NK",), "Gx": ("NK", "NX"), "Gy": ("NK", "NY"),
                   "Gth": ("NK", "NP"), "F": ("NQ",), "Fd": ("NQ",), "Nm": ("NQ", "NQ"),
                   "M": ("NQ", "NQ"), "rhs": ("NQ",), "phi": ("NK",), "wr": ("NY",),
                   "wn": ("NX",), "zc": ("NK",), "dth": ("NP",), "thn": ("NP",),
                   "lsn": ("LS1",), "v2": ("NV",), "g2": ("NK",), "Gx2": ("NK", "NX"),
                   "Gy2": ("NK", "NY"), "F2": ("NX",), "Fd2": ("NX",), "N2": ("NX", "NX"),
                   "M2": ("NX", "NX"), "rhs2": ("NX",), "w2": ("NY",)},
}


def dimensions(n: int, m: int, r: int, k: int, p: int, law_size: int) -> dict[str, int]:
    """The formulas' dimensions by name (module docstring) for a model and a law state.

    Parameters
    ----------
    n, m, r, k, p : int
        Dimensions of x, u, y, φ and θ.
    law_size : int
        Length of the update law's state.

    Returns
    -------
    dict of str to int

    Examples
    --------
    >>> dimensions(2, 1, 1, 1, 1, 0)["NQ"], dimensions(2, 1, 1, 1, 1, 0)["LS1"]
    (3, 1)
    """
    return {"NX": n, "NU": m, "NY": r, "NK": k, "NP": p, "LS": law_size, "NV": m + r,
            "NQ": n + k, "NP1": p + 1, "LS1": max(law_size, 1)}


def work_arrays(dims: Mapping[str, int], lead: tuple[int, ...] = ()) -> WorkArrays:
    """Zeroed work buffers ``W`` for rows of shape ``lead`` (one row: ``()``).

    Parameters
    ----------
    dims : mapping of str to int
        :func:`dimensions`.
    lead : tuple of int
        The batch shape.

    Returns
    -------
    WorkArrays

    Examples
    --------
    >>> W = work_arrays(dimensions(2, 1, 1, 1, 1, 0), (4,))
    >>> W.Gx.shape, W.lsn.shape
    ((4, 1, 2), (4, 1))
    """
    shapes = SHAPES["WorkArrays"]
    return WorkArrays(*(np.zeros(lead + tuple(dims[d] for d in shapes[name]))
                        for name in WorkArrays._fields))
