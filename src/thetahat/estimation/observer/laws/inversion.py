"""Propositions 1 and 2: θ̂ driven towards the inversion θ*(v, x̂, φ̂) of φ = g(v, x, θ).

:class:`IntermittentInversion` with an excitation weight l (Proposition 2, :func:`smooth_ramp`
for the Lipschitz l of Remark 5), and :func:`AlgebraicInversion`, the same law with l ≡ 1
(Proposition 1), with θ* given or derived by SymPy (:func:`algebraic_from_perturbation`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...._validate import positive_scalar, readonly
from ....errors import UpdateLawError
from ....model.paramset import ParameterSet
from ....model.perturbation import Perturbation
from ....model.set_geometry import safe_norm
from .base import (FAR, UpdateLaw, apply_saturation, as_batch, broadcast_rows,
                       check_law_options, is_diagonal, law_binding, law_program, project_rows)
from ...kernels.kernel_args import LawArrays
from .projection import Projection, Saturation, as_gain
from ...status import Status, status_constants
from .theta_star import ThetaStar

__all__ = ["AlgebraicInversion", "IntermittentInversion", "SmoothRamp", "WEIGHT_TOL",
           "algebraic_from_perturbation", "gain_eigen", "invalid_theta_star_error",
           "smooth_ramp"]

FloatArray = NDArray[np.float64]
ThetaStarFn = Callable[[FloatArray, FloatArray, FloatArray], Any]
Weight = Callable[[FloatArray, FloatArray, FloatArray], Any]
OnInvalid = Literal["raise", "freeze"]

#: Values of an excitation weight l within this distance outside [0, 1] are rounding and
#: clipped; larger excursions are an error in the user's l.
WEIGHT_TOL = 1e-12


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
        step = law_binding(law_program(), None, ("smoothstep",), False, dict)["smoothstep"]
        return np.asarray(step(np.asarray(s, dtype=np.float64), self.low, self.high))

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
    >>> from thetahat.estimation.observer.laws import smooth_ramp
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


def invalid_theta_star_error(owner: str, count: int | None) -> UpdateLawError:
    """The error every back end raises when θ* is NaN or inf where l > 0 (on_invalid='raise').

    Parameters
    ----------
    owner : str
        The law's name.
    count : int or None
        Number of points (batch rows) affected, when known (the formulas' status
        :attr:`~thetahat.estimation.status.Status.THETA_STAR` does not count them).

    Returns
    -------
    UpdateLawError
    """
    where = "some point(s)" if count is None else f"{count} point(s)"
    return UpdateLawError(f"{owner}: theta_star is NaN or inf at {where} where the "
                          f"weight is positive; make l vanish where the inversion is "
                          f"undefined, or pass on_invalid='freeze'.")


def _checked_weight(weight: Weight, owner: str, v: FloatArray, x: FloatArray, phi: FloatArray,
                    batch: tuple[int, ...]) -> FloatArray:
    """l(v, x̂, φ̂) broadcast to the batch, checked to lie in [0, 1] (rounding clipped)."""
    lw = np.broadcast_to(np.asarray(weight(v, x, phi), dtype=np.float64), batch).copy()
    ok = (-WEIGHT_TOL <= float(lw) <= 1 + WEIGHT_TOL if lw.ndim == 0      # NaN fails too
          else bool(((lw >= -WEIGHT_TOL) & (lw <= 1 + WEIGHT_TOL)).all()))
    if not ok:
        raise UpdateLawError(f"{owner}: the excitation weight l must return values in "
                             f"[0, 1] (Proposition 2); got values in [{np.nanmin(lw)}, "
                             f"{np.nanmax(lw)}] (or NaN).")
    return np.clip(lw, 0.0, 1.0)


def _checked_theta_star(theta_star: ThetaStar | ThetaStarFn, owner: str, v: FloatArray,
                        x: FloatArray, phi: FloatArray, batch: tuple[int, ...],
                        p: int) -> FloatArray:
    """θ*(v, x̂, φ̂) broadcast to the batch (NaN and inf allowed), its width checked."""
    with np.errstate(all="ignore"):
        ts = np.asarray(theta_star(v, x, phi), dtype=np.float64)
    if ts.ndim == 0 or ts.shape[-1] != p:
        raise UpdateLawError(f"{owner}: theta_star must return shape (..., {p}); got "
                             f"{ts.shape}.")
    return ts if ts.shape == batch + (p,) else np.broadcast_to(ts, batch + (p,))


def gain_eigen(Gamma: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(Λ, V, Vᵀ) with Γ = V diag(Λ) Vᵀ, for one Γ (p, p) or one per row (..., p, p).

    A diagonal Γ gives V = I exactly (its diagonal is Λ).

    Parameters
    ----------
    Gamma : ndarray, shape (..., p, p)
        Symmetric positive definite.

    Returns
    -------
    lam : ndarray, shape (..., p)
    V, VT : ndarray, shape (..., p, p) or (p, p)

    Examples
    --------
    >>> import numpy as np
    >>> lam, V, VT = gain_eigen(np.diag([2.0, 3.0]))
    >>> lam.tolist(), V.tolist()
    ([2.0, 3.0], [[1.0, 0.0], [0.0, 1.0]])
    """
    p = Gamma.shape[-1]
    if is_diagonal(Gamma):
        eye = np.eye(p)
        return np.diagonal(Gamma, axis1=-2, axis2=-1).copy(), eye, eye
    lam, V = np.linalg.eigh(Gamma)
    return lam, V, np.swapaxes(V, -1, -2).copy()


def _inversion_names(law: IntermittentInversion) -> dict[str, Any]:
    """The hooks of :func:`law_formulas.inversion_law` for one law."""
    owner = "IntermittentInversion"
    p = law.parameter_set.dim

    def weight(LP: LawArrays, v: FloatArray, x: FloatArray, phi: FloatArray) -> Any:
        if law.l is None:
            return 1.0
        return _checked_weight(law.l, owner, v, x, phi, phi.shape[:-1])

    def theta_star(v: FloatArray, x: FloatArray, phi: FloatArray, ts: FloatArray) -> None:
        ts[...] = _checked_theta_star(law.theta_star, owner, v, x, phi, phi.shape[:-1], p)

    def project(LP: LawArrays, thn: FloatArray) -> int:
        thn[...] = project_rows(law._proj, thn, LP.Gamma_rows)
        return 0

    return {"weight": weight, "theta_star": theta_star, "project": project,
            "freeze": lambda LP: law.on_invalid == "freeze", "NP": p, "FAR": FAR,
            **status_constants()}


#: The law formulas an IntermittentInversion runs (``rate``, ``step``).
_ROOTS = ("inversion_target", "inversion_law")


@final
@dataclass(frozen=True, slots=True, eq=False)
class IntermittentInversion(UpdateLaw):
    r"""Propositions 1 and 2: θ̂̇ = Proj(l(v, x̂, φ̂) Γ(θ*(v, x̂, φ̂) - θ̂)).

    $$
    \dot{\hat\theta} = \operatorname{Proj}\bigl(l(v, \hat x, \hat\phi)\,
      \Gamma\,(\theta^*(v, \hat x, \hat\phi) - \hat\theta)\bigr)
    $$

    Parameters
    ----------
    theta_star : ThetaStar or callable
        ``theta_star(v, x_hat, phi_hat)``, shape (..., p): the unique solution of
        φ = g(v, x, θ) wherever l > 0 (anything, NaN included, where l = 0). A
        :class:`~thetahat.estimation.observer.laws.theta_star.ThetaStar` carries its SymPy form too, which
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
    >>> from thetahat.estimation.observer.laws import IntermittentInversion, smooth_ramp
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
        check_law_options("IntermittentInversion", parameter_set, on_invalid, saturation)
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
        <thetahat.estimation.observer.laws.theta_star.ThetaStar.solve>`); ``l=None`` is Proposition 1.

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

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """θ̂̇ = Proj(lΓ(θ* - θ̂)); shape (..., p).

        θ* and l from :func:`~thetahat.estimation.observer.laws.formulas.inversion_target` on NumPy
        arrays (the step's own rule for an invalid θ*).
        """
        v_, x, phi, th, batch = as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        x, phi = apply_saturation(self.saturation, x, phi)
        args = broadcast_rows(batch, v_, x, phi, th)
        target = np.empty(batch + th.shape[-1:])
        env = law_binding(self, None, _ROOTS, batch == (), lambda: _inversion_names(self))
        nbad, lw = env["inversion_target"](LawArrays(), args[0], args[1], args[2], args[3],
                                           target)
        if nbad and self.on_invalid == "raise":
            raise invalid_theta_star_error("IntermittentInversion", nbad)
        tau = np.broadcast_to(lw, batch)[..., None] * ((target - args[3]) @ self.Gamma)
        return self._proj.proj(tau, args[3])

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float, *, Gamma: ArrayLike | None = None) -> FloatArray:
        """Exact step θ* + e^(-lΓ dt)(θ̂ - θ*), then the Γ⁻¹-weighted projection; in Θ.

        :func:`~thetahat.estimation.observer.laws.formulas.inversion_law` on NumPy arrays. ``Gamma``
        (shape (..., p, p)) gives one Γ per batch row in place of the law's own.
        """
        dt = positive_scalar("dt", dt)
        v_, x, phi, th, batch = as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        x, phi = apply_saturation(self.saturation, x, phi)
        p = th.shape[-1]
        G = None if Gamma is None else np.asarray(Gamma, dtype=np.float64)
        lam, V, VT = ((self._eig[0], self._eig[1], self._eig[1].T) if G is None
                      else gain_eigen(G))
        args = broadcast_rows(batch, v_, x, phi, th)
        thn = np.empty(batch + (p,))
        env = law_binding(self, None, _ROOTS, batch == (), lambda: _inversion_names(self))
        with np.errstate(over="ignore", invalid="ignore"):
            LP = LawArrays(lam=lam, V=V, VT=VT, ts=np.empty_like(thn), err=np.empty_like(thn),
                           Gamma_rows=G)
            status = env["inversion_law"](LP, args[0], args[1], args[2], args[3], dt, thn,
                                          None)
        if status == Status.THETA_STAR:
            raise invalid_theta_star_error("IntermittentInversion", None)
        return thn


def AlgebraicInversion(theta_star: ThetaStar | ThetaStarFn, Gamma: ArrayLike,  # noqa: N802
                       parameter_set: ParameterSet, *, saturation: Saturation | None = None,
                       layer: float = 0.0,
                       on_invalid: OnInvalid = "raise") -> IntermittentInversion:
    """Proposition 1, θ̂̇ = Proj(Γ(θ*(v, x̂, φ̂) - θ̂)): :class:`IntermittentInversion` with l ≡ 1.

    A named constructor: the law it returns is an ``IntermittentInversion`` whose ``l`` is
    None. :func:`algebraic_from_perturbation` derives θ* with SymPy.

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
    >>> from thetahat.estimation.observer.laws import AlgebraicInversion
    >>> law = AlgebraicInversion(lambda v, x, phi: np.arcsinh(phi), 2.0, Box([-2.0], [2.0]))
    >>> law.rate([0.0, 0.0], [0.0, 0.0], [np.sinh(0.5)], [0.0]).round(12).tolist()
    [1.0]
    >>> law.l is None
    True
    """
    return IntermittentInversion(theta_star, None, Gamma, parameter_set, saturation=saturation,
                                 layer=layer, on_invalid=on_invalid)


def algebraic_from_perturbation(perturbation: Perturbation, *, Gamma: ArrayLike,
                                parameter_set: ParameterSet,
                                saturation: Saturation | None = None, layer: float = 0.0,
                                on_invalid: OnInvalid = "raise",
                                seed: int = 0) -> IntermittentInversion:
    """Proposition 1 with θ* derived by ``sympy.solve``: :func:`AlgebraicInversion` of
    :meth:`IntermittentInversion.from_perturbation` (l ≡ 1).

    Parameters
    ----------
    perturbation : SymbolicPerturbation
        g, whose inversion φ = g(v, x, θ) in θ gives θ*.
    Gamma, parameter_set, saturation, layer, on_invalid, seed
        As for :meth:`IntermittentInversion.from_perturbation`.

    Returns
    -------
    IntermittentInversion
        With ``l`` None.

    Raises
    ------
    UpdateLawError
        SymPy cannot solve, or not exactly one branch inverts g.

    Examples
    --------
    >>> import sympy as sp
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.model.perturbation import SymbolicPerturbation
    >>> y, x, th = sp.symbols("y x theta")
    >>> g = SymbolicPerturbation.from_sympy(th * y, u=[], y=[y], x=[x], theta=[th])
    >>> law = algebraic_from_perturbation(g, Gamma=1.0, parameter_set=Box([0.5], [2.0]))
    >>> law.l is None
    True
    """
    return IntermittentInversion.from_perturbation(
        perturbation, None, Gamma=Gamma, parameter_set=parameter_set, saturation=saturation,
        layer=layer, on_invalid=on_invalid, seed=seed)
