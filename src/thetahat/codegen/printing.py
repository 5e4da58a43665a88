"""C99 functions for g, its Jacobians and θ*, printed by SymPy's C99 printer with ``sympy.cse``.

One printed function per model piece the step needs (:func:`c_function`): its arguments are
arrays (``v``, ``x``, ``th``, ``phi``), every symbol of the expression is replaced by the array
element it is stored in, common subexpressions become ``const`` locals, and the outputs are
written in row-major order. The float variant prints single-precision functions and literals
(``expf``, ``1.5F``) so that a ``float`` build never computes in double.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import sympy as sp
from sympy.codegen.ast import float32, real
from sympy.printing.c import C99CodePrinter

from ..errors import UnsupportedError
from ..model.lambdify import numpy_ready

__all__ = ["REALS", "c_function", "c_printer"]

#: The C types a generated observer can compute in.
REALS = ("double", "float")


def c_printer(real_type: str) -> C99CodePrinter:
    """SymPy's C99 printer for ``real_type`` ("double" or "float"), without POSIX macros.

    ``M_PI`` and friends are POSIX, not C99: ``math_macros={}`` prints them as literals.

    Parameters
    ----------
    real_type : {"double", "float"}

    Returns
    -------
    sympy.printing.c.C99CodePrinter

    Examples
    --------
    >>> import sympy as sp
    >>> c_printer("float").doprint(sp.exp(sp.Symbol("x")) / 2)
    '(1.0F/2.0F)*expf(x)'
    """
    if real_type not in REALS:
        raise UnsupportedError(f"real must be one of {REALS}; got {real_type!r}.")
    settings: dict[str, object] = {"math_macros": {}}
    if real_type == "float":
        settings["type_aliases"] = {real: float32}
    return C99CodePrinter(settings)


def c_function(name: str, inputs: Sequence[tuple[str, Sequence[sp.Symbol]]],
               outputs: Sequence[tuple[str, sp.Matrix]], real_type: str) -> str:
    """Source of ``static void name(const real_t in1[], ..., real_t out1[], ...)``.

    Parameters
    ----------
    name : str
        C name of the function.
    inputs : sequence of (array name, symbols)
        Each symbol is read from ``array[i]`` at its position i.
    outputs : sequence of (array name, sympy.Matrix)
        The entries are written to ``array[i * cols + j]``.
    real_type : {"double", "float"}

    Returns
    -------
    str

    Raises
    ------
    UnsupportedError
        An entry is complex or uses a function C99 does not have.

    Examples
    --------
    >>> import sympy as sp
    >>> y, th = sp.symbols("y theta")
    >>> print(c_function("g", [("v", [y]), ("th", [th])],
    ...                  [("out", sp.Matrix([th * sp.sin(y)]))], "double"))
    static void g(const real_t v[], const real_t th[], real_t out[])
    {
        out[0] = th[0]*sin(v[0]);
    }
    """
    subs = {}
    for array, symbols in inputs:
        for i, s in enumerate(symbols):
            subs[s] = sp.Symbol(f"{array}[{i}]", real=True)
    flat, targets = [], []
    for array, M in outputs:
        M = sp.Matrix(M)
        for i in range(M.rows):
            for j in range(M.cols):
                entry = numpy_ready(sp.sympify(M[i, j])).xreplace(subs)
                if entry.has(sp.I) or entry.has(sp.zoo, sp.nan, sp.oo):
                    raise UnsupportedError(f"{name}: entry {M[i, j]} is complex or infinite; the C "
                                       "observer needs a real formula (write θ* or g with "
                                       "real functions only).")
                flat.append(entry)
                targets.append(f"{array}[{i * M.cols + j}]")
    replacements, reduced = sp.cse(flat, symbols=sp.numbered_symbols("cse"))
    printer = c_printer(real_type)
    body = [f"    const real_t {sym} = {printer.doprint(e)};" for sym, e in replacements]
    body += [f"    {t} = {printer.doprint(e)};" for t, e in zip(targets, reduced)]
    if printer._not_supported:
        bad = ", ".join(sorted(map(str, printer._not_supported)))
        raise UnsupportedError(f"{name}: SymPy's C99 printer cannot print {bad}; rewrite the model "
                           "with elementary functions.")
    used = "\n".join(body)
    params = [f"const real_t {a}[]" for a, _ in inputs] + [f"real_t {a}[]" for a, _ in outputs]
    unused = [f"    (void){a};" for a, _ in inputs if not re.search(rf"\b{a}\[", used)]
    return "\n".join([f"static void {name}({', '.join(params)})", "{", *unused, *body, "}"])
