"""Parameter update laws u_θ(v, x̂, φ̂, θ̂) of Sec. IV (Propositions 1–4).

Every law has two entry points over one formula: ``rate`` returns θ̂̇ = u_θ(v, x̂, φ̂, θ̂) (8),
projection included, for ODE integrators and for the observer's (3b); ``step`` advances θ̂ over
a time step and always returns a point of Θ, whatever the data and the step length.

Batch convention: ``v (..., m + r)``, ``x_hat (..., n)``, ``phi_hat (..., k)``,
``theta_hat (..., p)``; leading shapes broadcast, results have shape ``(..., p)``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, final

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from .._validate import check_finite, positive_scalar, readonly
from ..errors import DimensionError, ParameterSetError, UpdateLawError
from ..model.paramset import Box, ParameterSet, safe_norm
from ..model.jacobian_check import require_theta_dependence
from ..model.perturbation import Perturbation
from .projection import Projection, Saturation, as_gain
from .theta_star import ThetaStar

FloatArray = NDArray[np.float64]
ThetaStarFn = Callable[[FloatArray, FloatArray, FloatArray], Any]
Weight = Callable[[FloatArray, FloatArray, FloatArray], Any]
OnInvalid = Literal["raise", "freeze"]

__all__ = ["UpdateLaw", "ConstantLaw", "AlgebraicInversion", "IntermittentInversion",
           "GradientInversion", "SmoothRamp", "invalid_theta_star_error", "smooth_ramp"]

#: θ̂₀ may lie this far outside Θ, relative to max(1, ‖θ̂₀‖), and still be accepted (and snapped
#: onto Θ): a boundary point written with 15 significant digits is off by rounding only.
INIT_RTOL = 1e-12
#: Values of an excitation weight l within this distance outside [0, 1] are rounding and
#: clipped; larger excursions are an error in the user's l.
WEIGHT_TOL = 1e-12
#: Candidate points are clipped to ±FAR before the projection: far enough to be projected onto
#: the same face as an overflowing value, small enough that differences with points of Θ stay
#: finite.
FAR = 1e300


def _as_batch(v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
              p: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, tuple[int, ...]]:
    arrs = []
    for name, a in (("v", v), ("x_hat", x_hat), ("phi_hat", phi_hat), ("theta_hat", theta_hat)):
        arr = np.asarray(a, dtype=np.float64)
        if arr.ndim == 0:
            raise DimensionError(f"{name} must have shape (..., size); got a scalar. Wrap it, "
                                 f"e.g. np.atleast_1d({name}).")
        check_finite(name, arr)
        arrs.append(arr)
    if arrs[3].shape[-1] != p:
        raise DimensionError(f"theta_hat must have shape (..., {p}); got {arrs[3].shape}.")
    try:
        batch = np.broadcast_shapes(*(a.shape[:-1] for a in arrs))
    except ValueError as exc:
        raise DimensionError(f"leading (batch) shapes do not broadcast: v {arrs[0].shape}, "
                             f"x_hat {arrs[1].shape}, phi_hat {arrs[2].shape}, theta_hat "
                             f"{arrs[3].shape}.") from exc
    return arrs[0], arrs[1], arrs[2], arrs[3], batch


def _finite_candidate(cand: FloatArray, fallback: FloatArray) -> FloatArray:
    """NaN -> fallback, ±inf and huge values -> ±FAR, so that the projection can handle them."""
    cand = np.where(np.isnan(cand), fallback, cand)
    return np.clip(cand, -FAR, FAR)


def _check_dt(dt: Any) -> float:
    return positive_scalar("dt", dt)


class UpdateLaw(ABC):
    """Abstract update law (8): θ̂̇ = u_θ(v, x̂, φ̂, θ̂), projection included.

    Concrete laws are final frozen dataclasses. Two entry points over one law:
    ``rate`` for continuous time (the observer's (3b) uses it as θ̂̇) and ``step`` for
    discrete time, which must return a point of Θ whatever the data.
    """

    @property
    @abstractmethod
    def parameter_set(self) -> ParameterSet:
        """Θ, where θ̂ stays."""

    @abstractmethod
    def rate(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
             theta_hat: FloatArray) -> FloatArray:
        """θ̂̇ = u_θ(v, x̂, φ̂, θ̂) (8); shape (..., p)."""

    def step(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
             theta_hat: FloatArray, dt: float, *, Gamma: ArrayLike | None = None
             ) -> FloatArray:
        """θ̂ after a step of length dt, guaranteed in Θ (default: Euler, then ``nearest``).

        ``Gamma`` (shape (..., p, p), one Γ per batch row) replaces the law's own Γ; laws
        without a Γ refuse it.
        """
        dt = _check_dt(dt)
        if Gamma is not None:
            raise UpdateLawError(f"{type(self).__name__} has no gain Γ; pass Gamma=None.")
        th = np.asarray(theta_hat, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            nxt = th + dt * self.rate(v, x_hat, phi_hat, theta_hat)
        return self.parameter_set.nearest(_finite_candidate(nxt, th))

    # ------------------------------------------------------------------ batched contract
    @property
    def gain(self) -> FloatArray | None:
        """The per-row parameter of the law, Γ (p, p), or None for a law without one.

        A batch of observers passes one Γ per row to :meth:`advance` (``Gamma=``, shape
        (B, p, p)); everything else about the law is shared by the rows.
        """
        G = getattr(self, "Gamma", None)
        return None if G is None else np.asarray(G, dtype=np.float64)

    @property
    def state_size(self) -> int:
        """Length of the law's own state (a gain matrix, filtered regressors, ...); 0 here.

        The state lives in the observer state after θ̂ (and x̂₂) and is advanced by
        :meth:`advance` in the same step.
        """
        return 0

    def init_state(self, theta_hat0: FloatArray) -> FloatArray:
        """Initial law state for the validated θ̂₀ (shape (..., p)); shape (..., state_size).

        Parameters
        ----------
        theta_hat0 : ndarray, shape (..., p)

        Returns
        -------
        ndarray, shape (..., state_size)
        """
        th = np.asarray(theta_hat0, dtype=np.float64)
        return np.zeros(th.shape[:-1] + (self.state_size,))

    def advance(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
                theta_hat: FloatArray, state: FloatArray, dt: float, *,
                Gamma: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
        """One step of θ̂ and of the law's state: the entry point of the observer's step.

        Parameters
        ----------
        v : ndarray, shape (B, m + r)
        x_hat : ndarray, shape (B, n)
        phi_hat : ndarray, shape (B, k)
        theta_hat : ndarray, shape (B, p)
        state : ndarray, shape (B, state_size)
            The law's state at the start of the step.
        dt : float
            Step length > 0.
        Gamma : ndarray, shape (B|1, p, p), optional
            Γ per row (default: the law's own).

        Returns
        -------
        theta_hat : ndarray, shape (B, p)
            In Θ.
        state : ndarray, shape (B, state_size)

        Notes
        -----
        The default (memoryless laws) is ``step`` with the state passed through; a law with a
        state overrides it and propagates both in one go.
        """
        if Gamma is None:
            th = self.step(v, x_hat, phi_hat, theta_hat, dt)
        else:
            th = self.step(v, x_hat, phi_hat, theta_hat, dt, Gamma=Gamma)
        return np.asarray(th, dtype=np.float64), state

    def init(self, theta_hat0: ArrayLike | None = None) -> FloatArray:
        """Validated initial estimate θ̂(t₀) ∈ Θ, shape (..., p).

        Parameters
        ----------
        theta_hat0 : array_like, shape (..., p), optional
            Defaults to the interior point (centre) of Θ.

        Raises
        ------
        ParameterSetError
            θ̂₀ lies outside Θ (Assumption 3 needs θ̂(t₀) ∈ Θ).
        NonFiniteError
            θ̂₀ holds NaN or inf.
        """
        ps = self.parameter_set
        th = np.array(ps.interior_point if theta_hat0 is None else theta_hat0, dtype=np.float64)
        if th.ndim == 0 or th.shape[-1] != ps.dim:
            raise DimensionError(f"theta_hat0 must have shape (..., {ps.dim}); got {th.shape}.")
        check_finite("theta_hat0", th)
        tol = INIT_RTOL * max(1.0, float(np.max(np.abs(th))))
        inside = np.asarray(ps.contains(th, tol=tol))
        if not np.all(inside):
            bad = th if th.ndim == 1 else th.reshape(-1, ps.dim)[~inside.reshape(-1)][0]
            raise ParameterSetError(f"theta_hat0 = {np.round(bad, 6).tolist()} lies outside "
                                    f"Θ = {ps!r}; start the estimator inside Θ, e.g. at "
                                    f"parameter_set.nearest(theta_hat0).")
        return ps.nearest(th)


@final
@dataclass(frozen=True, slots=True, eq=False)
class ConstantLaw(UpdateLaw):
    """θ̂̇ = 0: the parameter estimate is held at a known or assumed value.

    Parameters
    ----------
    theta : array_like, shape (p,)
        The value held; it is also what ``init()`` returns.
    parameter_set : ParameterSet
        Θ; ``theta`` must lie in it.

    Raises
    ------
    ParameterSetError
        ``theta`` is outside Θ.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.update_laws import ConstantLaw
    >>> law = ConstantLaw([0.3], Box([0.0], [1.0]))
    >>> law.init().tolist(), law.rate([0.0, 1.0], [0.0, 0.0], [2.0], [0.3]).tolist()
    ([0.3], [0.0])
    """

    theta: FloatArray
    parameter_set: ParameterSet

    def __init__(self, theta: ArrayLike, parameter_set: ParameterSet) -> None:
        if not isinstance(parameter_set, ParameterSet):
            raise DimensionError(f"parameter_set must be a thetahat ParameterSet; got "
                                 f"{type(parameter_set).__name__}.")
        object.__setattr__(self, "parameter_set", parameter_set)
        th = UpdateLaw.init(self, np.atleast_1d(np.asarray(theta, dtype=np.float64)))
        th.setflags(write=False)
        object.__setattr__(self, "theta", th)

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """Zero, shape (..., p)."""
        *_, batch = _as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        return np.zeros(batch + (self.parameter_set.dim,))

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float, *, Gamma: ArrayLike | None = None) -> FloatArray:
        """θ̂ unchanged (projected onto Θ should it lie outside); shape (..., p).

        ``Gamma`` is accepted for the batched contract and has no effect (θ̂̇ = 0).
        """
        _check_dt(dt)
        *_, th, batch = _as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        return self.parameter_set.nearest(np.broadcast_to(th, batch + th.shape[-1:]))

    def init(self, theta_hat0: ArrayLike | None = None) -> FloatArray:
        """``theta`` when θ̂₀ is not given, else the validated θ̂₀."""
        return UpdateLaw.init(self, self.theta if theta_hat0 is None else theta_hat0)


@final
@dataclass(frozen=True, slots=True, eq=False)
class SmoothRamp:
    """The excitation weight of :func:`smooth_ramp`: a C¹ ramp of ‖φ̂‖ from 0 to 1 (Remark 5).

    Parameters
    ----------
    low, high : float
        0 <= low < high: the weight is 0 for ‖φ̂‖ <= low and 1 for ‖φ̂‖ >= high. Build it with
        :func:`smooth_ramp`, which checks them.
    """

    low: float
    high: float

    def weight(self, s: ArrayLike) -> FloatArray:
        """0 for s <= low, 1 for s >= high, 3t² - 2t³ with t = (s - low)/(high - low) between."""
        t = np.clip((np.asarray(s, dtype=np.float64) - self.low) / (self.high - self.low), 0, 1)
        return t * t * (3.0 - 2.0 * t)

    def __call__(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike) -> FloatArray:
        """l(v, x̂, φ̂) = weight(‖φ̂‖); shape (...)."""
        return self.weight(safe_norm(np.asarray(phi_hat, dtype=np.float64)))

    def __repr__(self) -> str:
        return f"smooth_ramp(low={self.low}, high={self.high})"


def smooth_ramp(low: float, high: float) -> SmoothRamp:
    """Lipschitz excitation weight l(v, x̂, φ̂) of ‖φ̂‖ for :class:`IntermittentInversion`.

    Parameters
    ----------
    low, high : float
        0 <= low < high. The weight is 0 for ‖φ̂‖ <= low, 1 for ‖φ̂‖ >= high, and the C¹
        smoothstep 3t² - 2t³, t = (‖φ̂‖ - low)/(high - low), in between.

    Returns
    -------
    callable
        ``l(v, x_hat, phi_hat)`` returning shape (...); its ``weight(s)`` method applies the
        same ramp to any array ``s`` (to build weights of other signals, e.g. |y|).

    Notes
    -----
    This is the fix Remark 5 asks for: the LuGre example of Sec. VIII switches l from 0 to 1
    at |φ̂| = 1, which breaks the Lipschitz condition of Assumption 4. The ramp is Lipschitz
    with constant 1.5/(high - low). Proposition 2 needs l > 0 only where θ* is unique, so
    choose ``low`` at or above the level where the inversion becomes well posed.

    Examples
    --------
    >>> from thetahat.estimation.update_laws import smooth_ramp
    >>> l = smooth_ramp(0.5, 1.0)
    >>> l([0.0], [0.0], [[0.2], [0.75], [3.0]]).tolist()
    [0.0, 0.5, 1.0]
    """
    try:
        lo, hi = float(low), float(high)
    except (TypeError, ValueError) as exc:
        raise UpdateLawError(f"smooth_ramp: low and high must be numbers; got {low!r}, "
                             f"{high!r}.") from exc
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo < hi):
        raise UpdateLawError(f"smooth_ramp needs 0 <= low < high (finite); got low={lo}, "
                             f"high={hi}.")
    return SmoothRamp(lo, hi)


def invalid_theta_star_error(owner: str, count: int) -> UpdateLawError:
    """The error every back end raises when θ* is NaN or inf where l > 0 (on_invalid='raise').

    Parameters
    ----------
    owner : str
        The law's name.
    count : int
        Number of points (batch rows) affected.

    Returns
    -------
    UpdateLawError
    """
    return UpdateLawError(f"{owner}: theta_star is NaN or inf at {count} point(s) where the "
                          f"weight is positive; make l vanish where the inversion is "
                          f"undefined, or pass on_invalid='freeze'.")


def _inversion_target(theta_star: ThetaStar | ThetaStarFn, weight: Weight | None,
                      on_invalid: OnInvalid,
                      owner: str, v: FloatArray, x: FloatArray, phi: FloatArray,
                      th: FloatArray, batch: tuple[int, ...]) -> tuple[FloatArray, FloatArray]:
    """(θ*, l) broadcast to the batch; θ* replaced by θ̂ where l = 0 (so that NaN is harmless)."""
    p = th.shape[-1]
    if weight is None:
        lw = np.ones(batch)
    else:
        lw = np.broadcast_to(np.asarray(weight(v, x, phi), dtype=np.float64), batch).copy()
        if np.any(np.isnan(lw)) or np.any(lw < -WEIGHT_TOL) or np.any(lw > 1 + WEIGHT_TOL):
            raise UpdateLawError(f"{owner}: the excitation weight l must return values in "
                                 f"[0, 1] (Proposition 2); got values in [{np.nanmin(lw)}, "
                                 f"{np.nanmax(lw)}] (or NaN).")
        lw = np.clip(lw, 0.0, 1.0)
    with np.errstate(all="ignore"):
        ts = np.asarray(theta_star(v, x, phi), dtype=np.float64)
    if ts.ndim == 0 or ts.shape[-1] != p:
        raise UpdateLawError(f"{owner}: theta_star must return shape (..., {p}); got "
                             f"{ts.shape}.")
    ts = np.broadcast_to(ts, batch + (p,))
    bad = (lw > 0) & ~np.all(np.isfinite(ts), axis=-1)
    if np.any(bad):
        if on_invalid == "raise":
            raise invalid_theta_star_error(owner, int(np.sum(bad)))
        lw = np.where(bad, 0.0, lw)
    th_b = np.broadcast_to(th, batch + (p,))
    target = np.where((lw > 0)[..., None], ts, th_b)
    return target, lw


def _inversion_step(proj: Projection, eig: tuple[FloatArray, FloatArray], target: FloatArray,
                    lw: FloatArray, th: FloatArray, dt: float,
                    Gamma: ArrayLike | None) -> FloatArray:
    """Exact flow of θ̇ = lΓ(θ* - θ) over dt with θ* held, then the Γ⁻¹-weighted projection.

    ``eig`` is the eigen-decomposition of the law's Γ; ``Gamma`` (B|1, p, p) replaces it per row.
    """
    th_b = np.broadcast_to(th, target.shape)
    G = None if Gamma is None else np.asarray(Gamma, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        if G is None:
            lam, V = eig
            err = (target - th_b) @ V
            cand = target - (np.exp(-lw[..., None] * dt * lam) * err) @ V.T
        elif _is_diagonal(G):
            lam = np.diagonal(G, axis1=-2, axis2=-1)
            cand = target - np.exp(-lw[..., None] * dt * lam) * (target - th_b)
        else:
            lam, V = np.linalg.eigh(G)
            err = np.einsum("...i,...ij->...j", target - th_b, V)
            cand = target - np.einsum("...j,...ij->...i",
                                      np.exp(-lw[..., None] * dt * lam) * err, V)
    return _project_rows(proj, _finite_candidate(cand, th_b), G)


def _is_diagonal(G: FloatArray) -> bool:
    d = np.diagonal(G, axis1=-2, axis2=-1)
    return bool(np.array_equal(G, d[..., None] * np.eye(G.shape[-1])))


def _project_rows(proj: Projection, cand: FloatArray, G: FloatArray | None) -> FloatArray:
    """The Γ⁻¹-weighted projection onto Θ with the law's Γ, or one Γ per row of ``G``."""
    if G is None:
        return proj.project(cand)
    ps = proj.parameter_set
    if isinstance(ps, Box) and _is_diagonal(G):
        return ps.nearest(cand)          # a clip, whatever the diagonal metric
    p = cand.shape[-1]
    flat = cand.reshape(-1, p)
    Gs = np.broadcast_to(G, flat.shape[:1] + (p, p))
    out = np.empty_like(flat)
    distinct, which = np.unique(Gs.reshape(len(flat), -1), axis=0, return_inverse=True)
    for j, Gj in enumerate(distinct):
        rows = np.flatnonzero(which.reshape(-1) == j)
        out[rows] = Projection(ps, Gj.reshape(p, p), layer=proj.layer).project(flat[rows])
    return out.reshape(cand.shape)


def _check_common(owner: str, parameter_set: ParameterSet, on_invalid: str,
                  saturation: Saturation | None) -> None:
    if not isinstance(parameter_set, ParameterSet):
        raise DimensionError(f"{owner}: parameter_set must be a thetahat ParameterSet; got "
                             f"{type(parameter_set).__name__}.")
    if on_invalid not in ("raise", "freeze"):
        raise UpdateLawError(f"{owner}: on_invalid must be 'raise' or 'freeze'; got "
                             f"{on_invalid!r}.")
    if saturation is not None and not isinstance(saturation, Saturation):
        raise UpdateLawError(f"{owner}: saturation must be a Saturation or None.")


def _apply_saturation(sat: Saturation | None, x: FloatArray,
                      phi: FloatArray) -> tuple[FloatArray, FloatArray]:
    return (x, phi) if sat is None else sat.apply(x, phi)


@final
@dataclass(frozen=True, slots=True, eq=False)
class IntermittentInversion(UpdateLaw):
    """Propositions 1 and 2: θ̂̇ = Proj(l(v, x̂, φ̂) Γ(θ*(v, x̂, φ̂) - θ̂)).

    Parameters
    ----------
    theta_star : ThetaStar or callable
        ``theta_star(v, x_hat, phi_hat)``, shape (..., p): the unique solution of
        φ = g(v, x, θ) wherever l > 0 (anything, NaN included, where l = 0). A
        :class:`~thetahat.estimation.theta_star.ThetaStar` carries its SymPy form too, which
        the compiled path needs.
    l : callable or None
        ``l(v, x_hat, phi_hat)`` with values in [0, 1], shape (...). :func:`smooth_ramp`
        builds a Lipschitz one. ``None`` means l ≡ 1: Proposition 1 (see
        :func:`AlgebraicInversion`).
    Gamma : float or array_like, shape (p, p)
        Symmetric positive-definite gain Γ.
    parameter_set : ParameterSet
        Θ.
    saturation : Saturation, optional
        Saturation of x̂ and φ̂ before use (Remark 3).
    layer : float, optional
        Boundary layer of the projection (0 = hard projection, the default).
    on_invalid : {'raise', 'freeze'}, optional
        θ* NaN or inf where l > 0 means l does not guard the domain of θ*: ``'raise'``
        (default) raises :class:`~thetahat.errors.UpdateLawError`; ``'freeze'`` sets l = 0 at
        those points, so θ̂ is held there.

    Raises
    ------
    UpdateLawError
        Γ not symmetric positive definite; l outside [0, 1]; θ* invalid where l > 0 (with
        ``on_invalid='raise'``).

    Notes
    -----
    With x̂ = x and φ̂ = φ, θ̃̇ = -Proj(lΓθ̃); the proof uses the persistency of excitation
    ∫_t^(t+T) l dτ >= σ (with l ≡ 1, Proposition 1: V = ½θ̃ᵀΓ⁻¹θ̃ gives V̇ <= -‖θ̃‖²).
    ``step`` integrates θ̇ = lΓ(θ* - θ) exactly over dt with l and θ* held, then projects
    (Γ⁻¹-weighted), so for p = 1 and no projection θ̃(t) = e^(-γ∫l)θ̃(0); it contracts for
    every dt.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.update_laws import IntermittentInversion, smooth_ramp
    >>> law = IntermittentInversion(lambda v, x, phi: 1.0 / phi, smooth_ramp(0.5, 1.0), 1.0,
    ...                             Box([0.1], [5.0]))
    >>> law.rate([0.0, 0.0], [0.0, 0.0], [[0.0], [2.0]], [1.0]).tolist()  # l = 0, then l = 1
    [[0.0], [-0.5]]
    """

    theta_star: ThetaStar | ThetaStarFn
    l: Weight | None
    Gamma: FloatArray
    parameter_set: ParameterSet
    saturation: Saturation | None = None
    layer: float = 0.0
    on_invalid: OnInvalid = "raise"
    _proj: Projection = field(init=False, repr=False)
    _eig: tuple[FloatArray, FloatArray] = field(init=False, repr=False)

    def __init__(self, theta_star: ThetaStar | ThetaStarFn,
                 l: Weight | None,  # noqa: E741
                 Gamma: ArrayLike, parameter_set: ParameterSet, *,
                 saturation: Saturation | None = None, layer: float = 0.0,
                 on_invalid: OnInvalid = "raise") -> None:
        _check_common("IntermittentInversion", parameter_set, on_invalid, saturation)
        if not (callable(theta_star) and (l is None or callable(l))):
            raise UpdateLawError("IntermittentInversion: theta_star must be a callable of "
                                 "(v, x_hat, phi_hat), and l one too (or None for l ≡ 1).")
        proj = Projection(parameter_set, as_gain("Gamma", Gamma, parameter_set.dim),
                          layer=layer)
        lam, V = np.linalg.eigh(proj.Gamma)
        for name, val in (("theta_star", theta_star), ("l", l), ("Gamma", proj.Gamma),
                          ("parameter_set", parameter_set), ("saturation", saturation),
                          ("layer", proj.layer), ("on_invalid", on_invalid), ("_proj", proj),
                          ("_eig", (readonly(lam), readonly(V)))):
            object.__setattr__(self, name, val)

    @classmethod
    def from_perturbation(cls, perturbation: Perturbation,
                          l: Weight | None = None,  # noqa: E741
                          *, Gamma: ArrayLike, parameter_set: ParameterSet,
                          saturation: Saturation | None = None, layer: float = 0.0,
                          on_invalid: OnInvalid = "raise",
                          seed: int = 0) -> IntermittentInversion:
        """Derive θ* by ``sympy.solve`` (:meth:`ThetaStar.solve
        <thetahat.estimation.theta_star.ThetaStar.solve>`); ``l=None`` is Proposition 1.

        Parameters
        ----------
        perturbation : SymbolicPerturbation
        l : callable or None
            As for the constructor.
        Gamma, parameter_set, saturation, layer, on_invalid
            As for the constructor.
        seed : int
            Seed of the random points that pick the branch of the solution that inverts g.

        Returns
        -------
        IntermittentInversion

        Raises
        ------
        UpdateLawError
            SymPy cannot solve, or not exactly one branch inverts g (the solution is not
            unique): pass ``theta_star`` yourself or use :class:`GradientInversion`.
        """
        ts = ThetaStar.solve(perturbation, parameter_set, seed=seed)
        return cls(ts, l, Gamma, parameter_set, saturation=saturation, layer=layer,
                   on_invalid=on_invalid)

    def _target(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
                theta_hat: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        v_, x, phi, th, batch = _as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        x, phi = _apply_saturation(self.saturation, x, phi)
        target, lw = _inversion_target(self.theta_star, self.l, self.on_invalid,
                                       "IntermittentInversion", v_, x, phi, th, batch)
        return target, lw, th

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """θ̂̇ = Proj(lΓ(θ* - θ̂)); shape (..., p)."""
        target, lw, th = self._target(v, x_hat, phi_hat, theta_hat)
        th_b = np.broadcast_to(th, target.shape)
        tau = lw[..., None] * ((target - th_b) @ self.Gamma)
        return self._proj.proj(tau, th_b)

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float, *, Gamma: ArrayLike | None = None) -> FloatArray:
        """Exact step θ* + e^(-lΓ dt)(θ̂ - θ*), then the Γ⁻¹-weighted projection; in Θ.

        ``Gamma`` (shape (..., p, p)) gives one Γ per batch row in place of the law's own.
        """
        dt = _check_dt(dt)
        target, lw, th = self._target(v, x_hat, phi_hat, theta_hat)
        return _inversion_step(self._proj, self._eig, target, lw, th, dt, Gamma)


def AlgebraicInversion(theta_star: ThetaStar | ThetaStarFn, Gamma: ArrayLike,  # noqa: N802
                       parameter_set: ParameterSet, *, saturation: Saturation | None = None,
                       layer: float = 0.0,
                       on_invalid: OnInvalid = "raise") -> IntermittentInversion:
    """Proposition 1, θ̂̇ = Proj(Γ(θ*(v, x̂, φ̂) - θ̂)): :class:`IntermittentInversion` with l ≡ 1.

    A named constructor: the law it returns is an ``IntermittentInversion`` whose ``l`` is
    None. ``AlgebraicInversion.from_perturbation(...)`` derives θ* with SymPy.

    Parameters
    ----------
    theta_star : ThetaStar or callable
        ``theta_star(v, x_hat, phi_hat)`` returning the unique solution θ of φ = g(v, x, θ),
        shape (..., p).
    Gamma : float or array_like, shape (p, p)
        Symmetric positive-definite gain Γ.
    parameter_set : ParameterSet
        Θ.
    saturation, layer, on_invalid
        As for :class:`IntermittentInversion` (``on_invalid`` acts wherever θ* is NaN or inf).

    Returns
    -------
    IntermittentInversion

    Notes
    -----
    With x̂ = x and φ̂ = φ, θ* = θ and ‖θ̃(t)‖_Γ⁻¹ <= e^(-λ_min(Γ) t)‖θ̃(0)‖_Γ⁻¹.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.update_laws import AlgebraicInversion
    >>> law = AlgebraicInversion(lambda v, x, phi: np.arcsinh(phi), 2.0, Box([-2.0], [2.0]))
    >>> law.rate([0.0, 0.0], [0.0, 0.0], [np.sinh(0.5)], [0.0]).round(12).tolist()
    [1.0]
    >>> law.l is None
    True
    """
    return IntermittentInversion(theta_star, None, Gamma, parameter_set, saturation=saturation,
                                 layer=layer, on_invalid=on_invalid)


def _algebraic_from_perturbation(perturbation: Perturbation, **options: Any
                                 ) -> IntermittentInversion:
    """Proposition 1 with θ* by ``sympy.solve``: :meth:`IntermittentInversion.from_perturbation`
    with l ≡ 1 (same keywords)."""
    return IntermittentInversion.from_perturbation(perturbation, None, **options)


AlgebraicInversion.from_perturbation = _algebraic_from_perturbation  # type: ignore[attr-defined]


@final
@dataclass(frozen=True, slots=True, eq=False)
class GradientInversion(UpdateLaw):
    """Propositions 3 and 4: θ̂̇ = Proj(Γ M(v, x̂, θ̂)(φ̂ - g(v, x̂, θ̂))).

    Parameters
    ----------
    perturbation : Perturbation
        g and ∂g/∂θ.
    Gamma : float or array_like, shape (p, p)
        Symmetric positive-definite gain Γ.
    parameter_set : ParameterSet
        Θ; its dimension must equal the perturbation's p.
    M : callable, optional
        ``M(v, x, theta)`` of shape (..., p, k). Default (∂g/∂θ)ᵀ(v, x, θ̂) (gradient descent
        on ½‖φ̂ - g‖²).
    saturation : Saturation, optional
        Saturation of x̂ and φ̂ before use (Remark 3).
    layer : float, optional
        Boundary layer of the projection (0 = hard projection, the default).

    Raises
    ------
    UpdateLawError
        Γ not symmetric positive definite; M returns the wrong shape.
    DimensionError
        Θ and the perturbation disagree on p.

    Notes
    -----
    Proposition 3 needs M(v, x, θ₁)∂g/∂θ(v, x, θ₂) + (…)ᵀ >= 2P > 0 on Θ × Θ (13); then
    V = ½θ̃ᵀΓ⁻¹θ̃ decays with V̇ <= -θ̃ᵀPθ̃ and ‖θ̃‖ at rate >= λ_min(P)λ_min(Γ). Proposition 4
    only needs >= 2S(v, x) >= 0 (14) with ∫ S persistently exciting. Check both with
    :func:`thetahat.estimation.checks.check_monotonicity` and
    :func:`~thetahat.estimation.checks.excitation_report`.

    ``step`` uses the exponential (Rosenbrock) Euler method: with K = ΓM∂g/∂θ and
    f = ΓM(φ̂ - g) at θ̂, it integrates the linearisation θ̇ = f - K(θ - θ̂) exactly over dt
    (one (p+1)×(p+1) matrix exponential), then applies the Γ⁻¹-weighted projection. Under (13)
    the eigenvalues of K have positive real parts, so the step is stable for every dt (for a
    huge dt it becomes a Newton step on φ̂ = g(θ)); plain Euler would oscillate once
    ‖K‖dt > 2.

    Examples
    --------
    A perturbation linear in θ, g = θ y (p = k = 1):

    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.model.perturbation import Perturbation
    >>> class Lin(Perturbation):
    ...     dims = (1, 1, 1, 1, 1)
    ...     def g(self, v, x, th): return th * v[..., 1:]
    ...     def dg_dv(self, v, x, th): raise NotImplementedError
    ...     def dg_dx(self, v, x, th): raise NotImplementedError
    ...     def dg_dtheta(self, v, x, th): return v[..., 1:, None] + 0 * th[..., None]
    >>> from thetahat.estimation.update_laws import GradientInversion
    >>> law = GradientInversion(Lin(), 1.0, Box([-5.0], [5.0]))
    >>> law.rate([0.0, 2.0], [0.0], [2.0], [0.0]).tolist()  # Γ y (φ - θ̂ y)
    [4.0]
    """

    perturbation: Perturbation
    Gamma: FloatArray
    parameter_set: ParameterSet
    M: Callable[[FloatArray, FloatArray, FloatArray], Any] | None = None
    saturation: Saturation | None = None
    layer: float = 0.0
    _proj: Projection = field(init=False, repr=False)

    def __init__(self, perturbation: Perturbation, Gamma: ArrayLike,
                 parameter_set: ParameterSet, *,
                 M: Callable[[FloatArray, FloatArray, FloatArray], Any] | None = None,
                 saturation: Saturation | None = None, layer: float = 0.0) -> None:
        _check_common("GradientInversion", parameter_set, "raise", saturation)
        if not isinstance(perturbation, Perturbation):
            raise DimensionError(f"perturbation must be a thetahat Perturbation; got "
                                 f"{type(perturbation).__name__}.")
        if perturbation.dims[3] != parameter_set.dim:
            raise DimensionError(f"parameter_set has dimension {parameter_set.dim} but the "
                                 f"perturbation has p = {perturbation.dims[3]} parameters.")
        require_theta_dependence(perturbation, parameter_set, owner="GradientInversion")
        if M is not None and not callable(M):
            raise UpdateLawError("GradientInversion: M must be a callable M(v, x, theta) -> "
                                 "(..., p, k), or None for (∂g/∂θ)ᵀ.")
        proj = Projection(parameter_set, as_gain("Gamma", Gamma, parameter_set.dim),
                          layer=layer)
        object.__setattr__(self, "perturbation", perturbation)
        object.__setattr__(self, "Gamma", proj.Gamma)
        object.__setattr__(self, "parameter_set", parameter_set)
        object.__setattr__(self, "M", M)
        object.__setattr__(self, "saturation", saturation)
        object.__setattr__(self, "layer", proj.layer)
        object.__setattr__(self, "_proj", proj)

    def _inputs(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, tuple[int, ...]]:
        """(v, x̂, φ̂, θ̂, batch shape), checked, with x̂ and φ̂ saturated."""
        n, m, r, p, k = self.perturbation.dims
        v_, x, phi, th, batch = _as_batch(v, x_hat, phi_hat, theta_hat, p)
        for name, arr, size in (("v", v_, m + r), ("x_hat", x, n), ("phi_hat", phi, k)):
            if arr.shape[-1] != size:
                raise DimensionError(f"{name} must have shape (..., {size}); got {arr.shape}.")
        x, phi = _apply_saturation(self.saturation, x, phi)
        return v_, x, phi, th, batch

    def _jacobian(self, v: FloatArray, x: FloatArray, th: FloatArray, batch: tuple[int, ...]
                  ) -> FloatArray:
        """∂g/∂θ broadcast to the batch, shape (..., k, p)."""
        _, _, _, p, k = self.perturbation.dims
        with np.errstate(over="ignore", invalid="ignore"):
            J = np.asarray(self.perturbation.dg_dtheta(v, x, th), dtype=np.float64)
        return np.broadcast_to(J, batch + (k, p))

    def _terms(self, v_: FloatArray, x: FloatArray, phi: FloatArray, th: FloatArray,
               batch: tuple[int, ...], J: FloatArray | None, Gamma: FloatArray | None = None
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(f = ΓM(φ̂ - g), ΓM, θ̂) broadcast to the batch; J: ∂g/∂θ if already evaluated."""
        _, _, _, p, k = self.perturbation.dims
        with np.errstate(over="ignore", invalid="ignore"):
            resid = phi - np.asarray(self.perturbation.g(v_, x, th), dtype=np.float64)
            if self.M is None:
                Mm = np.swapaxes(self._jacobian(v_, x, th, batch) if J is None else J, -1, -2)
            else:
                Mm = np.asarray(self.M(v_, x, th), dtype=np.float64)
                if Mm.shape[-2:] != (p, k):
                    raise UpdateLawError(f"GradientInversion: M must return shape (..., {p}, "
                                         f"{k}); got {Mm.shape}.")
            G = self.Gamma if Gamma is None else Gamma
            GM = np.broadcast_to(G @ Mm, batch + (p, k))
            f = np.einsum("...pk,...k->...p", GM, np.broadcast_to(resid, batch + (k,)))
        return f, GM, np.broadcast_to(th, batch + (p,))

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """θ̂̇ = Proj(ΓM(φ̂ - g(v, x̂, θ̂))); shape (..., p)."""
        v_, x, phi, th_in, batch = self._inputs(v, x_hat, phi_hat, theta_hat)
        f, _, th = self._terms(v_, x, phi, th_in, batch, None)
        if not np.all(np.isfinite(f)):
            raise UpdateLawError("GradientInversion: the rate overflowed (φ̂ - g or Γ too "
                                 "large); saturate φ̂ and x̂ (Saturation) or reduce Γ.")
        return self._proj.proj(f, th)

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float, *, Gamma: ArrayLike | None = None) -> FloatArray:
        """Exponential-Euler step of the linearised law, then the Γ⁻¹ projection; in Θ.

        ``Gamma`` (shape (..., p, p)) gives one Γ per batch row in place of the law's own.
        """
        dt = _check_dt(dt)
        G = None if Gamma is None else np.asarray(Gamma, dtype=np.float64)
        v_, x, phi, th_in, batch = self._inputs(v, x_hat, phi_hat, theta_hat)
        J = self._jacobian(v_, x, th_in, batch)
        f, GM, th = self._terms(v_, x, phi, th_in, batch, J, Gamma=G)
        p = th.shape[-1]
        with np.errstate(over="ignore", invalid="ignore"):
            K = GM @ J
            Z = np.zeros(th.shape[:-1] + (p + 1, p + 1))
            Z[..., :p, :p] = -dt * K
            Z[..., :p, p] = dt * f
            ok = np.all(np.isfinite(Z), axis=(-2, -1))
            Z = np.where(ok[..., None, None], Z, 0.0)
            delta = scipy.linalg.expm(Z)[..., :p, p]
            euler = np.where(np.isfinite(f), dt * f, np.sign(np.nan_to_num(f)) * FAR)
            delta = np.where((ok[..., None] & np.all(np.isfinite(delta), axis=-1, keepdims=True)),
                             delta, euler)
            cand = th + delta
        return _project_rows(self._proj, _finite_candidate(cand, th), G)
