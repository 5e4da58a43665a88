"""Model-file report: Assumptions 1 and 2, the SCB, K(ε) and the spectra (``thetahat analyze``)."""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..design.design_system import DesignSystemReport, apply_design
from ..design.gains import GainDesign, extended_system
from ..errors import ThetahatError
from ..model.state_set import (ASSUMPTION_2_REMEDY, GROWTH_DECADES, GROWTH_LIMIT,
                               lipschitz_growth, state_scale)
from ..structure.assumptions import AssumptionReport, check_assumption_1
from ..structure.scb import SCBResult, scb
from .assembly import design_gains, design_matrices
from .schema import ModelSpec

__all__ = ["ModelAnalysis", "analyze_model"]

FloatArray = NDArray[np.float64]

@dataclass(frozen=True, slots=True, repr=False)
class ModelAnalysis:
    """Structural report of a model file (``thetahat analyze``).

    Attributes
    ----------
    spec : ModelSpec
    assumption : AssumptionReport
        Assumption 1 for the true (C, A, E).
    scb : SCBResult or None
        SCB of the extended error system (4) with K = 0 (true matrices); None when it cannot
        be computed (the reason is in ``design_error``).
    scb_design : SCBResult or None
        The same for the design system, when the file gives one.
    design : GainDesign or None
        K(ε) = [K_x; K_φ] (None when the design failed: see ``design_error``).
    spectra : DesignSystemReport or None
        eig of (4) with K(ε) on the design system and on the true system.
    design2 : GainDesign or None
        Gain of the second observer.
    spectra2 : DesignSystemReport or None
        Its closed-loop spectra on the design and true systems.
    design_error : str or None
        Why the gains (or the SCB) could not be computed.
    warnings : tuple of str
        Warnings raised during the analysis (e.g. an ill-conditioned SCB).
    x_growth : float
        Assumption 2's global condition probed at the scenario's x(0) and θ (u = 0): how much
        ‖∂g/∂x‖ grows from x(0)'s scale to 100 times it
        (:func:`~thetahat.model.state_set.lipschitz_growth`; NaN when g could not be probed).
    """

    spec: ModelSpec
    assumption: AssumptionReport
    scb: SCBResult | None
    scb_design: SCBResult | None
    design: GainDesign | None
    spectra: DesignSystemReport | None
    design2: GainDesign | None
    spectra2: DesignSystemReport | None
    design_error: str | None
    warnings: tuple[str, ...]
    x_growth: float = float("nan")

    @property
    def ok(self) -> bool:
        """Assumption 1 holds and every design is stable on the true system
        (``thetahat analyze`` exits 0 exactly then)."""
        return (self.assumption.holds and self.design is not None
                and self.spectra is not None and self.spectra.stable
                and (self.spectra2 is None or self.spectra2.stable))

    def verdict(self) -> str:
        """One sentence: why the analysis passed or failed."""
        if self.ok:
            return "Assumption 1 holds and the design is stable on the true system."
        if not self.assumption.holds:
            bad = ", ".join(f"{complex(z):.6g}" for z in self.assumption.offending_zeros)
            why = ("(C, A, E) is not left-invertible" if not self.assumption.left_invertible
                   else f"invariant zero(s) {bad} in the closed right half-plane")
            return f"Assumption 1 fails on the true system: {why}."
        if self.design is None:
            return f"the gains could not be designed: {self.design_error}"
        return "the design leaves the true error system unstable (see the spectra above)."

    def __repr__(self) -> str:
        return (f"ModelAnalysis(name={self.spec.name!r}, assumption_1={self.assumption.holds}, "
                f"stable={None if self.spectra is None else self.spectra.stable})")

    def __str__(self) -> str:
        def eig(z: Any) -> str:
            return "[" + ", ".join(_complex(v) for v in z) + "]"

        def vec(K: FloatArray) -> str:
            if K.shape[1] == 1:
                return "[" + ", ".join(f"{v:.6g}" for v in K.ravel()) + "]"
            return "[" + "; ".join(", ".join(f"{v:.6g}" for v in row) for row in K) + "]"

        est = self.spec.estimator
        s = self.spec.system
        lines = [f"model: {self.spec.name} ({self.spec.source})",
                 f"  n = {s.n}, m = {s.m}, r = {s.r}, k = {s.k}, p = {s.p}; law = {est.law}",
                 str(self.assumption),
                 f"SCB of the error system (4), true matrices: "
                 f"{'not computed' if self.scb is None else repr(self.scb)}"]
        if self.scb_design is not None:
            lines.append(f"SCB of the error system (4), design system: {self.scb_design!r}")
        if self.design_error is not None:
            lines.append(f"gain design FAILED: {self.design_error}")
        if self.design is not None and self.spectra is not None:
            n = self.spec.system.n
            auto = " (eps = 'auto' is chosen on a record: shown at 1)" if est.eps_auto else ""
            lines += [f"K(eps = {self.design.eps:g}) = [K_x; K_phi] = {vec(self.design.K)}{auto}",
                      f"  K_x = {vec(self.design.K[:n])}, K_phi = {vec(self.design.K[n:])}",
                      f"  eig on the design system: {eig(self.spectra.eig_design)}",
                      f"  eig on the true system:   {eig(self.spectra.eig_true)}",
                      f"  stable on the true system: {self.spectra.stable}"]
        if self.design2 is not None and self.spectra2 is not None:
            lines += [f"second observer: K(eps2 = {self.design2.eps:g}) = {vec(self.design2.K)}",
                      f"  eig on the design system: {eig(self.spectra2.eig_design)}",
                      f"  eig on the true system:   {eig(self.spectra2.eig_true)}",
                      f"  stable on the true system: {self.spectra2.stable}"]
        lines.append(self._assumption_2())
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)

    def _assumption_2(self) -> str:
        head = "Assumption 2 (g Lipschitz in x for every x̂, probed at the scenario's x0): "
        X = self.spec.state_set
        if X is not None:
            return (head + "holds by construction: g is saturated outside X = [state_set] "
                    "(Remark 1)")
        if not self.x_growth > GROWTH_LIMIT:
            return head + ("not probed" if math.isnan(self.x_growth)
                           else f"looks global (‖∂g/∂x‖ at {10 ** GROWTH_DECADES} times x0's "
                                f"scale is {self.x_growth:.3g} × its largest value nearer)")
        growth = ("without bound" if math.isinf(self.x_growth)
                  else f"{self.x_growth:.3g}-fold")
        return (head + f"FAILS: ‖∂g/∂x‖ grows {growth} at {10 ** GROWTH_DECADES} times x0's "
                "scale, so the paper's guarantee is not global and its observer can be driven "
                f"off; {ASSUMPTION_2_REMEDY}")


def _x_growth(spec: ModelSpec) -> float:
    """:func:`~thetahat.model.state_set.lipschitz_growth` at the scenario's x(0) and θ."""
    s, sc = spec.system, spec.scenario
    if s.perturbation is None:
        return math.nan
    x0 = np.asarray(sc.x0, dtype=np.float64)
    v = np.concatenate([np.zeros(s.m), s.C @ x0])
    try:
        return lipschitz_growth(s.perturbation, v, x0, np.asarray(sc.theta, dtype=np.float64),
                                state_scale(x0))
    except ThetahatError:
        return math.nan


def _complex(v: complex) -> str:
    v = complex(v)
    if abs(v.imag) <= 1e-12 * max(1.0, abs(v.real)):
        return f"{v.real:.6g}"
    return f"{v.real:.6g}{v.imag:+.6g}j"


def analyze_model(spec: ModelSpec) -> ModelAnalysis:
    """Assumption 1, the SCB of (4), K(ε) and the closed-loop spectra of a model file.

    Parameters
    ----------
    spec : ModelSpec
        From :func:`load_model`.

    Returns
    -------
    ModelAnalysis
        ``str(result)`` is the report ``thetahat analyze`` prints.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, analyze_model, loads_model
    >>> report = analyze_model(loads_model(EXAMPLE_MODEL))
    >>> report.assumption.holds, report.spectra.stable
    (True, True)
    """
    s = spec.system
    caught: list[str] = []
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        assumption = check_assumption_1(s.A, s.E, s.C)
        A_d, E_d, C = design_matrices(spec)
        design = design2 = spectra = spectra2 = sc = sc_d = None
        error = None
        try:
            sc = scb(*extended_system(s.A, s.E, s.C))
            if spec.estimator.A_design is not None or spec.estimator.E_design is not None:
                sc_d = scb(*extended_system(A_d, E_d, C))
            # the report shows Assumption 1 and the true spectra itself: design without the
            # refusals that building an estimator applies
            study = dataclasses.replace(spec, estimator=dataclasses.replace(
                spec.estimator, allow_nonminimum_phase=True))
            design, design2 = design_gains(study, None)
        except ThetahatError as exc:
            error = str(exc)
        if design is not None:
            spectra = apply_design(design, s.A, s.E, s.C, allow_unstable=True)
        if design2 is not None:
            spectra2 = apply_design(design2, s.A, s.E, s.C, allow_unstable=True)
    caught = [f"{w.category.__name__}: {w.message}" for w in record]
    return ModelAnalysis(spec=spec, assumption=assumption, scb=sc, scb_design=sc_d,
                         design=design, spectra=spectra, design2=design2, spectra2=spectra2,
                         design_error=error, warnings=tuple(dict.fromkeys(caught)),
                         x_growth=_x_growth(spec))
