"""The plant model of stage 2 as scalar code: f, ∂f/∂x, ∂f/∂θ and the sampled-data map (RK4).

Stage 2 of the guarded estimator (the EKF, the maximum-likelihood fit) and the Cramér–Rao
bound all need the *plant* model of eq. (1) with y = C x substituted into the perturbation,

    ẋ = f(x, u, θ) = A x + B u + E g(col(u, C x), x, θ),

its Jacobians F_x = A + E (∂g/∂x + ∂g/∂y C) and F_θ = E ∂g/∂θ, and the map over one sample
x_k → x_{k+1} with its exact derivatives Φ = ∂x_{k+1}/∂x_k and Γ = ∂x_{k+1}/∂θ (the
variational equations of the discrete map). :func:`model_kernel` derives all of them once
from a :class:`~thetahat.model.system.PerturbedLinearSystem` whose perturbation is a
:class:`~thetahat.model.perturbation.SymbolicPerturbation`: SymPy differentiates, common
subexpressions are eliminated and SymPy's Python printer writes the scalar code of
``rhs_jac``, which is printed with the RK4 kernels of this module (:func:`stage_jac`,
:func:`propagate`, :func:`spectral_radius_bound`) into one module, imported from the cache of
printed modules (:mod:`~thetahat.estimation.kernels.modules`); with numba installed (extra
``speed``) its functions are compiled (once per machine), otherwise they run as plain Python.

The sampled-data map is classical RK4 with u interpolated linearly between the samples
(first-order hold) and a number of sub-steps chosen per sample from the spectral radius ρ of
F_x at the start of the sample, n = ceil(h ρ / ``h_rho``) (RK4 is stable for h ρ ≤ 2.78 on
the real axis; ``h_rho = 2`` keeps a margin and follows the stiffness of models such as
LuGre's, where ρ ranges over 3e2 … 2e4 s⁻¹). Differentiating the RK4 stages gives the exact
Jacobian of the map actually used, so the EKF's linearisation and the fit's sensitivities are
those of the computed trajectory.
"""

from __future__ import annotations

import functools

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import sympy as sp
from numpy.typing import NDArray
from sympy.printing.pycode import PythonCodePrinter

from ...errors import DimensionError, FileAccessError, MissingExtraError
from ...model.perturbation import SymbolicPerturbation
from ...model.system import PerturbedLinearSystem
from ..kernels.kernel_cache import load_module, register
from ..kernels.modules import KernelSourceError, ModuleText, cached_njit

__all__ = ["ModelKernel", "model_kernel", "have_numba", "jit", "propagate",
           "spectral_radius_bound", "stage_jac"]

FloatArray = NDArray[np.float64]

#: Default bound on h ρ per RK4 sub-step (RK4's real stability interval is [−2.785, 0]).
H_RHO = 2.0
#: Largest number of RK4 sub-steps per sample.
MAX_SUBSTEPS = 500


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


def _ieee(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with NumPy's floating-point warnings off, as numba's arithmetic has them."""
    @functools.wraps(fn)
    def ieee(*args: Any) -> Any:
        with np.errstate(all="ignore"):
            return fn(*args)
    return ieee


def jit(fn: Callable[..., Any], compiled: bool) -> Callable[..., Any]:
    """``numba.njit(fn, nogil=True)`` when ``compiled``, else ``fn`` with IEEE arithmetic.

    Parameters
    ----------
    fn : callable
        A scalar-loop kernel written in numba's subset of Python.
    compiled : bool
        Compile with numba (which must be installed); False returns ``fn`` run under
        ``np.errstate(all="ignore")``: an overflow gives inf as in the compiled kernel, which
        the loops check and report as a status, instead of a NumPy warning per operation.

    Returns
    -------
    callable
        The compiled dispatcher (releasing the GIL, so a fit on a worker thread runs
        alongside the caller), or ``fn``. It comes from a printed module cached on disk
        (:func:`~thetahat.estimation.kernels.modules.cached_njit`), so later processes load the
        machine code instead of compiling; a kernel that cannot be printed that way is
        compiled in memory.
    """
    if not compiled:
        return _ieee(fn)
    try:
        return cached_njit(fn)
    except (KernelSourceError, FileAccessError):
        import numba
        return numba.njit(fn, nogil=True)     # a fit on a worker thread does not hold the GIL


def _plant_expressions(system: PerturbedLinearSystem) -> tuple[list[sp.Symbol], list[sp.Symbol],
                                                               list[sp.Symbol], sp.Matrix]:
    g = system.perturbation
    if not isinstance(g, SymbolicPerturbation):
        raise DimensionError("stage 2 and the CRLB need the perturbation as a "
                             "SymbolicPerturbation (SymPy expression) to derive ∂f/∂x and "
                             f"∂f/∂θ; got {type(g).__name__}. Build g with "
                             "SymbolicPerturbation.from_sympy or parse_perturbation.")
    n, m, p = system.n, system.m, system.p
    xs = [sp.Symbol(f"x_{i}", real=True) for i in range(n)]
    us = [sp.Symbol(f"u_{i}", real=True) for i in range(m)]
    ts = [sp.Symbol(f"th_{i}", real=True) for i in range(p)]
    C = sp.Matrix(system.C)
    y_model = C * sp.Matrix(xs)
    subs = dict(zip(g.x, xs))
    subs.update(zip(g.u, us))
    subs.update(zip(g.theta, ts))
    subs.update(zip(g.y, list(y_model)))
    phi = sp.Matrix(g.expr).xreplace(subs)
    f = (sp.Matrix(system.A) * sp.Matrix(xs) + sp.Matrix(system.B) * sp.Matrix(us)
         + sp.Matrix(system.E) * phi)
    return xs, us, ts, f


def _generate_source(system: PerturbedLinearSystem) -> str:
    """Python source of ``rhs_jac(x, u, th, f, Fx, Ft)`` writing f, ∂f/∂x, ∂f/∂θ in place."""
    xs, us, ts, f = _plant_expressions(system)
    Fx = f.jacobian(xs)
    Ft = f.jacobian(ts) if ts else sp.zeros(len(xs), 0)
    # d|z|/dz = sign(z) and DiracDelta terms of sign'(z) are dropped (a.e. derivatives)
    Fx = Fx.replace(sp.DiracDelta, lambda *a: sp.S.Zero)
    Ft = Ft.replace(sp.DiracDelta, lambda *a: sp.S.Zero)
    entries: list[tuple[str, tuple[int, ...], Any]] = [
        ("f", (i,), f[i]) for i in range(f.rows)]
    entries += [("Fx", (i, j), Fx[i, j]) for i in range(Fx.rows) for j in range(Fx.cols)]
    entries += [("Ft", (i, j), Ft[i, j]) for i in range(Ft.rows) for j in range(Ft.cols)]
    temps, reduced = sp.cse([e for _, _, e in entries], symbols=sp.numbered_symbols("c_"))
    printer = PythonCodePrinter({"fully_qualified_modules": True, "standard": "python3"})
    lines = ["def rhs_jac(x, u, th, f, Fx, Ft):"]
    lines += [f"    {s.name} = x[{i}]" for i, s in enumerate(xs)]
    lines += [f"    {s.name} = u[{i}]" for i, s in enumerate(us)]
    lines += [f"    {s.name} = th[{i}]" for i, s in enumerate(ts)]
    for sym, expr in temps:
        lines.append(f"    {sym.name} = {printer.doprint(expr)}")
    for (name, index, _), expr in zip(entries, reduced):
        lines.append(f"    {name}[{', '.join(map(str, index))}] = {printer.doprint(expr)}")
    return "\n".join(lines) + "\n"


def spectral_radius_bound(F: FloatArray) -> float:
    """An upper bound on the spectral radius of F: Gershgorin's after Osborne balancing.

    Four sweeps of diagonal balancing (D F D⁻¹ with equal off-diagonal row and column sums)
    make the bound tight for badly scaled models (a zero off-diagonal row or column is scaled
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
    """
    n = F.shape[0]
    B = F.copy()
    for _ in range(4):
        for i in range(n):
            c = 0.0
            r = 0.0
            for j in range(n):
                if j != i:
                    c += abs(B[j, i])
                    r += abs(B[i, j])
            if c > 0.0 or r > 0.0:
                # a zero row or column sum (a reducible F) can be scaled as small as wanted
                f = math.sqrt(max(c, 1e-16 * r) / max(r, 1e-16 * c))
                for j in range(n):
                    B[i, j] *= f
                    B[j, i] /= f
    rho = 0.0
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += abs(B[i, j])
        rho = max(rho, s)
    return rho


# Names of the printed plant module (declared for the type checker; never assigned here).
rhs_jac: Callable[..., None]


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
    n = Fx.shape[0]
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


def propagate(x: Any, th: Any, u0: Any, u1: Any, h: float, h_rho: float, want_jac: bool,
              Phi: Any, Gam: Any) -> Any:
    """x(t + h) by RK4 sub-steps, u linear from u0 to u1; Φ, Γ in place if ``want_jac``.

    Runs in the printed plant module, where ``rhs_jac`` is the model's
    (:attr:`ModelKernel.propagate`).

    Parameters
    ----------
    x : ndarray, shape (n,)
    th : ndarray, shape (p,)
    u0, u1 : ndarray, shape (m,)
        Inputs at the start and the end of the sample.
    h : float
        The sample's length.
    h_rho : float
        Bound on h ρ per sub-step (``H_RHO``).
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
    m = u0.shape[0]
    Fx = np.empty((n, n))
    Ft = np.empty((n, p))
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    xs = np.empty(n)
    ua = np.empty(m)
    rhs_jac(x, u0, th, k1, Fx, Ft)
    ratio = h * spectral_radius_bound(Fx) / h_rho
    ns = int(math.ceil(ratio)) if ratio < 500.0 else 500
    ns = max(ns, 1)
    dt = h / ns
    xa = x.copy()
    D1x = np.zeros((n, n))
    D2x = np.zeros((n, n))
    D3x = np.zeros((n, n))
    D4x = np.zeros((n, n))
    D1t = np.zeros((n, pg))
    D2t = np.zeros((n, pg))
    D3t = np.zeros((n, pg))
    D4t = np.zeros((n, pg))
    if want_jac:
        for i in range(n):
            for j in range(n):
                Phi[i, j] = 1.0 if i == j else 0.0
            for j in range(pg):
                Gam[i, j] = 0.0
    for s in range(ns):
        a = s / ns
        for j in range(m):
            ua[j] = u0[j] + a * (u1[j] - u0[j])
        rhs_jac(xa, ua, th, k1, Fx, Ft)
        if want_jac:
            stage_jac(Fx, Ft, Phi, Gam, D1x, D1t, 0.0, D1x, D1t)
        for j in range(m):
            ua[j] = u0[j] + (a + 0.5 / ns) * (u1[j] - u0[j])
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
        for j in range(m):
            ua[j] = u0[j] + (a + 1.0 / ns) * (u1[j] - u0[j])
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
    return xa


#: The decorator of the printed plant module's functions when compiled.
_NJIT = "@numba.njit(nogil=True, cache=True)"


def _plant_module(source: str, compiled: bool) -> Any:
    """The printed plant module: ``rhs_jac`` (``source``) and the RK4 kernels, compiled or
    plain Python, imported from the cache."""
    text = ModuleText("Printed by thetahat.estimation.statistical.plant_kernel: the plant "
                      "model of one system; do not edit (content-addressed).",
                      _NJIT if compiled else None)
    text.import_line("import math")
    text.import_line("import numpy as np")
    if compiled:
        text.import_line("import numba")
    text.text(((_NJIT + "\n") if compiled else "") + source)
    for fn in (spectral_radius_bound, stage_jac, propagate):
        text.definition(fn)
    mod = load_module(text.source(), "thetahat_plant")
    if compiled:
        for name in ("rhs_jac", "propagate"):
            register(getattr(mod, name), mod.__name__, name)
    return mod


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
        ``propagate(x, th, u0, u1, h, h_rho, want_jac, Phi (n, n), Gam (n, p)) -> x_next``:
        the RK4 map over one sample (first-order hold on u) and, when ``want_jac``, its exact
        Jacobians Φ = ∂x_next/∂x, Γ = ∂x_next/∂θ written into ``Phi``, ``Gam`` (a ``Gam``
        of shape (n, 0): Φ alone, a third of the work when p = 2n).
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


_CACHE: dict[tuple[str, bytes, bool], ModelKernel] = {}
_SOURCES: dict[int, tuple[PerturbedLinearSystem, str]] = {}


def model_kernel(system: PerturbedLinearSystem, *, compiled: bool | None = None) -> ModelKernel:
    """Derive the stage-2 plant kernels of a model (cached per model content and back end).

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a :class:`~thetahat.model.perturbation.SymbolicPerturbation`.
    compiled : bool, optional
        Compile with numba; default: when numba is installed.

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
        source = _generate_source(system)
        _SOURCES[id(system)] = (system, source)   # kept alive, so its id stays unique
    C = np.array(system.C, dtype=np.float64)
    key = (source, C.tobytes(), use)             # equal models share one compiled kernel
    hit = _CACHE.get(key)
    if hit is not None:
        return hit
    mod = _plant_module(source, use)
    kern = ModelKernel(n=system.n, m=system.m, r=system.r, p=system.p,
                       C=C, compiled=use, rhs_jac=mod.rhs_jac, propagate=mod.propagate,
                       source=source)
    _CACHE[key] = kern
    return kern
