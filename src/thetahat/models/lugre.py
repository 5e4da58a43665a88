"""The paper's example (Sec. VIII): a DC motor with LuGre friction and unknown Coulomb level.

The motor is ``J ω̇ = u - F`` with the LuGre friction torque ``F = σ0 η + σ1 η̇ + α2 ω`` and
bristle state ``η̇ = ω - σ0 η |ω| / ζ(ω, θ)``, ``ζ(ω, θ) = θ + α1 exp(-(ω/ω0)²)``, where the
unknown parameter is θ := α0 (Coulomb friction), known to lie in Θ = [0.05, 1] N·m. With
x = col(ω, η), y = ω, v = col(u, y) and φ = σ0 η |ω| / ζ(ω, θ) the plant is of the form (1):

    A = [[-(α2 + σ1)/J, -σ0/J], [1, 0]],  B = [[1/J], [0]],  E = [[σ1/J], [-1]],  C = [[1, 0]].

Two perturbations appear and must not be confused:

* the plant's **true** φ uses the true |ω| (:func:`true_phi`, used to simulate);
* the observer's **model** g(v, x, θ) = σ0 η |y| / ζ(ω, θ) uses the measured |y| (Remark 4),
  so that d is Lipschitz as Assumption 2 requires (:func:`perturbation`).

This module is the one factory that tests, the demo, the docs and the benchmarks import.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from .._validate import as_vector, positive_scalar
from ..design.gains import GainDesign, PoleSpec
from ..errors import ArgumentTypeError, DimensionError, ParameterSetError, ThetahatWarning
from ..estimation.observer.observer import ModifiedHighGainObserver
from ..estimation.protocol import Estimator
from ..estimation.observer.laws.theta_star import ThetaStar
from ..methods import MethodInputs, get_method
from ..model.paramset import Box
from ..model.perturbation import SymbolicPerturbation
from ..model.system import PerturbedLinearSystem
from ..simulation.noise import Seed, WhiteNoise
from ..simulation.signals import Multisine, Signal
from ..simulation.simulate import PlantTrajectory, simulate_plant
from ..spec import EstimatorSpec, SecondObserverSpec

if TYPE_CHECKING:
    from ..modelfile.study import StudySetup

__all__ = [
    "LUGRE_ATOL",
    "LUGRE_METHOD",
    "LUGRE_RTOL",
    "LuGreParameters",
    "LuGrePhi",
    "estimator",
    "Scenario",
    "design_system",
    "designs",
    "estimator_spec",
    "linear_part",
    "observer",
    "perturbation",
    "simulate",
    "study_setup",
    "system",
    "theta_star",
    "true_phi",
]

FloatArray = NDArray[np.float64]

#: Integrator of the default LuGre simulation. LSODA (stiffness-switching BDF/Adams with the
#: analytic Jacobian) reaches the accuracy of Radau at rtol 1e-8 about five times faster on the
#: 20 s scenario (both checked against Radau at rtol 1e-11).
LUGRE_METHOD = "LSODA"
#: Relative tolerance of the default LuGre simulation. With it the 20 s scenario agrees with a
#: Radau solution at rtol 1e-11 to about 1.3e-8 rad/s in ω and 1.3e-11 rad in η (measured;
#: asserted with margin in tests/models/test_lugre_plant.py).
LUGRE_RTOL = 1e-9
#: Absolute tolerance per state (ω in rad/s, η in rad): η never exceeds (α0 + α1)/σ0 ≈ 1.3e-3
#: rad, so its tolerance is scaled down by the same ~1e3 ratio as its magnitude.
LUGRE_ATOL = (1e-10, 1e-13)

@dataclass(frozen=True, slots=True)
class LuGreParameters:
    """Physical parameters of the DC motor with LuGre friction (Sec. VIII; defaults = paper).

    Parameters
    ----------
    J : float
        Motor and load inertia (kg m²).
    sigma0 : float
        Bristle stiffness σ0 (N m/rad).
    sigma1 : float
        Bristle damping σ1 (N m s/rad).
    alpha0 : float
        Coulomb friction level α0 (N m); the unknown θ, i.e. its true value.
    alpha1 : float
        Stribeck excess α1 (N m).
    alpha2 : float
        Viscous friction α2 (N m s/rad).
    omega0 : float
        Stribeck velocity ω0 (rad/s).
    theta_lower, theta_upper : float
        Θ = [theta_lower, theta_upper], the a-priori range of θ (N m).

    Raises
    ------
    DimensionError
        A parameter is non-positive where it must be positive (or negative where it must be
        non-negative), or ``theta_lower >= theta_upper``.

    Examples
    --------
    >>> from thetahat.models.lugre import LuGreParameters
    >>> p = LuGreParameters()
    >>> p.alpha0, (p.theta_lower, p.theta_upper)
    (0.28, (0.05, 1.0))
    >>> round(p.zeta(0.0), 6)      # α0 + α1 at standstill
    0.33
    """

    J: float = 0.0023
    sigma0: float = 260.0
    sigma1: float = 0.6
    alpha0: float = 0.28
    alpha1: float = 0.05
    alpha2: float = 0.176
    omega0: float = 0.01
    theta_lower: float = 0.05
    theta_upper: float = 1.0

    def __post_init__(self) -> None:
        for name in ("J", "sigma0", "alpha0", "omega0", "theta_lower", "theta_upper"):
            object.__setattr__(self, name, positive_scalar(name, getattr(self, name)))
        for name in ("sigma1", "alpha1", "alpha2"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value < 0:
                raise DimensionError(f"LuGreParameters.{name} must be finite and >= 0; got "
                                     f"{value}.")
            object.__setattr__(self, name, value)
        if self.theta_lower >= self.theta_upper:
            raise DimensionError(f"Θ = [theta_lower, theta_upper] must have theta_lower < "
                                 f"theta_upper; got [{self.theta_lower}, {self.theta_upper}].")

    def zeta(self, omega: ArrayLike, theta: ArrayLike | None = None) -> FloatArray | float:
        """ζ(ω, θ) = θ + α1 exp(-(ω/ω0)²), with θ = α0 when not given (Sec. VIII)."""
        th = self.alpha0 if theta is None else np.asarray(theta, dtype=np.float64)
        z = th + self.alpha1 * np.exp(-(np.asarray(omega, dtype=np.float64) / self.omega0) ** 2)
        return float(z) if np.ndim(z) == 0 else z

    @property
    def eta_bound(self) -> float:
        """(α0 + α1)/σ0: |η| stays below it when it starts below it (rad)."""
        return (self.alpha0 + self.alpha1) / self.sigma0


def linear_part(params: LuGreParameters = LuGreParameters(),
                sigma1: float | None = None) -> PerturbedLinearSystem:
    """The matrices (A, B, C, E) of the motor, with no perturbation attached (Sec. VIII).

    ``J ω̇ = u - (α2 + σ1) ω - σ0 η + σ1 φ`` and ``η̇ = ω - φ`` give

    ``A = [[-(α2 + σ1)/J, -σ0/J], [1, 0]]``, ``B = [[1/J], [0]]``, ``E = [[σ1/J], [-1]]``,
    ``C = [[1, 0]]``.

    Parameters
    ----------
    params : LuGreParameters, optional
    sigma1 : float, optional
        Overrides ``params.sigma1`` (``0`` gives :func:`design_system`).

    Returns
    -------
    PerturbedLinearSystem
        n = 2, m = 1, r = 1, k = 1, without perturbation and parameter set.

    Examples
    --------
    >>> from thetahat.models.lugre import linear_part
    >>> lin = linear_part()
    >>> lin.E.ravel().round(3).tolist()
    [260.87, -1.0]
    """
    s1 = params.sigma1 if sigma1 is None else float(sigma1)
    if not np.isfinite(s1) or s1 < 0:
        raise DimensionError(f"sigma1 must be finite and >= 0; got {s1}.")
    J = params.J
    return PerturbedLinearSystem(
        A=[[-(params.alpha2 + s1) / J, -params.sigma0 / J], [1.0, 0.0]],
        B=[[1.0 / J], [0.0]], C=[[1.0, 0.0]], E=[[s1 / J], [-1.0]])


def design_system(params: LuGreParameters = LuGreParameters()) -> PerturbedLinearSystem:
    """The simplified design system of Sec. VIII A: :func:`linear_part` with σ1 = 0.

    σ1 is a small perturbation of the system matrices that lowers the relative degree and
    makes the SCB of the true triple badly conditioned (Sec. VII); the gains are designed for
    this system instead.

    Parameters
    ----------
    params : LuGreParameters, optional
        Physical parameters; default: the paper's.

    Returns
    -------
    PerturbedLinearSystem
        n = 2, m = 1, r = 1, k = 1, without perturbation and parameter set.

    Examples
    --------
    >>> from thetahat.models.lugre import design_system
    >>> design_system().E.ravel().tolist()
    [0.0, -1.0]
    """
    return linear_part(params, sigma1=0.0)


@functools.lru_cache(maxsize=8)
def perturbation(params: LuGreParameters = LuGreParameters()) -> SymbolicPerturbation:
    """The observer's model g(v, x, θ) = σ0 η |y| / ζ(ω, θ), with v = (u, y), x = (ω, η).

    Remark 4: g uses the measured |y| rather than |ω|, so that the Lipschitz-like condition
    of Assumption 2 on d can hold; the plant itself has |ω| (:func:`true_phi`). Built once
    per parameter set with SymPy (exact Jacobians) and cached.

    Parameters
    ----------
    params : LuGreParameters, optional
        Physical parameters; default: the paper's.

    Returns
    -------
    SymbolicPerturbation
        dims (n, m, r, p, k) = (2, 1, 1, 1, 1); symbols ``u``, ``y``, ``omega``, ``eta``,
        ``theta``.

    Examples
    --------
    >>> from thetahat.models.lugre import perturbation
    >>> g = perturbation()
    >>> g.dims
    (2, 1, 1, 1, 1)
    >>> round(float(g.g([0.0, -2.0], [2.0, 1e-3], [0.28])[0]), 6)   # 260·1e-3·2/0.28
    1.857143
    """
    u, y, omega, eta, theta = sp.symbols("u y omega eta theta", real=True)
    p = params
    zeta = theta + sp.Float(p.alpha1) * sp.exp(-(omega / sp.Float(p.omega0)) ** 2)
    expr = sp.Float(p.sigma0) * eta * sp.Abs(y) / zeta
    return SymbolicPerturbation.from_sympy(expr, u=[u], y=[y], x=[omega, eta], theta=[theta])


def system(params: LuGreParameters = LuGreParameters()) -> PerturbedLinearSystem:
    """The motor as a :class:`~thetahat.model.system.PerturbedLinearSystem` (Sec. VIII).

    The true matrices of :func:`linear_part` (σ1 included), the observer's g of
    :func:`perturbation` and Θ = Box([theta_lower], [theta_upper]).

    Parameters
    ----------
    params : LuGreParameters, optional
        Physical parameters; default: the paper's.

    Returns
    -------
    PerturbedLinearSystem

    Examples
    --------
    >>> from thetahat.models.lugre import system
    >>> sys = system()
    >>> sys.n, sys.m, sys.r, sys.k, sys.p
    (2, 1, 1, 1, 1)
    """
    lin = linear_part(params)
    return PerturbedLinearSystem(A=lin.A, B=lin.B, C=lin.C, E=lin.E,
                                 perturbation=perturbation(params),
                                 parameter_set=Box([params.theta_lower], [params.theta_upper]))


@dataclass(frozen=True, slots=True)
class LuGrePhi:
    """The plant's true perturbation φ = σ0 η |ω| / ζ(ω, θ), with ∂φ/∂x (Sec. VIII).

    Call signature ``phi(t, x, u, theta)`` as :func:`~thetahat.simulation.simulate.simulate_plant`
    expects: ``x (..., 2) = (ω, η)``, ``theta (..., 1)``; returns ``(..., 1)``. ``t`` and ``u``
    are unused (the friction is time-invariant).

    Parameters
    ----------
    params : LuGreParameters

    Examples
    --------
    >>> from thetahat.models.lugre import true_phi
    >>> phi = true_phi()
    >>> round(float(phi(0.0, [1.0, 1e-3], None, [0.28])[0]), 6)   # 260·1e-3·1/0.28
    0.928571
    """

    params: LuGreParameters

    def __call__(self, t: ArrayLike, x: ArrayLike, u: ArrayLike | None, theta: ArrayLike
                 ) -> FloatArray:
        """φ(x, θ); shape (..., 1)."""
        x_ = np.asarray(x, dtype=np.float64)
        omega, eta = x_[..., 0], x_[..., 1]
        th = np.asarray(theta, dtype=np.float64)[..., 0]
        p = self.params
        zeta = th + p.alpha1 * np.exp(-(omega / p.omega0) ** 2)
        return (p.sigma0 * eta * np.abs(omega) / zeta)[..., None]

    def dphi_dx(self, t: ArrayLike, x: ArrayLike, u: ArrayLike | None, theta: ArrayLike
                ) -> FloatArray:
        """∂φ/∂x = [∂φ/∂ω, ∂φ/∂η]; shape (..., 1, 2) (sign(0) = 0 at ω = 0)."""
        x_ = np.asarray(x, dtype=np.float64)
        omega, eta = x_[..., 0], x_[..., 1]
        th = np.asarray(theta, dtype=np.float64)[..., 0]
        p = self.params
        stribeck = p.alpha1 * np.exp(-(omega / p.omega0) ** 2)
        zeta = th + stribeck
        dzeta = -2.0 * omega / p.omega0 ** 2 * stribeck
        d_omega = p.sigma0 * eta * (np.sign(omega) * zeta - np.abs(omega) * dzeta) / zeta ** 2
        d_eta = p.sigma0 * np.abs(omega) / zeta
        return np.stack([d_omega, d_eta], axis=-1)[..., None, :]


def true_phi(params: LuGreParameters = LuGreParameters()) -> LuGrePhi:
    """The plant's true φ = σ0 η |ω| / ζ(ω, θ) (with the *true* |ω|), for simulation.

    See :class:`LuGrePhi`; pass ``phi=f`` and ``dphi_dx=f.dphi_dx`` to
    :func:`~thetahat.simulation.simulate.simulate_plant`.

    Parameters
    ----------
    params : LuGreParameters, optional
        Physical parameters; default: the paper's.

    Returns
    -------
    LuGrePhi
    """
    return LuGrePhi(params)


def theta_star(params: LuGreParameters = LuGreParameters()) -> ThetaStar:
    """The paper's algebraic inverse θ*(v, x̂, φ̂) = σ0 η̂ |y| / φ̂ − α1 exp(−(ω̂/ω0)²) (Sec. VIII A).

    It solves φ̂ = g(v, x̂, θ) for θ; it is defined where φ̂ ≠ 0 (NaN where φ̂ = 0), and the
    paper uses it only where the excitation indicator l(v, x̂, φ̂) = 1, i.e. |φ̂| ≥ 1. The
    :class:`~thetahat.estimation.observer.laws.theta_star.ThetaStar` carries the SymPy expression (in the
    symbols of :func:`perturbation` and ``phi``) and its numpy function, so the Python and the
    compiled paths evaluate the same formula.

    Parameters
    ----------
    params : LuGreParameters, optional
        Physical parameters; default: the paper's.

    Returns
    -------
    ThetaStar

    Examples
    --------
    θ* inverts g exactly: with φ̂ = g(v, x, 0.28) it returns 0.28.

    >>> from thetahat.models.lugre import theta_star, LuGreParameters
    >>> p = LuGreParameters()
    >>> x = [2.0, 1e-3]
    >>> phi = p.sigma0 * x[1] * abs(x[0]) / p.zeta(x[0], 0.28)
    >>> round(float(theta_star(p)([0.0, 2.0], x, [phi])[0]), 12)
    0.28
    >>> sorted(str(s) for s in theta_star(p).expr[0].free_symbols)
    ['eta', 'omega', 'phi', 'y']
    """
    g = perturbation(params)
    (y,) = g.y
    omega, eta = g.x
    phi = sp.Symbol("phi", real=True)
    expr = (sp.Float(params.sigma0) * eta * sp.Abs(y) / phi
            - sp.Float(params.alpha1) * sp.exp(-(omega / sp.Float(params.omega0)) ** 2))
    return ThetaStar.from_expr(expr, perturbation=g, phi=[phi])


def _default_input() -> Signal:
    return Multisine([0.7, 0.25], [0.5, 1.3])


@dataclass(frozen=True, slots=True, eq=False)
class Scenario:
    """The default LuGre experiment (ours: the paper does not list its input or noise).

    Parameters
    ----------
    t_end : float
        Duration (s); default 20.
    fs : float
        Output sampling frequency (Hz); default 1000.
    u : Signal
        Motor torque (N m); default 0.7 sin(2π·0.5 t) + 0.25 sin(2π·1.3 t).
    x0 : tuple of float
        Initial (ω, η); default (0, 0).
    noise_std : float
        Standard deviation of the white Gaussian noise on y (rad/s); default 0.02; 0 for
        noise-free outputs.
    theta_hat0 : float
        Initial parameter estimate θ̂(0) (N m) for the observer; default 0.5; must be in Θ.
    params : LuGreParameters
        Physical parameters; the true θ is ``params.alpha0``.

    Raises
    ------
    DimensionError
        Bad shapes or values (``t_end``/``fs`` <= 0, negative ``noise_std``, ...).
    ParameterSetError
        ``theta_hat0`` lies outside Θ.

    Warns
    -----
    ThetahatWarning
        The true θ (``params.alpha0``) lies outside Θ.

    Examples
    --------
    >>> from thetahat.models.lugre import Scenario
    >>> s = Scenario(t_end=5.0)
    >>> s.t_end, s.fs, s.theta, s.theta_hat0
    (5.0, 1000.0, 0.28, 0.5)
    """

    t_end: float = 20.0
    fs: float = 1000.0
    u: Signal = field(default_factory=_default_input)
    x0: tuple[float, float] = (0.0, 0.0)
    noise_std: float = 0.02
    theta_hat0: float = 0.5
    params: LuGreParameters = LuGreParameters()

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_end", positive_scalar("t_end", self.t_end))
        object.__setattr__(self, "fs", positive_scalar("fs", self.fs))
        if not isinstance(self.params, LuGreParameters):
            raise ArgumentTypeError(f"params must be LuGreParameters; got {type(self.params).__name__}.")
        if not isinstance(self.u, Signal) or self.u.dim != 1:
            raise DimensionError("u must be a single-channel thetahat Signal (the motor torque); "
                                 f"got {self.u!r}.")
        object.__setattr__(self, "x0", tuple(float(s) for s in as_vector("x0", self.x0, 2)))
        std = float(self.noise_std)
        if not np.isfinite(std) or std < 0:
            raise DimensionError(f"noise_std must be finite and >= 0; got {std}.")
        object.__setattr__(self, "noise_std", std)
        p = self.params
        th0 = float(as_vector("theta_hat0", self.theta_hat0, 1)[0])
        if not p.theta_lower <= th0 <= p.theta_upper:
            raise ParameterSetError(f"theta_hat0 = {th0} lies outside Θ = [{p.theta_lower}, "
                                    f"{p.theta_upper}]; start the estimate inside Θ.")
        object.__setattr__(self, "theta_hat0", th0)
        if not p.theta_lower <= p.alpha0 <= p.theta_upper:
            warnings.warn(f"the true θ = alpha0 = {p.alpha0} lies outside Θ = "
                          f"[{p.theta_lower}, {p.theta_upper}].", ThetahatWarning, stacklevel=3)

    @property
    def theta(self) -> float:
        """The true θ = α0 (N m)."""
        return self.params.alpha0


def simulate(seed: Seed = 0, *, scenario: Scenario | None = None,
             method: str = LUGRE_METHOD,
             rtol: float = LUGRE_RTOL, atol: ArrayLike = LUGRE_ATOL,
             **scenario_overrides: Any) -> PlantTrajectory:
    """Simulate the LuGre motor plant for a scenario, with seeded noise on y = ω.

    Integrates the true plant (true |ω| in φ, σ1 included) with a stiff integrator
    (:data:`LUGRE_METHOD`) and the analytic Jacobian, samples it at ``fs`` and adds
    ``N(0, noise_std²)`` to y.

    Parameters
    ----------
    seed : int or numpy.random.SeedSequence, optional
        Seed of the measurement noise.
    scenario : Scenario, optional
        Base scenario; default ``Scenario()``.
    method, rtol, atol
        Integrator settings, as in :func:`~thetahat.simulation.simulate.simulate_plant`.
    **scenario_overrides
        Fields of :class:`Scenario` to replace (``t_end``, ``fs``, ``u``, ``x0``,
        ``noise_std``, ``theta_hat0``, ``params``).

    Returns
    -------
    PlantTrajectory
        ``t (N,)``, ``u (N, 1)``, ``y (N, 1)`` (noisy), ``y_clean``, ``x (N, 2) = (ω, η)``,
        ``phi (N, 1)`` (true φ), ``theta (1,)`` = α0.

    Raises
    ------
    TypeError
        An override is not a field of :class:`Scenario`.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> res = lugre.simulate(seed=0, t_end=1.0)
    >>> res.x.shape, res.theta.tolist()
    ((1001, 2), [0.28])
    """
    base = Scenario() if scenario is None else scenario
    unknown = set(scenario_overrides) - {f.name for f in dataclasses.fields(Scenario)}
    if unknown:
        raise ArgumentTypeError(f"unknown scenario field(s) {sorted(unknown)}; Scenario has "
                        f"{[f.name for f in dataclasses.fields(Scenario)]}.")
    sc = dataclasses.replace(base, **scenario_overrides) if scenario_overrides else base
    phi = true_phi(sc.params)
    noise = WhiteNoise(sc.noise_std) if sc.noise_std > 0 else None
    return simulate_plant(linear_part(sc.params), phi=phi, dphi_dx=phi.dphi_dx, u=sc.u,
                          t_end=sc.t_end, fs=sc.fs, x0=sc.x0, theta=[sc.theta], noise=noise,
                          seed=seed, method=method, rtol=rtol, atol=atol)


# ---------------------------------------------------------------------------------------------
# The paper's observer (Sec. VIII-A)
# ---------------------------------------------------------------------------------------------

#: Default excitation ramp of |φ̂| (N m): l = 0 below 0.75, 1 above 1.0 — the paper's hard
#: switch |φ̂| ≥ 1 made Lipschitz (Remark 5), so Assumption 4 holds.
EXCITATION = (0.75, 1.0)


def estimator_spec(eps: float = 1.0, *, Gamma: float = 1.0, eps2: float = 1.0,
                   params: LuGreParameters = LuGreParameters(),
                   excitation: tuple[float, float] = EXCITATION, second: bool = True,
                   chain_poles: PoleSpec = None, second_poles: PoleSpec = None) -> EstimatorSpec:
    """The paper's estimator for the DC motor (Sec. VIII-A) as an :class:`EstimatorSpec`.

    A modified high-gain observer (3) whose gains are designed on the σ1 = 0 design system
    with chain poles −1, −2, −3 (ε = 1 gives K ≈ [6, 0, 6]ᵀ), Proposition 2's update law with
    the algebraic inverse θ* and a smooth excitation weight l(|φ̂|), and the second observer of
    Sec. VI (poles −1, −2; ε2 = 1 gives K ≈ [3, 0]ᵀ) with g evaluated on its own estimates.
    The estimator uses the known parameters and the data only, never the true α0.

    Parameters
    ----------
    eps : float
        ε of the first observer (0 < ε ≤ 1).
    Gamma : float
        Γ of the update law (the paper: 1).
    eps2 : float
        ε of the second observer.
    params : LuGreParameters
        Known parameters (α0 is only used for Θ's bounds, not as a value).
    excitation : (float, float)
        |φ̂| thresholds of the smooth excitation ramp (see ``EXCITATION``).
    second : bool
        Attach the second observer (fills ``x_hat_refined``).
    chain_poles, second_poles : list of pole lists, optional
        Chain poles of the two designs (defaults −1, −2, −3 and −1, −2).

    Returns
    -------
    EstimatorSpec
        ``build(eps=…, Gamma=…)`` gives the observer for any ε and Γ from one SCB.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> spec = lugre.estimator_spec()
    >>> [round(float(v), 4) for v in spec.design.K.ravel()]
    [6.0, -0.0042, 6.0075]
    """
    from ..estimation.observer.laws import IntermittentInversion, smooth_ramp

    sys = system(params)
    law = IntermittentInversion(theta_star(params), smooth_ramp(*excitation), Gamma,
                                Box([params.theta_lower], [params.theta_upper]),
                                on_invalid="freeze")
    obs2 = None
    if second:
        obs2 = SecondObserverSpec(eps2=eps2, chain_poles=second_poles or [[-1.0, -2.0]],
                                  g_on_estimates=True)
    return EstimatorSpec(system=sys, law=law, eps=eps,
                         chain_poles=chain_poles or [[-1.0, -2.0, -3.0]],
                         design_system=design_system(params), second=obs2)


def observer(eps: float = 1.0, *, Gamma: float = 1.0, eps2: float = 1.0,
             params: LuGreParameters = LuGreParameters(),
             excitation: tuple[float, float] = EXCITATION, second: bool = True,
             chain_poles: PoleSpec = None, second_poles: PoleSpec = None
             ) -> ModifiedHighGainObserver:
    """The paper's estimator for the DC motor, ready to ``run(t, u, y)``: the observer that
    ``estimator_spec(...).build()`` makes (Sec. VIII-A).

    Parameters
    ----------
    eps, Gamma, eps2, params, excitation, second, chain_poles, second_poles
        As in :func:`estimator_spec`.

    Returns
    -------
    ModifiedHighGainObserver
        With ``run(t, u, y)``, ``init``/``step`` and ``rhs``. For many ε or Γ, build from one
        :func:`estimator_spec` instead (one SCB for all).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> data = lugre.simulate(seed=0, t_end=1.0)
    >>> res = lugre.observer().run(data.t, data.u, data.y)
    >>> res.theta_hat.shape
    (1001, 1)
    """
    return estimator_spec(eps, Gamma=Gamma, eps2=eps2, params=params, excitation=excitation,
                          second=second, chain_poles=chain_poles,
                          second_poles=second_poles).build()


def designs(eps: float = 1.0, *, eps2: float = 1.0, params: LuGreParameters = LuGreParameters(),
            chain_poles: PoleSpec = None, second_poles: PoleSpec = None
            ) -> tuple[GainDesign, GainDesign]:
    """The two gain designs of Sec. VIII on the σ1 = 0 design system: (first, second).

    Parameters
    ----------
    eps, eps2, params, chain_poles, second_poles
        As in :func:`estimator_spec`.

    Returns
    -------
    design : GainDesign
        K(ε) = [K_x; K_φ] of the first observer.
    design2 : GainDesign
        The second observer's gain.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> d1, d2 = lugre.designs()
    >>> [round(float(v), 4) for v in d1.K.ravel()], [round(float(v), 4) for v in d2.K.ravel()]
    ([6.0, -0.0042, 6.0075], [3.0, -0.002])
    """
    spec = estimator_spec(eps, eps2=eps2, params=params, chain_poles=chain_poles,
                          second_poles=second_poles)
    return spec.design, cast(GainDesign, spec.design2)       # second=True: always designed


def estimator(method: str = "guarded", *, eps: float = 1.0, Gamma: float = 1.0,
              noise_std: float | None = None, params: LuGreParameters = LuGreParameters(),
              compiled: bool | None = None, dt: float = 1e-3) -> Estimator:
    """The LuGre estimator by method: ``"paper"``, ``"guarded"``, ``"mle"`` or ``"ekf"``.

    * ``"paper"``: :func:`observer` (stage 1 as printed, Sec. VIII-A), with ``eps``, ``Gamma``;
    * ``"guarded"``: :class:`~thetahat.estimation.statistical.guarded.GuardedEstimator` — that observer
      (compiled for step ``dt`` when numba is available) guarding an EKF on col(ω, η, θ)
      re-anchored by MAP fits; streaming-capable;
    * ``"mle"``: :class:`~thetahat.estimation.statistical.mle.MapEstimator` — MAP fits of (x(0), θ) on a
      dense schedule (offline);
    * ``"ekf"``: :class:`~thetahat.estimation.statistical.ekf.JointEKF` on col(ω, η, θ) alone.

    Each is an :class:`~thetahat.estimation.protocol.Estimator` (``init``, ``step``,
    ``run``) whose result has ``theta_hat`` of shape (N, 1).

    Parameters
    ----------
    method : str
        The estimator, one of :data:`thetahat.methods.ESTIMATION_METHODS` (default
        ``"guarded"``).
    eps, Gamma : float
        Stage 1's tuning: ε of the observer and Γ of the update law (the paper's: 1, 1);
        not used by ``"mle"``.
    noise_std : float, optional
        σ of the speed measurement for stage 2 (EKF, MAP fits); default (None) estimated
        from the data. Not used by ``"paper"``.
    params : LuGreParameters
        The known motor and friction parameters (default :class:`LuGreParameters`); α0 only
        sets Θ's bounds.
    compiled : bool, optional
        numba kernels for stage 2 and, with ``"guarded"``, a compiled stage 1; default
        (None): when numba is installed.
    dt : float
        Sampling period for the compiled stage 1 of ``"guarded"`` (default 1e-3 s; the
        records must be sampled at it).

    Returns
    -------
    Estimator
        The observer of :func:`observer` for ``"paper"``, a
        :class:`~thetahat.estimation.statistical.guarded.GuardedEstimator` for ``"guarded"``, a
        :class:`~thetahat.estimation.statistical.mle.MapEstimator` for ``"mle"``, a
        :class:`~thetahat.estimation.statistical.ekf.JointEKF` for ``"ekf"``.

    Raises
    ------
    OptionError
        Unknown method (:func:`thetahat.methods.get_method`).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> est = lugre.estimator("mle", compiled=False)
    >>> data = lugre.simulate(seed=0, t_end=0.2)
    >>> res = est.run(data.t, data.u, data.y, state0=est.init(theta_hat0=[1.0]))
    >>> res.theta_hat.shape
    (201, 1)
    """
    how = get_method(method)

    def stage1() -> Estimator:                   # the fastest back end for steps of dt
        from ..estimation.drive import runner
        from ..estimation.statistical.plant_kernel import have_numba
        obs = observer(eps, Gamma=Gamma, params=params)
        use = have_numba() if compiled is None else compiled
        return cast(Estimator, runner(obs, (0.0, dt), compiled=True)) if use else obs

    return how.build(MethodInputs(
        system=system(params), observer=lambda: observer(eps, Gamma=Gamma, params=params),
        stage1=stage1, noise_std=noise_std, compiled=compiled))


def study_setup(*, t_end: float | None = None) -> StudySetup:
    """What ``thetahat sweep`` and ``thetahat tune`` run without a model file: the paper's
    estimator on the default scenario.

    Parameters
    ----------
    t_end : float, optional
        Simulated time (s); default 20, the :class:`Scenario`'s.

    Returns
    -------
    StudySetup
        :func:`estimator_spec`, :func:`simulate` for ``t_end``, the scenario's θ̂(0) and the
        state names ω, η.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> setup = lugre.study_setup(t_end=1.0)
    >>> setup.state_names, float(setup.simulate(0).t[-1])
    (('omega', 'eta'), 1.0)
    """
    from ..modelfile.study import StudySetup
    return StudySetup(estimator=estimator_spec(),
                      simulate=functools.partial(simulate, t_end=Scenario().t_end
                                                 if t_end is None else t_end),
                      theta_hat0=[Scenario().theta_hat0],
                      state_names=tuple(str(s) for s in perturbation().x))
