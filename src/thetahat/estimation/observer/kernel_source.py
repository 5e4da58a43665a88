"""The scalar back end: the step's formulas printed, as scalar loops, into a numba module.

:func:`kernel_source` writes one module per model and configuration: the formulas of
:mod:`~thetahat.estimation.observer.formulas` and :mod:`~thetahat.estimation.observer.laws.formulas`
printed for the ``"scalar"`` target of :class:`~thetahat.estimation.kernels.printer.Program`
(block statements as loops, views as offsets, the vocabulary as syntax or the scalar
functions of :mod:`~thetahat.estimation.kernels.scalar_primitives`), the model functions g,
∂g/∂x, ∂g/∂y, ∂g/∂θ and θ* printed from their SymPy expressions (with common subexpressions
computed once), the law's hooks (:func:`law_hooks`: its weight, the projection onto Θ — a
clip for a box with a diagonal Γ, the Γ⁻¹-weighted projection of
:mod:`~thetahat.estimation.kernels.set_projection` for a ball or an ellipsoid) and the
dimensions as constants. Every function is ``numba.njit``-compiled with ``cache=True`` and the
formulas are inlined into the loop (:func:`~thetahat.estimation.kernels.scalar_primitives.kernel_run`),
so that the compiled step is the formulas' step, specialised to one row.
:mod:`~thetahat.estimation.observer.compiled` loads the module through
:func:`~thetahat.estimation.kernels.kernel_cache.load_module`; :mod:`thetahat.codegen` prints
the same program (:func:`kernel_program`) as C.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable, Sequence
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
from ..kernels.modules import ModuleText
from ..kernels.set_projection import OBSERVER_MARGIN, project_box_metric, project_into
from ..kernels.printer import Program
from ..kernels.subset import External, definition, definitions
from ..status import status_constants

__all__ = ["INLINE_FROM", "LAWS", "formula_decorator", "kernel_program", "kernel_source",
           "law_hooks", "model_source"]

#: The law formulas the compiled path supports, by code (see ``compiled.KernelParts``).
LAWS = {0: "held_law", 1: "inversion_law", 2: "inversion_law", 3: "gradient_law",
        4: "least_squares_law"}

#: numba options. ``_nrt=False``: no reference counting (the kernels allocate nothing; the
#: counting of ~30 array variables per sample took 40 % of the time). The blocks are printed
#: into the formulas as loops; the model functions and the scalar functions of the vocabulary
#: (exp, norm, sumsq, expm; not solve, whose call per step cost ~60 % of the LuGre step) stay
#: separate (inlining them too tripled the compile time and gained nothing measurable).
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

    ``inputs`` pairs an element template such as ``"x[x_at + {}]"`` with the symbols at its
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


#: The parameters of a printed model function before its outputs: x̂ and θ̂ are views (an
#: array and an offset, :class:`~thetahat.estimation.kernels.printer.Program`).
_MODEL_PARAMS = "v, x, x_at, th, th_at"


def _model_inputs(pert: SymbolicPerturbation) -> list[tuple[str, Sequence[sp.Symbol]]]:
    """Where the model functions read g's symbols: v = col(u, y), x̂ = x[x_at:], θ̂ = th[th_at:]."""
    return [("v[{}]", (*pert.u, *pert.y)), ("x[x_at + {}]", pert.x),
            ("th[th_at + {}]", pert.theta)]


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
        :mod:`~thetahat.estimation.observer.laws.formulas` in the scalar target (x̂ and θ̂ an
        array and an offset: ``theta_star(v, x, x_at, phi, ts)``).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> src = model_source(lugre.perturbation(), None, None)
    >>> "def g_dx(v, x, x_at, th, th_at, g, Gx):" in src
    True
    """
    n, m, r, _, _ = pert.dims
    params = _MODEL_PARAMS
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
    ts_params = "v, x, x_at, phi, ts"
    if theta_star is None:
        parts.append(f"{_INLINE}\ndef theta_star({ts_params}):\n"
                     "    for j in range(NP):\n        ts[j] = math.nan\n    return 0\n")
    else:
        a = ts_args or ()
        ins = [("v[{}]", a[:m + r]), ("x[x_at + {}]", a[m + r:m + r + n]),
               ("phi[{}]", a[m + r + n:])]
        parts.append(_function("theta_star", ts_params, ins,
                               [("ts", sp.Matrix(theta_star), True)]))
    return "\n\n".join(parts)


def law_hooks(law: str, project_into: str | None = None) -> str:
    """The law's hooks ``weight``, ``freeze``, ``project`` and a stub ``m_matrix`` (used when
    the kernel has no user's M) for one law formula, in the formulas' language.

    Parameters
    ----------
    law : str
        A value of :data:`LAWS`.
    project_into : str, optional
        Θ is a ball or an ellipsoid: the name the module gives
        :func:`~thetahat.estimation.kernels.set_projection.project_into`, which ``project``
        calls with the metric M = ``LP.Gamma`` (the Γ⁻¹-weighted projection), Θ from
        ``LP.ell``, the scratch ``LP.pw`` and
        :data:`~thetahat.estimation.kernels.set_projection.OBSERVER_MARGIN`. None: Θ is a
        box with diagonal Γ, and ``project`` is a clip. For ``"least_squares_law"``: the name
        of :func:`~thetahat.estimation.kernels.set_projection.project_box_metric`, called
        with the metric R⁺ = ``LP.Rn`` (Θ a box).

    Returns
    -------
    str
        Source in the formulas' language (:mod:`~thetahat.estimation.kernels.subset`); Θ and
        the inversion law's options are read from ``LP.lower``, ``LP.upper`` (``LP.Gamma``,
        ``LP.ell``) and ``LP.opts`` (:class:`~thetahat.estimation.kernels.kernel_args.LawArrays`).

    Examples
    --------
    >>> "def project(LP, thn):" in law_hooks("held_law")
    True
    """
    ramp = law == "inversion_law"
    weight = ("    if LP.opts[2] != 0.0:\n"
              "        return smoothstep(norm(phi), LP.opts[0], LP.opts[1])\n"
              "    return 1.0\n") if ramp else "    return 1.0\n"
    project = ("    for i in range(NP):\n"
               "        thn[i] = clip(thn[i], LP.lower[i], LP.upper[i])\n"
               if project_into is None else
               f"    {project_into}(thn, LP.Rn, LP.lower, LP.upper, LP.pw)\n"
               if law == "least_squares_law" else
               f"    {project_into}(thn, LP.Gamma, LP.lower, LP.upper, LP.ell, LP.pw, "
               f"{OBSERVER_MARGIN!r})\n")
    return (_hook("weight", "LP, v, x, phi", "x : array\nphi : array, shape (NK,)", weight)
            + _hook("freeze", "LP", "", f"    return {'LP.opts[3] != 0.0' if ramp else 'False'}\n")
            + _hook("project", "LP, thn", "thn : array, shape (NP,)", project + "    return 0\n")
            + _hook("m_matrix", "v, x, th, Mt", "x, th : array", "    return 0\n"))


def _hook(name: str, params: str, declared: str, body: str) -> str:
    doc = ""
    if declared:
        lines = "\n".join(f"    {line}" for line in declared.splitlines())
        doc = f'    """\n    Parameters\n    ----------\n{lines}\n    """\n'
    return f"def {name}({params}):\n{doc}{body}\n\n"


#: The model functions the printed kernel defines from SymPy, with their parameters.
_MODEL_CALLS = {**{name: params for name, params in formulas.CALLS.items()
                   if name != "law_step"},
                "theta_star": law_formulas.HOOKS["theta_star"],
                "m_matrix": law_formulas.HOOKS["m_matrix"]}


@functools.cache
def kernel_program(law: str, user_m: bool = False, project_into: str | None = None) -> Program:
    """The formulas of the compiled step for one law formula, as one program: the observer's
    and the law's formulas, the law's hooks (:func:`law_hooks`), the scalar functions of the
    vocabulary and the loop, with g, its Jacobians and θ* (and a user's M) defined by the
    printed model (:func:`model_source`).

    Parameters
    ----------
    law : str
        A value of :data:`LAWS`.
    user_m : bool
        ``m_matrix`` is printed from a user's M (else the hooks' stub).
    project_into : str, optional
        As for :func:`law_hooks`.

    Returns
    -------
    Program
        ``law_step`` calls the law formula.

    Examples
    --------
    >>> kernel_program("held_law").closure(["kernel_run"])[-1]
    'kernel_run'
    """
    sources: dict[str, Callable[..., Any]] = {
        **scalar_primitives.SCALAR_PRIMITIVES, **law_formulas.LAW_FORMULAS, **formulas.FORMULAS,
        "load_phis": scalar_primitives.load_phis, "kernel_run": scalar_primitives.kernel_run}
    functions = {name: definition(fn) for name, fn in sources.items()}
    hooks = definitions(law_hooks(law, project_into), "thetahat.estimation.observer.kernel_source")
    if user_m:
        del hooks["m_matrix"]
    functions.update(hooks)
    model = {name: External(params, frozenset(params) & formulas.VIEWED)
             for name, params in _MODEL_CALLS.items() if name != "m_matrix" or user_m}
    return Program(functions, model, {"law_step": law})


def kernel_source(pert: SymbolicPerturbation, theta_star: tuple[sp.Expr, ...] | None,
                  ts_args: tuple[sp.Symbol, ...] | None, law: str, *,
                  numba: bool = True, M: sp.Matrix | None = None,
                  ellipsoid: bool = False, law_size: int = 0) -> str:
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
        calls it; False: Θ is a box, projected by a clip (by
        :func:`~thetahat.estimation.kernels.set_projection.project_box_metric` in R⁺'s metric
        for ``"least_squares_law"``).
    law_size : int
        Length of the law's state (``LS``; the least-squares law's col(w, w_b, a, R)).

    Returns
    -------
    str
        A module defining ``kernel_run`` (:mod:`~thetahat.estimation.kernels.scalar_primitives`)
        and every formula it calls, printed for the scalar target
        (:meth:`~thetahat.estimation.kernels.printer.Program.printed`).
    """
    n, m, r, p, k = pert.dims
    form = formula_decorator(_numba_version())
    text = ModuleText("Printed by thetahat.estimation.observer.kernel_source from the formulas "
                      "of thetahat.estimation.observer; do not edit (content-addressed).",
                      _INLINE)
    text.import_line("import math")
    text.import_line("from numba import njit")
    for name, value in (("NX", n), ("NU", m), ("NY", r), ("NK", k), ("NP", p), ("NV", m + r),
                        ("NQ", n + k), ("NP1", p + 1), ("LS", law_size),
                        ("LS1", max(law_size, 1)),
                        ("IMPLICITNESS", IMPLICITNESS), ("FAR", FAR),
                        ("EXP_TINY_ARG", scalar_primitives.EXP_TINY_ARG),
                        ("BOUND_SQ", DIVERGENCE_BOUND ** 2), *status_constants().items(),
                        ("USER_M", M is not None)):
        text.constant(name, repr(value))
    entry = (text.bound(project_box_metric, "@numba.njit(nogil=True, cache=True)")
             if law == "least_squares_law" else
             text.bound(project_into, "@numba.njit(nogil=True, cache=True)") if ellipsoid
             else None)                                            # its one definition
    text.text(model_source(pert, theta_star, ts_args))
    if M is not None:
        text.text(_function("m_matrix", _MODEL_PARAMS + ", Mt", _model_inputs(pert),
                            [("Mt", sp.Matrix(M), False)]))
    program = kernel_program(law, M is not None, entry)
    inlined = {*law_formulas.LAW_FORMULAS, *formulas.FORMULAS, "solve", "weight", "freeze",
               "project", "m_matrix"}
    # the scalar functions first: the model functions call exp too
    for name in program.closure([*scalar_primitives.SCALAR_PRIMITIVES, "kernel_run"]):
        text.function(program.printed(name, "scalar"), form if name in inlined else None)
    text.text(f"law_step = {law}")
    source = text.source()
    if not numba:
        source = "\n".join(line for line in source.splitlines()
                           if not line.startswith(("@njit(", "from numba import", "@numba.",
                                                    "import numba"))) + "\n"
    return source


def _numba_version() -> str:
    """numba's version, or "0" without numba (the text is then for plain Python only)."""
    try:
        import numba
    except ImportError:
        return "0"
    return str(numba.__version__)
