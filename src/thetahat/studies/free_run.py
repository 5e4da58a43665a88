"""Free-run simulation: the model (1) with θ driven by a record's inputs alone.

:func:`simulate_output` integrates ẋ = A x + B u + E g(col(u, C x), x, θ) over a record and
returns ŷ = C x at the samples. Between the samples the input is what the ``hold``
reconstructs (:mod:`thetahat.estimation.hold`, the one definition every estimator uses):
``"zoh"`` holds each sample until the next; ``"foh"`` interpolates linearly; ``"smooth"``
interpolates linearly through the samples corrected for a smooth signal's curvature
(:func:`~thetahat.estimation.statistical.input_hold.stage2_samples`, as stage 2 does);
``"bandlimited"`` is the band-limited (windowed-sinc) interpolation of the samples — what a
signal sampled without aliasing is — a modelling choice that a lightly damped resonance near
the Nyquist frequency makes visible.

The map between two samples is stage 2's own
(:func:`~thetahat.estimation.statistical.plant_kernel.propagate`: classical RK4 sub-steps
reading the held input at each sub-step's start, midpoint and end, with the exact Jacobians
Φ, Γ of the map): a free run here is the trajectory an estimator's fit computes with the same
hold and the same sub-steps. ``substeps`` is the floor of sub-steps per sample (the stability
choice ceil(h ρ / h_rho) may take more). Without it, the floor is doubled from
:data:`FIRST_SUBSTEPS` until two simulations agree to ``rtol`` (:func:`converged_substeps`):
the simulation is then accurate to well below any measurement noise. :class:`FreeRun` is a
record bound to a model, which also gives the sensitivities ∂ŷ/∂x(0) and ∂ŷ/∂θ (Φ and Γ of
each sample chained by the Cramér–Rao bound's own kernel,
:func:`~thetahat.estimation.statistical.crlb.sensitivities`) for the fits of
:mod:`thetahat.studies.validation`.

What it may import: the model, the estimation wing's hold, input samples, plant kernel and
CRLB kernel, the package's validation and errors.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_samples, as_vector
from ..errors import ConvergenceWarning, DimensionError, NonFiniteError, OptionError
from ..estimation.hold import DEFAULT_HOLD, check_hold, reconstruct
from ..estimation.statistical.crlb import sensitivity_kernel
from ..estimation.statistical.input_hold import stage2_samples
from ..estimation.statistical.plant_kernel import H_RHO, ModelKernel, Propagation, model_kernel
from ..model.system import PerturbedLinearSystem

__all__ = ["DEFAULT_RTOL", "FIRST_SUBSTEPS", "FreeRun", "MAX_SUBSTEPS", "converged_substeps",
           "input_path", "simulate_output"]

FloatArray = NDArray[np.float64]

#: Sub-steps per sample at which :func:`converged_substeps` starts doubling.
FIRST_SUBSTEPS = 2
#: The most sub-steps per sample :func:`converged_substeps` tries (RK4 converges as S⁻⁴: a
#: simulation that has not settled by then diverges or is chaotic with this θ, and more steps
#: would not make its score mean more).
MAX_SUBSTEPS = 64
#: Two simulations agree when the RMS of their difference is at most this fraction of the RMS
#: of the output: 1e-4 of a 50 mV signal is 5 µV, far below any instrument's noise.
DEFAULT_RTOL = 1e-4
#: Uniform sampling for the band-limited reconstruction: steps within this relative spread.
UNIFORM_RTOL = 1e-6


def input_path(t: ArrayLike, u: ArrayLike, hold: str, substeps: int
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The input at the three points where each RK4 sub-step reads it, and the sub-steps' lengths.

    The hold's reconstruction (:func:`~thetahat.estimation.hold.reconstruct`, of the
    corrected samples under ``"smooth"``) at the fractions s/S, (s + ½)/S and (s + 1)/S of
    each interval: what :func:`~thetahat.estimation.statistical.plant_kernel.propagate` reads
    with S sub-steps
    (for an independent integrator to be driven by the same input).

    Parameters
    ----------
    t : array_like, shape (N,)
        Strictly increasing sample times.
    u : array_like, shape (N, m)
        Input samples.
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        The reconstruction between samples (module docstring).
    substeps : int
        Sub-steps per sample interval, ≥ 1.

    Returns
    -------
    UA, UM, UB : ndarray, shape ((N − 1) · substeps, m)
        u at the start, the midpoint and the end of each sub-step ("zoh": the sample held,
        its left limit at the end).
    DT : ndarray, shape ((N − 1) · substeps,)
        The sub-steps' lengths.

    Raises
    ------
    OptionError
        Unknown hold, or ``substeps`` < 1.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.studies.free_run import input_path
    >>> UA, UM, UB, DT = input_path([0.0, 1.0, 2.0], np.array([[0.0], [2.0], [2.0]]), "foh", 2)
    >>> UA[:, 0].tolist(), UM[:, 0].tolist(), UB[:, 0].tolist(), DT.tolist()
    ([0.0, 1.0, 2.0, 2.0], [0.5, 1.5, 2.0, 2.0], [1.0, 2.0, 2.0, 2.0], [0.5, 0.5, 0.5, 0.5])
    >>> input_path([0.0, 1.0, 2.0], np.array([[0.0], [2.0], [2.0]]), "zoh", 2)[2][:, 0].tolist()
    [0.0, 0.0, 2.0, 2.0]
    """
    check_hold(hold)
    if not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise OptionError(f"substeps: expected an integer >= 1; got {substeps!r}.")
    S = int(substeps)
    t = as_vector("t", t)
    U = stage2_samples(np.asarray(u, dtype=np.float64).reshape(t.size, -1), hold)[0]
    N = U.shape[0]
    DT = np.repeat(np.diff(t) / S, S)
    k = np.repeat(np.arange(N - 1), S)
    s = np.tile(np.arange(S, dtype=np.float64), N - 1)
    parts = tuple(np.ascontiguousarray(reconstruct(U, hold, k, np.minimum((s + c) / S, 1.0)))
                  for c in (0.0, 0.5, 1.0))
    return parts[0], parts[1], parts[2], DT


@dataclass(frozen=True, slots=True, eq=False)
class FreeRun:
    """A record's t and u bound to a model and a hold: what a free-run simulation reads.

    Attributes
    ----------
    system : PerturbedLinearSystem
    model : ModelKernel
        Stage 2's plant kernel of ``system``.
    t : ndarray, shape (N,)
    U : ndarray, shape (N, m)
        The samples the hold reconstructs from (the corrected ones under ``"smooth"``).
    hold : str
        One of :data:`thetahat.estimation.hold.HOLDS`.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.studies.free_run import FreeRun
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 2.0, 0.1)
    >>> run = FreeRun.of(spec.system, t, np.sin(t)[:, None], "foh", compiled=False)
    >>> Y, SX, ST = run.run(np.array([0.5]), np.array([0.1, 0.0]), 4, want=True)
    >>> Y.shape, SX.shape, ST.shape
    ((20, 1), (20, 1, 2), (20, 1, 1))
    """

    system: PerturbedLinearSystem
    model: ModelKernel
    t: FloatArray
    U: FloatArray
    hold: str

    @classmethod
    def of(cls, system: PerturbedLinearSystem, t: ArrayLike, u: ArrayLike | None, hold: str,
           compiled: bool | None = None) -> FreeRun:
        """Validate t, u and the hold and derive the plant kernel.

        Parameters
        ----------
        system : PerturbedLinearSystem
        t : array_like, shape (N,)
            At least two strictly increasing times.
        u : array_like, shape (N, m), or None when m = 0
        hold : str
        compiled : bool, optional

        Returns
        -------
        FreeRun

        Raises
        ------
        DimensionError, NonFiniteError, OptionError
            Shapes; a non-finite input; an unknown hold.
        """
        check_hold(hold)
        t = as_vector("t", t)
        if t.size < 2 or not np.all(np.diff(t) > 0):
            raise DimensionError("t: expected at least two strictly increasing sample times.")
        m = system.m
        U = (np.zeros((t.size, 0)) if u is None and m == 0
             else as_samples("u", u).reshape(t.size, -1) if u is not None else None)
        if U is None or U.shape != (t.size, m):
            raise DimensionError(f"u: expected shape ({t.size}, {m}) (one row per sample, one "
                                 f"column per input); got "
                                 f"{None if u is None else np.shape(u)}.")
        steps = np.diff(t)
        if hold == "bandlimited" and np.ptp(steps) > UNIFORM_RTOL * float(np.median(steps)):
            raise DimensionError("hold='bandlimited' needs a uniformly sampled record (the "
                                 "band-limited interpolation is defined on a uniform grid); "
                                 "t's steps range over "
                                 f"[{steps.min():.6g}, {steps.max():.6g}]. Use 'smooth', "
                                 "'foh' or 'zoh', or resample the record first.")
        if not np.all(np.isfinite(U)):
            raise NonFiniteError("u holds NaN or inf; a free-run simulation needs every input "
                                 "sample.")
        return cls(system, model_kernel(system, compiled=compiled), t,
                   stage2_samples(U, hold)[0], hold)

    def segment(self, start: int, stop: int) -> FreeRun:
        """Samples [start, stop) of the record (the same model and hold)."""
        return FreeRun(self.system, self.model, self.t[start:stop], self.U[start:stop],
                       self.hold)

    def run(self, theta: FloatArray, x0: FloatArray, substeps: int, *, want: bool,
            stop: int | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Simulate from x0 with θ.

        Parameters
        ----------
        theta : ndarray, shape (p,)
        x0 : ndarray, shape (n,)
        substeps : int
            RK4 steps per sample interval (the floor: the stability choice may take more).
        want : bool
            Also the sensitivities.
        stop : int, optional
            Simulate the first ``stop`` samples only (default all).

        Returns
        -------
        Y : ndarray, shape (N, r)
            ŷ.
        SX, ST : ndarray, shapes (N, r, n) and (N, r, p)
            ∂ŷ/∂x(0) and ∂ŷ/∂θ with ``want`` (empty otherwise).

        Raises
        ------
        NonFiniteError
            The state is not finite at some sample (named).
        """
        N = self.t.size if stop is None else stop
        r, n, p = self.model.r, self.model.n, self.model.p
        C = self.model.C
        pc, WT = Propagation(hold=self.hold, substeps=int(substeps), h_rho=H_RHO).arrays()
        x0_ = np.ascontiguousarray(x0, dtype=np.float64)
        th = np.ascontiguousarray(theta, dtype=np.float64)
        X = np.empty((N, n))
        if want:                 # S = ∂x/∂(θ, x(0)), columns θ first (crlb.sensitivities)
            S0 = np.concatenate([np.zeros((n, p)), np.eye(n)], axis=1)
            S = np.empty((N, n, p + n))
            bad = sensitivity_kernel(self.model)(x0_, th, self.U[:N], self.t[:N], pc, WT, S0,
                                                 X, S)
            done = N if bad < 0 else bad
            CS = np.einsum("rn,knq->krq", C, S[:done])
            SX, ST = CS[:, :, p:], CS[:, :, :p]
            Y = X[:done] @ C.T
        else:
            Y = np.empty((N, r))
            done = int(self.model.free_run(x0_, th, self.U[:N], self.t[:N], 0, N, pc, WT, Y,
                                           X))
            bad = -1 if done == N else done
            SX, ST = np.empty((0, r, n)), np.empty((0, r, p))
        if bad >= 0:
            raise NonFiniteError(f"the free-run simulation with θ = {theta.tolist()} is not "
                                 f"finite at sample {bad} (t = {self.t[bad]:.6g}): the model "
                                 f"diverges with this θ and input (is θ in Θ, and x(0) "
                                 f"plausible?).")
        return Y, SX, ST

    def converged(self, theta: FloatArray, x0: FloatArray, rtol: float = DEFAULT_RTOL) -> int:
        """The fewest sub-steps (a power of two, from :data:`FIRST_SUBSTEPS`) whose simulation
        agrees with twice as many to ``rtol`` × RMS(ŷ) (:func:`converged_substeps`).

        Parameters
        ----------
        theta : ndarray, shape (p,)
        x0 : ndarray, shape (n,)
        rtol : float

        Returns
        -------
        int

        Warns
        -----
        ConvergenceWarning
            No agreement within :data:`MAX_SUBSTEPS`.
        """
        S = FIRST_SUBSTEPS
        y_prev = self.run(theta, x0, S, want=False)[0]
        while 2 * S <= MAX_SUBSTEPS:
            y = self.run(theta, x0, 2 * S, want=False)[0]
            if _rms(y - y_prev) <= rtol * max(_rms(y), np.finfo(float).tiny):
                return S
            S, y_prev = 2 * S, y
        warnings.warn(f"the free-run simulation did not converge to rtol = {rtol:g} within "
                      f"{MAX_SUBSTEPS} sub-steps per sample; using {S}.", ConvergenceWarning,
                      stacklevel=3)
        return S


def _rms(a: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.square(a)))) if a.size else 0.0


def _check_theta(system: PerturbedLinearSystem, theta: ArrayLike) -> FloatArray:
    return np.ascontiguousarray(as_vector("theta", theta, system.p))


def _check_x0(system: PerturbedLinearSystem, x0: ArrayLike) -> FloatArray:
    return np.ascontiguousarray(as_vector("x0", x0, system.n))


def converged_substeps(system: PerturbedLinearSystem, theta: ArrayLike, t: ArrayLike,
                       u: ArrayLike | None, *, x0: ArrayLike, hold: str = DEFAULT_HOLD,
                       rtol: float = DEFAULT_RTOL, compiled: bool | None = None) -> int:
    """The fewest sub-steps per sample (a power of two) at which the simulation has converged.

    Doubles S from :data:`FIRST_SUBSTEPS` until the simulations with S and 2S sub-steps differ
    by at most ``rtol`` × RMS(ŷ) (RMS over the record), and returns that S: RK4's error falls
    16-fold per doubling, so ŷ with S sub-steps is within about ``rtol`` of the exact flow of the
    reconstructed input.

    Parameters
    ----------
    system, theta, t, u, x0, hold, compiled
        As for :func:`simulate_output`.
    rtol : float
        The agreement asked for.

    Returns
    -------
    int

    Warns
    -----
    ConvergenceWarning
        No agreement within :data:`MAX_SUBSTEPS`; the largest S tried is returned.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.studies.free_run import converged_substeps
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 10.0, 0.1)
    >>> converged_substeps(spec.system, [0.5], t, np.sin(t)[:, None], x0=[0.0, 0.0],
    ...                    compiled=False)
    2
    """
    rec = FreeRun.of(system, t, u, hold, compiled)
    return rec.converged(_check_theta(system, theta), _check_x0(system, x0), float(rtol))


def simulate_output(system: PerturbedLinearSystem, theta: ArrayLike, t: ArrayLike,
                    u: ArrayLike | None, *, x0: ArrayLike, hold: str = DEFAULT_HOLD,
                    substeps: int | None = None, rtol: float = DEFAULT_RTOL,
                    compiled: bool | None = None) -> FloatArray:
    """The free-run output ŷ = C x of the model (1) with θ, driven by the input alone.

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a symbolic perturbation (stage 2's plant kernel is derived from it).
    theta : array_like, shape (p,)
    t : array_like, shape (N,)
        Strictly increasing sample times (s).
    u : array_like, shape (N, m), or None when m = 0
    x0 : array_like, shape (n,)
        x at t[0].
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        The input between the samples (module docstring).
    substeps : int, optional
        RK4 steps per sample interval; default: :func:`converged_substeps` with ``rtol``.
    rtol : float
        The convergence asked for when ``substeps`` is not given.
    compiled : bool, optional
        numba kernels (default: when installed).

    Returns
    -------
    ndarray, shape (N, r)
        ŷ at the samples (ŷ[0] = C x0).

    Raises
    ------
    NonFiniteError
        The simulation diverges (the message names the sample), or u is not finite.
    DimensionError
        Shapes; "bandlimited" on a non-uniform t.
    OptionError
        Unknown hold.

    Examples
    --------
    With g ≡ 0 (θ = 0 in the example's g) the model is a harmonic oscillator; its response to a
    held unit step is 1 − cos t:

    >>> import numpy as np
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.model.system import PerturbedLinearSystem
    >>> from thetahat.studies.free_run import simulate_output
    >>> g = parse_perturbation("a*u - x1", u=["u"], y=["y"], x=["x1", "x2"], theta=["a"])
    >>> s = PerturbedLinearSystem(A=[[0, 1], [0, 0]], B=[[0], [0]], C=[[1, 0]], E=[[0], [1]],
    ...                           perturbation=g, parameter_set=Box([0.0], [2.0]))
    >>> t = np.linspace(0.0, 3.0, 31)
    >>> y = simulate_output(s, [1.0], t, np.ones((31, 1)), x0=[0.0, 0.0], compiled=False)
    >>> bool(np.max(np.abs(y[:, 0] - (1 - np.cos(t)))) < 1e-6)
    True
    """
    rec = FreeRun.of(system, t, u, hold, compiled)
    th, x = _check_theta(system, theta), _check_x0(system, x0)
    S = rec.converged(th, x, float(rtol)) if substeps is None else substeps
    return rec.run(th, x, S, want=False)[0]
