"""Parse a perturbation given as text (model files, the command line) without eval.

The text is parsed with Python's :mod:`ast` and only a whitelist of node types (numbers,
declared names, whitelisted functions, + − * / ** and unary minus) is turned into SymPy
expressions by hand, so no code from the file is ever executed. The size limits of
:mod:`thetahat.limits` (length, nesting depth, exponents, towers of powers) are checked
before anything is built. :func:`parse_expression` is the one parser every API that accepts
strings uses (model files, :func:`parse_perturbation`, θ*, string entries of
:func:`~thetahat.structure.scb_symbolic.scb_symbolic`).
"""

from __future__ import annotations

import ast
import keyword
import math
import unicodedata
from collections.abc import Callable, Iterable, Mapping, Sequence
from types import MappingProxyType
from typing import Any

import numpy as np
import sympy as sp

from .. import limits
from ..errors import DimensionError, InputLimitError, ModelFileError, NonFiniteError
from .perturbation import SymbolicPerturbation

__all__ = ["parse_perturbation", "parse_expression", "normalize_name"]


#: Functions allowed in :func:`parse_perturbation`, with their number of arguments
#: (None: two or more).
_FUNCTIONS: Mapping[str, tuple[Callable[..., sp.Expr], int | None]] = MappingProxyType({
    "exp": (sp.exp, 1), "log": (sp.log, 1), "sqrt": (sp.sqrt, 1),
    "sin": (sp.sin, 1), "cos": (sp.cos, 1), "tan": (sp.tan, 1),
    "sinh": (sp.sinh, 1), "cosh": (sp.cosh, 1), "tanh": (sp.tanh, 1),
    "asinh": (sp.asinh, 1), "atanh": (sp.atanh, 1), "atan": (sp.atan, 1),
    "Abs": (sp.Abs, 1), "abs": (sp.Abs, 1), "sign": (sp.sign, 1),
    "Min": (sp.Min, None), "Max": (sp.Max, None),
})

#: Named constants always available in :func:`parse_perturbation`.
_BUILTIN_CONSTANTS: Mapping[str, sp.Expr] = MappingProxyType({"pi": sp.pi})

_BINARY_OPS: Mapping[type, Callable[[sp.Expr, sp.Expr], sp.Expr]] = MappingProxyType({
    ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b, ast.Div: lambda a, b: a / b,
})

_ALLOWED = ("numbers, the declared names, the functions " + ", ".join(_FUNCTIONS)
            + ", the operators + - * / ** and unary minus, and parentheses")


class _ExpressionBuilder:
    """Builds a SymPy expression from a Python AST, refusing anything not whitelisted."""

    def __init__(self, text: str, what: str, names: Mapping[str, sp.Expr],
                 new_symbol: Callable[[str], sp.Expr] | None = None) -> None:
        self.text = text
        self.what = what
        self.names = names
        self.new_symbol = new_symbol

    def fail(self, node: ast.AST, what: str) -> ModelFileError:
        segment = ast.get_source_segment(self.text, node) or type(node).__name__
        if len(segment) > 60:
            segment = segment[:57] + "..."
        column = getattr(node, "col_offset", 0) + 1
        declared = ("any name" if self.new_symbol is not None
                    else ", ".join(self.names) or "(none)")
        return ModelFileError(
            f"{self.what}: {what} {segment!r} at column {column} is not allowed. Allowed: "
            f"{_ALLOWED}. Declared names: {declared}.")

    def build(self, node: ast.AST) -> sp.Expr:
        if isinstance(node, ast.Constant):
            value = node.value
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise self.fail(node, "the literal")
            return sp.Integer(value) if isinstance(value, int) else sp.Float(value)
        if isinstance(node, ast.Name):
            if node.id in self.names:
                return self.names[node.id]
            if node.id in _FUNCTIONS:
                raise self.fail(node, "the function name without a call")
            if self.new_symbol is None or node.id.startswith("_"):
                raise self.fail(node, "the unknown name")
            return self.new_symbol(node.id)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            operand = self.build(node.operand)
            return -operand if isinstance(node.op, ast.USub) else operand
        if isinstance(node, ast.BinOp):
            return self._binary(node)
        if isinstance(node, ast.Call):
            return self._call(node)
        raise self.fail(node, f"the {type(node).__name__.lower()} construct")

    def _binary(self, node: ast.BinOp) -> sp.Expr:
        if isinstance(node.op, ast.Pow):
            base, exponent = self.build(node.left), self.build(node.right)
            if base.is_Number and exponent.is_Number:
                # Evaluate numeric powers in float64: 9**9**9 must neither build a gigantic
                # exact integer nor an mpmath float with a gigantic exponent.
                try:
                    value = math.pow(float(base), float(exponent))
                except (OverflowError, ValueError):
                    value = math.nan
                if not math.isfinite(value):
                    raise self.fail(node, "the numeric power (its value is not a finite "
                                          "float64 number)")
                return sp.Integer(int(value)) if value.is_integer() and abs(value) < 2**53 \
                    and base.is_Integer and exponent.is_Integer else sp.Float(value)
            if exponent.is_Number and abs(float(exponent)) > limits.MAX_EXPONENT:
                raise InputLimitError(
                    f"{self.what}: the exponent {exponent} in "
                    f"{ast.get_source_segment(self.text, node)!s:.60} exceeds the limit "
                    f"|exponent| <= {limits.MAX_EXPONENT:g} (thetahat.limits.MAX_EXPONENT); "
                    f"rewrite the formula (e.g. with exp and log).")
            return base ** exponent
        op = _BINARY_OPS.get(type(node.op))
        if op is None:
            hint = " (use ** for powers)" if isinstance(node.op, ast.BitXor) else ""
            raise self.fail(node, f"the operator{hint} in")
        return op(self.build(node.left), self.build(node.right))

    def _call(self, node: ast.Call) -> sp.Expr:
        if not isinstance(node.func, ast.Name) or node.func.id not in _FUNCTIONS:
            raise self.fail(node.func, "the function")
        if node.keywords or any(isinstance(a, ast.Starred) for a in node.args):
            raise self.fail(node, "keyword or starred arguments in")
        func, arity = _FUNCTIONS[node.func.id]
        if (arity is None and len(node.args) < 2) or (arity is not None
                                                      and len(node.args) != arity):
            want = "two or more arguments" if arity is None else f"{arity} argument"
            raise self.fail(node, f"{node.func.id} takes {want};")
        return func(*(self.build(a) for a in node.args))


def _literal_exponent(node: ast.AST) -> float:
    """|e| of a numeric literal exponent (``2``, ``-0.5``), else 1 (the tower limit applies)."""
    try:
        value = ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return 1.0
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return 1.0
    try:
        return abs(float(value))
    except OverflowError:
        return math.inf


def _check_shape(tree: ast.AST, what: str, text: str = "") -> None:
    """Nesting depth, power towers and the product of nested exponents of a parsed formula
    (``((y**100)**100)**100`` is y**1000000), walked without recursion."""
    stack: list[tuple[ast.AST, int, int, float]] = [(tree, 0, 0, 1.0)]
    while stack:
        node, depth, towers, power = stack.pop()
        if depth > limits.MAX_EXPRESSION_DEPTH:
            raise InputLimitError(
                f"{what}: the formula is nested deeper than {limits.MAX_EXPRESSION_DEPTH} "
                f"levels (thetahat.limits.MAX_EXPRESSION_DEPTH); simplify it or split it "
                f"with constants.")
        if towers > limits.MAX_POWER_NESTING:
            raise InputLimitError(
                f"{what}: a tower of more than {limits.MAX_POWER_NESTING} nested powers "
                f"(like y**y**y**y; thetahat.limits.MAX_POWER_NESTING) is not accepted; "
                f"rewrite it with exp and log.")
        is_pow = isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow)
        if is_pow:
            own = _literal_exponent(node.right)         # type: ignore[attr-defined]
            power *= own
            if power > limits.MAX_EXPONENT >= own:       # (one exponent: _binary says so)
                raise InputLimitError(
                    f"{what}: the nested powers in {ast.get_source_segment(text, node)!s:.60} "
                    f"raise to an exponent of {power:g} in all, beyond the limit |exponent| "
                    f"<= {limits.MAX_EXPONENT:g} (thetahat.limits.MAX_EXPONENT, which applies "
                    f"to the product of nested exponents); rewrite the formula.")
        for child in ast.iter_child_nodes(node):
            in_exponent = is_pow and child is node.right      # type: ignore[attr-defined]
            stack.append((child, depth + 1, towers + int(in_exponent),
                          1.0 if in_exponent else power))


def parse_expression(text: str, names: Mapping[str, sp.Expr], *, what: str = "expression",
                     new_symbol: Callable[[str], sp.Expr] | None = None) -> sp.Expr:
    """Parse one formula into a SymPy expression without evaluating it as code.

    Parameters
    ----------
    text : str
        The formula, in the whitelisted syntax of :func:`parse_perturbation`.
    names : mapping of str to sympy.Expr
        What each allowed name stands for (symbols, constants); ``pi`` is always known.
    what : str
        Names the formula in error messages (e.g. "perturbation component 0").
    new_symbol : callable, optional
        Called with an undeclared name to create its symbol; default ``None`` refuses
        undeclared names. Names starting with an underscore are always refused.

    Returns
    -------
    sympy.Expr

    Raises
    ------
    ModelFileError
        The text does not parse, or uses something outside the whitelist.
    InputLimitError
        The text is longer, deeper nested, or has larger exponents or higher towers of
        powers than :mod:`thetahat.limits` allows.

    Examples
    --------
    >>> import sympy as sp
    >>> from thetahat.model.parse import parse_expression
    >>> y = sp.Symbol("y", real=True)
    >>> parse_expression("2*exp(-y**2)", {"y": y})
    2*exp(-y**2)
    >>> parse_expression("__import__('os').system('true')", {"y": y})
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: expression: the function "__import__('os').system" at column 1 is not allowed. ...
    """
    if not isinstance(text, str):
        raise ModelFileError(f"{what} must be a string; got {type(text).__name__}.")
    if len(text) > limits.MAX_EXPRESSION_CHARS:
        raise InputLimitError(f"{what} has {len(text)} characters; at most "
                              f"{limits.MAX_EXPRESSION_CHARS} are accepted "
                              f"(thetahat.limits.MAX_EXPRESSION_CHARS).")
    source = text.strip()
    try:
        tree = ast.parse(source, mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        raise ModelFileError(f"{what} is not a valid expression: {text:.80s} "
                             f"({type(exc).__name__}: {exc}).") from exc
    _check_shape(tree.body, what, source)
    table = dict(names)
    table.update({k: v for k, v in _BUILTIN_CONSTANTS.items() if k not in table})
    return _ExpressionBuilder(source, what, table, new_symbol).build(tree.body)


def normalize_name(name: str) -> str:
    """A declared name in the form the formula parser sees it: Unicode NFKC, as Python
    normalises identifiers (a full-width ``ｅ`` is ``e``, the micro sign ``µ`` is Greek ``μ``).

    Parameters
    ----------
    name : str

    Returns
    -------
    str

    Examples
    --------
    >>> from thetahat.model.parse import normalize_name
    >>> normalize_name("\uff45ta"), normalize_name("\u00b50") == normalize_name("\u03bc0")
    ('eta', True)
    """
    return unicodedata.normalize("NFKC", name)


def _parse_names(group: str, names: Any) -> tuple[sp.Symbol, ...]:
    if isinstance(names, (str, sp.Symbol)):
        names = [names]
    if not isinstance(names, Iterable):
        raise ModelFileError(f"{group} must be a sequence of names; got {names!r}.")
    out = []
    for name in names:
        if isinstance(name, sp.Symbol):
            out.append(name)
            continue
        if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name):
            raise ModelFileError(f"{group}: {name!r} is not a valid name (letters, digits and "
                                 f"underscores, not starting with a digit).")
        out.append(sp.Symbol(normalize_name(name), real=True))
    return tuple(out)


def _parse_constants(constants: Mapping[str, float] | None) -> dict[str, sp.Expr]:
    out: dict[str, sp.Expr] = {}
    for name, value in (constants or {}).items():
        if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name):
            raise ModelFileError(f"constant name {name!r} is not a valid name.")
        if normalize_name(name) in out:
            raise ModelFileError(f"the constant {name!r} is the same name as another constant "
                                 f"once Unicode look-alikes are normalised (NFKC): rename one.")
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float,
                                                                      np.integer, np.floating)):
            raise ModelFileError(f"constant {name} must be a real number; got {value!r}.")
        try:
            number = float(value)
        except OverflowError:
            number = math.inf
        if not math.isfinite(number):
            shown = value if isinstance(value, (float, np.floating)) else \
                f"an integer of {len(str(abs(int(value))))} digits"
            raise ModelFileError(f"constant {name} must be finite (a float64 number); got "
                                 f"{shown}.")
        out[normalize_name(name)] = sp.Integer(int(value)) \
            if isinstance(value, (int, np.integer)) else sp.Float(number)
    return out


def parse_perturbation(text: str | Sequence[str], *, u: Sequence[str | sp.Symbol],
                       y: Sequence[str | sp.Symbol], x: Sequence[str | sp.Symbol],
                       theta: Sequence[str | sp.Symbol],
                       constants: Mapping[str, float] | None = None) -> SymbolicPerturbation:
    """Read g from text, without evaluating it as code.

    The text is parsed with :mod:`ast` and the SymPy expression is built node by node from
    a whitelist: numbers, the declared names, ``pi``, the functions exp, log, sqrt, sin,
    cos, tan, sinh, cosh, tanh, asinh, atanh, atan, Abs (or abs), sign, Min and Max, the
    operators ``+ - * / **``, unary minus and parentheses. Everything else (attribute
    access, subscripts, lambdas, other calls, unknown names) is refused.

    Parameters
    ----------
    text : str or sequence of str
        One string per component of φ (k strings), within the limits of
        :mod:`thetahat.limits` (length, nesting, exponents).
    u, y, x, theta : sequence of str or sympy.Symbol
        Names of the inputs (may be empty), outputs, states and parameters. Strings become
        real SymPy symbols.
    constants : mapping of str to float, optional
        Known constants, substituted as numbers.

    Returns
    -------
    SymbolicPerturbation

    Raises
    ------
    ModelFileError
        The text does not parse, uses something outside the whitelist, a name is invalid
        or declared twice, or the resulting g is invalid (the message says why).
    InputLimitError
        A component exceeds a limit of :mod:`thetahat.limits`.

    Examples
    --------
    >>> from thetahat.model.parse import parse_perturbation
    >>> g = parse_perturbation(
    ...     "sigma0*eta*Abs(y)/(alpha0 + alpha1*exp(-(omega/omega0)**2))",
    ...     u=["u"], y=["y"], x=["omega", "eta"], theta=["alpha0"],
    ...     constants={"sigma0": 260.0, "alpha1": 0.05, "omega0": 0.01})
    >>> g.dims
    (2, 1, 1, 1, 1)
    >>> round(float(g.g([0.0, 1.0], [1.0, 1e-3], [0.28])[0]), 12)  # 260 * 1e-3 * 1 / 0.28
    0.928571428571
    """
    components = [text] if isinstance(text, str) else list(text) \
        if isinstance(text, Iterable) else None
    if not components or not all(isinstance(c, str) for c in components):
        raise ModelFileError(f"text must be a string or a non-empty list of strings, one per "
                             f"component of phi; got {text!r}.")
    groups = {g: _parse_names(g, s) for g, s in (("u", u), ("y", y), ("x", x),
                                                  ("theta", theta))}
    names: dict[str, sp.Expr] = {}
    for group, symbols in groups.items():
        for s in symbols:
            if s.name in names or s.name in _FUNCTIONS or s.name in _BUILTIN_CONSTANTS:
                raise ModelFileError(f"the name {s.name!r} in {group} is declared twice or "
                                     f"clashes with a function or constant name (names are "
                                     f"compared after Unicode NFKC normalisation, as in "
                                     f"formulas: look-alikes such as a full-width letter or "
                                     f"the micro sign count as the same name).")
            names[s.name] = s
    for name, value in _parse_constants(constants).items():
        if name in names or name in _FUNCTIONS or name in _BUILTIN_CONSTANTS:
            raise ModelFileError(f"the constant {name!r} clashes with a declared symbol, a "
                                 f"function or a built-in constant.")
        names[name] = value
    exprs = [parse_expression(c, names, what=f"perturbation component {i}")
             for i, c in enumerate(components)]
    try:
        return SymbolicPerturbation.from_sympy(exprs, **groups)
    except (DimensionError, NonFiniteError) as exc:
        raise ModelFileError(f"the parsed perturbation is invalid: {exc}") from exc
