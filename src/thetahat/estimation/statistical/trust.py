"""Can the result be trusted? Identifiability, Θ's boundary, the guard's band, the model error.

A number is only as good as what it says about itself. :func:`trust_report` checks an
estimate θ̂ of a record against four questions and :class:`TrustReport` answers them, in its
``lines`` for a summary and as :class:`~thetahat.errors.ThetahatWarning` texts in
``warnings``:

* **How well does this record pin each parameter?** The Cramér–Rao standard deviation of θ at
  θ̂ for this record: the inverse of the Fisher information of the innovations of the model
  (the Gauss–Newton information of
  :mod:`~thetahat.estimation.statistical.likelihood`), with the process noise that the data support
  (q̂ from a one-dimensional search of the likelihood at θ̂; 0 for an exact model, when the
  bound is the output-error one with x(0) unknown). A parameter whose standard deviation is
  at least :data:`UNPINNED_FRACTION` of Θ's width is named as one the data cannot pin: the
  record says no more about it than Θ does.
* **Did θ̂ end on Θ's boundary?** Then Θ, not the data, decided it (within
  :data:`BOUNDARY_RTOL` of a face of a box; for a ball, ellipsoid or convex set, within that
  fraction of the boundary surface, naming the parameters along which its normal points:
  :func:`~thetahat.estimation.statistical.stage2_set.on_boundary`).
* **Was the guarantee empty?** For the guarded estimator: the fraction of the run in which the
  guard's band δ was Θ's full width — per component, the width of Θ's bounding box (the
  output then is stage 2's, projected onto Θ, and stage 1's
  convergence guarantees nothing); warned when above :data:`EMPTY_GUARD_FRACTION`.
* **Is the model wrong?** When the likelihood prefers process noise on φ (q̂ > 0 at more than
  :data:`MODEL_ERROR_Q` times the data's own scale q₀), the model does not explain the record
  to the measurement noise: the estimate is the best symmetric fit of a model that errs.

  The scale is that of the measurement noise σ̂ estimated from the record, at least
  :data:`NOISE_FLOOR` of the output's spread: σ̂ ≈ 0 (a noise-free record) would make the
  rounding of the model's discretisation a "model error" of 10⁵ × a scale of 10⁻¹⁵⁰.
* **Is θ̂ where the data put it?** (every method; the check the paper's method needs most.)
  Rao's score test at θ̂ with the gradient and the Gauss–Newton information of the same
  innovations likelihood that gives the bound
  (:func:`~thetahat.estimation.statistical.likelihood.record_evidence`, no extra filter
  pass): the statistic δᵀIδ, δ the Gauss–Newton step from θ̂, is χ²_p when θ̂ is the true
  θ, and a fit's θ̂ makes it ≈ 0. Above the χ²_p quantile at 1 − :data:`CONSISTENCY_ALPHA`
  the estimate is not consistent with the record; the report gives θ̂ + δ (projected onto Θ),
  where one step puts the data's preference. The joint statistic spreads one parameter's
  miss over p degrees of freedom (p = 4: one parameter 4.2 sd off passes it), so each
  component is tested too: δᵢ / sdᵢ is N(0, 1) at the true θ (δ ~ N(0, (JᵀJ)⁺), sdᵢ the
  bound's), and above :func:`component_limit`, the two-sided normal quantile at level
  :data:`CONSISTENCY_ALPHA` / p (Bonferroni: a true θ fails some component on at most α of
  the records), that parameter is not where the data put it. The two tests together fail a
  true θ on at most 2α of the records. A parameter that passes with its step beyond
  :data:`BORDERLINE_SDS` (3 sd) is reported as borderline: a warning, not a rejection, so
  that no θ̂ more than 3 of its own standard deviations from the data's preference goes
  unsaid. The score test rather than the likelihood ratio
  against a fit: it needs no fit (the paper's method would otherwise pay for the MAP fits it
  avoids), and its ingredients are those of the bound.
* **Has θ̂ settled?** The drift of each component of θ̂ over the last :data:`SETTLE_TAIL` of
  the record (:func:`tail_movement`), in its Cramér–Rao standard deviations: above
  :data:`SETTLE_SDS`, the estimate is still on its way when the record ends.
* **Did the law's conditions hold along the run?** For the paper's observer, (14) and the
  excitation of Props. 2–4 sampled along the run's own (v, x̂, θ̂)
  (:func:`~thetahat.estimation.observer.checks.law_conditions_on_record`, computed by the
  caller and carried here).

What it may import: :mod:`thetahat.model`, the package's errors, the observer's checks (their
report's type), and, in this room, ``common``, ``input_hold``, ``likelihood``,
``noise_level``, ``plant_kernel`` and ``stage2_set``; the estimators' results reach it as
arrays (it imports no estimator).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import gammaincinv, ndtri

from ...errors import OptionError, ThetahatError
from ...model.system import PerturbedLinearSystem
from ..hold import DEFAULT_HOLD
from .common import sample_interval, theta_box, x_prior_sd
from .input_hold import stage2_samples
from .stage2_set import BOUNDARY_RTOL, on_boundary, project_theta
from .likelihood import (Q_FIRST_HEAD, RecordEvidence, innovation_substeps, process_noise_at,
                         process_noise_scale, record_evidence)
from .plant_kernel import H_RHO, MAX_ACCURATE_SUBSTEPS
from .noise_level import MIN_SAMPLES, estimate_noise_std

if TYPE_CHECKING:
    from ..observer.checks import LawConditionReport

__all__ = ["TrustReport", "trust_report", "UNPINNED_FRACTION", "BOUNDARY_RTOL",
           "EMPTY_GUARD_FRACTION", "MODEL_ERROR_Q", "NOISE_FLOOR",
           "CONSISTENCY_ALPHA", "BORDERLINE_SDS", "component_limit",
           "SETTLE_TAIL", "SETTLE_SDS", "ADVICE", "FIT_KINDS", "chi2_limit", "report_noise_std",
           "tail_movement"]

FloatArray = NDArray[np.float64]

#: A Cramér–Rao standard deviation of at least this fraction of Θ's width: the record does not
#: pin the parameter (the prior from Θ, centre ± |Θ|/4, says as much).
UNPINNED_FRACTION = 0.25
#: Warn when the guard's band was Θ's full width for more than this fraction of the run.
EMPTY_GUARD_FRACTION = 0.5
#: q̂ / q₀ above this: the model error shows (q₀ is the intensity whose effect on y over one
#: sample equals the measurement noise; well below it, process noise is invisible in the data).
MODEL_ERROR_Q = 1e-2
#: σ of the report is at least this fraction of each output's spread (its standard deviation
#: over the record): a noise-free record's σ̂ ≈ 0 (estimate_noise_std gives 0, or the
#: integrator's roughness, 1e-11 to 3e-7 of the spread on the shipped scenarios) made the
#: scale q₀ 10⁻¹⁵⁰ and a q̂ of 1e-142 "8.6e5 × the measurement noise's scale". The floor is
#: below the finest real record we hold (the EMPS encoder, σ̂ = 2e-7 of the spread, whose
#: model error must still show), so on a noise-free record the model's own discretisation
#: error (1e-6 to 1e-5 of the spread) can still be reported as a model error: it is one, at
#: that resolution.
NOISE_FLOOR = 1e-7
#: The score test's level: θ̂ is inconsistent with the record when its statistic exceeds the
#: χ²_p quantile at 1 − CONSISTENCY_ALPHA (a true θ passes 999 records in 1000).
CONSISTENCY_ALPHA = 1e-3
#: A parameter whose step δᵢ / sdᵢ exceeds BORDERLINE_SDS yet passes the test
#: (:func:`component_limit`, 3.29–3.66 sd for p = 1 … 4) is reported as borderline: a
#: warning, not a rejection — beyond 3 sd a true θ falls on 0.27 % of the records per
#: parameter — so that no θ̂ more than 3 of its own standard deviations from where the data
#: put it goes without a word.
BORDERLINE_SDS = 3.0
#: The settling check looks at the last SETTLE_TAIL of the record's duration.
SETTLE_TAIL = 0.25
#: θ̂ has not settled when a component drifts by more than SETTLE_SDS of its Cramér–Rao sd
#: over that tail (:func:`tail_movement`; a fit on a growing record drifts by well under one).
SETTLE_SDS = 2.0
#: What the warnings advise for a θ̂ the score test rejects and for one still moving at the
#: record's end, by how it was made (:attr:`TrustReport.fits`): by a recursion without fits
#: (the paper's observer, the joint EKF), by MAP fits of the whole record (guarded, mle), by
#: fits of a bounded window.
ADVICE = {
    "none": ("use method guarded or mle, or a longer record",
             "the estimate is on its way when the record ends (a longer record, other "
             "excitation, or method guarded or mle, which use the whole record)"),
    "record": ("the fits of the whole record stopped short of the data's optimum, or the "
               "model errs: start θ̂(0) at the one-step θ, or check the model",
               "the record's last part still moved the fit of the whole record: the data do "
               "not yet pin θ (a longer record, or other excitation)"),
    "window": ("the last window's fit is not the whole record's: a longer window "
               "(window=None fits all the data)",
               "the bounded window follows the recent data: a longer window, or a longer "
               "record"),
}
#: The ways an estimate can be made (the keys of :data:`ADVICE`).
FIT_KINDS = tuple(ADVICE)
#: At an inconsistent θ̂ the process noise q̂ found there absorbs θ̂'s own error (and inflates
#: the bound): q is searched again at the one-step θ, up to this many times (each costs one q
#: search on the head and p + 1 passes over the record: bounded at one), and the test and
#: the bound are recomputed at θ̂ with the smaller q (the data's noise, not θ̂'s error).
Q_REFINEMENTS = 1
#: A refined q replaces the last one only when smaller by at least this factor.
Q_REFINE_FACTOR = 0.3


def chi2_limit(p: int) -> float:
    """The χ²_p quantile at 1 − :data:`CONSISTENCY_ALPHA`: 2 P⁻¹(p/2, 1 − α), P the
    regularised lower incomplete gamma function (scipy.special; scipy.stats costs the
    command line a second of imports for this one number).

    Parameters
    ----------
    p : int
        The degrees of freedom (the number of parameters tested).

    Returns
    -------
    float
        The quantile: a score above it is evidence against θ̂ at level α.

    Examples
    --------
    >>> from thetahat.estimation.statistical.trust import chi2_limit
    >>> round(chi2_limit(1), 2), round(chi2_limit(3), 2)
    (10.83, 16.27)
    """
    return float(2.0 * gammaincinv(0.5 * p, 1.0 - CONSISTENCY_ALPHA))


def component_limit(p: int) -> float:
    """The limit of one parameter's step in standard deviations, |δᵢ| / sdᵢ, among p tested:
    the two-sided standard normal quantile at level :data:`CONSISTENCY_ALPHA` / p
    (Bonferroni over the p components, so that a true θ fails some component on at most α of
    the records). For p = 1 it is √:func:`chi2_limit` (1): the joint test itself.

    Parameters
    ----------
    p : int
        The number of parameters tested.

    Returns
    -------
    float
        The limit: a component whose step exceeds it is evidence against θ̂ at level α.

    Examples
    --------
    >>> from thetahat.estimation.statistical.trust import chi2_limit, component_limit
    >>> round(component_limit(1) ** 2, 2) == round(chi2_limit(1), 2)
    True
    >>> round(component_limit(3), 2), round(component_limit(4), 2)
    (3.59, 3.66)
    """
    return float(ndtri(1.0 - 0.5 * CONSISTENCY_ALPHA / p))


@dataclass(frozen=True, slots=True, eq=False)
class TrustReport:
    """What an estimate says about itself (see the module docstring).

    Attributes
    ----------
    names : tuple of str
        The parameters' names.
    theta : ndarray (p,)
        The final estimate θ̂.
    crlb_sd : ndarray (p,)
        Cramér–Rao standard deviation of each parameter for this record, at θ̂ (NaN when the
        model cannot be evaluated along the record at θ̂; inf for a direction the record does
        not determine).
    unpinned : tuple of str
        Parameters the record does not pin (sd ≥ UNPINNED_FRACTION · Θ's width).
    on_boundary : tuple of str
        Parameters whose θ̂ lies on Θ's boundary.
    empty_guard : ndarray (p,) or None
        Fraction of the run with the guard's band at Θ's full width (guarded estimator only).
    process_noise : float
        q̂ (0: the model explains the record to the measurement noise): searched at θ̂, and at
        the one-step θ when θ̂ fails the score test (then the smaller: at an inconsistent θ̂,
        the data's noise rather than θ̂'s own error).
    process_noise_scale : float
        q₀, the data's own scale of q.
    score : float
        Rao's score statistic at θ̂ (NaN when not computed).
    one_step : ndarray (p,) or None
        θ̂ + δ, the Gauss–Newton step of the innovations likelihood from θ̂, projected onto Θ:
        where the data put θ after one linearisation.
    step_sds : ndarray (p,) or None
        |δᵢ| / sdᵢ, each component of that step (before the projection) in its Cramér–Rao
        standard deviations: tested against :func:`component_limit` (NaN where the sd is not
        finite and > 0).
    tail_sds : ndarray (p,) or None
        Drift of each θ̂ component over the last :data:`SETTLE_TAIL` of the record, in its
        Cramér–Rao sd (:func:`tail_movement`; None without the run's path).
    law_conditions : LawConditionReport or None
        The paper's law's conditions along the run (observer methods only).
    noise_floored : bool
        σ̂ was below :data:`NOISE_FLOOR` of an output's spread and was raised to it.
    fits : {"none", "record", "window"}
        How the estimate was made, which decides what the warnings advise: ``"none"``, by a
        recursion over the samples (the paper's observer, the joint EKF), for which MAP fits
        (method guarded or mle) are the remedy; ``"record"``, by MAP fits of all the data
        so far (guarded, mle), which that advice would not help; ``"window"``, by fits of a
        bounded window, which forget the older data.
    """

    names: tuple[str, ...]
    theta: FloatArray
    crlb_sd: FloatArray
    unpinned: tuple[str, ...]
    on_boundary: tuple[str, ...]
    empty_guard: FloatArray | None
    process_noise: float
    process_noise_scale: float
    score: float = math.nan
    one_step: FloatArray | None = None
    step_sds: FloatArray | None = None
    tail_sds: FloatArray | None = None
    law_conditions: LawConditionReport | None = None
    noise_floored: bool = False
    fits: str = "none"

    def __post_init__(self) -> None:
        if self.fits not in FIT_KINDS:
            raise OptionError(f"TrustReport: fits must be one of {FIT_KINDS}; got "
                              f"{self.fits!r}.")

    @property
    def model_error(self) -> bool:
        """The likelihood prefers process noise on φ well above the data's own scale."""
        return self.process_noise > MODEL_ERROR_Q * self.process_noise_scale

    @property
    def consistent(self) -> bool:
        """θ̂ passes the score test, jointly and per component (True when not computed)."""
        return _passes(self.score, self.step_sds, self.theta.shape[0])

    def _components_off(self) -> list[tuple[str, float]]:
        """The parameters whose step exceeds :func:`component_limit`, with it in sd."""
        if self.step_sds is None:
            return []
        limit = component_limit(self.theta.shape[0])
        return [(n, float(v)) for n, v in zip(self.names, self.step_sds) if v > limit]

    @property
    def settled(self) -> bool:
        """No component of θ̂ moved more than SETTLE_SDS sd over the record's last part."""
        return self.tail_sds is None or not np.any(self.tail_sds > SETTLE_SDS)

    @property
    def crlb_rel_sd(self) -> FloatArray:
        """crlb_sd / |θ̂| (inf where θ̂ = 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.theta != 0.0, self.crlb_sd / np.abs(self.theta), np.inf)

    @property
    def warnings(self) -> tuple[str, ...]:
        """The findings that make the result less than trustworthy, one sentence each."""
        out = list(self._consistency_warnings())
        if self.unpinned:
            out.append(f"the record does not pin {', '.join(self.unpinned)}: its Cramér–Rao "
                       f"standard deviation is at least {UNPINNED_FRACTION:g} of Θ's width "
                       "(more excitation, a longer record, or fix it as a constant)")
        if self.on_boundary:
            out.append(f"θ̂ ends on Θ's boundary for {', '.join(self.on_boundary)}: Θ, not the "
                       "data, decided it (widen Θ or check the model)")
        if self.empty_guard is not None:
            empty = [n for n, f in zip(self.names, self.empty_guard)
                     if f > EMPTY_GUARD_FRACTION]
            if empty:
                worst = float(np.max(self.empty_guard))
                out.append(f"the guarantee was empty for {', '.join(empty)}: the guard's band "
                           f"was Θ's full width for up to {100 * worst:.0f} % of the run "
                           "(stage 1 showed no convergence; the output is stage 2's)")
        if self.model_error:
            ratio = self.process_noise / self.process_noise_scale
            out.append(f"model error: at θ̂ the model explains the record only with process "
                       f"noise on φ (q̂ = {self.process_noise:.3g}, {ratio:.3g} × the "
                       "measurement noise's scale): the model errs (an effect it leaves out, "
                       "a wrong structure), and θ̂ is its best symmetric fit, not a truth")
        if self.law_conditions is not None:
            out += self.law_conditions.warnings
        return tuple(out)

    def _borderline(self) -> list[tuple[str, float]]:
        """The parameters whose step is beyond :data:`BORDERLINE_SDS` sd but within
        :func:`component_limit`, with it in sd (none when θ̂ fails the test)."""
        if self.step_sds is None or not self.consistent:
            return []
        return [(n, float(v)) for n, v in zip(self.names, self.step_sds)
                if v > BORDERLINE_SDS]

    def _consistency_warnings(self) -> list[str]:
        out = []
        near = self._borderline()
        if near:
            p = self.theta.shape[0]
            off = ", ".join(f"{n} by {v:.3g} sd" for n, v in near)
            out.append(f"θ̂ is borderline: {off} from where one Gauss–Newton step puts the "
                       f"data's preference, beyond {BORDERLINE_SDS:g} of its Cramér–Rao sd "
                       f"but within the score test's limit ({component_limit(p):.3g} sd "
                       f"among {p}, level {CONSISTENCY_ALPHA:g}); {ADVICE[self.fits][0]}")
        if not self.consistent:
            p = self.theta.shape[0]
            z = self.step_sds if self.step_sds is not None else np.full(p, np.nan)
            far = [f"{n} by {v:.3g} sd" for n, v in zip(self.names, z) if v > 1.0]
            prefer = ("" if self.one_step is None else "; the data prefer θ ≈ (" + ", ".join(
                f"{n} = {v:.4g}" for n, v in zip(self.names, self.one_step)) + ") (one "
                "Gauss–Newton step)")
            if self.score > chi2_limit(p):
                what = (f"{math.sqrt(self.score):.3g} standard errors away (score test, "
                        f"χ²_{p} = {self.score:.3g}{', ' + ', '.join(far) if far else ''})")
            else:
                off = ", ".join(f"{n} by {v:.3g} sd" for n, v in self._components_off())
                what = (f"{off} (score test per parameter, limit {component_limit(p):.3g} sd "
                        f"among {p}; jointly χ²_{p} = {self.score:.3g} passes)")
            out.append(f"θ̂ is not where the data put it: {what}{prefer}; "
                       f"{ADVICE[self.fits][0]}")
        if not self.settled and self.tail_sds is not None:
            moved = [f"{n} by {v:.3g} sd" for n, v in zip(self.names, self.tail_sds)
                     if v > SETTLE_SDS]
            out.append(f"θ̂ has not settled: over the last {100 * SETTLE_TAIL:.0f} % of the "
                       f"record it still drifted ({', '.join(moved)} of its Cramér–Rao sd); "
                       f"{ADVICE[self.fits][1]}")
        return out

    def lines(self) -> list[str]:
        """Summary lines: the relative Cramér–Rao standard deviation per parameter, and the
        checks that were made."""
        rel = self.crlb_rel_sd
        parts = [f"{n} {100 * r:.2g} %" if math.isfinite(r) else f"{n} n/a"
                 for n, r in zip(self.names, rel)]
        out = ["Cramér–Rao relative sd on this record: " + ", ".join(parts)
               + (f" (σ̂ below {NOISE_FLOOR:g} of the output's spread: judged at that "
                  "floor)" if self.noise_floored else "")]
        if math.isfinite(self.score):
            p = self.theta.shape[0]
            verdict = ("NOT consistent with the record" if not self.consistent
                       else "consistent with the record, borderline" if self._borderline()
                       else "consistent with the record")
            worst = ("" if self.step_sds is None or not np.any(np.isfinite(self.step_sds))
                     else f"; largest parameter step {np.nanmax(self.step_sds):.3g} sd (limit "
                          f"{component_limit(p):.3g})")
            out.append(f"score test at θ̂: χ²_{p} = {self.score:.3g} (limit "
                       f"{chi2_limit(p):.3g}){worst}: {verdict}")
        if self.law_conditions is not None and self.law_conditions.proposition:
            lc = self.law_conditions
            cond = ("held on the samples" if not lc.failing and lc.exciting
                    else "FAILED (see the warnings)")
            out.append(f"the law's conditions along the run ({lc.proposition}, excitation): "
                       f"{cond}")
        return out

    def __repr__(self) -> str:
        return (f"TrustReport(crlb_rel_sd={np.round(self.crlb_rel_sd, 4).tolist()}, "
                f"unpinned={list(self.unpinned)}, on_boundary={list(self.on_boundary)}, "
                f"model_error={self.model_error}, consistent={self.consistent}, "
                f"settled={self.settled})")


def report_noise_std(Y: FloatArray, noise_std: ArrayLike | None) -> tuple[FloatArray, bool]:
    """σ of the report: the given or estimated σ̂, at least :data:`NOISE_FLOOR` of each
    output's spread.

    Parameters
    ----------
    Y : ndarray (N, r)
        The outputs (NaN: missing).
    noise_std : array_like (r,), optional
        The estimator's σ (estimated from ``Y`` when None).

    Returns
    -------
    sigma : ndarray (r,)
        Finite and > 0.
    floored : bool
        Some σ̂ was below the floor and was raised to it.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.trust import report_noise_std
    >>> t = np.linspace(0.0, 10.0, 1001)
    >>> sigma, floored = report_noise_std(np.sin(t)[:, None], None)      # noise-free
    >>> floored, bool(abs(sigma[0] / (1e-7 * np.std(np.sin(t))) - 1) < 1e-9)
    (True, True)
    """
    r = Y.shape[1]
    sigma = (estimate_noise_std(Y) if noise_std is None
             else np.broadcast_to(np.asarray(noise_std, dtype=np.float64), (r,)).copy())
    with np.errstate(invalid="ignore"):
        spread = np.nanstd(Y, axis=0) if Y.shape[0] else np.zeros(r)
    floor = NOISE_FLOOR * np.where(np.isfinite(spread) & (spread > 0), spread, 1.0)
    low = ~(sigma >= floor)
    return np.where(low, floor, sigma), bool(np.any(low))


def tail_movement(t: FloatArray, theta_path: FloatArray, sd: FloatArray) -> FloatArray:
    """θ̂'s drift over the last SETTLE_TAIL of the record, in sd: the median over the tail's
    second half minus that over its first half (an estimate that jitters about its value
    drifts by little; one still on its way, by its whole remaining path). NaN where the sd
    is not finite and > 0.

    Parameters
    ----------
    t : ndarray (N,)
    theta_path : ndarray (N, p)
    sd : ndarray (p,)

    Returns
    -------
    ndarray (p,)

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.trust import tail_movement
    >>> t = np.linspace(0.0, 1.0, 101)
    >>> path = np.stack([1.0 + 0.0 * t, 1.0 - np.exp(-2 * t)], axis=1)
    >>> tail_movement(t, path, np.array([0.01, 0.01])).round(1).tolist()
    [0.0, 4.5]
    """
    start = t[-1] - SETTLE_TAIL * (t[-1] - t[0])
    tail = theta_path[t >= start]
    half = tail.shape[0] // 2
    if half == 0:
        return np.full(theta_path.shape[1], np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        moved = np.abs(np.median(tail[half:], axis=0) - np.median(tail[:half], axis=0)) / sd
    return np.where(np.isfinite(sd) & (sd > 0), moved, np.nan)


def trust_report(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
                 theta: FloatArray, names: Sequence[str], *, x_hat0: FloatArray,
                 x_sd: ArrayLike | None = None, band: FloatArray | None = None,
                 noise_std: FloatArray | None = None, hold: str = DEFAULT_HOLD,
                 substeps: int | None = None, h_rho: float = H_RHO,
                 compiled: bool | None = None, theta_path: FloatArray | None = None,
                 law_conditions: LawConditionReport | None = None,
                 fits: str = "none", fit_q: float | None = None) -> TrustReport:
    """Check a final estimate θ̂ against its record (module docstring).

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a symbolic g and any convex Θ.
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        The record.
    theta : ndarray (p,)
        The final estimate.
    names : sequence of str
        The p parameters' names.
    x_hat0 : ndarray (n,)
        Prior mean of x(0).
    x_sd : float or array_like (n,), optional
        Its standard deviation; default :func:`~thetahat.estimation.statistical.common.x_prior_sd`
        of ``x_hat0``.
    band : ndarray (N, p), optional
        The guard's band δ over the run (guarded estimator).
    noise_std : ndarray (r,), optional
        The estimator's σ (default: estimated from y); floored by :func:`report_noise_std`.
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples, as the estimate used it (:mod:`~thetahat.estimation.hold`).
    substeps : int, optional
        The RK4 sub-steps' floor of every filter pass; default: the innovations' own at θ̂
        (:func:`~thetahat.estimation.statistical.likelihood.innovation_substeps` at q̂).
    h_rho : float
    compiled : bool, optional
    theta_path : ndarray (N, p), optional
        θ̂ over the run: its movement over the last part of the record is checked.
    law_conditions : LawConditionReport, optional
        The law's conditions along the run
        (:func:`~thetahat.estimation.observer.checks.law_conditions_on_record`).
    fits : {"none", "record", "window"}
        How θ̂ was made (:attr:`TrustReport.fits`): it decides what the warnings advise.
    fit_q : float, optional
        The process-noise intensity of the estimator's own MAP fit of this record at θ̂,
        when it made one that the record found consistent (0: an output-error fit). The
        search of q̂ starts there, and q̂ = 0 stands without the long head's search when the
        record's first samples agree (:func:`_evidence`): what the estimator computed is not
        paid for twice.

    Returns
    -------
    TrustReport

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.estimation.statistical.trust import trust_report
    >>> d = prop3_monotone.simulate(seed=0, t_end=10.0)                  # θ = 1.2
    >>> rep = trust_report(prop3_monotone.system(), d.t, np.asarray(d.u), np.asarray(d.y),
    ...                    np.array([1.2]), ["theta"], x_hat0=np.zeros(2), compiled=False)
    >>> rep.unpinned, rep.on_boundary, rep.model_error, rep.consistent
    ((), (), False, True)
    >>> off = trust_report(prop3_monotone.system(), d.t, np.asarray(d.u), np.asarray(d.y),
    ...                    np.array([1.5]), ["theta"], x_hat0=np.zeros(2), compiled=False)
    >>> off.consistent, bool(abs(off.one_step[0] - 1.2) < 0.05)
    (False, True)
    """
    lo, hi = theta_box(system)
    width = hi - lo
    theta_set = system.require_parameter_set("trust_report")
    th = np.asarray(theta, dtype=np.float64)
    sigma, floored = report_noise_std(Y, noise_std)
    names_ = tuple(str(n) for n in names)
    crlb_sd = np.full(th.shape[0], np.nan)
    q, q0, score, one_step, step_sds = 0.0, 1.0, math.nan, None, None
    if t.shape[0] >= MIN_SAMPLES:
        q0 = process_noise_scale(system, sample_interval(t), sigma)
        try:
            ev = _evidence(system, t, np.ascontiguousarray(stage2_samples(U, hold)[0]), Y,
                           th, x_hat0=x_hat0, x_sd=x_prior_sd(x_hat0, x_sd), noise_std=sigma,
                           q0=q0, hold=hold, substeps=substeps, h_rho=h_rho,
                           compiled=compiled, fit_q=fit_q)
            q = ev.q
            crlb_sd = np.sqrt(np.maximum(np.diag(ev.cov), 0.0))
            if np.all(np.isfinite(ev.step)):
                score = ev.score
                one_step = project_theta(theta_set, th + ev.step)
                step_sds = _step_sds(ev.step, crlb_sd)
        except (ThetahatError, ArithmeticError, np.linalg.LinAlgError):
            # the model cannot be evaluated along the record at θ̂ (e.g. g not differentiable
            # there): the bound is unknown (n/a in the summary) and the estimate stands
            q = 0.0
    unpinned = tuple(n for n, sd, w in zip(names_, crlb_sd, width)
                     if not np.isnan(sd) and not (sd < UNPINNED_FRACTION * w))
    flags = on_boundary(theta_set, th)
    on_bnd = tuple(n for n, flag in zip(names_, flags) if flag)
    empty = None
    if band is not None:
        B = np.asarray(band, dtype=np.float64).reshape(-1, th.shape[0])
        empty = np.mean(B >= (1.0 - 1e-9) * width, axis=0)
    tail = None
    if theta_path is not None and t.shape[0] > 1:
        tail = tail_movement(t, np.asarray(theta_path, dtype=np.float64).reshape(
            t.shape[0], -1), crlb_sd)
    return TrustReport(names=names_, theta=th.copy(), crlb_sd=crlb_sd, unpinned=unpinned,
                       on_boundary=on_bnd, empty_guard=empty, process_noise=float(q),
                       process_noise_scale=float(q0), score=float(score), one_step=one_step,
                       step_sds=step_sds,
                       tail_sds=tail, law_conditions=law_conditions, noise_floored=floored,
                       fits=fits)


def _evidence(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
              theta: FloatArray, *, x_hat0: FloatArray, x_sd: FloatArray,
              noise_std: FloatArray, q0: float, hold: str, substeps: int | None,
              h_rho: float, compiled: bool | None, fit_q: float | None = None
              ) -> RecordEvidence:
    """The score and the bound at θ̂ with the q the data support (module docstring; q₀ the
    data's scale of q): q
    searched at θ̂, and again at the one-step θ while θ̂ fails the test (Q_REFINEMENTS).
    The sub-steps (when not given) are those of the likelihood it evaluates
    (:func:`~thetahat.estimation.statistical.likelihood.innovation_substeps`, as a fit with
    process noise chooses its own): a first q̂ is searched on the record's first
    :data:`~thetahat.estimation.statistical.likelihood.Q_FIRST_HEAD` samples at the smaller
    of the floors of (θ̂, 0) and (θ̂, q₀), then the floor of (θ̂, q̂), where the evidence is
    evaluated, is taken for every pass that follows, and q is searched at it around the
    first q̂ (``near`` of
    :func:`~thetahat.estimation.statistical.likelihood.search_process_noise`; the whole
    range when the first q̂ is 0), so that q̂ is the search's at its own floor and the long
    head is searched once (Silverbox's training split: 11 passes on it instead of 22). Not the
    free run's:
    with process noise the filter corrects x at every sample (EMPS: 2 sub-steps at q₀ against
    16 at 0); nor the larger of the two, as a fit takes: LuGre's needs 8 at q₀ and 2 at 0 and
    at its q̂ ≈ 10⁻⁴ q₀ (measured once).

    ``fit_q`` (the q of the estimator's consistent fit of the record at θ̂): the first search
    is around it when it is > 0; when it is 0 (the record's output-error fit passed its
    consistency test) and the first head's likelihood also prefers q = 0, q̂ = 0 without the
    long head's search. Two statements of one fact, each on its own evidence: the fit's cost
    on the whole record, the likelihood on its head. On the Silverbox training split that
    search was 14 passes over the record, a third of mle's run (measured once,
    2026-12-07)."""
    theta_set = system.require_parameter_set("trust_report")

    def floor_at(q: float, start: int = 1, limit: int | None = None) -> int:
        return innovation_substeps(system, t, U, Y, theta=theta, q=q, x_hat0=x_hat0,
                                   x_sd=x_sd, noise_std=noise_std, hold=hold, h_rho=h_rho,
                                   compiled=compiled, start=start, limit=limit)

    def smaller_floor(qa: float, qb: float) -> int:
        # min(floor_at(qa), floor_at(qb)) with both doubled together: the larger floor's
        # finer runs (EMPS: 16 sub-steps at q = 0) are never made
        n = 1
        while n < MAX_ACCURATE_SUBSTEPS:
            if any(floor_at(q, start=n, limit=2 * n) == n for q in (qa, qb)):
                return n
            n *= 2
        return n

    def q_at(th: FloatArray, near: float | None = None, samples: int | None = None) -> float:
        k = t.shape[0] if samples is None else samples
        return process_noise_at(system, t[:k], U[:k], Y[:k], theta=th, x_hat0=x_hat0,
                                x_sd=x_sd, noise_std=noise_std, hold=hold, substeps=n_sub,
                                h_rho=h_rho, compiled=compiled, near=near)

    def evidence(q: float) -> RecordEvidence:
        return record_evidence(system, t, U, Y, theta=theta, x_hat0=x_hat0, x_sd=x_sd,
                               noise_std=noise_std, q=q, hold=hold, substeps=n_sub,
                               h_rho=h_rho, compiled=compiled)

    if substeps is not None:
        n_sub = substeps
        q = q_at(theta, near=fit_q)
    else:
        # a first q̂ on the short head at the cheaper of the two ends' floors, then the search
        # at that q̂'s own floor, around it
        n_sub = smaller_floor(q0, 0.0)
        first = q_at(theta, samples=Q_FIRST_HEAD, near=fit_q)
        n_sub = floor_at(first)
        # the fit's consistency on the whole record and the head's likelihood agree on q = 0
        q = 0.0 if fit_q == 0.0 and first == 0.0 else q_at(theta, near=first)

    ev = evidence(q)
    for _ in range(Q_REFINEMENTS):
        if not (q > 0 and _fails(ev) and np.all(np.isfinite(ev.step))):
            break
        q_new = q_at(project_theta(theta_set, theta + ev.step), near=q)
        if not q_new < Q_REFINE_FACTOR * q:
            break
        q = q_new
        ev = evidence(q)
    return ev


def _fails(ev: RecordEvidence) -> bool:
    """θ̂ fails the score test of this evidence, jointly or in some component."""
    sd = np.sqrt(np.maximum(np.diag(ev.cov), 0.0))
    return not _passes(ev.score, _step_sds(ev.step, sd), ev.step.shape[0])


def _passes(score: float, step_sds: FloatArray | None, p: int) -> bool:
    """The score test's verdict, the one rule: the joint statistic within :func:`chi2_limit`
    and every parameter's step within :func:`component_limit` (NaN passes: not computed, or
    a direction the record does not pin)."""
    within = step_sds is None or not np.any(step_sds > component_limit(p))
    return not (score > chi2_limit(p)) and within


def _step_sds(step: FloatArray, sd: FloatArray) -> FloatArray:
    """|δᵢ| / sdᵢ (NaN where sdᵢ is not finite and > 0: a direction the record does not pin,
    or a bound that could not be computed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(sd) & (sd > 0), np.abs(step) / sd, np.nan)
