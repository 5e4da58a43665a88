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

What it may import: :mod:`thetahat.model`, the package's errors, and, in this room,
``common``, ``input_hold``, ``likelihood``, ``noise_level``, ``plant_kernel`` and
``stage2_set``; the estimators' results reach it as arrays (it imports no estimator).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...errors import ThetahatError
from ...model.system import PerturbedLinearSystem
from .common import sample_interval, theta_box, x_prior_sd
from .input_hold import smooth_input
from .stage2_set import BOUNDARY_RTOL, on_boundary
from .likelihood import process_noise_scale, record_bound
from .plant_kernel import H_RHO
from .noise_level import MIN_SAMPLES, estimate_noise_std

__all__ = ["TrustReport", "trust_report", "UNPINNED_FRACTION", "BOUNDARY_RTOL",
           "EMPTY_GUARD_FRACTION", "MODEL_ERROR_Q"]

FloatArray = NDArray[np.float64]

#: A Cramér–Rao standard deviation of at least this fraction of Θ's width: the record does not
#: pin the parameter (the prior from Θ, centre ± |Θ|/4, says as much).
UNPINNED_FRACTION = 0.25
#: Warn when the guard's band was Θ's full width for more than this fraction of the run.
EMPTY_GUARD_FRACTION = 0.5
#: q̂ / q₀ above this: the model error shows (q₀ is the intensity whose effect on y over one
#: sample equals the measurement noise; well below it, process noise is invisible in the data).
MODEL_ERROR_Q = 1e-2


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
        q̂ at θ̂ (0: the model explains the record to the measurement noise).
    process_noise_scale : float
        q₀, the data's own scale of q.
    """

    names: tuple[str, ...]
    theta: FloatArray
    crlb_sd: FloatArray
    unpinned: tuple[str, ...]
    on_boundary: tuple[str, ...]
    empty_guard: FloatArray | None
    process_noise: float
    process_noise_scale: float

    @property
    def model_error(self) -> bool:
        """The likelihood prefers process noise on φ well above the data's own scale."""
        return self.process_noise > MODEL_ERROR_Q * self.process_noise_scale

    @property
    def crlb_rel_sd(self) -> FloatArray:
        """crlb_sd / |θ̂| (inf where θ̂ = 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.theta != 0.0, self.crlb_sd / np.abs(self.theta), np.inf)

    @property
    def warnings(self) -> tuple[str, ...]:
        """The findings that make the result less than trustworthy, one sentence each."""
        out = []
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
                       "measurement noise's scale): the model errs, or θ̂ is not yet where the "
                       "data put it")
        return tuple(out)

    def lines(self) -> list[str]:
        """Summary lines: the relative Cramér–Rao standard deviation per parameter."""
        rel = self.crlb_rel_sd
        parts = [f"{n} {100 * r:.2g} %" if math.isfinite(r) else f"{n} n/a"
                 for n, r in zip(self.names, rel)]
        return ["Cramér–Rao relative sd on this record: " + ", ".join(parts)]

    def __repr__(self) -> str:
        return (f"TrustReport(crlb_rel_sd={np.round(self.crlb_rel_sd, 4).tolist()}, "
                f"unpinned={list(self.unpinned)}, on_boundary={list(self.on_boundary)}, "
                f"model_error={self.model_error})")


def trust_report(system: PerturbedLinearSystem, t: FloatArray, U: FloatArray, Y: FloatArray,
                 theta: FloatArray, names: Sequence[str], *, x_hat0: FloatArray,
                 x_sd: ArrayLike | None = None, band: FloatArray | None = None,
                 noise_std: FloatArray | None = None, h_rho: float = H_RHO,
                 compiled: bool | None = None) -> TrustReport:
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
        Default: estimated from y.
    h_rho : float
    compiled : bool, optional

    Returns
    -------
    TrustReport

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import prop3_monotone
    >>> from thetahat.estimation.statistical.trust import trust_report
    >>> d = prop3_monotone.simulate(seed=0, t_end=10.0)
    >>> rep = trust_report(prop3_monotone.system(), d.t, np.asarray(d.u), np.asarray(d.y),
    ...                    np.array([1.2]), ["theta"], x_hat0=np.zeros(2), compiled=False)
    >>> rep.unpinned, rep.on_boundary, rep.model_error
    ((), (), False)
    """
    lo, hi = theta_box(system)
    width = hi - lo
    th = np.asarray(theta, dtype=np.float64)
    sigma = (estimate_noise_std(Y) if noise_std is None
             else np.asarray(noise_std, dtype=np.float64))
    sigma = np.where(sigma > 0, sigma, np.finfo(float).tiny ** 0.25)
    names_ = tuple(str(n) for n in names)
    crlb_sd = np.full(th.shape[0], np.nan)
    q, q0 = 0.0, 1.0
    if t.shape[0] >= MIN_SAMPLES:
        h_med = sample_interval(t)
        q0 = process_noise_scale(system, h_med, sigma)
        x_sds = x_prior_sd(x_hat0, x_sd)
        try:
            q, cov = record_bound(system, t, np.ascontiguousarray(smooth_input(U)[0]), Y,
                                  theta=th, x_hat0=x_hat0, x_sd=x_sds,
                                  noise_std=sigma, h_rho=h_rho, compiled=compiled)
            crlb_sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        except (ThetahatError, ArithmeticError, np.linalg.LinAlgError):
            # the model cannot be evaluated along the record at θ̂ (e.g. g not differentiable
            # there): the bound is unknown (n/a in the summary) and the estimate stands
            q = 0.0
    unpinned = tuple(n for n, sd, w in zip(names_, crlb_sd, width)
                     if not np.isnan(sd) and not (sd < UNPINNED_FRACTION * w))
    flags = on_boundary(system.require_parameter_set("trust_report"), th)
    on_bnd = tuple(n for n, flag in zip(names_, flags) if flag)
    empty = None
    if band is not None:
        B = np.asarray(band, dtype=np.float64).reshape(-1, th.shape[0])
        empty = np.mean(B >= (1.0 - 1e-9) * width, axis=0)
    return TrustReport(names=names_, theta=th.copy(), crlb_sd=crlb_sd, unpinned=unpinned,
                       on_boundary=on_bnd, empty_guard=empty, process_noise=float(q),
                       process_noise_scale=float(q0))
