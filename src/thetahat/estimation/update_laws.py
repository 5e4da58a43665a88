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
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from .._validate import check_finite, positive_scalar
from ..errors import DimensionError, ParameterSetError, UpdateLawError
from ..model.paramset import ParameterSet, _safe_norm
from ..model.perturbation import Perturbation, lambdify_numpy
from .projection import Projection, Saturation, as_gain

FloatArray = NDArray[np.float64]
ThetaStar = Callable[[FloatArray, FloatArray, FloatArray], Any]
Weight = Callable[[FloatArray, FloatArray, FloatArray], Any]
OnInvalid = Literal["raise", "freeze"]

__all__ = ["UpdateLaw", "ConstantLaw", "AlgebraicInversion", "IntermittentInversion",
           "GradientInversion", "smooth_ramp"]

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
#: Relative accuracy with which a θ* derived by SymPy must recover θ from φ = g(v, x, θ) at the
#: random check points (the expressions are exact, so this only absorbs rounding).
SOLVE_RTOL = 1e-6
#: Number of random points used to tell the right branch of a SymPy solution from the others.
SOLVE_SAMPLES = 32


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
             theta_hat: FloatArray, dt: float) -> FloatArray:
        """θ̂ after a step of length dt, guaranteed in Θ (default: Euler, then ``nearest``)."""
        dt = _check_dt(dt)
        th = np.asarray(theta_hat, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            nxt = th + dt * self.rate(v, x_hat, phi_hat, theta_hat)
        return self.parameter_set.nearest(_finite_candidate(nxt, th))

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
             dt: float) -> FloatArray:
        """θ̂ unchanged (projected onto Θ should it lie outside); shape (..., p)."""
        _check_dt(dt)
        *_, th, batch = _as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        return self.parameter_set.nearest(np.broadcast_to(th, batch + th.shape[-1:]))

    def init(self, theta_hat0: ArrayLike | None = None) -> FloatArray:
        """``theta`` when θ̂₀ is not given, else the validated θ̂₀."""
        return UpdateLaw.init(self, self.theta if theta_hat0 is None else theta_hat0)


@final
@dataclass(frozen=True, slots=True, eq=False)
class _SmoothRamp:
    low: float
    high: float

    def weight(self, s: ArrayLike) -> FloatArray:
        """0 for s <= low, 1 for s >= high, 3t² - 2t³ with t = (s - low)/(high - low) between."""
        t = np.clip((np.asarray(s, dtype=np.float64) - self.low) / (self.high - self.low), 0, 1)
        return t * t * (3.0 - 2.0 * t)

    def __call__(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike) -> FloatArray:
        """l(v, x̂, φ̂) = weight(‖φ̂‖); shape (...)."""
        return self.weight(_safe_norm(np.asarray(phi_hat, dtype=np.float64)))

    def __repr__(self) -> str:
        return f"smooth_ramp(low={self.low}, high={self.high})"


def smooth_ramp(low: float, high: float) -> _SmoothRamp:
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
    return _SmoothRamp(lo, hi)


@final
@dataclass(frozen=True, slots=True, eq=False)
class _SympyThetaStar:
    """θ*(v, x, φ) lambdified from a SymPy solution of φ = g(v, x, θ)."""

    solution: tuple[sp.Expr, ...]
    m: int
    fn: Callable[..., Any] = field(repr=False)
    #: The real dummies the solution is written in, in call order: col(u, y), x, then φ.
    arguments: tuple[sp.Symbol, ...] = field(default=(), repr=False)

    def __call__(self, v: ArrayLike, x: ArrayLike, phi: ArrayLike) -> FloatArray:
        v_, x_, ph = (np.asarray(a, dtype=np.float64) for a in (v, x, phi))
        args = [*np.moveaxis(v_, -1, 0), *np.moveaxis(x_, -1, 0), *np.moveaxis(ph, -1, 0)]
        with np.errstate(all="ignore"):
            vals = [np.asarray(e) for e in self.fn(*args)]
        vals = np.broadcast_arrays(*vals, *(a for a in args))[:len(vals)]
        out = np.stack(vals, axis=-1)
        if np.iscomplexobj(out):
            real = np.abs(out.imag) <= SOLVE_RTOL * (1.0 + np.abs(out.real))
            out = np.where(real, out.real, np.nan)
        return out.astype(np.float64)

    @property
    def sympy_form(self) -> tuple[tuple[sp.Expr, ...], tuple[sp.Symbol, ...]]:
        """(θ* entries, their arguments col(u, y), x, φ in call order), for code printers."""
        return self.solution, self.arguments


def _solve_theta_star(perturbation: Perturbation, parameter_set: ParameterSet,
                      seed: int) -> _SympyThetaStar:
    """θ* from SymPy's solve of φ = g(v, x, θ), keeping the one branch that inverts g on Θ."""
    for attr in ("expr", "u", "y", "x", "theta"):
        if not hasattr(perturbation, attr):
            raise UpdateLawError("from_perturbation needs a SymbolicPerturbation (with expr, u, "
                                 "y, x, theta); for other perturbations pass theta_star.")
    n, m, r, p, k = perturbation.dims
    if parameter_set.dim != p:
        raise DimensionError(f"parameter_set has dimension {parameter_set.dim} but the "
                             f"perturbation has p = {p} parameters.")
    u, y, x, th = (tuple(getattr(perturbation, a)) for a in ("u", "y", "x", "theta"))
    reps = {s: sp.Dummy(s.name, real=True) for s in (*u, *y, *x, *th)}
    phi = [sp.Dummy(f"phi{i}", real=True) for i in range(k)]
    expr = sp.Matrix(perturbation.expr)
    eqs = [sp.Eq(expr[i].xreplace(reps), phi[i]) for i in range(k)]
    unknowns = [reps[t] for t in th]
    try:
        sols = sp.solve(eqs, unknowns, dict=True, check=False, simplify=False)
    except (NotImplementedError, ValueError, TypeError) as exc:
        raise UpdateLawError(f"SymPy cannot solve φ = g(v, x, θ) for θ ({exc}); pass "
                             f"theta_star explicitly.") from exc
    args = [reps[s] for s in (*u, *y, *x)] + phi
    branches, underdetermined = [], False
    for sol in sols:
        if not set(unknowns) <= set(sol) or any(sol[t].free_symbols & set(unknowns)
                                                for t in unknowns):
            underdetermined = True
            continue
        exprs = tuple(sol[t] for t in unknowns)
        if any(e.has(sp.zoo, sp.nan) for e in exprs):
            continue
        # SymPy's raw form can overflow where θ* is harmless (LuGre: it multiplies by
        # exp(ω²/ω0²) and divides by it again, inf·0 = NaN for |ω| > 0.27); the expanded form
        # cancels such factors. Both forms are checked below and the better one is kept.
        forms = []
        for form in dict.fromkeys((exprs, tuple(sp.expand(e) for e in exprs))):
            try:
                fn = lambdify_numpy(args, form)
            except Exception:  # noqa: BLE001 - SymPy raises many types for unprintable forms
                continue
            forms.append(_SympyThetaStar(form, m, fn, tuple(args)))
        branches.append(forms)
    rng = np.random.default_rng(seed)
    theta_s = parameter_set.sample(rng, SOLVE_SAMPLES)
    v_s = rng.standard_normal((SOLVE_SAMPLES, m + r))
    x_s = rng.standard_normal((SOLVE_SAMPLES, n))
    phi_s = np.asarray(perturbation.g(v_s, x_s, theta_s), dtype=np.float64)
    good = []
    for forms in branches:
        best, best_ok = None, SOLVE_SAMPLES // 2 - 1
        for cand in forms:
            try:
                est = cand(v_s, x_s, phi_s)
            except Exception:  # noqa: BLE001 - a form that numpy cannot evaluate is no inverse
                continue
            ok = np.all(np.isfinite(est), axis=-1)
            err = np.max(np.abs(est - theta_s), axis=-1)
            if (np.sum(ok) > best_ok and np.all(
                    err[ok] <= SOLVE_RTOL * (1 + np.max(np.abs(theta_s[ok]), axis=-1)))):
                best, best_ok = cand, int(np.sum(ok))
        if best is not None:
            good.append(best)
    if not good and underdetermined:
        raise UpdateLawError("SymPy's solution of φ = g(v, x, θ) leaves some parameters free: "
                             "one value of φ does not determine θ (e.g. p > k). Use "
                             "GradientInversion with persistent excitation (Proposition 4).")
    if len(good) != 1:
        found = "no" if not good else f"{len(good)}"
        raise UpdateLawError(f"SymPy found {len(sols)} solution(s) of φ = g(v, x, θ) but {found} "
                             f"branch(es) recover θ ∈ Θ at random points; the inverse is not "
                             f"unique (or not available) — pass theta_star explicitly, or use "
                             f"GradientInversion (Propositions 3–4).")
    return good[0]


def _inversion_target(theta_star: ThetaStar, weight: Weight | None, on_invalid: OnInvalid,
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
            raise UpdateLawError(f"{owner}: theta_star is NaN or inf at {int(np.sum(bad))} "
                                 f"point(s) where the weight is positive; make l vanish where "
                                 f"the inversion is undefined, or pass on_invalid='freeze'.")
        lw = np.where(bad, 0.0, lw)
    th_b = np.broadcast_to(th, batch + (p,))
    target = np.where((lw > 0)[..., None], ts, th_b)
    return target, lw


def _inversion_step(proj: Projection, target: FloatArray, lw: FloatArray, th: FloatArray,
                    dt: float) -> FloatArray:
    """Exact flow of θ̇ = lΓ(θ* - θ) over dt with θ* held, then the Γ⁻¹-weighted projection."""
    lam, V = np.linalg.eigh(proj.Gamma)
    th_b = np.broadcast_to(th, target.shape)
    with np.errstate(over="ignore", invalid="ignore"):
        err = (target - th_b) @ V
        decay = np.exp(-lw[..., None] * dt * lam)
        cand = target - (decay * err) @ V.T
    return proj.project(_finite_candidate(cand, th_b))


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
class AlgebraicInversion(UpdateLaw):
    """Proposition 1: θ̂̇ = Proj(Γ(θ*(v, x̂, φ̂) - θ̂)).

    Parameters
    ----------
    theta_star : callable
        ``theta_star(v, x_hat, phi_hat)`` returning the unique solution θ of φ = g(v, x, θ),
        shape (..., p). See :meth:`from_perturbation` to derive it with SymPy.
    Gamma : float or array_like, shape (p, p)
        Symmetric positive-definite gain Γ.
    parameter_set : ParameterSet
        Θ.
    saturation : Saturation, optional
        Saturation of x̂ and φ̂ before use (Remark 3).
    layer : float, optional
        Boundary layer of the projection (0 = hard projection, the default).
    on_invalid : {'raise', 'freeze'}, optional
        What to do where θ* is NaN or inf: raise :class:`~thetahat.errors.UpdateLawError`
        (default) or freeze the update (θ̂̇ = 0) there.

    Raises
    ------
    UpdateLawError
        Γ not symmetric positive definite; a bad option.

    Notes
    -----
    With x̂ = x and φ̂ = φ, θ* = θ and V = ½θ̃ᵀΓ⁻¹θ̃ gives V̇ <= -‖θ̃‖², so
    ‖θ̃(t)‖_Γ⁻¹ <= e^(-λ_min(Γ) t)‖θ̃(0)‖_Γ⁻¹. ``step`` integrates θ̇ = Γ(θ* - θ) exactly over
    dt with θ* held (θ* + e^(-Γ dt)(θ̂ - θ*)), which contracts for every dt, and then applies
    the Γ⁻¹-weighted projection onto Θ.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.update_laws import AlgebraicInversion
    >>> law = AlgebraicInversion(lambda v, x, phi: np.arcsinh(phi), 2.0, Box([-2.0], [2.0]))
    >>> law.rate([0.0, 0.0], [0.0, 0.0], [np.sinh(0.5)], [0.0]).round(12).tolist()
    [1.0]
    """

    theta_star: ThetaStar
    Gamma: FloatArray
    parameter_set: ParameterSet
    saturation: Saturation | None = None
    layer: float = 0.0
    on_invalid: OnInvalid = "raise"
    _proj: Projection = field(init=False, repr=False)

    def __init__(self, theta_star: ThetaStar, Gamma: ArrayLike, parameter_set: ParameterSet,
                 *, saturation: Saturation | None = None, layer: float = 0.0,
                 on_invalid: OnInvalid = "raise") -> None:
        _check_common("AlgebraicInversion", parameter_set, on_invalid, saturation)
        if not callable(theta_star):
            raise UpdateLawError("AlgebraicInversion: theta_star must be a callable "
                                 "theta_star(v, x_hat, phi_hat) -> (..., p).")
        proj = Projection(parameter_set, as_gain("Gamma", Gamma, parameter_set.dim),
                          layer=layer)
        object.__setattr__(self, "theta_star", theta_star)
        object.__setattr__(self, "Gamma", proj.Gamma)
        object.__setattr__(self, "parameter_set", parameter_set)
        object.__setattr__(self, "saturation", saturation)
        object.__setattr__(self, "layer", proj.layer)
        object.__setattr__(self, "on_invalid", on_invalid)
        object.__setattr__(self, "_proj", proj)

    @classmethod
    def from_perturbation(cls, perturbation: Perturbation, *, Gamma: ArrayLike,
                          parameter_set: ParameterSet, saturation: Saturation | None = None,
                          layer: float = 0.0, on_invalid: OnInvalid = "raise",
                          seed: int = 0) -> AlgebraicInversion:
        """Derive θ* by ``sympy.solve`` from a SymbolicPerturbation.

        Among SymPy's solutions, the one branch that recovers θ from φ = g(v, x, θ) at
        random points (θ ∈ Θ drawn with ``seed``, v and x standard normal) is kept.

        Raises
        ------
        UpdateLawError
            SymPy cannot solve, or not exactly one branch inverts g (the solution is not
            unique): pass ``theta_star`` yourself or use :class:`GradientInversion`.
        """
        ts = _solve_theta_star(perturbation, parameter_set, seed)
        return cls(ts, Gamma, parameter_set, saturation=saturation, layer=layer,
                   on_invalid=on_invalid)

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """θ̂̇ = Proj(Γ(θ* - θ̂)); shape (..., p)."""
        v_, x, phi, th, batch = _as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        x, phi = _apply_saturation(self.saturation, x, phi)
        target, lw = _inversion_target(self.theta_star, None, self.on_invalid,
                                       "AlgebraicInversion", v_, x, phi, th, batch)
        th_b = np.broadcast_to(th, target.shape)
        tau = lw[..., None] * ((target - th_b) @ self.Gamma)
        return self._proj.proj(tau, th_b)

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float) -> FloatArray:
        """Exact step θ* + e^(-Γ dt)(θ̂ - θ*), then the Γ⁻¹-weighted projection; in Θ."""
        dt = _check_dt(dt)
        v_, x, phi, th, batch = _as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        x, phi = _apply_saturation(self.saturation, x, phi)
        target, lw = _inversion_target(self.theta_star, None, self.on_invalid,
                                       "AlgebraicInversion", v_, x, phi, th, batch)
        return _inversion_step(self._proj, target, lw, th, dt)


@final
@dataclass(frozen=True, slots=True, eq=False)
class IntermittentInversion(UpdateLaw):
    """Proposition 2: θ̂̇ = Proj(l(v, x̂, φ̂) Γ(θ*(v, x̂, φ̂) - θ̂)).

    Parameters
    ----------
    theta_star : callable
        ``theta_star(v, x_hat, phi_hat)``, shape (..., p): the unique solution of
        φ = g(v, x, θ) wherever l > 0 (anything, NaN included, where l = 0).
    l : callable
        ``l(v, x_hat, phi_hat)`` with values in [0, 1], shape (...). :func:`smooth_ramp`
        builds a Lipschitz one.
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
    ∫_t^(t+T) l dτ >= σ. ``step`` integrates θ̇ = lΓ(θ* - θ) exactly over dt with l and θ*
    held, then projects (Γ⁻¹-weighted), so for p = 1 and no projection θ̃(t) = e^(-γ∫l)θ̃(0).

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

    theta_star: ThetaStar
    l: Weight
    Gamma: FloatArray
    parameter_set: ParameterSet
    saturation: Saturation | None = None
    layer: float = 0.0
    on_invalid: OnInvalid = "raise"
    _proj: Projection = field(init=False, repr=False)

    def __init__(self, theta_star: ThetaStar, l: Weight, Gamma: ArrayLike,  # noqa: E741
                 parameter_set: ParameterSet, *, saturation: Saturation | None = None,
                 layer: float = 0.0, on_invalid: OnInvalid = "raise") -> None:
        _check_common("IntermittentInversion", parameter_set, on_invalid, saturation)
        if not (callable(theta_star) and callable(l)):
            raise UpdateLawError("IntermittentInversion: theta_star and l must be callables of "
                                 "(v, x_hat, phi_hat).")
        proj = Projection(parameter_set, as_gain("Gamma", Gamma, parameter_set.dim),
                          layer=layer)
        object.__setattr__(self, "theta_star", theta_star)
        object.__setattr__(self, "l", l)
        object.__setattr__(self, "Gamma", proj.Gamma)
        object.__setattr__(self, "parameter_set", parameter_set)
        object.__setattr__(self, "saturation", saturation)
        object.__setattr__(self, "layer", proj.layer)
        object.__setattr__(self, "on_invalid", on_invalid)
        object.__setattr__(self, "_proj", proj)

    @classmethod
    def from_perturbation(cls, perturbation: Perturbation, l: Weight,  # noqa: E741
                          *, Gamma: ArrayLike, parameter_set: ParameterSet,
                          saturation: Saturation | None = None, layer: float = 0.0,
                          on_invalid: OnInvalid = "raise",
                          seed: int = 0) -> IntermittentInversion:
        """Derive θ* by ``sympy.solve`` (see :meth:`AlgebraicInversion.from_perturbation`)."""
        ts = _solve_theta_star(perturbation, parameter_set, seed)
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
             dt: float) -> FloatArray:
        """Exact step θ* + e^(-lΓ dt)(θ̂ - θ*), then the Γ⁻¹-weighted projection; in Θ."""
        dt = _check_dt(dt)
        target, lw, th = self._target(v, x_hat, phi_hat, theta_hat)
        return _inversion_step(self._proj, target, lw, th, dt)


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

    def _terms(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
               jacobian: bool) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray]:
        """(f = ΓM(φ̂ - g), ΓM, ∂g/∂θ or None, θ̂) broadcast to the batch."""
        n, m, r, p, k = self.perturbation.dims
        v_, x, phi, th, batch = _as_batch(v, x_hat, phi_hat, theta_hat, p)
        for name, arr, size in (("v", v_, m + r), ("x_hat", x, n), ("phi_hat", phi, k)):
            if arr.shape[-1] != size:
                raise DimensionError(f"{name} must have shape (..., {size}); got {arr.shape}.")
        x, phi = _apply_saturation(self.saturation, x, phi)
        with np.errstate(over="ignore", invalid="ignore"):
            resid = phi - np.asarray(self.perturbation.g(v_, x, th), dtype=np.float64)
            J = None
            if self.M is None or jacobian:
                J = np.broadcast_to(self.perturbation.dg_dtheta(v_, x, th), batch + (k, p))
            if self.M is None:
                Mm = np.swapaxes(J, -1, -2)
            else:
                Mm = np.asarray(self.M(v_, x, th), dtype=np.float64)
                if Mm.shape[-2:] != (p, k):
                    raise UpdateLawError(f"GradientInversion: M must return shape (..., {p}, "
                                         f"{k}); got {Mm.shape}.")
            GM = np.broadcast_to(self.Gamma @ Mm, batch + (p, k))
            f = np.einsum("...pk,...k->...p", GM, np.broadcast_to(resid, batch + (k,)))
        return f, GM, J, np.broadcast_to(th, batch + (p,))

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """θ̂̇ = Proj(ΓM(φ̂ - g(v, x̂, θ̂))); shape (..., p)."""
        f, _, _, th = self._terms(v, x_hat, phi_hat, theta_hat, jacobian=False)
        if not np.all(np.isfinite(f)):
            raise UpdateLawError("GradientInversion: the rate overflowed (φ̂ - g or Γ too "
                                 "large); saturate φ̂ and x̂ (Saturation) or reduce Γ.")
        return self._proj.proj(f, th)

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float) -> FloatArray:
        """Exponential-Euler step of the linearised law, then the Γ⁻¹ projection; in Θ."""
        dt = _check_dt(dt)
        f, GM, J, th = self._terms(v, x_hat, phi_hat, theta_hat, jacobian=True)
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
        return self._proj.project(_finite_candidate(cand, th))
