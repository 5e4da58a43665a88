"""A compiled fast path for the observer: one numba kernel per symbolic model (optional extra).

:func:`compile_observer` turns a :class:`~thetahat.estimation.observer.ModifiedHighGainObserver`
whose parts are all symbolic or structured into a :class:`CompiledObserver` whose ``step`` and
``run`` execute the observer's step (eqs. (3), (8) and the second observer of Sec. VI) as
machine code. Supported:

* g: a :class:`~thetahat.model.perturbation.SymbolicPerturbation` (g, ∂g/∂x, ∂g/∂θ and ∂g/∂v
  are printed to scalar Python code with SymPy's common-subexpression elimination);
* Θ: a :class:`~thetahat.model.paramset.Box`, with a diagonal Γ (the Γ⁻¹-weighted projection
  onto a box is then a clip);
* update laws: :class:`~thetahat.estimation.update_laws.ConstantLaw`,
  :class:`~thetahat.estimation.update_laws.IntermittentInversion` (l ≡ 1, as built by
  :func:`~thetahat.estimation.update_laws.AlgebraicInversion`, or the weight of
  :func:`~thetahat.estimation.update_laws.smooth_ramp`) whose θ* is a
  :class:`~thetahat.estimation.theta_star.ThetaStar` (from ``from_perturbation`` or
  ``ThetaStar.from_expr``), and
  :class:`~thetahat.estimation.update_laws.GradientInversion` with the default M = (∂g/∂θ)ᵀ;
  none of them with a ``saturation``;
* an attached :class:`~thetahat.estimation.redesign.SecondObserver`;
* a fixed step dt and the zero-order hold (Φ₁ is computed once).

Everything else raises :class:`~thetahat.errors.UnsupportedError` (a NotImplementedError) naming the part; use the Python observer.

The generated source is written to a cache directory (``$THETAHAT_CACHE_DIR``, default
``~/.cache/thetahat``, else a temporary directory) under a name that hashes its content, and
compiled with ``numba.njit(cache=True)``: the first compilation of a model costs a few
seconds, later processes load the machine code from disk. The gains, ε, Γ, Θ, the ramp and dt
are data, not code: observers that differ only in them share one kernel.

numba is the optional extra ``speed``; without it this module imports, and
:func:`compile_observer` raises :class:`ImportError`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any, NoReturn

import numpy as np
import sympy as sp
from numpy.typing import NDArray
from sympy.printing.pycode import PythonCodePrinter

from .._validate import as_vector, positive_scalar
from ..errors import DimensionError, MissingExtraError, UnsupportedError
from ..model.paramset import Box
from ..model.perturbation import SymbolicPerturbation, numpy_ready
from ._kernel_template import CORE
from .discretize import IMPLICITNESS
from .kernel_cache import load_module
from .observer import ModifiedHighGainObserver, ObserverResult
from .plan import StepPlan
from .step import DIVERGENCE_BOUND, divergence_error
from .theta_star import ThetaStar
from .update_laws import (FAR, ConstantLaw, GradientInversion, IntermittentInversion, SmoothRamp,
                          invalid_theta_star_error)

__all__ = ["CompiledObserver", "KernelParts", "compile_observer", "kernel_parts"]

FloatArray = NDArray[np.float64]

#: The samples given to ``CompiledObserver.run`` must be spaced by dt to this relative accuracy.
#: A uniform grid ``np.arange(N) * dt`` has spacings off by up to ~1e-12 relative (rounding);
#: the kernel uses Φ₁(dt) for every step, and each step's own spacing in the update law and
#: the ∂g/∂θ term, as the Python ``run`` does. 1e-9 changes Φ₁ by far less than the 1e-9
#: agreement promised between the two paths.
DT_RTOL = 1e-9

_SUPPORTED = ("supported: a SymbolicPerturbation g, a Box Θ with diagonal Γ, ConstantLaw, "
              "IntermittentInversion (l ≡ 1, i.e. AlgebraicInversion, or a smooth_ramp weight) "
              "with a ThetaStar θ*, GradientInversion with the default M, no saturation, no law "
              "state, an optional SecondObserver, fixed dt and zero-order hold")


def _require_numba() -> Any:
    try:
        import numba
    except ImportError as exc:  # pragma: no cover - exercised only without numba
        raise MissingExtraError("compile_observer needs numba, the optional extra 'speed': "
                          "pip install 'thetahat[speed]'. Without it, use the observer's own "
                          "run/step, or thetahat.estimation.batch_run.run_batch for many "
                          "runs.") from exc
    return numba


# --------------------------------------------------------------------------- code generation
class _Printer(PythonCodePrinter):
    """Python printer for numba: ``math`` functions, and no partially printed code."""

    def __init__(self) -> None:
        try:
            super().__init__({"fully_qualified_modules": True, "strict": True})
        except TypeError:               # SymPy < 1.13 has no "strict": checked in doprint
            super().__init__({"fully_qualified_modules": True})

    def doprint(self, expr: Any, assign_to: Any = None) -> str:
        """Code for ``expr``; raises instead of printing a "not supported" comment."""
        code = super().doprint(expr, assign_to)
        if "Not supported" in code:
            raise UnsupportedError(f"SymPy cannot print {expr} as Python code: {code}")
        return code


def _scalar_function(name: str, params: str, inputs: Sequence[tuple[str, Sequence[sp.Symbol]]],
                     outputs: Sequence[tuple[str, sp.Matrix]]) -> str:
    """Source of ``def name(params)`` computing the entries of ``outputs`` from ``inputs``.

    ``inputs`` pairs an element template such as ``"w[o_v + {}]"`` with the symbols stored
    at its positions 0, 1, …; ``outputs`` pairs a template with a matrix whose entries are
    written at the row-major positions. Common subexpressions are computed once.
    """
    subs: dict[sp.Symbol, sp.Symbol] = {}
    lines = ["@njit(cache=True, error_model='numpy')", f"def {name}({params}):"]
    for template, symbols in inputs:
        for i, s in enumerate(symbols):
            local = sp.Symbol(f"_s{len(subs)}")
            subs[s] = local
            lines.append(f"    {local} = {template.format(i)}")
    flat, targets = [], []
    for template, M in outputs:
        for i in range(M.rows):
            for j in range(M.cols):
                flat.append(numpy_ready(sp.sympify(M[i, j])).xreplace(subs))
                targets.append(template.format(i * M.cols + j))
    replacements, reduced = sp.cse(flat, symbols=sp.numbered_symbols("_c"))
    printer = _Printer()
    try:
        for sym, e in replacements:
            lines.append(f"    {sym} = {printer.doprint(e)}")
        for target, e in zip(targets, reduced):
            lines.append(f"    {target} = {printer.doprint(e)}")
    except Exception as exc:  # SymPy's printer raises several types
        raise UnsupportedError(f"compile_observer cannot print {name[1:]} as numba code "
                                  f"({exc}); rewrite it with elementary functions or use the "
                                  "Python observer.") from exc
    lines.append("    return 0")
    return "\n".join(lines) + "\n"


def _model_source(pert: SymbolicPerturbation, theta_star: tuple[sp.Expr, ...] | None,
                  ts_args: tuple[sp.Symbol, ...] | None) -> str:
    """The model functions: g, (g, ∂g/∂x), ∂g/∂θ, ∂g/∂v and θ* as scalar code.

    Each reads v from the work vector w at ``o_v``, x and θ from row ``i`` of a state array S
    at ``o_x`` and ``o_t``, and writes its outputs into w at the given offsets.
    """
    n, m, r, _, _ = pert.dims
    params = "w, S, i, o_v, o_x, o_t"
    ins = [("w[o_v + {}]", (*pert.u, *pert.y)), ("S[i, o_x + {}]", pert.x),
           ("S[i, o_t + {}]", pert.theta)]
    g = sp.Matrix(pert.expr)
    parts = [
        _scalar_function("_g", params + ", o_g", ins, [("w[o_g + {}]", g)]),
        _scalar_function("_g_dx", params + ", o_g, o_gx", ins,
                         [("w[o_g + {}]", g), ("w[o_gx + {}]", pert.jacobian("x"))]),
        _scalar_function("_dg_dtheta", params + ", o_gt", ins,
                         [("w[o_gt + {}]", pert.jacobian("theta"))]),
        _scalar_function("_dg_dv", params + ", o_gv", ins,
                         [("w[o_gv + {}]", pert.jacobian("v"))]),
    ]
    ts_params = "w, S, i, o_v, o_x, o_phi, o_out"
    if theta_star is None:
        parts.append("@njit(cache=True, error_model='numpy')\n"
                     f"def _theta_star({ts_params}):\n"
                     "    for j in range(NP):\n        w[o_out + j] = math.nan\n"
                     "    return 0\n")
    else:
        ts_args = ts_args or ()
        ins = [("w[o_v + {}]", ts_args[:m + r]), ("S[i, o_x + {}]", ts_args[m + r:m + r + n]),
               ("w[o_phi + {}]", ts_args[m + r + n:])]
        parts.append(_scalar_function("_theta_star", ts_params, ins,
                                      [("w[o_out + {}]", sp.Matrix(theta_star))]))
    return "\n\n".join(parts)


Layout = dict[str, tuple[int, tuple[int, ...]]]


def _layout(blocks: Sequence[tuple[str, tuple[int, ...]]]) -> tuple[Layout, int]:
    """Offsets of named blocks packed one after the other into a flat vector."""
    out: Layout = {}
    offset = 0
    for name, shape in blocks:
        out[name] = (offset, shape)
        offset += int(np.prod(shape, dtype=np.int64))
    return out, offset


def _layouts(n: int, m: int, r: int, k: int, p: int) -> tuple[Layout, int, Layout, int]:
    """Layouts of the constants vector P and of the work vector w."""
    nz, nv = n + k, m + r
    consts, P_size = _layout([
        ("L", (nz, nz)), ("Bv", (nz, nv)), ("KxC", (n, n)), ("Kx", (n, r)), ("C", (r, n)),
        ("E", (n, k)), ("Phi1", (nz, nz)), ("A", (n, n)), ("Bm", (n, m)), ("K2", (n, r)),
        ("Phi12", (n, n)), ("lower", (p,)), ("upper", (p,)), ("Gam", (p, p)), ("ramp", (2,)),
        ("flags", (4,))])
    work, W_size = _layout([
        ("v", (nv,)), ("g", (k,)), ("Gx", (k, n)), ("Gth", (k, p)), ("Gv", (k, nv)),
        ("F", (nz,)), ("Nm", (nz, nz)), ("M", (nz, nz)), ("rhs", (nz,)), ("phi", (k,)),
        ("thn", (p,)), ("dth", (p,)), ("innov", (r,)), ("kin", (n,)), ("ts", (p,)),
        ("resid", (k,)), ("GM", (p, k)), ("fvec", (p,)), ("Kmat", (p, p)),
        ("Zm", (p + 1, p + 1)), ("Ex", (p + 1, p + 1)), ("T1", (p + 1, p + 1)),
        ("T2", (p + 1, p + 1)), ("v2", (nv,)), ("yhat", (r,)), ("g2", (k,)),
        ("Gx2", (k, n)), ("Gv2", (k, nv)), ("F2", (n,)), ("N2", (n, n)), ("M2", (n, n)),
        ("rhs2", (n,)), ("inn2", (r,))])
    return consts, P_size, work, W_size


def _expand(template: str, layouts: Sequence[tuple[str, str, Layout]],
            state: dict[str, str]) -> str:
    """Rewrite ``Name[i]`` / ``Name[i, j]`` of the named blocks into flat indexing.

    A block of the constants (``"P"``) or work (``"w"``) vector becomes
    ``P[P_Name + (i) * cols + (j)]``; a part of the state (``state`` maps its name to an offset
    expression) becomes ``Sin[iin, offset + (i)]``. Numba then indexes one flat array instead
    of creating array views, which cost reference counting on every sample.
    """
    rules: dict[str, Any] = {}
    for array, prefix, layout in layouts:
        for name, (_, shape) in layout.items():
            rules[name] = (array, f"{prefix}_{name}", shape)
    names = sorted({*rules, *state}, key=len, reverse=True)
    pattern = re.compile(r"(?<![\w.])(" + "|".join(map(re.escape, names)) + r")\[")
    out, pos = [], 0
    for match in pattern.finditer(template):
        if match.start() < pos:
            continue
        depth, end = 1, match.end()
        while depth:
            depth += {"[": 1, "]": -1}.get(template[end], 0)
            end += 1
        index = [part.strip() for part in _split_index(template[match.end():end - 1])]
        name = match.group(1)
        if name in state:
            text = f"Sin[iin, {state[name]} + ({index[0]})]"
        else:
            array, offset, shape = rules[name]
            flat = (f"({index[0]})" if len(shape) == 1
                    else f"({index[0]}) * {shape[1]} + ({index[1]})")
            text = f"{array}[{offset} + {flat}]"
        out.append(template[pos:match.start()] + text)
        pos = end
    out.append(template[pos:])
    return "".join(out)


def _split_index(text: str) -> list[str]:
    """Split an index expression at its top-level commas."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += {"[": 1, "(": 1, "]": -1, ")": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return parts



def _kernel_source(pert: SymbolicPerturbation, theta_star: tuple[sp.Expr, ...] | None,
                   ts_args: tuple[sp.Symbol, ...] | None) -> str:
    """The complete source of the kernel module of one model and configuration."""
    n, m, r, p, k = pert.dims
    consts, P_size, work, W_size = _layouts(n, m, r, k, p)
    header = [
        '"""Generated by thetahat.estimation.compiled; do not edit (content-addressed)."""',
        "import math", "import numpy as np", "from numba import njit", "",
        f"NX, NU, NY, NK, NP = {n}, {m}, {r}, {k}, {p}",
        "NZ, NV = NX + NK, NU + NY",
        f"IMPLICITNESS = {IMPLICITNESS!r}", f"FAR = {FAR!r}",
        f"BOUND_SQ = {DIVERGENCE_BOUND ** 2!r}",
        f"P_SIZE = {P_size}", f"W_SIZE = {W_size}"]
    header += [f"P_{name} = {off}" for name, (off, _) in consts.items()]
    header += [f"W_{name} = {off}" for name, (off, _) in work.items()]
    core = _expand(CORE, [("P", "P", consts), ("w", "W", work)],
                   {"x": "0", "z": "NX", "th": "NZ", "x2": "NZ + NP"})
    return "\n".join(header) + "\n\n\n" + _model_source(pert, theta_star, ts_args) + core


def _load(source: str) -> ModuleType:
    """Import the generated module (written once under its content hash, then cached)."""
    _require_numba()
    return load_module(source, "thetahat_kernel")


# --------------------------------------------------------------------------- support checks
def _unsupported(what: str) -> UnsupportedError:
    return UnsupportedError(f"compile_observer: {what} is not supported by the compiled path "
                               f"({_SUPPORTED}); use the Python observer (run/step) or "
                               "run_batch.")


def _diagonal_gain(law: Any) -> FloatArray:
    G = np.asarray(law.Gamma, dtype=np.float64)
    if not np.array_equal(G, np.diag(np.diag(G))):
        raise _unsupported("a non-diagonal Γ (its Γ⁻¹-weighted projection onto a box is a "
                           "least-squares problem)")
    return G


@dataclass(frozen=True, slots=True)
class KernelParts:
    """What the kernel takes from an observer, checked (see :func:`kernel_parts`).

    Attributes
    ----------
    code : int
        0 ConstantLaw, 1 IntermittentInversion with l ≡ 1, 2 with a smooth ramp, 3 gradient.
    perturbation : SymbolicPerturbation
        g, printed into the kernel.
    box : Box
        Θ.
    theta_star : ThetaStar or None
        θ* of the inversion laws.
    ramp : tuple of float or None
        (low, high) of the smooth ramp l (code 2).
    freeze : bool
        The inversion law's ``on_invalid == "freeze"``.
    """

    code: int
    perturbation: SymbolicPerturbation
    box: Box
    theta_star: ThetaStar | None = None
    ramp: tuple[float, float] | None = None
    freeze: bool = False


def kernel_parts(observer: ModifiedHighGainObserver) -> KernelParts:
    """Check that the kernel supports the observer's parts, and collect them.

    Parameters
    ----------
    observer : ModifiedHighGainObserver

    Returns
    -------
    KernelParts

    Raises
    ------
    UnsupportedError
        A part the kernel does not support (the message names it).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.compiled import kernel_parts
    >>> kernel_parts(lugre.observer(1.0)).code      # the intermittent law with a smooth ramp
    2
    """
    pert = observer.system.perturbation
    if not isinstance(pert, SymbolicPerturbation):
        raise _unsupported(f"a {type(pert).__name__} g (it must be a SymbolicPerturbation)")
    law = observer.update_law
    if law.state_size:
        raise _unsupported("an update law with a state")
    box = law.parameter_set
    if not isinstance(box, Box):
        raise _unsupported(f"Θ = {type(box).__name__} (it must be a Box)")
    if getattr(law, "saturation", None) is not None:
        raise _unsupported("an update law with saturation")
    if isinstance(law, ConstantLaw):
        return KernelParts(code=0, perturbation=pert, box=box)
    _diagonal_gain(law)
    if isinstance(law, GradientInversion):
        if law.M is not None:
            raise _unsupported("GradientInversion with a user M")
        if not (law.perturbation is pert or law.perturbation == pert):
            raise _unsupported("GradientInversion with a g other than the observer's")
        return KernelParts(code=3, perturbation=pert, box=box)
    if not isinstance(law, IntermittentInversion):
        raise _unsupported(f"the update law {type(law).__name__}")
    code, ramp = 1, None
    if isinstance(law.l, SmoothRamp):
        code, ramp = 2, (float(law.l.low), float(law.l.high))
    elif law.l is not None:
        raise _unsupported("an excitation weight l other than smooth_ramp(low, high)")
    ts = law.theta_star
    if isinstance(ts, ThetaStar):
        return KernelParts(code=code, perturbation=pert, box=box, theta_star=ts, ramp=ramp,
                           freeze=law.on_invalid == "freeze")
    raise UnsupportedError(
        f"compile_observer: the θ* of {type(law).__name__} is a Python callable "
        f"({type(ts).__name__}), which cannot be compiled; build the law with a ThetaStar "
        "(thetahat.estimation.theta_star.ThetaStar.from_expr(expr, perturbation=g, phi=[...]) "
        "or from_perturbation), which carries θ*'s SymPy form.")


# --------------------------------------------------------------------------- public API
def _as_input(name: str, a: Any, size: int) -> FloatArray:
    """A writable, contiguous float64 vector of length ``size`` (no copy if ``a`` is one).

    numba compiles one specialisation per array type, and read-only or strided arrays are
    other types: normalising them keeps the kernel at one compilation.
    """
    if (type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (size,)
            and a.flags.c_contiguous and a.flags.writeable):
        return a
    return np.array(as_vector(name, a, size, finite=False), dtype=np.float64, order="C")


def _kernel_array(a: FloatArray) -> FloatArray:
    """``a`` as a writable C-contiguous array (see :func:`_as_input`)."""
    if a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64, order="C")


@dataclass(frozen=True, slots=True, eq=False)
class CompiledObserver:
    """A :class:`ModifiedHighGainObserver` compiled for one step length (zero-order hold).

    ``step`` and ``run`` compute what the observer's own ``step`` and ``run(hold="zoh")``
    compute, in machine code. Build it with :func:`compile_observer`, which documents the
    parameters ``observer`` and ``dt``.

    Parameters
    ----------
    observer, dt, theta_star, phi
        As in :func:`compile_observer`.

    Attributes
    ----------
    observer : ModifiedHighGainObserver
        The observer it was compiled from (gains, law, second observer).
    dt : float
        The fixed step length (s).
    theta_star : ThetaStar or None
        The θ* compiled into the kernel, the update law's own (None for laws without θ*).
    plan : StepPlan
        The observer's plan for ``dt``, whose matrices the kernel reads.
    """

    observer: ModifiedHighGainObserver
    dt: float
    theta_star: ThetaStar | None
    plan: StepPlan
    _kernel: ModuleType
    _P: FloatArray

    def __init__(self, observer: ModifiedHighGainObserver, *, dt: float) -> None:
        _require_numba()
        if not isinstance(observer, ModifiedHighGainObserver):
            raise _unsupported(f"a {type(observer).__name__} (it must be a "
                               "ModifiedHighGainObserver)")
        h = positive_scalar("dt", dt)
        parts = kernel_parts(observer)
        ts = parts.theta_star
        plan = observer.plan(h)
        source = _kernel_source(parts.perturbation,
                                None if ts is None else ts.expr,
                                None if ts is None else ts.arguments)
        for name, value in (("observer", observer), ("dt", h), ("theta_star", ts),
                            ("plan", plan), ("_kernel", _load(source)),
                            ("_P", _constants(parts, plan))):
            object.__setattr__(self, name, value)

    @property
    def state_size(self) -> int:
        """Length of the state vector (as :attr:`ModifiedHighGainObserver.state_size`)."""
        return self.observer.state_size

    def init(self, x_hat0: Any = None, theta_hat0: Any = None, z0: Any = None, *,
             x_hat_refined0: Any = None) -> FloatArray:
        """Initial state; see :meth:`ModifiedHighGainObserver.init` (same parameters).

        Parameters
        ----------
        x_hat0, theta_hat0, z0, x_hat_refined0
            As for :meth:`ModifiedHighGainObserver.init`.

        Returns
        -------
        ndarray, shape (state_size,)
        """
        return self.observer.init(x_hat0, theta_hat0, z0, x_hat_refined0=x_hat_refined0)

    def _raise(self, status: int, where: str) -> NoReturn:
        if status == 2:
            raise invalid_theta_star_error(type(self.observer.update_law).__name__, 1)
        raise divergence_error(where)

    def step(self, state: Any, u: Any, y: Any) -> FloatArray:
        """Advance the state by ``dt`` holding the samples (as the observer's ``step``).

        Parameters
        ----------
        state : array_like, shape (state_size,)
        u : array_like, shape (m,)
            Current input sample (``None`` when m = 0).
        y : array_like, shape (r,)
            Current output sample (finite: the compiled path does not skip missing samples).

        Returns
        -------
        ndarray, shape (state_size,)

        Raises
        ------
        DimensionError
            Wrong shapes.
        NonFiniteError
            NaN or inf in the state, u or y, or the step diverged.
        UpdateLawError
            θ* invalid where l > 0 and ``on_invalid='raise'``.
        """
        obs = self.observer
        lay = obs.layout
        s = _as_input("state", state, lay.size)
        out = np.empty(lay.size)
        status = self._kernel.step(s, _as_input("u", np.empty(0) if u is None else u, lay.m),
                                   _as_input("y", y, lay.r), self.dt, self._P, out)
        if status == 0 and float(out @ out) <= DIVERGENCE_BOUND ** 2:
            return out
        # something is wrong: find out what, with the observer's own checks and messages
        obs.check_state(state)
        if not obs.check_samples(u, y)[2]:
            raise _no_prediction()
        self._raise(int(status) or 1, "in this step")

    def run(self, t: Any, u: Any, y: Any, *, state0: Any = None) -> ObserverResult:
        """Run over sampled records spaced by ``dt`` (the loop runs in machine code).

        Parameters
        ----------
        t : array_like, shape (N,)
            Sampling instants spaced by ``dt`` (to a relative ``DT_RTOL`` = 1e-9).
        u : array_like, shape (N, m) or (N,) when m = 1
            Input samples (``None`` when m = 0).
        y : array_like, shape (N, r) or (N,) when r = 1
            Output samples, finite.
        state0 : array_like, shape (state_size,), optional
            Initial state; default ``init()``.

        Returns
        -------
        ObserverResult
            As :meth:`ModifiedHighGainObserver.run` with ``hold="zoh"`` (agreement to rounding;
            see :func:`compile_observer`).

        Raises
        ------
        DimensionError
            Wrong shapes, or t not spaced by dt.
        NonFiniteError
            NaN or inf in t, u or y, or the state diverged.
        UpdateLawError
            θ* invalid where l > 0 and ``on_invalid='raise'``.
        """
        obs = self.observer
        lay = obs.layout
        t_, dts, U3, Y3, ok = obs.check_records(t, u, y)
        N = t_.shape[0]
        if N > 1 and not np.all(np.abs(dts - self.dt) <= DT_RTOL * self.dt):
            raise DimensionError(f"the compiled observer steps dt = {self.dt!r}; t has spacings "
                                 f"in [{float(dts.min())!r}, {float(dts.max())!r}]. Resample, "
                                 "or compile again with compile_observer(observer, dt=...).")
        if not ok.all():
            raise _no_prediction()
        U, Y, dts = (_kernel_array(a) for a in (U3[0], Y3[0], dts))
        s0 = _kernel_array(obs.init() if state0 is None else obs.check_state(state0))
        S = np.empty((N, lay.size))
        PHI = np.empty((N, lay.k))
        status, index = self._kernel.run(s0, U, Y, dts, self._P, S, PHI)
        if status:
            i = int(index)
            self._raise(int(status), f"in the step from t[{i}] = {t_[i]!r}")
        def frozen(a: NDArray[Any]) -> NDArray[Any]:
            out = np.array(a, copy=True)
            out.setflags(write=False)
            return out

        return ObserverResult(t=frozen(t_), x_hat=frozen(S[:, lay.x]), phi_hat=frozen(PHI),
                              theta_hat=frozen(S[:, lay.theta]),
                              x_hat_refined=frozen(S[:, lay.x2]) if lay.second else None,
                              skipped=frozen(np.zeros(N, dtype=bool)))

    def __repr__(self) -> str:
        return (f"CompiledObserver(dt={self.dt!r}, observer={self.observer!r}, "
                f"kernel={self._kernel.__name__})")


def _no_prediction() -> UnsupportedError:
    return UnsupportedError("y contains NaN (nan_policy='skip'); the compiled observer does "
                               "not predict over missing samples: use the observer's own "
                               "step/run or run_batch.")


def _constants(parts: KernelParts, plan: StepPlan) -> FloatArray:
    """The constants vector P from the plan: matrices, φ-matrices, Θ, Γ, ramp and the flags."""
    lay = plan.layout
    consts, P_size, _, _ = _layouts(lay.n, lay.m, lay.r, lay.k, lay.p)
    second = plan.second
    values = {"L": plan.L[0], "Bv": plan.Bv[0], "KxC": plan.KxC[0], "Kx": plan.K_x[0],
              "C": plan.C, "E": plan.E, "Phi1": plan.Phi1[0], "A": plan.A,
              "Bm": plan.B, "lower": parts.box.lower, "upper": parts.box.upper,
              "Gam": np.eye(lay.p) if plan.Gamma is None else plan.Gamma[0]}
    if second is not None:
        values["K2"] = second.K_x[0]
        values["Phi12"] = second.Phi1[0]
    if parts.ramp is not None:
        values["ramp"] = np.array(parts.ramp)
    values["flags"] = np.array([parts.code, parts.freeze, second is not None,
                                second is not None and second.g_on_estimates], dtype=np.float64)
    P = np.zeros(P_size)
    for name, (off, shape) in consts.items():
        if name in values:
            P[off:off + int(np.prod(shape, dtype=np.int64))] = np.asarray(
                values[name], dtype=np.float64).reshape(shape).ravel()
    P.setflags(write=False)
    return P


def compile_observer(observer: ModifiedHighGainObserver, *, dt: float) -> CompiledObserver:
    """Compile an observer's step for a fixed ``dt`` with numba (the optional extra ``speed``).

    Parameters
    ----------
    observer : ModifiedHighGainObserver
        Observer (3) with update law (8) and optionally a second observer (Sec. VI); its parts
        must be of the supported kinds (see the module docstring). A law with a θ* needs a
        :class:`~thetahat.estimation.theta_star.ThetaStar` (it carries the SymPy form).
    dt : float
        The step length (s) > 0; ``run`` checks that its t is spaced by it.

    Returns
    -------
    CompiledObserver

    Raises
    ------
    ImportError
        numba is missing: ``pip install 'thetahat[speed]'``.
    NotImplementedError
        A part of the observer is not supported by the compiled path (the message names it).

    Notes
    -----
    The kernel reads the observer's :class:`~thetahat.estimation.plan.StepPlan` for ``dt`` and
    performs the step of :mod:`thetahat.estimation.step` with the same operations in the same
    order, except for the summation order of the small matrix products, a hand-written pivoted
    LU in place of LAPACK's, and scalar code for g, its Jacobians and θ* (printed from the same
    SymPy expressions the Python path lambdifies). It applies the same divergence rule
    (:data:`~thetahat.estimation.step.DIVERGENCE_BOUND`) and raises the same errors. Measured
    on a shared 2-core machine: 0.25 µs per sample inside ``run``, a few µs per call of
    ``step`` from Python (validation and dispatch dominate). The first compilation of a model
    takes a few seconds; later ones load from the cache.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.compiled import compile_observer
    >>> data = lugre.simulate(seed=0, t_end=0.5)
    >>> obs = lugre.observer()
    >>> try:
    ...     fast = compile_observer(obs, dt=1e-3)
    ... except ImportError:                  # numba missing: pip install 'thetahat[speed]'
    ...     fast = None
    >>> res = obs.run(data.t, data.u, data.y)
    >>> res_fast = res if fast is None else fast.run(data.t, data.u, data.y)
    >>> bool(np.allclose(res_fast.theta_hat, res.theta_hat, rtol=1e-9, atol=0))
    True
    """
    return CompiledObserver(observer, dt=dt)
