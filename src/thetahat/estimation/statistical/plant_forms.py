"""The plant of stage 2 in SymPy: f(x, u, θ), ∂f/∂x, ∂f/∂θ, and their Python print ``rhs_jac``.

f = A x + B u + E g(col(u, C x), x, θ) (eq. (1) with y = C x substituted into g) and its
Jacobians, derived once by SymPy (:func:`plant_jacobians`); :func:`rhs_jac_source` prints them
as the Python function the printed kernels of
:mod:`~thetahat.estimation.statistical.plant_kernel` call, and
:mod:`thetahat.codegen.ekf_c` prints the same forms as C.

What it may import: the model and SymPy; nothing of this room.
"""

from __future__ import annotations

from typing import Any

import sympy as sp
from sympy.printing.precedence import PRECEDENCE
from sympy.printing.pycode import PythonCodePrinter

from ...errors import DimensionError
from ...model.perturbation import SymbolicPerturbation
from ...model.system import PerturbedLinearSystem

__all__ = ["plant_jacobians", "rhs_jac_source"]


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


def plant_jacobians(system: PerturbedLinearSystem) -> tuple[list[sp.Symbol], list[sp.Symbol],
                                                             list[sp.Symbol], sp.Matrix,
                                                             sp.Matrix, sp.Matrix]:
    """(x, u, θ symbols, f, ∂f/∂x, ∂f/∂θ): the SymPy forms every printer of ``rhs_jac`` prints.

    ``DiracDelta`` terms (of sign′(z), from d|z|/dz = sign(z)) are dropped: a.e. derivatives.

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a :class:`~thetahat.model.perturbation.SymbolicPerturbation`.

    Returns
    -------
    xs, us, ts : list of sympy.Symbol
        ``x_i``, ``u_i``, ``th_i``.
    f : sympy.Matrix (n, 1)
    Fx : sympy.Matrix (n, n)
    Ft : sympy.Matrix (n, p)
    """
    xs, us, ts, f = _plant_expressions(system)
    Fx = f.jacobian(xs).replace(sp.DiracDelta, lambda *a: sp.S.Zero)
    Ft = (f.jacobian(ts) if ts else sp.zeros(len(xs), 0)).replace(sp.DiracDelta,
                                                                   lambda *a: sp.S.Zero)
    return xs, us, ts, f, Fx, Ft


class _ExactPrinter(PythonCodePrinter):
    """SymPy's Python printer with every float literal exact (``repr``: 17 digits, not 15):
    the constants the numba kernels compute with are the model's, as in the generated C."""

    def _print_Float(self, expr: sp.Float) -> str:
        return repr(float(expr))

    def _print_Pow(self, expr: sp.Pow, rational: bool = False) -> str:
        # a symbol's square as a product in parentheses: numba computes x**2 as that product
        # (the same bits: a test on five models; estimates on LuGre, Silverbox and EMPS byte
        # for byte), but through a call its compiled RK4 stage does not fold away. LuGre's
        # MAP sweep (benchmarks/bench_plant_kernel.py, two runs alternated with the commit
        # before, 2026-12-07): 717 and 685 → 638 and 644 ns a sample; on models with fewer
        # squares per step the difference is within a run's noise. A denominator's square
        # (1/c**2) prints through here too.
        if expr.exp == 2 and expr.base.is_Atom:
            base = self.parenthesize(expr.base, PRECEDENCE["Mul"])
            return f"({base}*{base})"
        return str(super()._print_Pow(expr, rational=rational))


def rhs_jac_source(system: PerturbedLinearSystem) -> str:
    """Python source of ``rhs_jac(x, u, th, f, Fx, Ft)`` writing f, ∂f/∂x, ∂f/∂θ in place
    (the common subexpressions eliminated, every float literal exact).

    Parameters
    ----------
    system : PerturbedLinearSystem
        With a :class:`~thetahat.model.perturbation.SymbolicPerturbation`.

    Returns
    -------
    str

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> rhs_jac_source(lugre.system()).splitlines()[0]
    'def rhs_jac(x, u, th, f, Fx, Ft):'
    """
    xs, us, ts, f, Fx, Ft = plant_jacobians(system)
    entries: list[tuple[str, tuple[int, ...], Any]] = [
        ("f", (i,), f[i]) for i in range(f.rows)]
    entries += [("Fx", (i, j), Fx[i, j]) for i in range(Fx.rows) for j in range(Fx.cols)]
    entries += [("Ft", (i, j), Ft[i, j]) for i in range(Ft.rows) for j in range(Ft.cols)]
    temps, reduced = sp.cse([e for _, _, e in entries], symbols=sp.numbered_symbols("c_"))
    printer = _ExactPrinter({"fully_qualified_modules": True, "standard": "python3"})
    lines = ["def rhs_jac(x, u, th, f, Fx, Ft):"]
    lines += [f"    {s.name} = x[{i}]" for i, s in enumerate(xs)]
    lines += [f"    {s.name} = u[{i}]" for i, s in enumerate(us)]
    lines += [f"    {s.name} = th[{i}]" for i, s in enumerate(ts)]
    for sym, expr in temps:
        lines.append(f"    {sym.name} = {printer.doprint(expr)}")
    for (name, index, _), expr in zip(entries, reduced):
        lines.append(f"    {name}[{', '.join(map(str, index))}] = {printer.doprint(expr)}")
    return "\n".join(lines) + "\n"
