"""The syntax tables of the C printer (:mod:`.c_printer`): operators, helpers, assignments.

Python's operators as C's (:data:`BINOPS`, :data:`CMPS`) and as the folds of constants
(:data:`FOLD`, :data:`CMP_FOLD`); the small C helpers a printed unit emits when it uses them
(:data:`HELPERS`); which names a function assigns more than once (:func:`analysis`).
"""

from __future__ import annotations

import ast
import functools
import re
from collections.abc import Callable
from typing import Any

__all__ = ["BINOPS", "CMPS", "CMP_FOLD", "FOLD", "HELPERS", "analysis", "identifiers"]

#: Small C helpers, emitted when used: Python's max/min of reals and of integers (the first
#: argument on ties and NaN).
HELPERS = {
    "max": "static REAL py_max(REAL a, REAL b)\n{\n    return b > a ? b : a;\n}\n",
    "min": "static REAL py_min(REAL a, REAL b)\n{\n    return b < a ? b : a;\n}\n",
    "imax": "static int py_imax(int a, int b)\n{\n    return b > a ? b : a;\n}\n",
    "imin": "static int py_imin(int a, int b)\n{\n    return b < a ? b : a;\n}\n",
}


@functools.lru_cache(maxsize=512)
def analysis(fdef: ast.FunctionDef) -> tuple[dict[str, int], bool]:
    """How often each name of ``fdef`` is assigned (a loop or an update counts twice), and
    whether the function returns tuples.

    Parameters
    ----------
    fdef : ast.FunctionDef

    Returns
    -------
    assigned : dict of str to int
    returns_tuple : bool

    Examples
    --------
    >>> analysis(ast.parse("def f(a):\\n    b = 1\\n    b += a\\n    return b").body[0])
    ({'b': 3}, False)
    """
    assigned: dict[str, int] = {}
    for node in ast.walk(fdef):
        targets: list[ast.expr] = []
        weight = 1
        if isinstance(node, ast.Assign):
            targets = list(node.targets)
        elif isinstance(node, (ast.AugAssign, ast.For)):
            targets, weight = [node.target], 2
        for t in targets:
            for n in ast.walk(t):
                if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
                    assigned[n.id] = assigned.get(n.id, 0) + weight
    returns_tuple = any(isinstance(n, ast.Return) and isinstance(n.value, ast.Tuple)
                        for n in ast.walk(fdef))
    return assigned, returns_tuple


def identifiers(text: str) -> list[str]:
    """The C identifiers (and keywords) of ``text``, in order.

    Parameters
    ----------
    text : str

    Returns
    -------
    list of str

    Examples
    --------
    >>> identifiers("a[i] = b1 + 2;")
    ['a', 'i', 'b1']
    """
    return re.findall(r"[A-Za-z_]\w*", text)


BINOPS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Mod: "%",
          ast.BitAnd: "&"}
FOLD: dict[type, Callable[[Any, Any], Any]] = {
    ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b, ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b, ast.FloorDiv: lambda a, b: a // b,
    ast.Mod: lambda a, b: a % b, ast.Pow: lambda a, b: a ** b,
    ast.BitAnd: lambda a, b: a & b}
CMPS = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!="}
CMP_FOLD: dict[type, Callable[[Any, Any], Any]] = {
    ast.Lt: lambda a, b: a < b, ast.LtE: lambda a, b: a <= b, ast.Gt: lambda a, b: a > b,
    ast.GtE: lambda a, b: a >= b, ast.Eq: lambda a, b: a == b,
    ast.NotEq: lambda a, b: a != b}
