"""The plant model of stage 2 as scalar code: f, ∂f/∂x, ∂f/∂θ and the sampled-data map (RK4).

Stage 2 of the guarded estimator (the EKF, the MAP fits, the likelihood with process noise),
the Cramér–Rao bound, the trust report and the free-run simulation all need the *plant* model
of eq. (1) with y = C x substituted into the perturbation,

    ẋ = f(x, u, θ) = A x + B u + E g(col(u, C x), x, θ),

its Jacobians F_x = A + E (∂g/∂x + ∂g/∂y C) and F_θ = E ∂g/∂θ, and the map over one sample
x_k → x_{k+1} with its exact derivatives Φ = ∂x_{k+1}/∂x_k and Γ = ∂x_{k+1}/∂θ (the
variational equations of the discrete map). :func:`model_kernel` derives all of them once
from a :class:`~thetahat.model.system.PerturbedLinearSystem` whose perturbation is a
:class:`~thetahat.model.perturbation.SymbolicPerturbation`: SymPy differentiates, common
subexpressions are eliminated and SymPy's Python printer writes the scalar code of
``rhs_jac``, which is printed with the kernels of this module (:func:`propagate`,
:func:`free_run` and what they call) into one module
(:meth:`~thetahat.estimation.kernels.modules.ModuleText.bound`), imported from the cache of
printed modules; with numba installed (extra ``speed``) its functions are compiled (once per
machine), otherwise they run as plain Python. The kernels of the EKF, the fits, the
likelihood, the bound and the guard are printed the same way into modules of their own that
import this one's (:func:`printed_kernels`).

**The sampled-data map** is classical RK4 over n sub-steps of each sample, with u between the
samples as the hold reconstructs it (:mod:`~thetahat.estimation.hold`: zero-order, linear or
band-limited; at the sub-step nodes a = s/n, (s + ½)/n of the interval). Differentiating the
RK4 stages gives the exact Jacobian of the map actually used, so the EKF's linearisation and
the fit's sensitivities are those of the computed trajectory. The number of sub-steps of a
sample is the larger of two:

* **stability**: ceil(h ρ / ``h_rho``) with ρ the spectral radius of F_x at the start of the
  sample (RK4 is stable for h ρ ≤ 2.78 on the real axis; ``h_rho`` = :data:`H_RHO` = 2 keeps
  a margin and follows the stiffness of models such as LuGre's, where ρ ranges over
  3e2 … 2e4 s⁻¹);
* **accuracy**: the record's own floor ``substeps`` (:class:`Propagation`), chosen by
  :func:`choose_substeps` so that the output trajectory is accurate to the data's noise level.

**Accurate to the noise level.** A systematic error e_k in the model's outputs biases a fit of
N samples by at most ‖e‖_{R⁻¹} = (Σ_k e_kᵀ R⁻¹ e_k)^½ of its standard errors in any
direction (the bias is the projection of the whitened error on the span of the whitened
sensitivities, and the standard error of any linear combination of θ is 1 in those
coordinates). :func:`choose_substeps` runs the model free from the start values (a MAP fit's
trajectory) with the floor n = 1, 2, 4, … and with every sample's sub-steps doubled (the floor
and the stability bound alike: where the stability bound rules, doubling the floor alone
changes nothing and proves nothing), over the first :data:`ACCURACY_SAMPLES` samples, and
takes the first n at which the two runs' difference ‖y_n − y_{n,×2}‖_{R⁻¹}, scaled to the
whole record (× √(N / samples compared)), is at most :data:`ACCURACY` = 0.1: the trajectory's
discretisation error (≈ that difference for RK4, whose error falls 16-fold per doubling) then
moves θ̂ by at most a tenth of a standard error. The likelihood with process noise applies
the same rule to its normalised innovations
(:func:`~thetahat.estimation.statistical.likelihood.fit_process_noise`). A record at a high
rate keeps n = 1 (the stability choice alone, as before); a lightly damped resonance at 9
samples per period takes 8–16 (the error of one RK4 step is ∝ (ωh)⁵). The stretch compared
ends where the free run leaves ten times the data's range around it (a run that diverges
from wrong start values says nothing about the trajectories a fit visits).

What it may import: the model, SymPy, the hold (:mod:`~thetahat.estimation.hold`) and the
printed modules' machinery (:mod:`~thetahat.estimation.kernels`); nothing of this room.
"""

from __future__ import annotations

import functools
import importlib.util
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import ModuleType, SimpleNamespace
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from ...errors import DimensionError, FileAccessError, MissingExtraError, OptionError
from ...model.system import PerturbedLinearSystem
from ..hold import DEFAULT_HOLD, KAISER_BETA, check_hold, half_width, hold_code, hold_weights
from ..kernels.kernel_cache import load_module, register
from ..kernels.modules import ModuleText
from .plant_forms import rhs_jac_source

__all__ = ["ACCURACY", "ACCURACY_SAMPLES", "BALANCED", "BALANCE_SWEEPS", "H_RHO",
           "KERNEL_CONSTANTS", "MAX_ACCURATE_SUBSTEPS", "MAX_SUBSTEPS",
           "ModelKernel", "Propagation", "TABLE_SUBSTEPS", "choose_substeps", "doubling_floor",
           "balanced_radius", "free_run", "have_numba", "held_input", "model_kernel",
           "plant_work", "printed_kernels", "propagate", "propagate_into",
           "spectral_radius_bound", "stage_jac"]

FloatArray = NDArray[np.float64]

#: Default bound on h ρ per RK4 sub-step (RK4's real stability interval is [−2.785, 0]).
H_RHO = 2.0
#: Largest number of RK4 sub-steps per sample.
MAX_SUBSTEPS = 500
#: The band-limited hold's taps are tabulated per sample for sub-step counts up to this.
TABLE_SUBSTEPS = 64
#: Osborne's balancing scales row and column i by f = √(c_i / r_i) only where f is outside
#: [BALANCED, 1/BALANCED] (a pair balanced to 5 % changes the bound by less), and stops after a
#: sweep that scaled nothing (LAPACK's gebal stops at the same 0.95) or after BALANCE_SWEEPS
#: sweeps: a 2 × 2 F is balanced by the first sweep, so the second ends it without a square
#: root (the bound was a quarter of the C EKF step with four full sweeps).
BALANCED = 0.95
BALANCE_SWEEPS = 4
#: The module's constants the kernels read, by name (the C printers bind them so).
KERNEL_CONSTANTS = {"MAX_SUBSTEPS": MAX_SUBSTEPS, "TABLE_SUBSTEPS": TABLE_SUBSTEPS,
                    "BALANCED": BALANCED, "BALANCE_SWEEPS": BALANCE_SWEEPS}
#: The discretisation error allowed, in standard errors of θ̂ (module docstring).
ACCURACY = 0.1
#: :func:`choose_substeps` doubles the sub-steps up to this floor.
MAX_ACCURATE_SUBSTEPS = 64
#: :func:`choose_substeps` compares the free runs over at most this many samples.
ACCURACY_SAMPLES = 4096
#: The free run is compared while it stays within this many times the data's range of it.
RANGE_FACTOR = 10.0
#: The decorator of the printed kernels when compiled (nogil: a fit on a worker thread runs
#: alongside the caller; error_model='numpy': a division by zero gives inf or NaN, as the
#: NumPy back end does, for the runs' own finiteness checks to report — numba's default raises
#: a bare ZeroDivisionError from inside the kernel).
NJIT = "@numba.njit(nogil=True, cache=True, error_model='numpy')"


def have_numba() -> bool:
    """Whether numba (the optional extra ``speed``) is importable.

    Returns
    -------
    bool
        True when ``import numba`` succeeds: stage 2's kernels are then compiled by default.
    """
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass(frozen=True, slots=True)
class Propagation:
    """How stage 2 propagates the model between two samples: the hold and the sub-steps.

    Parameters
    ----------
    hold : {"zoh", "foh", "bandlimited", "smooth"}
        u between the samples (:mod:`~thetahat.estimation.hold`). ``"smooth"`` is
        linear between the samples ũ of
        :func:`~thetahat.estimation.statistical.input_hold.stage2_samples` (u corrected where
        it is a sampled smooth signal).
    substeps : int
        The accuracy floor of RK4 sub-steps per sample (:func:`choose_substeps`), 1 …
        :data:`MAX_SUBSTEPS`.
    h_rho : float
        Bound on h ρ per sub-step (:data:`H_RHO`): the stability floor.

    Examples
    --------
    >>> pc, WT = Propagation(hold="bandlimited", substeps=4).arrays()
    >>> pc.tolist()[:3], WT.shape
    ([2.0, 4.0, 2.0], (129, 32))
    """

    hold: str = DEFAULT_HOLD
    substeps: int = 1
    h_rho: float = H_RHO

    def __post_init__(self) -> None:
        check_hold(self.hold)
        if not (isinstance(self.substeps, (int, np.integer))
                and 1 <= self.substeps <= MAX_SUBSTEPS):
            raise OptionError(f"substeps must be an integer in 1 … {MAX_SUBSTEPS}; got "
                              f"{self.substeps!r}.")
        if not (math.isfinite(self.h_rho) and self.h_rho > 0.0):
            raise OptionError(f"h_rho must be finite and > 0; got {self.h_rho!r}.")

    def arrays(self) -> tuple[FloatArray, FloatArray]:
        """(pc, WT): what the kernels read, new for each run (WT is the run's taps table).

        Returns
        -------
        pc : ndarray, shape (5,)
            (h_rho, substeps, hold code, Kaiser β, sub-steps tabulated in WT (0: none)).
        WT : ndarray, shape (2 · TABLE_SUBSTEPS + 1, 2L)
            The band-limited hold's taps at the fractions i / (2n) of the interval.
        """
        pc = np.array([self.h_rho, float(self.substeps), float(hold_code(self.hold)),
                       KAISER_BETA, 0.0])
        L = half_width(self.hold)
        return pc, np.zeros((2 * TABLE_SUBSTEPS + 1, 2 * L))


def spectral_radius_bound(F: FloatArray) -> float:
    """An upper bound on the spectral radius of F: Gershgorin's after Osborne balancing.

    Up to four sweeps of diagonal balancing (D F D⁻¹ with off-diagonal row and column sums
    equal to :data:`BALANCED`) make the bound tight for badly scaled models (a zero off-diagonal row or column is scaled
    down by 1e-8) (LuGre's ∂f/∂x has entries from 1 to 1e5,
    its eigenvalues ~3e2): ρ(F) ≤ max_i (|B_ii| + Σ_{j≠i} |B_ij|), B = D F D⁻¹.

    Parameters
    ----------
    F : ndarray, shape (n, n)
        A square matrix (here F_x = ∂f/∂x at the start of a sample); not modified.

    Returns
    -------
    float
        The bound ρ ≥ ρ(F) (0 for n = 0), which sets the number of RK4 sub-steps
        ceil(h ρ / ``h_rho``).

    Examples
    --------
    >>> import numpy as np
    >>> bool(spectral_radius_bound(np.array([[0.0, 1.0], [-4.0, 0.0]])) >= 2.0)
    True
    """
    return balanced_radius(F.copy())


def balanced_radius(B: Any) -> float:
    """:func:`spectral_radius_bound` of B, balancing B in place (its work array).

    Parameters
    ----------
    B : ndarray, shape (n, n)
        Overwritten by D B D⁻¹.

    Returns
    -------
    float
    """
    n = B.shape[0]
    sweeps = 0
    moved = True
    while moved and sweeps < BALANCE_SWEEPS:
        moved = False
        for i in range(n):
            c = 0.0
            r = 0.0
            for j in range(n):
                if j != i:
                    c += abs(B[j, i])
                    r += abs(B[i, j])
            if c > 0.0 or r > 0.0:
                # a zero row or column sum (a reducible F) can be scaled as small as wanted
                g = max(c, 1e-16 * r) / max(r, 1e-16 * c)
                if g < BALANCED * BALANCED or g * BALANCED * BALANCED > 1.0:
                    f = math.sqrt(g)
                    moved = True
                    for j in range(n):
                        if j != i:                  # (the diagonal keeps its value)
                            B[i, j] *= f
                            B[j, i] /= f
        sweeps += 1
    rho = 0.0
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += abs(B[i, j])
        rho = max(rho, s)
    return rho


# Names of the printed plant module (declared for the type checker; bound when printed).
rhs_jac: Callable[..., None]
C_OUT: FloatArray


def stage_jac(Fx: Any, Ft: Any, Phi: Any, Gam: Any, Dx_prev: Any, Dt_prev: Any, c: float,
              Dx: Any, Dt: Any) -> None:
    """One RK4 stage of the variational equations: Dx = Fx (Φ + c Dx_prev),
    Dt = Fx (Γ + c Dt_prev) + Ft (c = 0: no previous stage); Dt's columns only (none: Φ alone).

    Parameters
    ----------
    Fx : ndarray, shape (n, n)
    Ft : ndarray, shape (n, p)
        ∂f/∂x and ∂f/∂θ at the stage.
    Phi : ndarray, shape (n, n)
    Gam : ndarray, shape (n, pg)
        Φ and Γ at the start of the sub-step.
    Dx_prev : ndarray, shape (n, n)
    Dt_prev : ndarray, shape (n, pg)
        The previous stage's derivatives.
    c : float
        The stage's weight of the previous stage (0, dt/2 or dt).
    Dx : ndarray, shape (n, n)
    Dt : ndarray, shape (n, pg)
        Output.
    """
    n = C_OUT.shape[1]              # a constant of the printed module: the loops over x unroll
    p = Dt.shape[1]
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += Fx[i, k] * (Phi[k, j] + c * Dx_prev[k, j])
            Dx[i, j] = s
        for j in range(p):
            s = Ft[i, j]
            for k in range(n):
                s += Fx[i, k] * (Gam[k, j] + c * Dt_prev[k, j])
            Dt[i, j] = s


def held_input(U: Any, k: int, code: int, a: float, beta: float, WT: Any, i: int, tab: bool,
               w: Any, ua: Any) -> None:
    """u at the fraction ``a`` of the interval from sample k to k + 1, as the hold has it.

    Parameters
    ----------
    U : ndarray, shape (N, m)
        The samples (past the record's ends: its first and last, as
        :func:`~thetahat.estimation.hold.reconstruct`).
    k : int
    code : int
        :func:`~thetahat.estimation.hold.hold_code`.
    a : float
        The fraction, in [0, 1].
    beta : float
        Kaiser's β (band-limited hold).
    WT : ndarray, shape (·, 2L)
        The band-limited taps at the fractions i / (2n) when ``tab``.
    i : int
        The row of ``WT`` at ``a``.
    tab : bool
        ``WT[i]`` holds the taps at ``a``; else they are computed into ``w``.
    w : ndarray, shape (2L,)
        Scratch.
    ua : ndarray, shape (m,)
        Output.
    """
    N = U.shape[0]
    m = U.shape[1]
    k1 = k + 1 if k + 1 < N else N - 1
    if code == 0:
        for j in range(m):
            ua[j] = U[k, j]
        return
    if code == 1:
        for j in range(m):
            ua[j] = U[k, j] + a * (U[k1, j] - U[k, j])
        return
    if tab:
        for c in range(w.shape[0]):
            w[c] = WT[i, c]
    else:
        hold_weights(code, a, beta, w)
    L = w.shape[0] // 2
    for j in range(m):
        acc = 0.0
        for c in range(w.shape[0]):
            r = k + c - L + 1
            r = 0 if r < 0 else (N - 1 if r > N - 1 else r)
            acc += w[c] * U[r, j]
        ua[j] = acc


def propagate(x: Any, th: Any, U: Any, k: int, h: float, pc: Any, WT: Any, want_jac: bool,
              Phi: Any, Gam: Any) -> Any:
    """x(t_{k+1}) from x(t_k) by RK4 sub-steps, u held between samples k and k + 1 as ``pc``
    says; Φ, Γ in place if ``want_jac``.

    Runs in the printed plant module, where ``rhs_jac`` is the model's
    (:attr:`ModelKernel.propagate`). :func:`propagate_into` with work arrays of its own (a
    loop over samples allocates them once: :func:`plant_work`).

    Parameters
    ----------
    x : ndarray, shape (n,)
    th : ndarray, shape (p,)
    U : ndarray, shape (N, m)
        The input samples (rows k − L + 1 … k + L are read, L of the hold).
    k : int
        The interval's first sample.
    h : float
        The interval's length.
    pc, WT : ndarray
        :meth:`Propagation.arrays` (``pc[4]`` and ``WT`` are the run's taps table, updated
        here when the sub-step count changes).
    want_jac : bool
    Phi : ndarray, shape (n, n)
    Gam : ndarray, shape (n, pg)
        Output: Φ = ∂x_next/∂x and Γ's first pg columns (pg = 0: Φ alone).

    Returns
    -------
    ndarray, shape (n,)
        x_next.
    """
    n = x.shape[0]
    p = th.shape[0]
    pg = Gam.shape[1]
    xa = np.empty(n)
    # the allocations of plant_work, written out: the C printer takes neither a star-argument
    # nor a returned tuple without copying it every step
    propagate_into(x, xa, th, U, k, h, pc, WT, want_jac, Phi, Gam,
                   np.empty((n, n)), np.empty((n, p)), np.empty(n), np.empty(n), np.empty(n),
                   np.empty(n), np.empty(n), np.empty(U.shape[1]), np.empty(WT.shape[1]),
                   np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)),
                   np.empty((n, pg)), np.empty((n, pg)), np.empty((n, pg)), np.empty((n, pg)))
    return xa


def plant_work(n: int, p: int, pg: int, m: int, wl: int) -> Any:
    """The work arrays of :func:`propagate_into` (the arguments after ``Gam``), allocated once
    for a loop over samples.

    Parameters
    ----------
    n, p, m : int
        States, parameters, inputs.
    pg : int
        Γ's columns wanted (0: Φ alone).
    wl : int
        The band-limited taps' length (``WT.shape[1]``).

    Returns
    -------
    tuple of ndarray
        Fx (n, n), Ft (n, p), the four stages' slopes and x at a stage (five (n,)), u (m,),
        taps (wl,), the stages' ∂/∂x (four (n, n)) and ∂/∂θ (four (n, pg)).
    """
    return (np.empty((n, n)), np.empty((n, p)), np.empty(n), np.empty(n), np.empty(n),
            np.empty(n), np.empty(n), np.empty(m), np.empty(wl),
            np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)),
            np.empty((n, pg)), np.empty((n, pg)), np.empty((n, pg)), np.empty((n, pg)))


def propagate_into(x: Any, xa: Any, th: Any, U: Any, k: int, h: float, pc: Any, WT: Any,
                   want_jac: bool, Phi: Any, Gam: Any, Fx: Any, Ft: Any, k1: Any, k2: Any,
                   k3: Any, k4: Any, xs: Any, ua: Any, w: Any, D1x: Any, D2x: Any,
                   D3x: Any, D4x: Any, D1t: Any, D2t: Any, D3t: Any, D4t: Any) -> None:
    """:func:`propagate` writing x_next into ``xa`` (which may be ``x``), over the work arrays
    of :func:`plant_work` (their contents on entry are not read).

    Parameters
    ----------
    x : ndarray, shape (n,)
    xa : ndarray, shape (n,)
        Output: x_next.
    th, U, k, h, pc, WT, want_jac, Phi, Gam
        As for :func:`propagate`.
    Fx, Ft, k1, k2, k3, k4, xs, ua, w, D1x, D2x, D3x, D4x, D1t, D2t, D3t, D4t : ndarray
        Work (:func:`plant_work`).
    """
    n = C_OUT.shape[1]              # as in stage_jac: a constant of the printed module
    pg = Gam.shape[1]
    m = U.shape[1]
    code = int(pc[2])
    for j in range(m):
        ua[j] = U[k, j]
    rhs_jac(x, ua, th, xs, Fx, Ft)
    ratio = h * balanced_radius(Fx) / pc[0]       # (Fx is written again by the first stage)
    ns = int(math.ceil(ratio)) if ratio < MAX_SUBSTEPS else MAX_SUBSTEPS
    ns = max(ns, int(pc[1]), 1)
    ns = min(ns, MAX_SUBSTEPS)
    tab = code == 2 and ns <= TABLE_SUBSTEPS
    if tab and pc[4] != ns:
        for i in range(2 * ns + 1):
            hold_weights(code, i / (2.0 * ns), pc[3], WT[i])
        pc[4] = ns
    dt = h / ns
    for i in range(n):
        xa[i] = x[i]
        for j in range(n):
            D1x[i, j] = 0.0
            D2x[i, j] = 0.0
            D3x[i, j] = 0.0
            D4x[i, j] = 0.0
        for j in range(pg):
            D1t[i, j] = 0.0
            D2t[i, j] = 0.0
            D3t[i, j] = 0.0
            D4t[i, j] = 0.0
    if want_jac:
        for i in range(n):
            for j in range(n):
                Phi[i, j] = 1.0 if i == j else 0.0
            for j in range(pg):
                Gam[i, j] = 0.0
    for s in range(ns):
        a = s / ns
        held_input(U, k, code, a, pc[3], WT, 2 * s, tab, w, ua)
        rhs_jac(xa, ua, th, k1, Fx, Ft)
        if want_jac:
            stage_jac(Fx, Ft, Phi, Gam, D1x, D1t, 0.0, D1x, D1t)
        held_input(U, k, code, a + 0.5 / ns, pc[3], WT, 2 * s + 1, tab, w, ua)
        for i in range(n):
            xs[i] = xa[i] + 0.5 * dt * k1[i]
        rhs_jac(xs, ua, th, k2, Fx, Ft)
        if want_jac:
            stage_jac(Fx, Ft, Phi, Gam, D1x, D1t, 0.5 * dt, D2x, D2t)
        for i in range(n):
            xs[i] = xa[i] + 0.5 * dt * k2[i]
        rhs_jac(xs, ua, th, k3, Fx, Ft)
        if want_jac:
            stage_jac(Fx, Ft, Phi, Gam, D2x, D2t, 0.5 * dt, D3x, D3t)
        held_input(U, k, code, a + 1.0 / ns, pc[3], WT, 2 * s + 2, tab, w, ua)
        for i in range(n):
            xs[i] = xa[i] + dt * k3[i]
        rhs_jac(xs, ua, th, k4, Fx, Ft)
        if want_jac:
            stage_jac(Fx, Ft, Phi, Gam, D3x, D3t, dt, D4x, D4t)
            for i in range(n):
                for j in range(n):
                    Phi[i, j] += dt / 6.0 * (D1x[i, j] + 2.0 * D2x[i, j] + 2.0 * D3x[i, j]
                                             + D4x[i, j])
                for j in range(pg):
                    Gam[i, j] += dt / 6.0 * (D1t[i, j] + 2.0 * D2t[i, j] + 2.0 * D3t[i, j]
                                             + D4t[i, j])
        for i in range(n):
            xa[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


def free_run(x0: Any, th: Any, U: Any, tt: Any, k0: int, k1: int, pc: Any, WT: Any,
             Y: Any, X: Any) -> int:
    """The model run free from x(t_{k0}) = x0 over samples k0 … k1 − 1: X[k − k0] = x_k,
    Y[k − k0] = C x_k.

    Parameters
    ----------
    x0 : ndarray, shape (n,)
    th : ndarray, shape (p,)
    U : ndarray, shape (N, m)
    tt : ndarray, shape (N,)
    k0, k1 : int
    pc, WT : ndarray
        :meth:`Propagation.arrays`.
    Y : ndarray, shape (k1 − k0, r)
    X : ndarray, shape (k1 − k0, n)
        Output.

    Returns
    -------
    int
        The rows written before the state stopped being finite (k1 − k0: all).
    """
    n = x0.shape[0]
    r = C_OUT.shape[0]
    x = x0.copy()
    Phi = np.empty((n, n))
    Gam = np.empty((n, 0))
    # Γ's width (0) as a run-time int: a literal 0 would compile plant_work a second time
    work = plant_work(n, th.shape[0], Gam.shape[1], U.shape[1], WT.shape[1])
    for k in range(k0, k1):
        if k > k0:
            propagate_into(x, x, th, U, k - 1, tt[k] - tt[k - 1], pc, WT, n < 0, Phi, Gam,
                           *work)
        ok = True
        for i in range(n):
            if not math.isfinite(x[i]):
                ok = False
        if not ok:
            return k - k0
        for i in range(n):
            X[k - k0, i] = x[i]
        for i in range(r):
            acc = 0.0
            for a in range(n):
                acc += C_OUT[i, a] * x[a]
            Y[k - k0, i] = acc
    return k1 - k0


def _ieee_function(name: str, ufunc: Any) -> Callable[..., float]:
    """``math.<name>`` whose overflow or domain error gives IEEE's inf or nan, as numba's does."""
    exact = getattr(math, name)

    def ieee(*args: float) -> float:
        try:
            return exact(*args)
        except (OverflowError, ValueError):          # only here: NumPy's IEEE result
            with np.errstate(all="ignore"):
                return float(ufunc(*args))
    ieee.__name__ = name
    return ieee


#: The ``math`` a plain-Python printed module sees (numba absent): Python's ``math`` raises
#: ``OverflowError`` for ``exp(1000)`` and ``ValueError`` for ``log(0)`` where the compiled
#: kernels return inf and -inf, which their loops check and report as a status; these
#: functions give the compiled kernels' results (at the cost of a try only).
IEEE_MATH = SimpleNamespace(**{
    **{k: getattr(math, k) for k in dir(math) if not k.startswith("_")},
    **{name: _ieee_function(name, ufunc) for name, ufunc in [
        ("exp", np.exp), ("expm1", np.expm1), ("exp2", np.exp2), ("cosh", np.cosh),
        ("sinh", np.sinh), ("pow", np.power), ("log", np.log), ("log2", np.log2),
        ("log10", np.log10), ("log1p", np.log1p), ("sqrt", np.sqrt), ("acos", np.arccos),
        ("asin", np.arcsin), ("acosh", np.arccosh), ("atanh", np.arctanh),
        ("fmod", np.fmod)] if hasattr(math, name)}})


def _ieee(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with NumPy's floating-point warnings off, as numba's arithmetic has them.

    A plain-Python kernel (numba absent) then gives inf or nan on an overflow, as the compiled
    one does, which the loops check and report as a status, instead of a NumPy warning per
    operation.
    """
    @functools.wraps(fn)
    def ieee(*args: Any) -> Any:
        with np.errstate(all="ignore"):
            return fn(*args)
    ieee.ieee = True  # type: ignore[attr-defined]
    ieee.py_func = fn  # type: ignore[attr-defined]   # the kernel itself, as numba's has it
    return ieee


def printed_kernels(prefix: str, doc: str, functions: Sequence[Callable[..., Any]],
                    provided: Mapping[str, Any], compiled: bool, *,
                    constants: Mapping[str, str] | None = None, text: str | None = None,
                    fresh: bool = False, inline: Sequence[Callable[..., Any]] = ()
                    ) -> tuple[ModuleType, list[str]]:
    """One printed module of stage-2 kernels: ``functions`` and what they call, free names bound.

    Parameters
    ----------
    prefix : str
        The module name's start (``<prefix>_<hash>``).
    doc : str
        Its docstring.
    functions : sequence of function
        Module-level kernels (numba's subset of Python) to print
        (:meth:`~thetahat.estimation.kernels.modules.ModuleText.bound`).
    provided : mapping
        Free names bound by the caller: a kernel of another printed module (imported from
        it), an array or number (a constant), or a string (a name the module defines).
    compiled : bool
        Decorate with :data:`NJIT` (numba installed) or print plain Python.
    constants : mapping of str to str, optional
        Module-level ``name = text`` lines (before the functions).
    text : str, optional
        Source printed elsewhere (SymPy's ``rhs_jac``), put before the functions.
    fresh : bool
        Import a new instance of the module (its globals the caller's to assign), not the
        shared one.
    inline : sequence of function
        Of ``functions`` or what they call: compiled into each caller (numba's
        ``inline='always'``, :class:`~thetahat.estimation.kernels.modules.ModuleText`).

    Returns
    -------
    module, list of str
        The module and the printed name of each of ``functions``, in order (each registered,
        so a module printed later that calls it imports it from here).
    """
    decorator = NJIT if compiled else None
    mt = ModuleText(doc, decorator, inline)
    mt.import_line("import math")
    mt.import_line("import numpy as np")
    for name, value in (constants or {}).items():
        mt.constant(name, value)
    if text is not None:
        mt.text(((NJIT + "\n") if compiled else "") + text)
        if compiled:
            mt.import_line("import numba")
    names = [mt.bound(fn, decorator, provided) for fn in functions]
    mod = load_module(mt.source(), prefix)
    if fresh:
        mod = _fresh(mod)
    if not compiled:
        mod.math = IEEE_MATH         # type: ignore[attr-defined]   # inf/nan, not exceptions
    for name in names:
        if not compiled and not getattr(getattr(mod, name), "ieee", False):
            setattr(mod, name, _ieee(getattr(mod, name)))
        register(getattr(mod, name), mod.__name__, name)
    return mod, names


def _fresh(mod: ModuleType) -> ModuleType:
    """A new instance of a printed module, imported from its file (its globals its own)."""
    path = getattr(mod, "__file__", None)
    spec = None if path is None else importlib.util.spec_from_file_location(
        f"{mod.__name__}_own{len(sys.modules)}", path)
    if spec is None or spec.loader is None:
        raise FileAccessError(f"cannot import the printed module {mod.__name__} again.")
    new = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(new)
    return new


@dataclass(frozen=True, slots=True, eq=False)
class ModelKernel:
    """The plant model of eq. (1) with y = C x, as scalar kernels (see the module docstring).

    Attributes
    ----------
    n, m, r, p : int
        States, inputs, outputs, parameters.
    C : ndarray, shape (r, n)
    compiled : bool
        Whether the kernels are numba-compiled.
    rhs_jac : callable
        ``rhs_jac(x (n,), u (m,), th (p,), f (n,), Fx (n, n), Ft (n, p))``: writes
        f(x, u, θ), ∂f/∂x and ∂f/∂θ in place.
    propagate : callable
        ``propagate(x, th, U, k, h, pc, WT, want_jac, Phi (n, n), Gam (n, p)) -> x_next``:
        :func:`propagate`, the RK4 map over the interval from sample k (u held as
        :class:`Propagation` says) and, when ``want_jac``, its exact Jacobians Φ, Γ written
        into ``Phi``, ``Gam`` (a ``Gam`` of shape (n, 0): Φ alone, a third of the work when
        p = 2n).
    propagate_into, plant_work : callable
        :func:`propagate_into` and :func:`plant_work`: the same map over work arrays
        allocated once (what a kernel's loop over samples calls).
    free_run : callable
        ``free_run(x0, th, U, t, k0, k1, pc, WT, Y, X) -> rows``: :func:`free_run`.
    module : module
        The printed module (other kernels import ``propagate`` from it).
    source : str
        The generated code of ``rhs_jac``.
    """

    n: int
    m: int
    r: int
    p: int
    C: FloatArray
    compiled: bool
    rhs_jac: Callable[..., None]
    propagate: Callable[..., FloatArray]
    propagate_into: Callable[..., None]
    plant_work: Callable[..., Any]
    free_run: Callable[..., int]
    module: ModuleType
    source: str

    def f(self, x: Any, u: Any, theta: Any) -> FloatArray:
        """f(x, u, θ) (convenience for tests and the CRLB), shape (n,)."""
        f, _, _ = self.jacobians(x, u, theta)
        return f

    def jacobians(self, x: Any, u: Any, theta: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(f, ∂f/∂x, ∂f/∂θ) at one point; shapes (n,), (n, n), (n, p)."""
        f = np.empty(self.n)
        Fx = np.empty((self.n, self.n))
        Ft = np.empty((self.n, self.p))
        self.rhs_jac(np.asarray(x, float).reshape(self.n), np.asarray(u, float).reshape(self.m),
                     np.asarray(theta, float).reshape(self.p), f, Fx, Ft)
        return f, Fx, Ft

    def __repr__(self) -> str:
        return (f"ModelKernel(n={self.n}, m={self.m}, r={self.r}, p={self.p}, "
                f"compiled={self.compiled})")


#: Compiled into their callers (numba's ``inline='always'``): with the state's dimension a
#: constant of the printed module (``C_OUT.shape[1]``), the variational equations of each RK4
#: stage unroll there. On the Silverbox model (n = 2, p = 5, 16 sub-steps a sample) the MAP
#: fit's sweep went from 6.7 to 2.8 µs a sample under the linear hold and from 8.1 to 4.1 under
#: the band-limited one, for about 0.8 s more of the plant module's first compilation
#: (measured once, 2026-12-07); inlining ``rhs_jac`` and ``held_input`` as well saved another
#: 25 % for 2 s more, not taken (the cold start counts).
INLINED = (stage_jac,)

_CACHE: dict[tuple[str, bytes, bool, bool], ModelKernel] = {}
_SOURCES: dict[int, tuple[PerturbedLinearSystem, str]] = {}


def model_kernel(system: PerturbedLinearSystem, *, compiled: bool | None = None,
                 inline: bool = True) -> ModelKernel:
    """Derive the stage-2 plant kernels of a model (cached per model content and back end).

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a :class:`~thetahat.model.perturbation.SymbolicPerturbation`.
    compiled : bool, optional
        Compile with numba; default: when numba is installed.
    inline : bool
        Compile :data:`INLINED` into their callers (default); False calls them (what
        ``benchmarks/bench_plant_kernel.py`` compares against).

    Returns
    -------
    ModelKernel

    Raises
    ------
    DimensionError
        The perturbation is not symbolic, or the system has no perturbation.
    MissingExtraError
        ``compiled=True`` without numba.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.plant_kernel import model_kernel
    >>> kern = model_kernel(lugre.system(), compiled=False)
    >>> f, Fx, Ft = kern.jacobians([1.0, 1e-3], [0.0], [0.28])
    >>> Fx.shape, Ft.shape
    ((2, 2), (2, 1))
    """
    if system.perturbation is None:
        raise DimensionError("the system has no perturbation g; stage 2 needs the full model.")
    use = have_numba() if compiled is None else bool(compiled)
    if use and not have_numba():
        raise MissingExtraError("compiled=True needs numba: pip install 'thetahat[speed]' "
                                "(or pass compiled=False for the numpy fallback).")
    known = _SOURCES.get(id(system))
    if known is not None and known[0] is system:
        source = known[1]
    else:
        source = rhs_jac_source(system)
        _SOURCES[id(system)] = (system, source)   # kept alive, so its id stays unique
    C = np.array(system.C, dtype=np.float64)
    key = (source, C.tobytes(), use, inline)     # equal models share one compiled kernel
    hit = _CACHE.get(key)
    if hit is not None:
        return hit
    mod, (prop, into, work, run) = printed_kernels(
        "thetahat_plant", "Printed by thetahat.estimation.statistical.plant_kernel: the plant "
        "model of one system; do not edit (content-addressed).",
        [propagate, propagate_into, plant_work, free_run],
        {"rhs_jac": "rhs_jac", "C_OUT": C}, use, text=source,
        inline=INLINED if inline else ())
    kern = ModelKernel(n=system.n, m=system.m, r=system.r, p=system.p, C=C, compiled=use,
                       rhs_jac=mod.rhs_jac, propagate=getattr(mod, prop),
                       propagate_into=getattr(mod, into), plant_work=getattr(mod, work),
                       free_run=getattr(mod, run), module=mod, source=source)
    _CACHE[key] = kern
    return kern


def choose_substeps(kern: ModelKernel, t: FloatArray, U: FloatArray, Y: FloatArray,
                    theta: FloatArray, x0: FloatArray, noise_std: FloatArray, *,
                    hold: str = DEFAULT_HOLD, h_rho: float = H_RHO, target: float = ACCURACY,
                    samples: int | None = None) -> int:
    """The accuracy floor of RK4 sub-steps of a record: output error ≤ ``target`` standard errors.

    The model is run free from ``x0`` at ``theta`` over the first :data:`ACCURACY_SAMPLES`
    samples with the floor n (n = 1, 2, 4, … up to :data:`MAX_ACCURATE_SUBSTEPS`) and with
    every sample's sub-steps doubled; the first n with ‖y_n − y_{n,×2}‖_{R⁻¹} · √(N / samples
    compared) ≤ ``target`` is returned (:func:`doubling_floor`, module docstring), the
    comparison ending where either run leaves :data:`RANGE_FACTOR` times the data's range
    around it or stops being finite.

    Parameters
    ----------
    kern : ModelKernel
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        The record (U: stage 2's samples, as the estimators propagate them; NaN in Y allowed).
    theta : ndarray (p,)
    x0 : ndarray (n,)
    noise_std : ndarray (r,)
        σ per output, > 0.
    hold : str
    h_rho : float
    target : float
        The error allowed in standard errors of θ̂ (:data:`ACCURACY`).
    samples : int, optional
        The record length the error is scaled to (default N).

    Returns
    -------
    int
        1 … :data:`MAX_ACCURATE_SUBSTEPS` (1: the stability choice alone suffices; also when
        fewer than 2 samples can be compared).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> d = lugre.simulate(seed=0, t_end=0.3)
    >>> kern = model_kernel(lugre.system(), compiled=False)
    >>> choose_substeps(kern, d.t, np.asarray(d.u), np.asarray(d.y), np.array([0.28]),
    ...                 np.zeros(2), np.array([0.02]))
    1
    """
    N = t.shape[0]
    total = N if samples is None else int(samples)
    K = min(N, ACCURACY_SAMPLES)
    if K < 2:
        return 1
    r = kern.r
    tt = np.ascontiguousarray(t, dtype=np.float64)
    Uc = np.ascontiguousarray(U, dtype=np.float64)
    th = np.array(theta, dtype=np.float64)
    x = np.array(x0, dtype=np.float64)
    scale = np.asarray(noise_std, dtype=np.float64).reshape(r)
    seen = Y[:K][np.isfinite(Y[:K]).all(axis=1)] if Y.shape[1] else np.zeros((0, r))
    centre = (np.median(seen, axis=0) if seen.shape[0] else np.zeros(r))
    spread = (RANGE_FACTOR * (np.ptp(seen, axis=0) + scale) if seen.shape[0]
              else np.full(r, np.inf))

    def run(n: int, refine: int) -> FloatArray:
        Yn = np.full((K, r), np.nan)
        pc, WT = Propagation(hold=hold, substeps=n * refine, h_rho=h_rho / refine).arrays()
        kern.free_run(x.copy(), th, Uc, tt, 0, K, pc, WT, Yn, np.empty((K, kern.n)))
        # compared while inside the data's range: outside it, not at all
        return np.where(np.abs(Yn - centre) <= spread, Yn / scale, np.nan)

    return doubling_floor(run, total, target=target)


def doubling_floor(run: Callable[[int, int], FloatArray], total: int, *,
                   target: float = ACCURACY, start: int = 1, limit: int | None = None) -> int:
    """The first floor n = start, 2 start, 4 start, … (up to :data:`MAX_ACCURATE_SUBSTEPS`)
    whose whitened outputs ``run(n, 1)`` differ from those with every sample's sub-steps doubled,
    ``run(n, 2)``, by at most ``target`` over ``total`` samples.

    The rule of :func:`choose_substeps` (the free run) and of the likelihood with process
    noise (its normalised innovations,
    :func:`~thetahat.estimation.statistical.likelihood.fit_process_noise`): for RK4,
    whose error falls 16-fold per doubling, the difference is the error of ``run(n, 1)``
    (within 20 % where a ceiling makes a doubling a factor of 1.5 only), and a whitened error
    e biases θ̂ by at most ‖e‖ of its standard errors (module docstring). The finer run
    doubles the sub-steps of *every* sample: the stability bound halved with the floor
    doubled. Doubling the floor alone compares nothing where the stability bound exceeds
    both floors (the two runs then agree exactly): a two-inertia drive with friction kept 1
    sub-step whose θ̂ was 1.6 standard errors off the converged one (a one-off measurement).

    Parameters
    ----------
    run : callable
        ``run(n, refine) -> ndarray (K, r)``: the outputs with the floor n · refine and the
        stability bound ``h_rho`` / refine, each divided by its standard deviation; rows not
        finite in either run end the comparison there.
    total : int
        The samples the error is scaled to: ‖run(n, 1) − run(n, 2)‖ · √(total / rows
        compared).
    target : float
        The error allowed in standard errors of θ̂ (:data:`ACCURACY`).
    start : int
        The first floor tried (≥ 1; default 1): a floor known to be needed, such as a shorter
        window's of the same record (the error allowed over ``total`` samples shrinks as
        ``total`` grows), whose smaller floors need not be run again.
    limit : int, optional
        Floors from ``limit`` on are not tried: the result is min(floor, ``limit``) (the
        smaller of two floors, the other known, without running this one's larger ones).

    Returns
    -------
    int
        ``start`` … :data:`MAX_ACCURATE_SUBSTEPS` (``start`` also when fewer than 2 rows can
        be compared), at most ``limit``.

    Examples
    --------
    >>> import numpy as np
    >>> grid = np.linspace(0.0, 1.0, 50)[:, None]
    >>> doubling_floor(lambda n, refine: np.sin(3.0 * grid) + 1.0 / (n * refine) ** 4, 50)
    4
    """
    top = MAX_ACCURATE_SUBSTEPS if limit is None else max(min(int(limit),
                                                              MAX_ACCURATE_SUBSTEPS), 1)
    n = min(max(int(start), 1), top)
    while n < top:
        coarse, fine = run(n, 1), run(n, 2)
        good = np.all(np.isfinite(coarse) & np.isfinite(fine), axis=1)
        stop = int(np.argmin(good)) if not good.all() else good.shape[0]
        if stop < 2:
            return n
        e = coarse[:stop] - fine[:stop]
        err = math.sqrt(float(np.sum(e * e)) * total / stop)
        if err <= target:
            return n
        n *= 2
    return min(n, top)
