"""A MIMO example from practice: a two-inertia drive with Coulomb friction on both sides.

A motor (inertia J_m) drives a load (J_l) through an elastic shaft (stiffness k_s, damping
d_s). Both sides have viscous friction (b_m, b_l, known) and Coulomb friction of unknown
levels θ = col(F_m, F_l) (N m), smoothed as F tanh(ω/v_s). A tachometer measures the motor
speed ω_m; the encoders at both ends give the shaft twist Δ = θ_m − θ_l (a dual-encoder
drive). With x = col(ω_m, Δ, ω_l), u = motor torque, y = col(ω_m, Δ) and
φ = col(F_m tanh(ω_m/v_s), F_l tanh(ω_l/v_s)) the drive is of the form (1):

    J_m ω̇_m = u − k_s Δ − d_s (ω_m − ω_l) − b_m ω_m − φ₁,
    Δ̇       = ω_m − ω_l,
    J_l ω̇_l = k_s Δ + d_s (ω_m − ω_l) − b_l ω_l − φ₂.

**Assumption 1.** φ₁ reaches y₁ = ω_m after one integration, φ₂ reaches y₂ = Δ after two
(through ω_l), and the decoupling matrix [[−1/J_m, 0], [−1/J_m, 1/J_l]] is nonsingular: the
system is left-invertible with infinite zeros of orders 1 and 2 and n_q = 3 = n, so it has no
invariant zeros at all (minimum-phase trivially). The error system (4) has the chains
n_q1 = 2 and n_q2 = 3 — *non-uniform*, which is where the corrigendum's scaling
K'_qj = col(K̄_qj1/ε, …, K̄_qjn_qj/ε^n_qj) differs from the original ε^(n̄_q − n_qj + i).
(A load encoder alone, y₂ = θ_l, would add the twist as zero dynamics with an invariant
zero at 0: not minimum-phase. Hence the twist measurement.)

**Assumption 3 (Proposition 4).** ∂g/∂θ = diag(tanh(ω_m/v_s), tanh(ω_l/v_s)) =: D, and with
M = (∂g/∂θ)ᵀ condition (14) holds with S(v, x) = D², positive semidefinite and singular when
a shaft end is at rest; a drive that keeps turning both ways makes ∫S dτ ≥ σI (persistent
excitation). ‖g(θ) − g(θ̂)‖ = ‖Dθ̃‖ = (θ̃ᵀSθ̃)^(1/2) gives L_g = 1. The gradient law
θ̂̇ = Proj(ΓM(φ̂ − g(v, x̂, θ̂))) therefore satisfies Assumption 3; g uses the measured y₁ for
the motor side (Remark 4) and x̂ for the load side, and tanh is globally Lipschitz
(Assumptions 2 and 4).

The load speed ω̂_l is not measured: it comes out of the length-3 chain (the twist's
derivative), and while the load creeps through zero speed its error is of the order of v_s,
where tanh is steepest. With M = D alone, F̂_l then dips by up to a third in every reversal.
:class:`LoadSpeedWeight` uses M = diag(D₁, w(|ω̂_l|) D₂) instead, with w a C¹ ramp from 0
at |ω̂_l| = 0.2 rad/s to 1 at 0.5: (14) still holds with S = diag(D₁², w D₂²) ⪰ 0, and the
drive's reversals pass through |ω_l| > 0.5 often enough for persistent excitation. The dips
fall to under 1 % (measured over the last 3 s of the default scenario).

Examples
--------
>>> from thetahat.models import two_inertia
>>> rep = two_inertia.assumption_report()
>>> rep.holds, two_inertia.design().scb.chain_lengths
(True, (2, 3))
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from .._validate import positive_scalar
from ..design.gains import GainDesign, modified_high_gain
from ..estimation.observer.observer import ModifiedHighGainObserver
from ..estimation.observer.laws import GradientInversion
from ..model.paramset import Box
from ..model.perturbation import SymbolicPerturbation
from ..model.system import PerturbedLinearSystem
from ..simulation.noise import Seed, WhiteNoise
from ..simulation.signals import Multisine, Signal
from ..simulation.simulate import PlantTrajectory, simulate_plant
from ..structure.assumptions import AssumptionReport, check_assumption_1

__all__ = ["DriveParameters", "LoadSpeedWeight", "LOAD_SPEED_RAMP", "Scenario", "THETA",
           "PARAMETER_SET", "EPS", "GAMMA", "TruePhi",
           "assumption_report", "design", "observer", "perturbation", "simulate", "system"]

FloatArray = NDArray[np.float64]

#: The true Coulomb levels (F_m, F_l) in N m used by the examples and tests.
THETA = (0.3, 0.5)
#: Θ = [0.05, 1]² N m: the Coulomb levels a drive of this size can have.
PARAMETER_SET = Box([0.05, 0.05], [1.0, 1.0])
#: Default ε. The shaft resonance √(k_s(1/J_m + 1/J_l)) ≈ 82 rad/s sets the scale: at ε = 1 the
#: uncancelled output terms D_qj dominate and A − KC is unstable; ε = 0.01 puts the chain poles
#: at ~100–300 rad/s, well inside the 1 kHz sampling (|λ|·dt ≤ 0.32).
EPS = 0.01
#: Default Γ of the gradient law: θ̃ decays like exp(−Γ tanh²(ω/v_s) t), ≈ 1/14 s on average.
GAMMA = 20.0


@dataclass(frozen=True, slots=True)
class DriveParameters:
    """Physical parameters of the two-inertia drive (SI units).

    Parameters
    ----------
    J_m, J_l : float
        Motor and load inertia (kg m²); default 0.01 and 0.03.
    k_s, d_s : float
        Shaft stiffness (N m/rad) and damping (N m s/rad); default 50 and 0.05.
    b_m, b_l : float
        Known viscous friction (N m s/rad); default 0.01 and 0.02.
    v_s : float
        Speed scale of the smoothed Coulomb friction F tanh(ω/v_s) (rad/s); default 0.05.
    """

    J_m: float = 0.01
    J_l: float = 0.03
    k_s: float = 50.0
    d_s: float = 0.05
    b_m: float = 0.01
    b_l: float = 0.02
    v_s: float = 0.05

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, positive_scalar(f.name, getattr(self, f.name)))


def _matrices(p: DriveParameters) -> dict[str, FloatArray]:
    A = np.array([[-(p.b_m + p.d_s) / p.J_m, -p.k_s / p.J_m, p.d_s / p.J_m],
                  [1.0, 0.0, -1.0],
                  [p.d_s / p.J_l, p.k_s / p.J_l, -(p.b_l + p.d_s) / p.J_l]])
    return {"A": A, "B": np.array([[1.0 / p.J_m], [0.0], [0.0]]),
            "C": np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
            "E": np.array([[-1.0 / p.J_m, 0.0], [0.0, 0.0], [0.0, -1.0 / p.J_l]])}


@functools.lru_cache(maxsize=8)
def perturbation(params: DriveParameters = DriveParameters()) -> SymbolicPerturbation:
    """g(v, x, θ) = col(F_m tanh(y₁/v_s), F_l tanh(ω_l/v_s)) in symbols u, y1, y2, omega_m,
    twist, omega_l, F_m, F_l."""
    u, y1, y2, wm, tw, wl, Fm, Fl = sp.symbols("u y1 y2 omega_m twist omega_l F_m F_l",
                                               real=True)
    vs = sp.Float(params.v_s)
    return SymbolicPerturbation.from_sympy([Fm * sp.tanh(y1 / vs), Fl * sp.tanh(wl / vs)],
                                           u=[u], y=[y1, y2], x=[wm, tw, wl], theta=[Fm, Fl])


def system(params: DriveParameters = DriveParameters()) -> PerturbedLinearSystem:
    """The drive as a :class:`PerturbedLinearSystem` with the observer's g and Θ.

    Parameters
    ----------
    params : DriveParameters
        Physical parameters of the drive; default ``DriveParameters()``.

    Returns
    -------
    PerturbedLinearSystem
        x = col(ω_m, Δ, ω_l), u = motor torque, y = col(ω_m, Δ), θ = col(F_m, F_l): A (3, 3),
        B (3, 1), C (2, 3), E (3, 2), g of :func:`perturbation` and Θ = :data:`PARAMETER_SET`.
    """
    return PerturbedLinearSystem(**_matrices(params), perturbation=perturbation(params),
                                 parameter_set=PARAMETER_SET)


def assumption_report(params: DriveParameters = DriveParameters()) -> AssumptionReport:
    """Assumption 1 for (C, A, E) of the drive.

    Parameters
    ----------
    params : DriveParameters
        Physical parameters of the drive; default ``DriveParameters()``.

    Returns
    -------
    AssumptionReport
        Left invertibility and minimum phase of (C, A, E); the drive has no invariant zeros.
    """
    m = _matrices(params)
    return check_assumption_1(m["A"], m["E"], m["C"])


def design(eps: float = EPS, *, params: DriveParameters = DriveParameters(),
           scaling: str = "corrigendum") -> GainDesign:
    """K(ε) of the modified high-gain observer on (4); chains (2, 3), default poles.

    ``scaling="original"`` gives the paper's uncorrected exponents, to show what the
    corrigendum fixes.

    Parameters
    ----------
    eps : float
        ε of the design; default :data:`EPS`.
    params : DriveParameters
        Physical parameters of the drive; default ``DriveParameters()``.
    scaling : {"corrigendum", "original"}
        The ε-exponents of the chain gains (see
        :func:`~thetahat.design.gains.high_gain`).

    Returns
    -------
    GainDesign
        K = [K_x; K_φ] with K_x (3, 2) and K_φ (2, 2), and the SCB of (4).
    """
    m = _matrices(params)
    return modified_high_gain(m["A"], m["E"], m["C"], eps, scaling=scaling)


#: Load-speed thresholds (rad/s) of the weight w(|ω̂_l|) in :class:`LoadSpeedWeight`.
LOAD_SPEED_RAMP = (0.2, 0.5)


@dataclass(frozen=True, slots=True)
class LoadSpeedWeight:
    """M(v, x̂, θ̂) = diag(tanh(y₁/v_s), w(|ω̂_l|) tanh(ω̂_l/v_s)) of the Proposition 4 law.

    w is :func:`~thetahat.estimation.observer.laws.smooth_ramp` over :data:`LOAD_SPEED_RAMP`.
    Called as ``M(v, x, theta)`` with v = col(u, y) (..., 3), x (..., 3) and θ (..., 2); returns
    shape (..., 2, 2).

    Parameters
    ----------
    v_s : float
        Speed scale of the smoothed Coulomb friction F tanh(ω/v_s) (rad/s), as in
        :class:`DriveParameters`.
    ramp : tuple of float
        (low, high) thresholds of |ω̂_l| (rad/s) of the weight w; default
        :data:`LOAD_SPEED_RAMP`.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models.two_inertia import LoadSpeedWeight
    >>> M = LoadSpeedWeight(v_s=0.05)
    >>> np.round(M(np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.1]), np.zeros(2)), 3)
    array([[1., 0.],
           [0., 0.]])
    """

    v_s: float
    ramp: tuple[float, float] = LOAD_SPEED_RAMP

    def __call__(self, v: ArrayLike, x: ArrayLike, theta: ArrayLike) -> FloatArray:
        from ..estimation.observer.laws import smooth_ramp

        v_, x_ = np.asarray(v, dtype=np.float64), np.asarray(x, dtype=np.float64)
        w = smooth_ramp(*self.ramp).weight(np.abs(x_[..., 2]))
        out = np.zeros(np.broadcast_shapes(v_.shape[:-1], x_.shape[:-1],
                                           np.shape(theta)[:-1]) + (2, 2))
        out[..., 0, 0] = np.tanh(v_[..., 1] / self.v_s)
        out[..., 1, 1] = w * np.tanh(x_[..., 2] / self.v_s)
        return out

    def sympy_form(self, perturbation: SymbolicPerturbation) -> sp.Matrix:
        """M as a SymPy matrix in the symbols of g (its y₁ and ω̂_l), for the compiled kernel.

        Parameters
        ----------
        perturbation : SymbolicPerturbation
            The drive's g (u, y = (y₁, y₂), x = (ω_m, D, ω_l), θ = (F_m, F_l)).

        Returns
        -------
        sympy.Matrix, shape (2, 2)
        """
        low, high = self.ramp
        y1, w_l = perturbation.y[0], perturbation.x[2]
        t = sp.Min(sp.Max((sp.Abs(w_l) - low) / (high - low), 0), 1)
        return sp.diag(sp.tanh(y1 / self.v_s), t * t * (3 - 2 * t) * sp.tanh(w_l / self.v_s))


def observer(eps: float = EPS, *, Gamma: float = GAMMA,
             params: DriveParameters = DriveParameters(),
             scaling: str = "corrigendum") -> ModifiedHighGainObserver:
    """The estimator: observer (3) with K(ε) and the Proposition 4 gradient law (Γ) with
    M = :class:`LoadSpeedWeight`.

    Parameters
    ----------
    eps : float
        ε of the gain design; default :data:`EPS`.
    Gamma : float
        Γ of the gradient law; default :data:`GAMMA`.
    params : DriveParameters
        Physical parameters of the drive; default ``DriveParameters()``.
    scaling : {"corrigendum", "original"}
        The ε-exponents of the chain gains, as in :func:`design`.

    Returns
    -------
    ModifiedHighGainObserver
        On :func:`system` with K(ε) of :func:`design` (K_x (3, 2), K_φ (2, 2)) and the
        :class:`~thetahat.estimation.observer.laws.GradientInversion` law on Θ.

    Examples
    --------
    >>> from thetahat.models import two_inertia
    >>> obs = two_inertia.observer()
    >>> obs.K_x.shape, obs.K_phi.shape
    ((3, 2), (2, 2))
    """
    sys_ = system(params)
    # system() always attaches g and the Box Θ
    law = GradientInversion(cast(SymbolicPerturbation, sys_.perturbation), Gamma,
                            cast(Box, sys_.parameter_set), M=LoadSpeedWeight(params.v_s))
    return ModifiedHighGainObserver.from_design(sys_, design(eps, params=params,
                                                             scaling=scaling), law)


@dataclass(frozen=True, slots=True)
class TruePhi:
    """The plant's friction φ(t, x, u, θ) and ∂φ/∂x, as :func:`simulate_plant` takes them.

    ``phi(t, x, u, theta)`` = col(F_m tanh(ω_m/v_s), F_l tanh(ω_l/v_s)), shape (..., 2), with
    the true ω_m (not the measured y₁); ``phi.dphi_dx(t, x, u, theta)`` has shape (2, 3).

    Parameters
    ----------
    v_s : float
        Speed scale of the smoothed Coulomb friction F tanh(ω/v_s) (rad/s), as in
        :class:`DriveParameters`.
    """

    v_s: float

    def __call__(self, t: Any, x: ArrayLike, u: Any, theta: ArrayLike) -> FloatArray:
        x_, th = np.asarray(x, dtype=np.float64), np.asarray(theta, dtype=np.float64)
        return np.stack([th[0] * np.tanh(x_[..., 0] / self.v_s),
                         th[1] * np.tanh(x_[..., 2] / self.v_s)], axis=-1)

    def dphi_dx(self, t: Any, x: ArrayLike, u: Any, theta: ArrayLike) -> FloatArray:
        x_, th = np.asarray(x, dtype=np.float64), np.asarray(theta, dtype=np.float64)
        out = np.zeros((2, 3))
        out[0, 0] = th[0] / self.v_s / np.cosh(x_[0] / self.v_s) ** 2
        out[1, 2] = th[1] / self.v_s / np.cosh(x_[2] / self.v_s) ** 2
        return out


def _default_input() -> Signal:
    return Multisine([1.0, 0.6], [0.5, 1.7])


@dataclass(frozen=True, slots=True, eq=False)
class Scenario:
    """The default experiment: a two-tone torque that reverses both shaft ends.

    Parameters
    ----------
    t_end : float
        Duration (s); default 5.
    fs : float
        Sampling frequency (Hz); default 1000.
    u : Signal
        Motor torque (N m); default sin(2π·0.5 t) + 0.6 sin(2π·1.7 t).
    theta : tuple of float
        True (F_m, F_l) (N m); default :data:`THETA`.
    noise_std : tuple of float
        Noise on (ω_m in rad/s, Δ in rad): a tachometer and 16-bit encoders; default
        (1e-3, 1e-4).
    params : DriveParameters
    """

    t_end: float = 5.0
    fs: float = 1000.0
    u: Signal = field(default_factory=_default_input)
    theta: tuple[float, float] = THETA
    noise_std: tuple[float, float] = (1e-3, 1e-4)
    params: DriveParameters = DriveParameters()


def simulate(seed: Seed = 0, *, scenario: Scenario | None = None,
             **overrides: Any) -> PlantTrajectory:
    """Simulate the drive (true friction, LSODA with the analytic Jacobian) with seeded noise.

    Parameters
    ----------
    seed : int or SeedSequence
        Seed of the measurement noise.
    scenario : Scenario, optional
    **overrides
        Fields of :class:`Scenario` to replace.

    Returns
    -------
    PlantTrajectory
        ``t (N,)``, ``u (N, 1)``, ``y (N, 2)``, ``x (N, 3)``, ``phi (N, 2)``, ``theta (2,)``.

    Examples
    --------
    >>> from thetahat.models import two_inertia
    >>> tr = two_inertia.simulate(seed=0, t_end=0.5)
    >>> tr.y.shape, tr.theta.tolist()
    ((501, 2), [0.3, 0.5])
    """
    sc = Scenario() if scenario is None else scenario
    if overrides:
        sc = dataclasses.replace(sc, **overrides)
    phi = TruePhi(sc.params.v_s)
    noise = WhiteNoise(list(sc.noise_std)) if any(sc.noise_std) else None
    return simulate_plant(system(sc.params), phi=phi, dphi_dx=phi.dphi_dx, u=sc.u,
                          t_end=sc.t_end, fs=sc.fs, x0=np.zeros(3), theta=list(sc.theta),
                          noise=noise, seed=seed, method="LSODA", rtol=1e-9,
                          atol=[1e-10, 1e-12, 1e-10])
