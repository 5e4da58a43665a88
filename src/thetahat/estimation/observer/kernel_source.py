"""The scalar back end: the step's formulas emitted, with scalar primitives, as a numba module.

:func:`kernel_source` writes one module per model and configuration: the source of the
formulas of :mod:`~thetahat.estimation.observer.formulas` and
:mod:`~thetahat.estimation.observer.laws.formulas` exactly as written there (``inspect.getsource``), the
scalar primitives of :mod:`~thetahat.estimation.kernels.scalar_primitives` under their primitive
names, the model functions g, ∂g/∂x, ∂g/∂y, ∂g/∂θ and θ* printed from their SymPy expressions
(with common subexpressions computed once), the law's hooks (its weight, the projection onto
Θ: a clip for a box with a diagonal Γ, the Γ⁻¹-weighted projection of
:mod:`~thetahat.estimation.kernels.set_projection` for a ball or an ellipsoid) and the dimensions as constants. Every function is
``numba.njit``-compiled with ``cache=True`` and inlined into the loops
(:func:`~thetahat.estimation.kernels.scalar_primitives.kernel_run`), so that the compiled step is the
formulas' step, specialised to one row. :mod:`~thetahat.estimation.observer.compiled` loads the
module through :func:`~thetahat.estimation.kernels.kernel_cache.load_module`.
"""

from __future__ import annotations

import ast
import copy as copy_module
import inspect
import re
import textwrap
from collections.abc import Sequence
from typing import Any

import sympy as sp
from sympy.printing.pycode import PythonCodePrinter

from ...errors import UnsupportedError
from ...model.perturbation import SymbolicPerturbation, numpy_ready
from . import formulas
from .laws import formulas as law_formulas
from ..kernels import scalar_primitives
from .discretize import IMPLICITNESS
from .formulas import DIVERGENCE_BOUND
from .laws.base import FAR
from ..kernels.kernel_cache import kernel_module_source
from ..kernels.primitives import check_aliasing
from ..kernels.set_projection import OBSERVER_MARGIN, project_into
from ..status import status_constants

__all__ = ["INLINE_FROM", "LAWS", "formula_decorator", "kernel_source", "law_source",
           "model_source", "rewritten"]

#: The law formulas the compiled path supports, by code (see ``compiled.KernelParts``).
LAWS = {0: "held_law", 1: "inversion_law", 2: "inversion_law", 3: "gradient_law"}

#: numba options. ``_nrt=False``: no reference counting (the kernels allocate nothing; the
#: counting of ~30 array variables per sample took 40 % of the time). The primitives are written
#: into the formulas as syntax (:class:`_Syntax`); the model functions and the few expression
#: primitives left (exp, norm, sumsq) stay calls (inlining them too tripled the compile time
#: and gained nothing measurable).
_INLINE = "@njit(cache=True, error_model='numpy', _nrt=False)"

#: numba from which the formulas are inlined into the loop (:func:`formula_decorator`).
INLINE_FROM = (0, 61)


def formula_decorator(version: str) -> str:
    """The decorator of the formulas for a numba version: inlined into the loop from
    :data:`INLINE_FROM` on, separate functions before.

    Inlined, the kernel is faster and takes longer to compile: the DC motor's kernel, measured
    in one run on a loaded 2-core machine with numba 0.68.1, compiles in 56 s and runs 0.33 µs
    a sample inlined, 21 s and 1.9 µs a sample as separate functions (earlier measurements:
    20–40 s inlined with 0.61.2 and 0.68.1). The first compilation happens once per machine
    (the cache), the per-sample cost at every run, so the formulas are inlined. numba 0.58.1
    had not finished inlining after 17 min and 7.7 GB, and compiles the separate functions in
    ≈ 12 s; 0.59–0.60 were not tried: they get the separate functions.

    Parameters
    ----------
    version : str
        ``numba.__version__``.

    Returns
    -------
    str

    Examples
    --------
    >>> "inline='always'" in formula_decorator("0.68.1"), "inline" in formula_decorator("0.58.1")
    (True, False)
    """
    parts = tuple(int(p) for p in re.findall(r"\d+", version)[:2])
    if parts >= INLINE_FROM:
        return "@njit(cache=True, error_model='numpy', inline='always', _nrt=False)"
    return _INLINE

class _Printer(PythonCodePrinter):
    """Python printer for numba: ``math`` functions (exp: the primitive), and no partially
    printed code."""

    def __init__(self) -> None:
        try:
            super().__init__({"fully_qualified_modules": True, "strict": True})
        except TypeError:               # SymPy < 1.13 has no "strict": checked in doprint
            super().__init__({"fully_qualified_modules": True})

    def _print_exp(self, expr: Any) -> str:
        """``exp(a)``: the scalar primitive (``math.exp`` without libm's underflow path)."""
        return f"exp({self._print(expr.args[0])})"

    def doprint(self, expr: Any, assign_to: Any = None) -> str:
        """Code for ``expr``; raises instead of printing a "not supported" comment."""
        code = super().doprint(expr, assign_to)
        if "Not supported" in code:
            raise UnsupportedError(f"SymPy cannot print {expr} as Python code: {code}")
        return code


def _function(name: str, params: str, inputs: Sequence[tuple[str, Sequence[sp.Symbol]]],
              outputs: Sequence[tuple[str, sp.Matrix, bool]]) -> str:
    """Source of ``def name(params)`` computing ``outputs`` from ``inputs`` (one row).

    ``inputs`` pairs an element template such as ``"x[xo + {}]"`` with the symbols at its
    positions 0, 1, …; ``outputs`` holds (array, matrix, is a vector): entries are written as
    ``array[i]`` or ``array[i, j]``. Common subexpressions are computed once.
    """
    subs: dict[sp.Symbol, sp.Symbol] = {}
    lines = [_INLINE, f"def {name}({params}):"]
    for template, symbols in inputs:
        for i, s in enumerate(symbols):
            local = sp.Symbol(f"_s{len(subs)}")
            subs[s] = local
            lines.append(f"    {local} = {template.format(i)}")
    flat, targets = [], []
    for array, M, vector in outputs:
        for i in range(M.rows):
            for j in range(M.cols):
                flat.append(numpy_ready(sp.sympify(M[i, j])).xreplace(subs))
                targets.append(f"{array}[{i}]" if vector else f"{array}[{i}, {j}]")
    replacements, reduced = sp.cse(flat, symbols=sp.numbered_symbols("_c"))
    printer = _Printer()
    try:
        for sym, e in replacements:
            lines.append(f"    {sym} = {printer.doprint(e)}")
        for target, e in zip(targets, reduced):
            lines.append(f"    {target} = {printer.doprint(e)}")
    except Exception as exc:  # SymPy's printer raises several types
        raise UnsupportedError(f"compile_observer cannot print {name} as numba code ({exc}); "
                               "rewrite it with elementary functions or use the Python "
                               "observer.") from exc
    lines.append("    return 0")
    return "\n".join(lines) + "\n"


def _model_inputs(pert: SymbolicPerturbation) -> list[tuple[str, Sequence[sp.Symbol]]]:
    """Where the model functions read g's symbols: v = col(u, y), x̂ = x[xo:], θ̂ = th[to:]."""
    return [("v[{}]", (*pert.u, *pert.y)), ("x[xo + {}]", pert.x), ("th[to + {}]", pert.theta)]


def model_source(pert: SymbolicPerturbation, theta_star: tuple[sp.Expr, ...] | None,
                 ts_args: tuple[sp.Symbol, ...] | None) -> str:
    """The model functions of the formulas as scalar code: g_dx, g_val, dg_dy, dg_dtheta, θ*.

    Parameters
    ----------
    pert : SymbolicPerturbation
    theta_star : tuple of sympy.Expr or None
        θ* of an inversion law.
    ts_args : tuple of sympy.Symbol or None
        Its arguments (v, x, φ).

    Returns
    -------
    str
        Source with the signatures of :mod:`~thetahat.estimation.observer.formulas` and
        :mod:`~thetahat.estimation.observer.laws.formulas` (``theta_star(v, x, xo, phi, ts)``).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> src = model_source(lugre.perturbation(), None, None)
    >>> "def g_dx(v, x, xo, th, to, g, Gx):" in src
    True
    """
    n, m, r, _, _ = pert.dims
    params = "v, x, xo, th, to"
    ins = _model_inputs(pert)
    g = sp.Matrix(pert.expr)
    Gv = pert.jacobian("v")
    parts = [
        _function("g_val", params + ", g", ins, [("g", g, True)]),
        _function("g_dx", params + ", g, Gx", ins,
                  [("g", g, True), ("Gx", pert.jacobian("x"), False)]),
        _function("dg_dtheta", params + ", Gth", ins,
                  [("Gth", pert.jacobian("theta"), False)]),
        _function("dg_dy", params + ", Gy", ins, [("Gy", Gv[:, m:m + r], False)]),
    ]
    ts_params = "v, x, xo, phi, ts"
    if theta_star is None:
        parts.append(f"{_INLINE}\ndef theta_star({ts_params}):\n"
                     "    for j in range(NP):\n        ts[j] = math.nan\n    return 0\n")
    else:
        a = ts_args or ()
        ins = [("v[{}]", a[:m + r]), ("x[xo + {}]", a[m + r:m + r + n]),
               ("phi[{}]", a[m + r + n:])]
        parts.append(_function("theta_star", ts_params, ins,
                               [("ts", sp.Matrix(theta_star), True)]))
    return "\n\n".join(parts)


#: Block primitives expanded in place where a formula calls them as a statement (then the
#: dimensions are constants there and the loops unroll); ``expm`` (the gradient law's, once
#: per sample) stays a call: expanding it costs ~15 s of compile time for no measurable gain;
#: ``solve`` stays a call because it returns a status (a zero pivot is ``ST_SINGULAR``).
_EXPANDED = ("copy", "axpy", "fill", "mv", "mm", "mmt", "eye_minus")


def _body(name: str) -> tuple[list[str], list[ast.stmt]]:
    """Parameters and body statements of a scalar primitive (docstring dropped)."""
    fn = ast.parse(textwrap.dedent(inspect.getsource(
        scalar_primitives.SCALAR_PRIMITIVES[name]))).body[0]
    assert isinstance(fn, ast.FunctionDef)
    body = [st for st in fn.body
            if not (isinstance(st, ast.Expr) and isinstance(st.value, ast.Constant))]
    return [a.arg for a in fn.args.args], body


class _Substitute(ast.NodeTransformer):
    """Parameters → argument expressions, locals → fresh names (one expansion)."""

    def __init__(self, args: dict[str, ast.expr], suffix: str) -> None:
        self.args, self.suffix = args, suffix

    def visit_Name(self, node: ast.Name) -> Any:
        if node.id in self.args:
            if not isinstance(node.ctx, ast.Load):
                raise UnsupportedError(f"scalar primitive assigns its parameter {node.id}")
            return copy_module.deepcopy(self.args[node.id])
        if node.id in _GLOBAL_NAMES:
            return node
        return ast.Name(f"{node.id}{self.suffix}", node.ctx)


#: Names a primitive's body may use that are not its locals.
_GLOBAL_NAMES = frozenset({"range", "abs", "min", "max", "math", "True", "False", "None"})


def _expand(name: str, args: Sequence[ast.expr], count: int) -> list[ast.stmt]:
    """The statements of primitive ``name`` applied to ``args`` (its locals renamed apart)."""
    params, body = _body(name)
    sub = _Substitute(dict(zip(params, args)), f"__{name}{count}")
    return [sub.visit(copy_module.deepcopy(st)) for st in body]


class _Syntax(ast.NodeTransformer):
    """The primitives of one row written into the formula (their scalar definitions inlined).

    Element primitives become syntax: ``get(a, i)`` → ``a[i]``, ``put(a, i, v)`` →
    ``a[i] = v``, ``where(c, a, b)`` → ``a if c else b``, ``clip(a, lo, hi)`` →
    ``min(max(a, lo), hi)``, … exactly what :mod:`~thetahat.estimation.kernels.scalar_primitives`
    defines them as. The block primitives used as statements (``mv``, ``mm``, ``solve``, …) are
    expanded in place: their body, with the arguments substituted for the parameters and
    their locals renamed apart (:func:`_expand`). The compiled step then has no call per
    primitive, and numba need not inline them (which multiplies the compile time).
    """

    def __init__(self) -> None:
        self.expansions = 0

    def visit_Expr(self, node: ast.Expr) -> Any:
        self.generic_visit(node)
        call = node.value
        if isinstance(call, ast.Call) and isinstance(call.func, ast.Name):
            name, args = call.func.id, call.args
            if name in _EXPANDED:
                self.expansions += 1
                return _expand(name, args, self.expansions)
            if name == "put":
                return ast.Assign(targets=[ast.Subscript(args[0], args[1], ast.Store())],
                                  value=args[2], lineno=node.lineno)
            if name == "put2":
                index = ast.Tuple([args[1], args[2]], ast.Load())
                return ast.Assign(targets=[ast.Subscript(args[0], index, ast.Store())],
                                  value=args[3], lineno=node.lineno)
        return node

    def visit_Call(self, node: ast.Call) -> Any:
        self.generic_visit(node)
        if not isinstance(node.func, ast.Name):
            return node
        name, a = node.func.id, node.args
        if name == "get":
            return ast.Subscript(a[0], a[1], ast.Load())
        if name == "get2":
            return ast.Subscript(a[0], ast.Tuple([a[1], a[2]], ast.Load()), ast.Load())
        if name == "where":
            return ast.IfExp(a[0], a[1], a[2])
        if name == "clip":
            return _call("min", _call("max", a[0], a[1]), a[2])
        if name in ("maximum", "absolute"):
            return _call({"maximum": "max", "absolute": "abs"}[name], *a)
        if name in ("sqrt", "isfinite"):
            return ast.Call(ast.Attribute(ast.Name("math", ast.Load()), name, ast.Load()),
                            list(a), [])
        if name == "not_":
            return ast.UnaryOp(ast.Not(), a[0])
        if name in ("and_", "or_"):
            return ast.BoolOp(ast.And() if name == "and_" else ast.Or(), list(a))
        if name == "any_":
            return a[0]
        if name == "count_":
            return ast.IfExp(a[0], ast.Constant(1), ast.Constant(0))
        return node


def _call(name: str, *args: ast.expr) -> ast.Call:
    return ast.Call(ast.Name(name, ast.Load()), list(args), [])


def rewritten(fn: Any) -> ast.Module:
    """A formula's (or scalar primitive's) source as the scalar back end emits it: the element
    primitives as syntax, the block primitives expanded in place (:class:`_Syntax`).

    The other printers of the formulas (the C of :mod:`thetahat.codegen`) start from this tree.

    Parameters
    ----------
    fn : function
        A function of :mod:`~thetahat.estimation.observer.formulas`,
        :mod:`~thetahat.estimation.observer.laws.formulas` or
        :mod:`~thetahat.estimation.kernels.scalar_primitives`.

    Returns
    -------
    ast.Module
        Holding the one function definition.

    Examples
    --------
    >>> import ast
    >>> ast.unparse(rewritten(formulas.phi_hat)).splitlines()[-1].strip()
    'phi[0 + i__axpy2] += 1.0 * s[NX + i__axpy2]'
    """
    tree = ast.parse(textwrap.dedent(inspect.getsource(fn)))
    return ast.fix_missing_locations(_Syntax().visit(tree))


def _source(fn: Any, name: str | None = None, decorator: str = _INLINE) -> str:
    """A function's source at module level, decorated, optionally renamed, with the element
    primitives as syntax (:class:`_Syntax`)."""
    text = ast.unparse(rewritten(fn))
    if name is not None and name != fn.__name__:
        text = text.replace(f"def {fn.__name__}(", f"def {name}(", 1)
    return f"{decorator}\n{text}\n"


def law_source(law: str, form: str, user_m: bool = False,
               ellipsoid: str | None = None) -> str:
    """law_step and the hooks weight, freeze, project (and a stub m_matrix without a user's
    M) for one law formula.

    Parameters
    ----------
    law : str
        A value of :data:`LAWS`.
    form : str
        The decorator line of each hook (empty for plain Python).
    user_m : bool
        The kernel has a user's M (m_matrix printed from its SymPy form); else a stub.
    ellipsoid : str, optional
        Θ is a ball or an ellipsoid: the name the module gives
        :func:`~thetahat.estimation.kernels.set_projection.project_into`, which ``project``
        calls with the metric M = ``LP.Gamma`` (the Γ⁻¹-weighted projection), Θ from
        ``LP.ell``, the scratch ``LP.pw`` and
        :data:`~thetahat.estimation.kernels.set_projection.OBSERVER_MARGIN`. None: Θ is a
        box with diagonal Γ, and ``project`` is a clip.

    Returns
    -------
    str
        Python source in the formulas' subset; Θ and the inversion law's options are
        read from ``LP.lower``, ``LP.upper`` (``LP.Gamma``, ``LP.ell``) and ``LP.opts``
        (:class:`~thetahat.estimation.kernels.kernel_args.LawArrays`).

    Examples
    --------
    >>> "law_step = held_law" in law_source("held_law", "")
    True
    """
    opts = "LP.opts"
    weight = (f"    if {opts}[2] != 0.0:\n"
              f"        return smoothstep(norm(phi, NK), {opts}[0], {opts}[1])\n"
              "    return 1.0\n") if law == "inversion_law" else "    return 1.0\n"
    freeze = f"{opts}[3] != 0.0" if law == "inversion_law" else "False"
    project = ("    lo, hi = LP.lower, LP.upper\n"
               "    for i in range(NP):\n        thn[i] = min(max(thn[i], lo[i]), hi[i])\n"
               if ellipsoid is None else
               f"    {ellipsoid}(thn, LP.Gamma, LP.lower, LP.upper, LP.ell, LP.pw, "
               f"{OBSERVER_MARGIN!r})\n")
    stub = "" if user_m else f"{form}\ndef m_matrix(v, x, xo, th, to, Mt):\n    return 0\n\n\n"
    return (f"{form}\ndef weight(LP, v, x, xo, phi):\n{weight}\n\n"
            f"{form}\ndef freeze(LP):\n    return {freeze}\n\n\n"
            f"{form}\ndef project(LP, thn):\n" + project + "    return 0\n\n\n"
            + stub + f"law_step = {law}\n")


def kernel_source(pert: SymbolicPerturbation, theta_star: tuple[sp.Expr, ...] | None,
                  ts_args: tuple[sp.Symbol, ...] | None, law: str, *,
                  numba: bool = True, M: sp.Matrix | None = None,
                  ellipsoid: bool = False) -> str:
    """The complete source of the kernel module of one model and configuration.

    Parameters
    ----------
    pert : SymbolicPerturbation
    theta_star, ts_args
        As for :func:`model_source`.
    law : str
        The law formula (a value of :data:`LAWS`); everything else about the law, the second
        observer and the gains is data.
    numba : bool
        Decorate the functions with ``numba.njit``; False gives plain Python (for tests).
    M : sympy.Matrix, shape (p, k), optional
        A user's M(v, x, θ) of the gradient law (Propositions 3–4) in g's symbols; default
        (∂g/∂θ)ᵀ.
    ellipsoid : bool
        Θ is a ball or an ellipsoid (data in ``LP.ell``): the module holds
        :func:`~thetahat.estimation.kernels.set_projection.project_into` and the projection
        calls it; False: Θ is a box, projected by a clip.

    Returns
    -------
    str
        A module defining ``kernel_run`` (:mod:`~thetahat.estimation.kernels.scalar_primitives`).
    """
    n, m, r, p, k = pert.dims
    for fn in (*law_formulas.LAW_FORMULAS.values(), *formulas.FORMULAS.values()):
        check_aliasing(fn)
    form = formula_decorator(_numba_version())
    header = [
        '"""Generated by thetahat.estimation.observer.kernel_source; do not edit (content-addressed).',
        "",
        "The formulas are thetahat.estimation.observer.formulas and law_formulas, verbatim.", '"""',
        "from __future__ import annotations", "",
        "import math", "", "import numpy as np", "from numba import njit", "",
        f"NX, NU, NY, NK, NP = {n}, {m}, {r}, {k}, {p}",
        "NV, NQ, NP1, LS, LS1 = NU + NY, NX + NK, NP + 1, 0, 1",
        f"IMPLICITNESS = {IMPLICITNESS!r}", f"FAR = {FAR!r}",
        f"EXP_TINY_ARG = {scalar_primitives.EXP_TINY_ARG!r}",
        f"BOUND_SQ = {DIVERGENCE_BOUND ** 2!r}",
        *(f"{name} = {code}" for name, code in status_constants().items()),
        f"USER_M = {M is not None}"]
    parts = ["\n".join(header)]
    # solve returns a status, so it is not expanded in place (_EXPANDED): numba inlines it
    # like the formulas instead (a call per step costs ~60 % of the LuGre step)
    parts += [_source(fn, name, form if name == "solve" else _INLINE)
              for name, fn in scalar_primitives.SCALAR_PRIMITIVES.items()]
    parts.append(model_source(pert, theta_star, ts_args))
    if M is not None:
        parts.append(_function("m_matrix", "v, x, xo, th, to, Mt", _model_inputs(pert),
                               [("Mt", sp.Matrix(M), False)]))
    parts += [_source(fn, None, form) for fn in law_formulas.LAW_FORMULAS.values()]
    parts += [_source(fn, None, form) for fn in formulas.FORMULAS.values()]
    entry = None
    if ellipsoid:                    # the one definition of the projection, emitted verbatim
        text, entry = kernel_module_source(project_into)
        parts.append(text)
    parts.append(law_source(law, form, M is not None, entry))
    parts += [_source(fn, decorator=_INLINE)
              for fn in (scalar_primitives.load_phis, scalar_primitives.kernel_run)]
    text = "\n\n".join(parts) + "\n"
    if not numba:
        text = "\n".join(line for line in text.splitlines()
                         if not line.startswith(("@njit(", "from numba import", "@numba.",
                                                  "import numba"))) + "\n"
    return text


def _numba_version() -> str:
    """numba's version, or "0" without numba (the text is then for plain Python only)."""
    try:
        import numba
    except ImportError:
        return "0"
    return str(numba.__version__)
