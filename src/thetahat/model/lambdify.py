"""SymPy to NumPy: the one lambdify of the package (element-wise, NaN-propagating).

:func:`numpy_ready` rewrites what NumPy would print wrongly (Heaviside), and
:func:`lambdify_numpy` prints expressions with element-wise Max/Min and common subexpressions
evaluated once; :class:`~thetahat.model.perturbation.SymbolicPerturbation`, θ* and the compiled
path all print through them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import sympy as sp
from sympy.printing.numpy import NumPyPrinter

__all__ = ["lambdify_numpy", "numpy_ready"]


def numpy_ready(entry: sp.Expr) -> sp.Expr:
    """Rewrite Heaviside(z) as (1 + sign(z))/2 so that NaN propagates in the printed code.

    Parameters
    ----------
    entry : sympy.Expr

    Returns
    -------
    sympy.Expr

    Examples
    --------
    >>> import sympy as sp
    >>> z = sp.Symbol("z")
    >>> numpy_ready(sp.Heaviside(z))
    sign(z)/2 + 1/2
    """
    def _heaviside(z: sp.Expr, h0: sp.Expr = sp.S.Half) -> sp.Expr:
        if h0 == sp.S.Half:
            return (1 + sp.sign(z)) / 2
        return sp.Heaviside(z, h0, evaluate=False)
    return entry.replace(sp.Heaviside, _heaviside)


class _ElementwisePrinter(NumPyPrinter):
    """NumPy printer whose Max/Min are element-wise on arrays and propagate NaN.

    SymPy's own NumPy printing of ``Max`` changed across versions (``amax`` of a tuple, which
    fails on arrays mixed with scalars in SymPy 1.12); nested ``numpy.maximum`` is right in all.
    """

    def _print_Max(self, expr: sp.Expr) -> str:
        return self._nested("numpy.maximum", expr)

    def _print_Min(self, expr: sp.Expr) -> str:
        return self._nested("numpy.minimum", expr)

    def _nested(self, name: str, expr: sp.Expr) -> str:
        func = self._module_format(name)
        args = [self._print(a) for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = f"{func}({out}, {a})"
        return out


def lambdify_numpy(args: Sequence[sp.Symbol], exprs: Sequence[sp.Expr]) -> Callable[..., list[Any]]:
    """Element-wise NumPy function of SymPy expressions: the one lambdify of the package.

    Heaviside is rewritten so that NaN propagates, Max/Min are element-wise, and common
    subexpressions are evaluated once.

    Parameters
    ----------
    args : sequence of sympy.Symbol
        The positional arguments of the function, in order.
    exprs : sequence of sympy.Expr
        The expressions; the function returns a list with one value per expression.

    Returns
    -------
    callable
        ``f(*arrays) -> list``; the arrays broadcast against each other.

    Examples
    --------
    >>> import numpy as np, sympy as sp
    >>> x, y = sp.symbols("x y")
    >>> f = lambdify_numpy([x, y], [sp.Max(x, 0) * y])
    >>> f(np.array([-1.0, 2.0, np.nan]), 3.0)[0]
    array([ 0.,  6., nan])
    """
    entries = [numpy_ready(sp.sympify(e)) for e in exprs]
    if not entries:
        return lambda *cols: []
    return sp.lambdify(list(args), entries, modules="numpy", printer=_ElementwisePrinter,
                       cse=True)
