"""The argument tuples of the step's formulas, named: one definition for every binding.

The formulas (:mod:`~thetahat.estimation.observer.formulas`, :mod:`~thetahat.estimation.observer.laws.formulas`)
take the plan's arrays and the law's arrays as tuples ``P``, ``P2`` and ``LP``. Every back end
builds them as the named tuples below, by keyword — the NumPy binding
(:mod:`~thetahat.estimation.observer.step`, the laws' own steps), the compiled kernel
(:mod:`~thetahat.estimation.observer.compiled`; numba compiles named tuples like tuples, with their
field names) — so that a field means the same everywhere: ``LP.Gamma`` is Γ and ``LP.lower``
Θ's lower bound in each, whatever else a binding fills in. A field a binding does not use is
None.
"""

from __future__ import annotations

from typing import Any, NamedTuple

__all__ = ["LawArrays", "PlanArrays", "SecondArrays"]


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
    ``Gamma_rows``, Γ per row (None: the law's own).
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
