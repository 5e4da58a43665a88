"""The perturbation φ = g(v, x, θ) and its Jacobians ∂g/∂v, ∂g/∂x, ∂g/∂θ (Sec. II).

Batch convention used throughout thetahat: arguments carry any leading batch shape,
``v (..., m + r)``, ``x (..., n)``, ``theta (..., p)``; results are ``g (..., k)``,
``dg_dv (..., k, m + r)``, ``dg_dx (..., k, n)``, ``dg_dtheta (..., k, p)``. Leading shapes
broadcast against each other.

Concrete, final classes: :class:`SymbolicPerturbation` (SymPy expression, exact Jacobians),
:class:`CallablePerturbation` (numeric functions, finite differences where no Jacobian is
given). :func:`~thetahat.model.jacobian_check.check_jacobians` compares Jacobians with finite
differences, and :func:`~thetahat.model.parse.parse_perturbation` reads g from text without
evaluating code; :mod:`thetahat.model.lambdify` prints SymPy to NumPy.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, final

import numpy as np
import sympy as sp
from numpy.typing import NDArray
from sympy.core.function import AppliedUndef

from ..errors import DimensionError, NonFiniteError
from .lambdify import lambdify_numpy, numpy_ready

__all__ = ["ARG_NAMES", "EVAL_BLOCK", "FD_REL_STEP", "Perturbation", "SymbolicPerturbation",
           "CallablePerturbation", "batch_args", "central_difference", "lambdify_numpy",
           "numpy_ready"]

FloatArray = NDArray[np.float64]

#: Samples a :class:`SymbolicPerturbation` evaluates at once: a longer record is evaluated a
#: block at a time, so that the printed expression's intermediates (one array per
#: subexpression, 10–20 for a friction law) take megabytes, not the record's size again.
EVAL_BLOCK = 1 << 16


class Perturbation(ABC):
    """Abstract φ = g(v, x, θ) with v = col(u, y).

    Concrete classes are final: combine them, do not subclass them.
    """

    @property
    @abstractmethod
    def dims(self) -> tuple[int, int, int, int, int]:
        """(n, m, r, p, k): states, inputs, outputs, parameters, perturbation size."""

    @abstractmethod
    def g(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """φ = g(v, x, θ); shape (..., k)."""

    @abstractmethod
    def dg_dv(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂v; shape (..., k, m + r)."""

    @abstractmethod
    def dg_dx(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂x; shape (..., k, n)."""

    @abstractmethod
    def dg_dtheta(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂θ; shape (..., k, p)."""


# ----------------------------------------------------------------------------------------------
# Shared helpers: argument validation and central finite differences
# ----------------------------------------------------------------------------------------------

#: Relative step of the central differences: h = FD_REL_STEP * max(|z|, 1). The truncation
#: error of a central difference is O(h**2) and its rounding error O(eps / h); eps**(1/3)
#: balances the two, leaving an error of order eps**(2/3) ≈ 4e-11 for a well-scaled g.
FD_REL_STEP: float = float(np.finfo(np.float64).eps ** (1.0 / 3.0))

#: The names of g's arguments, in order.
ARG_NAMES = ("v", "x", "theta")
_FLOAT64_MAX = sp.Float(float(np.finfo(np.float64).max))


def _batch_arg(name: str, value: Any, size: int, meaning: str) -> FloatArray:
    """``value`` as a float64 array of shape (..., size); NaN and inf pass through."""
    arr = np.asarray(value)
    if np.iscomplexobj(arr):
        raise DimensionError(f"{name} must be real; got a complex array.")
    try:
        arr = arr.astype(np.float64, copy=False)
    except (TypeError, ValueError) as exc:
        raise DimensionError(f"{name} must be a numeric array of shape (..., {size}) "
                             f"({meaning}); got {type(value).__name__}.") from exc
    if arr.ndim == 0 or arr.shape[-1] != size:
        got = "a scalar" if arr.ndim == 0 else f"shape {arr.shape}"
        raise DimensionError(f"{name} must have shape (..., {size}) ({meaning}); got {got}. "
                             f"The last axis holds the components; leading axes are the batch.")
    return arr


def batch_args(dims: tuple[int, int, int, int, int], v: Any, x: Any, theta: Any
                ) -> tuple[FloatArray, FloatArray, FloatArray, tuple[int, ...]]:
    """Validate (v, x, θ) against ``dims`` and return them with their common batch shape.

    Parameters
    ----------
    dims : tuple of int
        (n, m, r, p, k) of the perturbation.
    v, x, theta : array_like, shapes (..., m + r), (..., n), (..., p)
        Real arrays; NaN and inf pass through.

    Returns
    -------
    v, x, theta : ndarray
        As float64 arrays.
    batch : tuple of int
        The broadcast leading shape.

    Raises
    ------
    DimensionError
        A complex or non-numeric argument, a wrong last axis, or batch shapes that do not
        broadcast.

    Examples
    --------
    >>> batch_args((2, 1, 1, 1, 1), [0.0, 1.0], [[1.0, 2.0]] * 3, [0.5])[3]
    (3,)
    """
    n, m, r, p, _ = dims
    if (type(v) is np.ndarray and type(x) is np.ndarray and type(theta) is np.ndarray
            and v.dtype == x.dtype == theta.dtype == np.float64 and v.ndim and x.ndim
            and theta.ndim and v.shape[-1] == m + r and x.shape[-1] == n
            and theta.shape[-1] == p and v.shape[:-1] == x.shape[:-1] == theta.shape[:-1]):
        return v, x, theta, v.shape[:-1]     # valid as given (the observer's step): no copies
    v_ = _batch_arg("v", v, m + r, f"v = col(u, y) with m + r = {m} + {r}")
    x_ = _batch_arg("x", x, n, f"the state, n = {n}")
    t_ = _batch_arg("theta", theta, p, f"the parameters, p = {p}")
    try:
        batch = np.broadcast_shapes(v_.shape[:-1], x_.shape[:-1], t_.shape[:-1])
    except ValueError as exc:
        raise DimensionError(
            f"the leading (batch) shapes of v {v_.shape[:-1]}, x {x_.shape[:-1]} and theta "
            f"{t_.shape[:-1]} do not broadcast against each other.") from exc
    return v_, x_, t_, batch


def central_difference(g: Callable[[FloatArray, FloatArray, FloatArray], FloatArray],
                        wrt: int, args: list[FloatArray], batch: tuple[int, ...],
                        k: int) -> FloatArray:
    """∂g/∂args[wrt] by central differences, one column per component, over the batch.

    The step of component j is h = FD_REL_STEP * max(|z_j|, 1), and the divisor is the exactly
    representable difference (z_j + h) - (z_j - h).

    Parameters
    ----------
    g : callable
        ``g(v, x, theta)`` on validated arrays, returning shape (batch, k).
    wrt : int
        Which argument to differentiate (0: v, 1: x, 2: θ; see ARG_NAMES).
    args : list of ndarray
        [v, x, θ] as returned by :func:`batch_args`.
    batch : tuple of int
        Their broadcast leading shape.
    k : int
        Size of g.

    Returns
    -------
    ndarray, shape (batch, k, q)
        q is the length of ``args[wrt]``.

    Examples
    --------
    >>> import numpy as np
    >>> J = central_difference(lambda v, x, th: x**2, 1, [np.zeros(1), np.array([3.0]),
    ...                        np.zeros(1)], (), 1)
    >>> bool(abs(J[0, 0] - 6.0) < 1e-8)
    True
    """
    z = args[wrt]
    q = z.shape[-1]
    out = np.empty(batch + (k, q))
    for j in range(q):
        h = FD_REL_STEP * np.maximum(np.abs(z[..., j]), 1.0)
        z_plus, z_minus = z.copy(), z.copy()
        z_plus[..., j] += h
        z_minus[..., j] -= h
        step = z_plus[..., j] - z_minus[..., j]
        a_plus, a_minus = list(args), list(args)
        a_plus[wrt], a_minus[wrt] = z_plus, z_minus
        out[..., :, j] = (g(*a_plus) - g(*a_minus)) / step[..., np.newaxis]
    return out


# ----------------------------------------------------------------------------------------------
# SymbolicPerturbation
# ----------------------------------------------------------------------------------------------

def _as_symbols(group: str, symbols: Any) -> tuple[sp.Symbol, ...]:
    if isinstance(symbols, sp.Symbol):
        return (symbols,)
    if isinstance(symbols, (str, bytes)) or not isinstance(symbols, Iterable):
        raise DimensionError(f"{group} must be a sequence of SymPy symbols (for example "
                             f"sympy.symbols('a b')); got {symbols!r}.")
    out = tuple(symbols)
    for s in out:
        if not isinstance(s, sp.Symbol):
            raise DimensionError(f"{group} must hold SymPy symbols only; got {s!r} of type "
                                 f"{type(s).__name__}.")
    return out


def _as_column(expr: Any) -> sp.ImmutableMatrix:
    if isinstance(expr, sp.MatrixBase):
        if expr.rows != 1 and expr.cols != 1:
            raise DimensionError(f"expr must be a vector with k entries; got a {expr.rows}x"
                                 f"{expr.cols} matrix.")
        entries = list(expr)
    elif isinstance(expr, (list, tuple)):
        entries = list(expr)
    else:
        entries = [expr]
    if not entries:
        raise DimensionError("expr must have at least one entry (k >= 1); got none.")
    column = []
    for i, e in enumerate(entries):
        if isinstance(e, (str, bytes)):
            raise DimensionError(f"expr entry {i} is a string; build strings with "
                                 f"parse_perturbation, which never evaluates code.")
        try:
            e = sp.sympify(e, strict=True)
        except sp.SympifyError as exc:
            raise DimensionError(f"expr entry {i} is not a SymPy expression: {e!r}.") from exc
        if not isinstance(e, sp.Expr):
            raise DimensionError(f"expr entry {i} must be a scalar SymPy expression; got "
                                 f"{type(e).__name__}: {e}.")
        column.append(e)
    return sp.ImmutableMatrix(len(column), 1, column)


def _check_expression(expr: sp.ImmutableMatrix, declared: tuple[sp.Symbol, ...]) -> None:
    undeclared = expr.free_symbols - set(declared)
    if undeclared:
        names = ", ".join(sorted(str(s) for s in undeclared))
        raise DimensionError(
            f"expr depends on symbols that are not among u, y, x, theta: {names}. Declare "
            f"them in the right group, or substitute numbers for known constants "
            f"(expr.subs({{...}})).")
    undefined = expr.atoms(AppliedUndef)
    if undefined:
        raise DimensionError(f"expr contains undefined functions {sorted(map(str, undefined))}; "
                             f"g must be an explicit expression so that it can be differentiated.")
    if expr.has(sp.I):
        raise DimensionError("expr must be real-valued; it contains the imaginary unit I.")
    if expr.has(sp.zoo, sp.oo, -sp.oo, sp.nan):
        raise NonFiniteError(f"expr contains a non-finite constant (zoo, oo or nan): "
                             f"{list(expr)}; check for divisions by zero such as 1/0 or log(0).")
    huge = [a for a in expr.atoms(sp.Number) if abs(a) > _FLOAT64_MAX]
    if huge:
        raise NonFiniteError(f"expr contains constants beyond the float64 range: "
                             f"{[sp.N(a, 6) for a in huge]}.")


def _a_e_derivative(M: sp.ImmutableMatrix) -> sp.ImmutableMatrix:
    """Drop the DiracDelta terms of a derivative (zero away from the jumps of sign, Heaviside)."""
    return sp.ImmutableMatrix(M.replace(sp.DiracDelta, lambda *args: sp.S.Zero))


def _lambdify(args: list[sp.Symbol], M: sp.ImmutableMatrix) -> Callable[..., list[Any]]:
    return lambdify_numpy(args, list(M))


@final
@dataclass(frozen=True, slots=True, init=False, repr=False)
class SymbolicPerturbation(Perturbation):
    """φ = g(v, x, θ) given as a SymPy expression, with exact Jacobians (Sec. II).

    Build it with :meth:`from_sympy` (or :func:`parse_perturbation` from text). The
    Jacobians ∂g/∂v, ∂g/∂x and ∂g/∂θ are derived with SymPy, and g and the three Jacobians
    are lambdified to vectorised numpy functions, all once, on construction.

    Attributes
    ----------
    expr : sympy.ImmutableMatrix, shape (k, 1)
        g in the user's symbols.
    u, y, x, theta : tuple of sympy.Symbol
        The symbols of the inputs (may be empty), outputs, states and parameters, in the
        order of the components of v = col(u, y), x and θ.

    Notes
    -----
    Every symbol is replaced by a real-valued dummy before differentiating, so that
    d|y|/dy = sign(y) rather than an expression in re(y) and im(y). Derivatives of
    piecewise-constant functions are taken almost everywhere: the DiracDelta terms from
    sign or Heaviside are dropped. At y = 0, d|y|/dy evaluates to sign(0) = 0.

    NaN or inf in an argument is not an error here: it propagates, by numpy's rules, to
    every entry that depends on that argument (entries that do not depend on it stay
    finite). The observer decides what to do with non-finite data.

    Examples
    --------
    >>> import numpy as np, sympy as sp
    >>> from thetahat.model.perturbation import SymbolicPerturbation
    >>> u, y, w, eta, a0 = sp.symbols("u y omega eta alpha0")
    >>> g = SymbolicPerturbation.from_sympy(260 * eta * sp.Abs(y) / (a0 + 0.05),
    ...                                     u=[u], y=[y], x=[w, eta], theta=[a0])
    >>> g.dims
    (2, 1, 1, 1, 1)
    >>> g.jacobian("v")
    Matrix([[0, 260*eta*sign(y)/(alpha0 + 0.05)]])
    >>> g.dg_dv(np.array([[1.0, -2.0]]), np.array([0.5, 1e-3]), np.array([0.28])).shape
    (1, 1, 2)
    """

    expr: sp.ImmutableMatrix
    u: tuple[sp.Symbol, ...]
    y: tuple[sp.Symbol, ...]
    x: tuple[sp.Symbol, ...]
    theta: tuple[sp.Symbol, ...]
    _jacobians: Mapping[str, sp.ImmutableMatrix] = field(repr=False, compare=False)
    _functions: Mapping[str, Callable[..., list[Any]]] = field(repr=False, compare=False)
    _dims: tuple[int, int, int, int, int] = field(repr=False, compare=False)

    def __init__(self, *, expr: Any, u: Any, y: Any, x: Any, theta: Any) -> None:
        groups = {"u": _as_symbols("u", u), "y": _as_symbols("y", y),
                  "x": _as_symbols("x", x), "theta": _as_symbols("theta", theta)}
        if not groups["x"]:
            raise DimensionError("x must hold at least one symbol (n >= 1).")
        seen: dict[sp.Symbol, str] = {}
        for group, symbols in groups.items():
            for s in symbols:
                if s in seen:
                    where = ("twice in " + group) if seen[s] == group else \
                        f"in both {seen[s]} and {group}"
                    raise DimensionError(
                        f"symbol {s} appears {where}; every argument of g(v, x, theta) needs "
                        f"its own symbol (for a measured state use a separate output symbol, "
                        f"as the paper's LuGre g uses |y| rather than |omega|, Remark 4).")
                seen[s] = group
        declared = tuple(seen)
        column = _as_column(expr)
        _check_expression(column, declared)

        real = tuple(sp.Dummy(s.name, real=True) for s in declared)
        to_real, back = dict(zip(declared, real)), dict(zip(real, declared))
        g_real = column.xreplace(to_real)
        sizes = [len(groups[gname]) for gname in ("u", "y", "x", "theta")]
        m, r, n = sizes[0], sizes[1], sizes[2]
        wrt = {"v": list(real[:m + r]), "x": list(real[m + r:m + r + n]),
               "theta": list(real[m + r + n:])}
        jac_real: dict[str, sp.ImmutableMatrix] = {}
        for name, syms in wrt.items():
            J = _a_e_derivative(g_real.jacobian(syms) if syms
                                else sp.ImmutableMatrix.zeros(column.rows, 0))
            if J.has(sp.Derivative, sp.Subs):
                raise DimensionError(f"SymPy could not differentiate g with respect to {name}: "
                                     f"{J}. Rewrite g with elementary functions.")
            jac_real[name] = J
        args = list(real)
        functions = {"g": _lambdify(args, g_real)}
        functions.update({name: _lambdify(args, J) for name, J in jac_real.items()})
        jacobians = {name: sp.ImmutableMatrix(J.xreplace(back)) for name, J in jac_real.items()}

        object.__setattr__(self, "expr", column)
        for group, symbols in groups.items():
            object.__setattr__(self, group, symbols)
        object.__setattr__(self, "_jacobians", MappingProxyType(jacobians))
        object.__setattr__(self, "_functions", MappingProxyType(functions))
        object.__setattr__(self, "_dims", (len(self.x), len(self.u), len(self.y),
                                           len(self.theta), column.rows))

    @classmethod
    def from_sympy(cls, expr: Any, *, u: Sequence[sp.Symbol], y: Sequence[sp.Symbol],
                   x: Sequence[sp.Symbol], theta: Sequence[sp.Symbol]) -> SymbolicPerturbation:
        """Build g from a SymPy expression.

        Parameters
        ----------
        expr : sympy.Expr, list of sympy.Expr, or sympy.Matrix with k entries
            φ = g(v, x, θ); a row or column vector for k > 1.
        u : sequence of sympy.Symbol, length m
            Known inputs (may be empty). v = col(u, y).
        y : sequence of sympy.Symbol, length r
            Measured outputs.
        x : sequence of sympy.Symbol, length n
            States.
        theta : sequence of sympy.Symbol, length p
            Unknown parameters.

        Returns
        -------
        SymbolicPerturbation

        Raises
        ------
        DimensionError
            A symbol is declared twice, ``expr`` uses an undeclared symbol or an undefined
            function, is complex, empty or not a vector.
        NonFiniteError
            ``expr`` contains zoo, oo or nan.

        Examples
        --------
        >>> import sympy as sp
        >>> from thetahat.model.perturbation import SymbolicPerturbation
        >>> y, x1, th = sp.symbols("y x1 theta1")
        >>> SymbolicPerturbation.from_sympy([th * x1, sp.sin(y)], u=[], y=[y], x=[x1],
        ...                                 theta=[th]).dims
        (1, 0, 1, 1, 2)
        """
        return cls(expr=expr, u=u, y=y, x=x, theta=theta)

    @property
    def dims(self) -> tuple[int, int, int, int, int]:
        """(n, m, r, p, k): states, inputs, outputs, parameters, perturbation size."""
        return self._dims

    def jacobian(self, wrt: str) -> sp.ImmutableMatrix:
        """The symbolic Jacobian of g in the user's symbols.

        Parameters
        ----------
        wrt : {"v", "x", "theta"}
            ∂g/∂v (k, m + r) with v = col(u, y), ∂g/∂x (k, n) or ∂g/∂θ (k, p).

        Returns
        -------
        sympy.ImmutableMatrix

        Examples
        --------
        >>> import sympy as sp
        >>> from thetahat.model.perturbation import SymbolicPerturbation
        >>> y, x1, th = sp.symbols("y x1 theta1")
        >>> SymbolicPerturbation.from_sympy(th * x1**2, u=[], y=[y], x=[x1],
        ...                                 theta=[th]).jacobian("x")
        Matrix([[2*theta1*x1]])
        """
        if wrt not in self._jacobians:
            raise DimensionError(f"wrt must be one of 'v', 'x', 'theta'; got {wrt!r}.")
        return self._jacobians[wrt]

    def _evaluate(self, key: str, width: int | None, v: Any, x: Any, theta: Any) -> FloatArray:
        v_, x_, t_, batch = batch_args(self._dims, v, x, theta)
        k = self._dims[4]
        out = np.empty(batch + ((k,) if width is None else (k, width)))
        if len(batch) != 1 or batch[0] <= EVAL_BLOCK:
            self._fill(key, width, out, v_, x_, t_)
            return out
        # a long record a block of rows at a time: the printed expression's intermediates
        # (one array per subexpression) stay a block long
        for a in range(0, batch[0], EVAL_BLOCK):
            rows = slice(a, a + EVAL_BLOCK)
            self._fill(key, width, out[rows],
                       *(arg[rows] if arg.ndim == 2 and arg.shape[0] == batch[0] else arg
                         for arg in (v_, x_, t_)))
        return out

    def _fill(self, key: str, width: int | None, out: FloatArray, *args: FloatArray) -> None:
        """Write the entries of ``key`` at ``args`` (v, x, θ) into ``out``."""
        cols = [a[..., i] for a in args for i in range(a.shape[-1])]
        values = self._functions[key](*cols)          # the entries in row-major order
        if width is None:
            for i, value in enumerate(values):
                out[..., i] = value
        else:
            for i, value in enumerate(values):
                out[..., i // width, i % width] = value

    def g(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """φ = g(v, x, θ).

        Parameters
        ----------
        v : array_like, shape (..., m + r)
        x : array_like, shape (..., n)
        theta : array_like, shape (..., p)
            Leading (batch) shapes broadcast against each other.

        Returns
        -------
        ndarray, shape (..., k)

        Examples
        --------
        >>> import sympy as sp
        >>> from thetahat.model.perturbation import SymbolicPerturbation
        >>> y, x1, th = sp.symbols("y x1 theta1")
        >>> pert = SymbolicPerturbation.from_sympy(th * x1, u=[], y=[y], x=[x1], theta=[th])
        >>> pert.g([0.0], [[1.0], [2.0]], [3.0])
        array([[3.],
               [6.]])
        """
        return self._evaluate("g", None, v, x, theta)

    def dg_dv(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂v with v = col(u, y); shape (..., k, m + r). Arguments as in :meth:`g`."""
        return self._evaluate("v", self.dims[1] + self.dims[2], v, x, theta)

    def dg_dx(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂x; shape (..., k, n). Arguments as in :meth:`g`."""
        return self._evaluate("x", self.dims[0], v, x, theta)

    def dg_dtheta(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂θ; shape (..., k, p). Arguments as in :meth:`g`."""
        return self._evaluate("theta", self.dims[3], v, x, theta)

    def __reduce__(self) -> tuple[Any, ...]:
        # The lambdified functions do not pickle; rebuild them from the expression.
        return (_rebuild_symbolic, (self.expr, self.u, self.y, self.x, self.theta))

    def __repr__(self) -> str:
        def names(symbols: tuple[sp.Symbol, ...]) -> str:
            return "(" + ", ".join(map(str, symbols)) + ")"
        return (f"SymbolicPerturbation(g={list(self.expr)}, u={names(self.u)}, "
                f"y={names(self.y)}, x={names(self.x)}, theta={names(self.theta)})")


def _rebuild_symbolic(expr: sp.ImmutableMatrix, u: tuple[sp.Symbol, ...],
                      y: tuple[sp.Symbol, ...], x: tuple[sp.Symbol, ...],
                      theta: tuple[sp.Symbol, ...]) -> SymbolicPerturbation:
    return SymbolicPerturbation(expr=expr, u=u, y=y, x=x, theta=theta)


# ----------------------------------------------------------------------------------------------
# CallablePerturbation
# ----------------------------------------------------------------------------------------------

NumericFunction = Callable[[FloatArray, FloatArray, FloatArray], Any]


def _nonnegative_int(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise DimensionError(f"{name} must be an integer >= {minimum}; got {value!r}.")
    if value < minimum:
        raise DimensionError(f"{name} must be >= {minimum}; got {value}.")
    return int(value)


@final
@dataclass(frozen=True, slots=True, init=False, repr=False)
class CallablePerturbation(Perturbation):
    """φ = g(v, x, θ) given as numeric functions, with optional user Jacobians.

    Parameters
    ----------
    g : callable ``g(v, x, theta) -> (..., k)``
        Must work on batches: index the components along the last axis (``x[..., 1]``,
        not ``x[1]``). It receives v (..., m + r), x (..., n) and theta (..., p) already
        broadcast to one batch shape (read-only views) and must return exactly (..., k).
    n, m, r, p, k : int
        States, inputs, outputs, parameters and the size of φ (``n, k >= 1``).
    dg_dv, dg_dx, dg_dtheta : callable, optional
        ∂g/∂v (..., k, m + r), ∂g/∂x (..., k, n), ∂g/∂θ (..., k, p), same calling rule.
        A missing Jacobian is computed by central finite differences of ``g``: the step
        of component j is h = FD_REL_STEP * max(|z_j|, 1) with FD_REL_STEP = eps**(1/3)
        ≈ 6.1e-6, which balances truncation (O(h**2)) against rounding (O(eps / h));
        this costs 2 evaluations of g per component.

    Raises
    ------
    DimensionError
        A dimension is not a valid integer or a function is not callable; at call time,
        when a function returns the wrong shape.

    Notes
    -----
    What NaN does is up to the user's functions; finite differences propagate it.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.perturbation import CallablePerturbation
    >>> pert = CallablePerturbation(g=lambda v, x, th: th * x[..., :1] ** 2,
    ...                             n=1, m=0, r=1, p=1, k=1)
    >>> np.round(pert.dg_dx(np.array([0.0]), np.array([3.0]), np.array([2.0])), 6)
    array([[12.]])
    """

    _g: NumericFunction
    _dims: tuple[int, int, int, int, int]
    _dg_dv: NumericFunction | None
    _dg_dx: NumericFunction | None
    _dg_dtheta: NumericFunction | None

    def __init__(self, *, g: NumericFunction, n: int, m: int, r: int, p: int, k: int,
                 dg_dv: NumericFunction | None = None, dg_dx: NumericFunction | None = None,
                 dg_dtheta: NumericFunction | None = None) -> None:
        dims = (_nonnegative_int("n", n, 1), _nonnegative_int("m", m, 0),
                _nonnegative_int("r", r, 0), _nonnegative_int("p", p, 0),
                _nonnegative_int("k", k, 1))
        for name, func in (("g", g), ("dg_dv", dg_dv), ("dg_dx", dg_dx),
                           ("dg_dtheta", dg_dtheta)):
            if func is not None and not callable(func):
                raise DimensionError(f"{name} must be callable as {name}(v, x, theta); got "
                                     f"{type(func).__name__}.")
        object.__setattr__(self, "_g", g)
        object.__setattr__(self, "_dims", dims)
        object.__setattr__(self, "_dg_dv", dg_dv)
        object.__setattr__(self, "_dg_dx", dg_dx)
        object.__setattr__(self, "_dg_dtheta", dg_dtheta)

    @property
    def dims(self) -> tuple[int, int, int, int, int]:
        """(n, m, r, p, k): states, inputs, outputs, parameters, perturbation size."""
        return self._dims

    @property
    def supplied_jacobians(self) -> tuple[str, ...]:
        """Which Jacobians the user supplied, among ``("v", "x", "theta")``."""
        funcs = (self._dg_dv, self._dg_dx, self._dg_dtheta)
        return tuple(name for name, f in zip(ARG_NAMES, funcs) if f is not None)

    def _call(self, name: str, func: NumericFunction, shape: tuple[int, ...],
              v: FloatArray, x: FloatArray, theta: FloatArray,
              batch: tuple[int, ...]) -> FloatArray:
        n, m, r, p, _ = self._dims
        args = [np.broadcast_to(a, batch + (q,)) for a, q in ((v, m + r), (x, n), (theta, p))]
        value = np.asarray(func(*args))
        if np.iscomplexobj(value):
            raise DimensionError(f"the user function {name} returned complex values; g and "
                                 f"its Jacobians must be real.")
        value = value.astype(np.float64)
        if value.shape != batch + shape:
            raise DimensionError(
                f"the user function {name} returned shape {value.shape}; expected "
                f"{batch + shape} (batch {batch} + {shape}). Index the arguments along the "
                f"last axis (x[..., 0], not x[0]) and keep the batch axes.")
        return value

    def _g_validated(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        batch = np.broadcast_shapes(v.shape[:-1], x.shape[:-1], theta.shape[:-1])
        return self._call("g", self._g, (self._dims[4],), v, x, theta, batch)

    def g(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """φ = g(v, x, θ); shape (..., k).

        Parameters
        ----------
        v : array_like, shape (..., m + r)
        x : array_like, shape (..., n)
        theta : array_like, shape (..., p)
            Leading (batch) shapes broadcast against each other.

        Returns
        -------
        ndarray, shape (..., k)

        Examples
        --------
        >>> from thetahat.model.perturbation import CallablePerturbation
        >>> pert = CallablePerturbation(g=lambda v, x, th: th * x, n=1, m=0, r=1, p=1, k=1)
        >>> pert.g([0.0], [2.0], [[1.0], [3.0]])
        array([[2.],
               [6.]])
        """
        v_, x_, t_, batch = batch_args(self._dims, v, x, theta)
        return self._call("g", self._g, (self._dims[4],), v_, x_, t_, batch)

    def _jacobian(self, wrt: int, func: NumericFunction | None, v: Any, x: Any,
                  theta: Any) -> FloatArray:
        v_, x_, t_, batch = batch_args(self._dims, v, x, theta)
        args = [v_, x_, t_]
        width = args[wrt].shape[-1]
        if func is None:
            return central_difference(self._g_validated, wrt, args, batch, self._dims[4])
        return self._call("dg_d" + ARG_NAMES[wrt], func, (self._dims[4], width),
                          v_, x_, t_, batch)

    def dg_dv(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂v with v = col(u, y); shape (..., k, m + r). Arguments as in :meth:`g`."""
        return self._jacobian(0, self._dg_dv, v, x, theta)

    def dg_dx(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂x; shape (..., k, n). Arguments as in :meth:`g`."""
        return self._jacobian(1, self._dg_dx, v, x, theta)

    def dg_dtheta(self, v: FloatArray, x: FloatArray, theta: FloatArray) -> FloatArray:
        """∂g/∂θ; shape (..., k, p). Arguments as in :meth:`g`."""
        return self._jacobian(2, self._dg_dtheta, v, x, theta)

    def __repr__(self) -> str:
        n, m, r, p, k = self._dims
        fd = [name for name in ARG_NAMES if name not in self.supplied_jacobians]
        return (f"CallablePerturbation(g={getattr(self._g, '__name__', type(self._g).__name__)}, "
                f"n={n}, m={m}, r={r}, p={p}, k={k}, supplied_jacobians="
                f"{self.supplied_jacobians}, finite_differences={tuple(fd)})")
