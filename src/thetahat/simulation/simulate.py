"""Simulation of the true plant (1): ẋ = A x + B u + E φ, y = C x + noise.

The plant's perturbation is the *true* φ, a function ``phi(t, x, u, theta)`` of the true
state, which need not equal the observer's model g(v, x, θ) (in the LuGre example of
Sec. VIII the plant has σ0·η·|ω|/ζ(ω, θ), the observer's g uses |y|; Remark 4). Plants such
as the LuGre motor are stiff, so the default integrator is the implicit Radau IIA method with
tight tolerances, the analytic Jacobian ``A + E ∂φ/∂x`` when ``dphi_dx`` is given, and a
restart at every jump of the input. States are read off the solver's dense output on the
uniform sampling grid.
"""

from __future__ import annotations

import itertools
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import solve_ivp

from .._validate import as_vector, check_finite, positive_scalar
from ..errors import (
    ArgumentTypeError,
    ConvergenceWarning,
    DimensionError,
    NonFiniteError,
    SimulationError,
    ThetahatWarning,
)
from ..model.system import PerturbedLinearSystem
from .noise import NoiseModel, Seed, make_rng
from .signals import Signal, time_grid

__all__ = [
    "ConvergenceReport",
    "PlantTrajectory",
    "SolverStats",
    "convergence_check",
    "simulate_plant",
]

FloatArray = NDArray[np.float64]
PhiFunction = Callable[[Any, FloatArray, FloatArray, FloatArray], FloatArray]

#: Default relative tolerance: the LuGre plant is smooth between velocity reversals, and at
#: 1e-8 the sampled states agree with a 100x tighter solution to ~1e-8 relative (see
#: ``convergence_check`` and tests/models/test_lugre_plant.py) at a cost of a few seconds.
DEFAULT_RTOL = 1e-8
#: Default absolute tolerance, far below any physical state scale of interest (the LuGre
#: bristle deflection η is ~1e-3 rad); pass a per-state vector for badly scaled states.
DEFAULT_ATOL = 1e-10
#: Implicit methods of ``solve_ivp``, which accept (and here receive) an analytic Jacobian.
IMPLICIT_METHODS = ("Radau", "BDF", "LSODA")
#: All methods of ``solve_ivp``; the explicit ones are allowed for non-stiff plants.
METHODS = IMPLICIT_METHODS + ("RK45", "RK23", "DOP853")
#: Beyond this many input breakpoints in [t0, t_end] the integrator no longer restarts at
#: each one. A restart costs a new step-size search, but stepping over a jump or a kink costs
#: more: on the Silverbox scenario with its sines' samples held (1 831 breakpoints), DOP853
#: took 4x (linear hold) to 9x (zero-order hold) the time, Radau 1.8x, and was less accurate.
#: The limit only bounds the list of segments (one per breakpoint, 10^6 of them ~ 100 MB).
MAX_RESTARTS = 1_000_000
#: Tightening factor of the reference solution in :func:`convergence_check`.
DEFAULT_REFINEMENT = 100.0


@dataclass(frozen=True, slots=True)
class SolverStats:
    """How a plant simulation was integrated.

    Attributes
    ----------
    method : str
        The ``solve_ivp`` method.
    rtol : float
    atol : tuple of float
        Absolute tolerance per state.
    nfev, njev, nlu : int
        Right-hand-side and Jacobian evaluations, LU decompositions (summed over segments).
    n_segments : int
        Number of integration segments (1 + the input jumps restarted at).
    wall_time : float
        Seconds spent integrating.
    """

    method: str
    rtol: float
    atol: tuple[float, ...]
    nfev: int
    njev: int
    nlu: int
    n_segments: int
    wall_time: float


@dataclass(frozen=True, slots=True, eq=False)
class PlantTrajectory:
    """A simulated plant trajectory on a uniform sampling grid.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sample times (s), spaced ``1/fs``.
    u : ndarray, shape (N, m)
        Input samples.
    y : ndarray, shape (N, r)
        Measured outputs: ``y_clean`` plus measurement noise.
    y_clean : ndarray, shape (N, r)
        Noise-free outputs ``C x``.
    x : ndarray, shape (N, n)
        True states.
    phi : ndarray, shape (N, k)
        True perturbation φ along the trajectory.
    theta : ndarray, shape (p,)
        The true constant parameter vector θ.
    fs : float
        Sampling frequency (Hz).
    seed : int or None
        Seed of the measurement noise (None when the outputs are noise-free).
    stats : SolverStats
        Integrator settings and counters.
    """

    t: FloatArray
    u: FloatArray
    y: FloatArray
    y_clean: FloatArray
    x: FloatArray
    phi: FloatArray
    theta: FloatArray
    fs: float
    seed: int | None
    stats: SolverStats

    @property
    def v(self) -> FloatArray:
        """The known signals v = col(u, y) (Sec. II), with the noisy y; shape (N, m + r)."""
        return np.hstack([self.u, self.y])

    @property
    def noise(self) -> FloatArray:
        """The measurement noise ``y - y_clean``; shape (N, r)."""
        return self.y - self.y_clean

    def __repr__(self) -> str:
        n_s, n = self.x.shape
        return (f"PlantTrajectory(N={n_s}, t=[{self.t[0]:g}, {self.t[-1]:g}] s, fs={self.fs:g} "
                f"Hz, n={n}, m={self.u.shape[1]}, r={self.y.shape[1]}, k={self.phi.shape[1]}, "
                f"theta={self.theta.tolist()}, seed={self.seed}, method={self.stats.method!r}, "
                f"nfev={self.stats.nfev})")


@dataclass(frozen=True, slots=True, eq=False)
class ConvergenceReport:
    """Result of :func:`convergence_check`: a simulation against a tighter-tolerance one.

    Attributes
    ----------
    max_diff : float
        ``max |x - x_ref|`` over all samples and states.
    max_diff_per_state : ndarray, shape (n,)
        The same, per state.
    relative_per_state : ndarray, shape (n,)
        ``max_diff_per_state / max |x_ref|`` per state (``inf`` for a state that stays 0
        in the reference but not in the checked solution, 0 if both are 0).
    t_worst : float
        Time of the largest difference.
    rtol, reference_rtol : float
        Tolerances of the checked and the reference solutions.
    atol, reference_atol : ndarray, shape (n,)
    wall_time, reference_wall_time : float
        Seconds spent integrating each solution.
    """

    max_diff: float
    max_diff_per_state: FloatArray
    relative_per_state: FloatArray
    t_worst: float
    rtol: float
    reference_rtol: float
    atol: FloatArray
    reference_atol: FloatArray
    wall_time: float
    reference_wall_time: float

    def __repr__(self) -> str:
        return (f"ConvergenceReport(max_diff={self.max_diff:.3g}, max_diff_per_state="
                f"{np.array2string(self.max_diff_per_state, precision=3)}, relative_per_state="
                f"{np.array2string(self.relative_per_state, precision=3)}, t_worst="
                f"{self.t_worst:g}, rtol={self.rtol:g}, reference_rtol={self.reference_rtol:g})")


def _input_function(u: Signal | Callable[[float], ArrayLike] | None, m: int
                    ) -> tuple[Callable[[float], FloatArray], Callable[[FloatArray], FloatArray],
                               tuple[float, ...]]:
    """(value at one time, samples on a grid, jump times) for the plant input."""
    if u is None:
        if m != 0:
            raise DimensionError(f"the system has m = {m} inputs, so u must be given (a Signal "
                                 f"or a callable of t returning shape ({m},)).")
        return (lambda t: np.zeros(0)), (lambda t: np.zeros((t.size, 0))), ()
    if isinstance(u, Signal):
        if u.dim != m:
            raise DimensionError(f"u has {u.dim} channels but the system has m = {m} inputs "
                                 f"(B has shape (n, {m})).")
        return (lambda t: u(t)), u.sampled, u.breakpoints
    if not callable(u):
        raise ArgumentTypeError(f"u must be a Signal or a callable of t; got {type(u).__name__}.")

    def one(t: float) -> FloatArray:
        return as_vector("u(t)", u(t), m)

    def grid(t: FloatArray) -> FloatArray:
        return np.array([one(float(s)) for s in t], dtype=np.float64).reshape(t.size, m)

    return one, grid, ()


def _atol_vector(atol: ArrayLike, n: int) -> FloatArray:
    a = as_vector("atol", atol)
    if a.size not in (1, n) or np.any(a <= 0):
        raise DimensionError(f"atol must be one positive value or one per state (n = {n}); got "
                             f"{a.tolist()}.")
    return np.broadcast_to(a, (n,)).copy()


def _check_theta(system: PerturbedLinearSystem, theta: ArrayLike) -> FloatArray:
    th = as_vector("theta", theta, system.p if system.perturbation is not None else None)
    ps = system.parameter_set
    if ps is not None and ps.dim == th.size and not bool(ps.contains(th)):
        warnings.warn(f"the true theta={th.tolist()} lies outside the parameter set {ps!r}; "
                      f"the observer's assumptions (theta in Θ) do not hold for this plant.",
                      ThetahatWarning, stacklevel=3)
    return th


def _segments(t0: float, t_end: float, jumps: tuple[float, ...]) -> list[tuple[float, float]]:
    inner = [s for s in jumps if t0 < s < t_end]
    if len(inner) > MAX_RESTARTS:
        inner = []
    edges = [t0, *inner, t_end]
    return list(itertools.pairwise(edges))


def _vector_field(system: PerturbedLinearSystem, phi: PhiFunction,
                  dphi_dx: PhiFunction | None, u_at: Callable[[float], FloatArray],
                  theta: FloatArray, t_left: float
                  ) -> tuple[Callable[[float, FloatArray], FloatArray],
                             Callable[[float, FloatArray], FloatArray] | None]:
    """f(t, x) = A x + B u + E φ and, with dphi_dx, its Jacobian A + E ∂φ/∂x.

    The input is read at ``min(t, t_left)``: on a segment ending at a jump of u the
    integrator must see the value from the left, even at the segment's end point.
    """
    A, B, E, k, n = system.A, system.B, system.E, system.k, system.n

    def rhs(s: float, x: FloatArray) -> FloatArray:
        uu = u_at(min(s, t_left))
        return A @ x + B @ uu + E @ np.reshape(phi(s, x, uu, theta), -1)

    if dphi_dx is None:
        return rhs, None

    def jac(s: float, x: FloatArray) -> FloatArray:
        uu = u_at(min(s, t_left))
        return A + E @ np.reshape(dphi_dx(s, x, uu, theta), (k, n))

    return rhs, jac


def _integrate(system: PerturbedLinearSystem, phi: PhiFunction,
               dphi_dx: PhiFunction | None, u_at: Callable[[float], FloatArray],
               jumps: tuple[float, ...], t: FloatArray, x0: FloatArray, theta: FloatArray,
               method: str, rtol: float, atol: FloatArray, max_step: float
               ) -> tuple[FloatArray, SolverStats]:
    """Integrate the plant segment by segment; return x on the grid t, shape (N, n)."""
    t_end = float(t[-1])
    segments = _segments(float(t[0]), t_end, jumps)
    x_out = np.empty((t.size, system.n))
    counts = np.zeros(3, dtype=np.int64)
    x_start = x0
    start = time.perf_counter()
    for a, b in segments:
        rhs, jac = _vector_field(system, phi, dphi_dx, u_at, theta,
                                 float(np.nextafter(b, -np.inf)))
        last = b >= t_end
        mask = (t >= a) & ((t <= b) if last else (t < b))
        t_eval = np.unique(np.append(t[mask], b))
        options: dict[str, Any] = {}
        if jac is not None and method in IMPLICIT_METHODS:
            options["jac"] = jac
        sol = solve_ivp(rhs, (a, b), x_start, method=method, t_eval=t_eval, rtol=rtol,
                        atol=atol, max_step=max_step, **options)
        if sol.status < 0:
            raise SimulationError(
                f"the {method} integrator failed on [{a:g}, {b:g}] s: {sol.message} Try a "
                f"stiff method (Radau, BDF, LSODA), looser tolerances, or check that the plant "
                f"and phi stay bounded.")
        counts += (sol.nfev, sol.njev, sol.nlu)
        x_out[mask] = sol.y.T[np.isin(t_eval, t[mask])]
        x_start = sol.y[:, -1]
    stats = SolverStats(method=method, rtol=rtol, atol=tuple(float(a) for a in atol),
                        nfev=int(counts[0]), njev=int(counts[1]), nlu=int(counts[2]),
                        n_segments=len(segments), wall_time=time.perf_counter() - start)
    if not np.all(np.isfinite(x_out)):
        raise NonFiniteError(f"the simulated state became NaN or inf (method {method}); the "
                             f"plant or phi blows up. Check phi, x0 and the input.")
    return x_out, stats


def _prepare(system: PerturbedLinearSystem, phi: PhiFunction, dphi_dx: PhiFunction | None,
             u: Any, t_end: float, fs: float, x0: ArrayLike, theta: ArrayLike, method: str,
             rtol: float, atol: ArrayLike, t0: float) -> dict[str, Any]:
    """Validate everything once, before integrating."""
    if not isinstance(system, PerturbedLinearSystem):
        raise ArgumentTypeError(f"system must be a PerturbedLinearSystem; got {type(system).__name__}.")
    if method not in METHODS:
        raise DimensionError(f"method must be one of {METHODS}; got {method!r}.")
    if not callable(phi) or (dphi_dx is not None and not callable(dphi_dx)):
        raise ArgumentTypeError("phi (and dphi_dx when given) must be callables (t, x, u, theta).")
    n, k = system.n, system.k
    t = time_grid(t_end, fs, t0)
    x0_ = as_vector("x0", x0, n)
    th = _check_theta(system, theta)
    u_at, u_grid, jumps = _input_function(u, system.m)
    u0 = u_at(float(t[0]))
    phi0 = np.asarray(phi(float(t[0]), x0_, u0, th), dtype=np.float64)
    if phi0.size != k:
        raise DimensionError(f"phi(t, x, u, theta) must return {k} value(s) (E has {k} "
                             f"column(s)); got shape {phi0.shape} at t0.")
    check_finite("phi(t0, x0, u(t0), theta)", phi0)
    if dphi_dx is not None:
        J0 = np.asarray(dphi_dx(float(t[0]), x0_, u0, th), dtype=np.float64)
        if J0.size != k * n:
            raise DimensionError(f"dphi_dx must return a ({k}, {n}) Jacobian; got shape "
                                 f"{J0.shape} at t0.")
        check_finite("dphi_dx(t0, x0, u(t0), theta)", J0)
    return {"t": t, "x0": x0_, "theta": th, "u_at": u_at, "u_grid": u_grid, "jumps": jumps,
            "rtol": positive_scalar("rtol", rtol), "atol": _atol_vector(atol, n)}


def simulate_plant(system: PerturbedLinearSystem, *, phi: PhiFunction,
                   u: Signal | Callable[[float], ArrayLike] | None, t_end: float, fs: float,
                   x0: ArrayLike, theta: ArrayLike, dphi_dx: PhiFunction | None = None,
                   noise: NoiseModel | None = None, seed: Seed = 0, method: str = "Radau",
                   rtol: float = DEFAULT_RTOL, atol: ArrayLike = DEFAULT_ATOL,
                   max_step: float = np.inf, t0: float = 0.0) -> PlantTrajectory:
    """Simulate the true plant (1) and sample it at ``fs``, with seeded measurement noise.

    Integrates ``ẋ = A x + B u(t) + E φ`` with ``φ = phi(t, x, u(t), theta)`` from ``x0`` at
    ``t0`` to ``t_end``, reads the state off the dense output at ``t0 + i/fs``, and returns
    ``y = C x + e`` with ``e`` drawn from ``noise`` using ``seed``.

    Parameters
    ----------
    system : PerturbedLinearSystem
        Supplies A (n, n), B (n, m), C (r, n), E (n, k); its perturbation g (the observer's
        model) is *not* used, and its parameter set only to warn when θ lies outside Θ.
    phi : callable ``phi(t, x, u, theta) -> (k,)``
        The plant's true perturbation. After integration it is evaluated once on the whole
        grid with ``t (N,)``, ``x (N, n)``, ``u (N, m)`` and must then return ``(N, k)``.
    u : Signal or callable of t or None
        The input; a :class:`~thetahat.simulation.signals.Signal` (the integrator restarts at
        its ``breakpoints``) or any callable returning shape (m,). ``None`` when m = 0.
    t_end, fs : float
        Final time (s) and sampling frequency (Hz).
    x0 : array_like, shape (n,)
        Initial state at ``t0``.
    theta : array_like, shape (p,)
        The true constant parameters.
    dphi_dx : callable ``dphi_dx(t, x, u, theta) -> (k, n)``, optional
        ∂φ/∂x; gives the implicit methods the exact Jacobian ``A + E ∂φ/∂x`` (otherwise
        they use finite differences).
    noise : NoiseModel, optional
        Measurement noise added to ``C x``; ``None`` for noise-free outputs.
    seed : int or numpy.random.SeedSequence, optional
        Seed of the noise generator (:func:`~thetahat.simulation.noise.make_rng`).
    method : {"Radau", "BDF", "LSODA", "RK45", "RK23", "DOP853"}, optional
        ``solve_ivp`` method; keep an implicit one for stiff plants.
    rtol : float, optional
    atol : float or array_like of shape (n,), optional
        Integrator tolerances (see :data:`DEFAULT_RTOL`, :data:`DEFAULT_ATOL`).
    max_step : float, optional
        Largest integrator step (s).
    t0 : float, optional
        Initial time (s).

    Returns
    -------
    PlantTrajectory

    Raises
    ------
    DimensionError
        A shape disagrees with the system, or an option is unknown.
    NonFiniteError
        x0, θ, φ(t0) or the result holds NaN or inf.
    SimulationError
        The integrator failed; the message carries the solver's message.

    Warns
    -----
    ThetahatWarning
        θ lies outside the system's parameter set Θ.

    Examples
    --------
    A stable first-order plant with a parameterised perturbation φ = θ·x:

    >>> import numpy as np
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.simulation.signals import Steps
    >>> from thetahat.simulation.simulate import simulate_plant
    >>> sys = PerturbedLinearSystem(A=[[-1.0]], B=[[1.0]], C=[[1.0]], E=[[1.0]])
    >>> traj = simulate_plant(sys, phi=lambda t, x, u, th: th * x, u=Steps([0.0], [1.0]),
    ...                       t_end=40.0, fs=10.0, x0=[0.0], theta=[0.5])
    >>> traj.x.shape, round(float(traj.y[-1, 0]), 6)   # steady state 1 / (1 - 0.5)
    ((401, 1), 2.0)
    """
    prep = _prepare(system, phi, dphi_dx, u, t_end, fs, x0, theta, method, rtol, atol, t0)
    t, theta_ = prep["t"], prep["theta"]
    x, stats = _integrate(system, phi, dphi_dx, prep["u_at"], prep["jumps"], t, prep["x0"],
                          theta_, method, prep["rtol"], prep["atol"], max_step)
    u_s = prep["u_grid"](t)
    phi_s = np.asarray(phi(t, x, u_s, theta_), dtype=np.float64)
    if phi_s.size != t.size * system.k:
        raise DimensionError(f"phi must accept a batch (t (N,), x (N, n), u (N, m)) and return "
                             f"({t.size}, {system.k}); got shape {phi_s.shape}.")
    phi_s = phi_s.reshape(t.size, system.k)
    check_finite("phi along the trajectory", phi_s)
    y_clean = x @ system.C.T
    if noise is None:
        y, seed_out = y_clean.copy(), None
    else:
        if not isinstance(noise, NoiseModel):
            raise ArgumentTypeError(f"noise must be a thetahat NoiseModel or None; got "
                            f"{type(noise).__name__}.")
        e = noise.sample(make_rng(seed), t.size, system.r, float(fs))
        y, seed_out = y_clean + e, (seed if isinstance(seed, int) else None)
    arrays = {"t": t, "u": u_s, "y": y, "y_clean": y_clean, "x": x, "phi": phi_s,
              "theta": theta_}
    for a in arrays.values():
        a.setflags(write=False)
    return PlantTrajectory(**arrays, fs=float(fs), seed=seed_out, stats=stats)


def convergence_check(system: PerturbedLinearSystem, *, phi: PhiFunction,
                      u: Signal | Callable[[float], ArrayLike] | None, t_end: float, fs: float,
                      x0: ArrayLike, theta: ArrayLike, dphi_dx: PhiFunction | None = None,
                      method: str = "Radau", rtol: float = DEFAULT_RTOL,
                      atol: ArrayLike = DEFAULT_ATOL, max_step: float = np.inf,
                      t0: float = 0.0, factor: float = DEFAULT_REFINEMENT,
                      bound: float | None = None) -> ConvergenceReport:
    """Compare a plant simulation with one at ``factor``-times tighter tolerances.

    Both solutions use the same method, input and sampling grid; the reference runs with
    ``rtol / factor`` and ``atol / factor``. The difference on the samples estimates the
    global integration error of the checked solution.

    Parameters
    ----------
    system, phi, u, t_end, fs, x0, theta, dphi_dx, method, rtol, atol, max_step, t0
        As in :func:`simulate_plant` (there is no noise: only states are compared).
    factor : float, optional
        Tolerance ratio between the checked and the reference solutions, > 1.
    bound : float, optional
        If given, warn with :class:`~thetahat.errors.ConvergenceWarning` when
        ``max_diff > bound``.

    Returns
    -------
    ConvergenceReport

    Raises
    ------
    DimensionError, NonFiniteError, SimulationError
        As in :func:`simulate_plant`, or ``factor <= 1``.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.simulation.signals import Multisine
    >>> from thetahat.simulation.simulate import convergence_check
    >>> sys = PerturbedLinearSystem(A=[[-1.0]], B=[[1.0]], C=[[1.0]], E=[[1.0]])
    >>> rep = convergence_check(sys, phi=lambda t, x, u, th: -th * x**3, u=Multisine([1.0], [0.2]),
    ...                         t_end=10.0, fs=10.0, x0=[0.0], theta=[1.0], rtol=1e-6)
    >>> bool(rep.max_diff < 1e-5)
    True
    """
    ratio = positive_scalar("factor", factor)
    if ratio <= 1.0:
        raise DimensionError(f"factor must be > 1 (the reference is factor-times tighter); "
                             f"got {ratio}.")
    prep = _prepare(system, phi, dphi_dx, u, t_end, fs, x0, theta, method, rtol, atol, t0)
    t = prep["t"]
    common = (system, phi, dphi_dx, prep["u_at"], prep["jumps"], t, prep["x0"], prep["theta"],
              method)
    x, stats = _integrate(*common, prep["rtol"], prep["atol"], max_step)
    x_ref, stats_ref = _integrate(*common, prep["rtol"] / ratio, prep["atol"] / ratio,
                                  max_step)
    diff = np.abs(x - x_ref)
    per_state = diff.max(axis=0)
    scale = np.abs(x_ref).max(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = np.where(per_state == 0.0, 0.0, per_state / scale)
    i_worst = int(np.unravel_index(np.argmax(diff), diff.shape)[0])
    report = ConvergenceReport(
        max_diff=float(per_state.max()), max_diff_per_state=per_state,
        relative_per_state=relative, t_worst=float(t[i_worst]), rtol=stats.rtol,
        reference_rtol=stats_ref.rtol, atol=np.asarray(stats.atol),
        reference_atol=np.asarray(stats_ref.atol), wall_time=stats.wall_time,
        reference_wall_time=stats_ref.wall_time)
    if bound is not None and report.max_diff > bound:
        warnings.warn(f"simulation not converged: max |x - x_ref| = {report.max_diff:.3g} > "
                      f"bound {bound:g} (at t = {report.t_worst:g} s) with rtol={rtol:g}; "
                      f"tighten rtol/atol.", ConvergenceWarning, stacklevel=2)
    return report
