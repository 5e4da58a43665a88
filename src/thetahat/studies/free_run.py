"""Free-run simulation: the model (1) with θ driven by a record's inputs alone.

:func:`simulate_output` integrates ẋ = A x + B u + E g(col(u, C x), x, θ) over a record and
returns ŷ = C x at the samples. Between the samples the input is reconstructed by the
``hold`` (:data:`HOLDS`), a modelling choice that a lightly damped resonance near the Nyquist
frequency makes visible: ``"zoh"`` holds each sample until the next; ``"foh"`` interpolates
linearly; ``"bandlimited"`` is the band-limited (sinc) interpolation of the samples — what a
signal sampled without aliasing is — computed by ``scipy.signal.resample_poly`` (Kaiser
window, :data:`BANDLIMITED_WINDOW`). Each sample interval is cut into ``substeps`` classical
RK4 steps on stage 2's plant model
(:attr:`~thetahat.estimation.statistical.plant_kernel.ModelKernel.rhs_jac`), each reading the
reconstructed input at its start, midpoint and end (:func:`input_path`), so that the input is
integrated to RK4's own order whatever the hold. Without ``substeps`` they are doubled from
:data:`FIRST_SUBSTEPS` until two simulations agree to ``rtol`` (:func:`converged_substeps`):
the simulation is then accurate to well below any measurement noise. :class:`FreeRun` is a
record bound to a model, which also gives the sensitivities ∂ŷ/∂x(0) and ∂ŷ/∂θ (the
variational equations of the same RK4, with the plant kernel's
:func:`~thetahat.estimation.statistical.plant_kernel.stage_jac`) for the fits of
:mod:`thetahat.studies.validation`.

Written on stage 2's plant kernel, whose own ``propagate`` holds the input linear over a
sample (which the band-limited reconstruction is not). What it may import: the model, the
estimation wing's plant kernel, the package's validation and errors.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_samples, as_vector
from ..errors import ConvergenceWarning, DimensionError, NonFiniteError, OptionError
from ..estimation.statistical.plant_kernel import ModelKernel, jit, model_kernel, stage_jac
from ..model.system import PerturbedLinearSystem

__all__ = ["BANDLIMITED_WINDOW", "DEFAULT_RTOL", "FIRST_SUBSTEPS", "FreeRun", "HOLDS",
           "MAX_SUBSTEPS", "converged_substeps", "input_path", "simulate_output"]

FloatArray = NDArray[np.float64]

#: The reconstructions of the input between samples.
HOLDS = ("zoh", "foh", "bandlimited")
#: Sub-steps per sample at which :func:`converged_substeps` starts doubling.
FIRST_SUBSTEPS = 2
#: The most sub-steps per sample :func:`converged_substeps` tries (RK4 converges as S⁻⁴: a
#: simulation that has not settled by then diverges or is chaotic with this θ, and more steps
#: would not make its score mean more).
MAX_SUBSTEPS = 64
#: Two simulations agree when the RMS of their difference is at most this fraction of the RMS
#: of the output: 1e-4 of a 50 mV signal is 5 µV, far below any instrument's noise.
DEFAULT_RTOL = 1e-4
#: ``scipy.signal.resample_poly``'s window for the band-limited reconstruction: β = 8 puts the
#: stop band near −80 dB.
BANDLIMITED_WINDOW = ("kaiser", 8.0)
#: Samples mirrored (odd reflection) at each end of the input before the band-limited
#: reconstruction, more than the interpolation filter's half-length (10 samples), so that the
#: record's ends are not read as jumps to zero.
BANDLIMITED_PAD = 16
#: Uniform sampling for the band-limited reconstruction: steps within this relative spread.
UNIFORM_RTOL = 1e-6


def _check_hold(hold: str) -> str:
    if hold not in HOLDS:
        raise OptionError(f"hold: expected one of {list(HOLDS)}; got {hold!r}.")
    return hold


def input_path(t: ArrayLike, u: ArrayLike, hold: str, substeps: int
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The input at the three points where each RK4 sub-step reads it, and the sub-steps' lengths.

    Parameters
    ----------
    t : array_like, shape (N,)
        Strictly increasing sample times.
    u : array_like, shape (N, m)
        Input samples.
    hold : {"zoh", "foh", "bandlimited"}
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
    DimensionError
        "bandlimited" on a record that is not uniformly sampled.

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
    _check_hold(hold)
    if not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise OptionError(f"substeps: expected an integer >= 1; got {substeps!r}.")
    S = int(substeps)
    t = as_vector("t", t)
    U = np.asarray(u, dtype=np.float64).reshape(t.size, -1)
    N, m = U.shape
    steps = np.diff(t)
    DT = np.repeat(steps / S, S)
    if hold == "zoh":
        UA = np.repeat(U[:-1], S, axis=0)
        return UA, UA.copy(), UA.copy(), DT
    if hold == "foh":
        a = (np.arange(2 * S + 1) / (2 * S))[None, :, None]
        grid = U[:-1, None, :] + a * (U[1:, None, :] - U[:-1, None, :])   # (N−1, 2S+1, m)
    else:
        if N > 1 and np.ptp(steps) > UNIFORM_RTOL * float(np.median(steps)):
            raise DimensionError("hold='bandlimited' needs a uniformly sampled record (the "
                                 "band-limited interpolation is defined on a uniform grid); "
                                 "t's steps range over "
                                 f"[{steps.min():.6g}, {steps.max():.6g}]. Use 'foh' or "
                                 "'zoh', or resample the record first.")
        fine = _bandlimited(U, 2 * S)                              # ((N − 1)·2S + 1, m)
        grid = np.concatenate([fine[:-1].reshape(N - 1, 2 * S, m), fine[2 * S::2 * S, None]],
                              axis=1)                              # (N−1, 2S+1, m)
    return (np.ascontiguousarray(grid[:, 0:-1:2].reshape(-1, m)),
            np.ascontiguousarray(grid[:, 1::2].reshape(-1, m)),
            np.ascontiguousarray(grid[:, 2::2].reshape(-1, m)), DT)


def _bandlimited(U: FloatArray, L: int) -> FloatArray:
    """The band-limited interpolation of U's columns on L points per sample (the samples
    themselves kept: the interpolation filter is zero at multiples of L)."""
    from scipy.signal import resample_poly
    N = U.shape[0]
    if L == 1 or N < 2:
        return U.copy()
    P = min(BANDLIMITED_PAD, N - 1)
    padded = np.pad(U, ((P, P), (0, 0)), mode="reflect", reflect_type="odd")
    fine = resample_poly(padded, L, 1, axis=0, window=BANDLIMITED_WINDOW)
    return np.ascontiguousarray(fine[P * L:P * L + (N - 1) * L + 1])


def _make_free_run(model: ModelKernel) -> Callable[..., int]:
    rhs = model.rhs_jac
    stage = stage_jac
    C = model.C

    def free_run(x0, th, UA, UM, UB, DT, per, want, Y, SX, ST):
        """x from x0 by RK4 sub-steps (per of them per sample) with the input at each
        sub-step's start, midpoint and end; y = C x at each sample into Y; with want,
        ∂y/∂x(0) into SX and ∂y/∂θ into ST (the variational equations of the same RK4).
        Returns −1, or the first sample at which x is not finite."""
        n = x0.shape[0]
        p = th.shape[0]
        r = C.shape[0]
        N = Y.shape[0]
        pj = p if want else 0
        x = x0.copy()
        xs = np.empty(n)
        k1 = np.empty(n)
        k2 = np.empty(n)
        k3 = np.empty(n)
        k4 = np.empty(n)
        Fx = np.empty((n, n))
        Ft = np.empty((n, p))
        Jx = np.zeros((n, n))
        Jt = np.zeros((n, pj))
        D1x = np.zeros((n, n))
        D2x = np.zeros((n, n))
        D3x = np.zeros((n, n))
        D4x = np.zeros((n, n))
        D1t = np.zeros((n, pj))
        D2t = np.zeros((n, pj))
        D3t = np.zeros((n, pj))
        D4t = np.zeros((n, pj))
        for i in range(n):
            Jx[i, i] = 1.0
        for k in range(N):
            if k > 0:
                for j in range(per):
                    s = (k - 1) * per + j
                    dt = DT[s]
                    rhs(x, UA[s], th, k1, Fx, Ft)
                    if want:
                        stage(Fx, Ft, Jx, Jt, D1x, D1t, 0.0, D1x, D1t)
                    for i in range(n):
                        xs[i] = x[i] + 0.5 * dt * k1[i]
                    rhs(xs, UM[s], th, k2, Fx, Ft)
                    if want:
                        stage(Fx, Ft, Jx, Jt, D1x, D1t, 0.5 * dt, D2x, D2t)
                    for i in range(n):
                        xs[i] = x[i] + 0.5 * dt * k2[i]
                    rhs(xs, UM[s], th, k3, Fx, Ft)
                    if want:
                        stage(Fx, Ft, Jx, Jt, D2x, D2t, 0.5 * dt, D3x, D3t)
                    for i in range(n):
                        xs[i] = x[i] + dt * k3[i]
                    rhs(xs, UB[s], th, k4, Fx, Ft)
                    if want:
                        stage(Fx, Ft, Jx, Jt, D3x, D3t, dt, D4x, D4t)
                        for a in range(n):
                            for b in range(n):
                                Jx[a, b] += dt / 6.0 * (D1x[a, b] + 2.0 * D2x[a, b]
                                                        + 2.0 * D3x[a, b] + D4x[a, b])
                            for b in range(pj):
                                Jt[a, b] += dt / 6.0 * (D1t[a, b] + 2.0 * D2t[a, b]
                                                        + 2.0 * D3t[a, b] + D4t[a, b])
                    for i in range(n):
                        x[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            for a in range(n):
                if not math.isfinite(x[a]):
                    return k
            for i in range(r):
                acc = 0.0
                for a in range(n):
                    acc += C[i, a] * x[a]
                Y[k, i] = acc
                if want:
                    for b in range(n):
                        acc = 0.0
                        for a in range(n):
                            acc += C[i, a] * Jx[a, b]
                        SX[k, i, b] = acc
                    for b in range(p):
                        acc = 0.0
                        for a in range(n):
                            acc += C[i, a] * Jt[a, b]
                        ST[k, i, b] = acc
        return -1

    return jit(free_run, model.compiled)


@functools.lru_cache(maxsize=16)
def _free_run_for(model: ModelKernel) -> Callable[..., int]:
    return _make_free_run(model)


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
    hold : str
        One of :data:`HOLDS`.

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
        _check_hold(hold)
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
        if not np.all(np.isfinite(U)):
            raise NonFiniteError("u holds NaN or inf; a free-run simulation needs every input "
                                 "sample.")
        return cls(system, model_kernel(system, compiled=compiled), t,
                   np.ascontiguousarray(U), hold)

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
            RK4 steps per sample interval.
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
        UA, UM, UB, DT = input_path(self.t[:N], self.U[:N], self.hold, substeps)
        r, n, p = self.model.r, self.model.n, self.model.p
        Y = np.empty((N, r))
        SX = np.empty((N, r, n) if want else (0, r, n))
        ST = np.empty((N, r, p) if want else (0, r, p))
        bad = _free_run_for(self.model)(x0, theta, UA, UM, UB, DT, int(substeps), want,
                                        Y, SX, ST)
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
                       u: ArrayLike | None, *, x0: ArrayLike, hold: str = "foh",
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
                    u: ArrayLike | None, *, x0: ArrayLike, hold: str = "foh",
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
    hold : {"zoh", "foh", "bandlimited"}
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
