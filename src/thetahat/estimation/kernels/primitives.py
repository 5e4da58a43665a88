"""The vocabulary the step is written in, and its NumPy implementation (a leading batch axis).

The formulas of one sample (:mod:`~thetahat.estimation.observer.formulas`, the update laws'
:mod:`~thetahat.estimation.observer.laws.formulas`) are plain Python functions whose free names are the
*primitives* below, the model functions (g with its Jacobians, θ*) and the model's dimensions.
A back end is a binding of those names:

* :data:`NUMPY` (this module): a vector is an array of shape (..., size) — one row as ``(size,)``
  or B rows as ``(B, size)`` — and a matrix (a, b), (1, a, b) shared by the rows or (B, a, b)
  per row. ``get(a, i)`` is the column ``a[..., i]``, the products are (batched) ``matmul``,
  ``solve`` is LAPACK's, ``where`` is :func:`numpy.where`, ``any_`` reduces over the rows;
* the scalar back end (:mod:`~thetahat.estimation.observer.kernel_source`): one row, every primitive a
  loop over scalars, the whole emitted as the source of a numba module.

:func:`bind` gives formula functions the globals of a back end: the same code objects run
with other names (``types.FunctionType(code, globals)``). Per-row control flow in a formula is
written branch-free (``where``) or as a reduction over the rows (``if any_(bad): ...``), so it
means the same for one row and for B.

The primitives (``acc`` of the products: 0 assigns, 1 adds, -1 subtracts):

=======================================  ==========================================================
``get(a, i)``, ``put(a, i, val)``        entry i of a vector (a column of B rows)
``get2(M, i, j)``, ``put2(M, i, j, v)``  entry (i, j) of a per-row matrix
``copy(n, a, ao, out, oo)``              out[oo:oo+n] = a[ao:ao+n]
``axpy(n, c, a, ao, out, oo)``           out[oo:oo+n] += c·a[ao:ao+n]
``fill(M, val)``                         every entry of a work buffer
``mv(M, a, b, x, xo, out, oo, acc)``     out[oo:oo+a] (+|-)= M x[xo:xo+b], M (a, b)
``mm(A, B, a, c, b, out, ro, co, acc)``  out[ro:ro+a, co:co+b] (+)= A B, A (a, c), B (c, b)
``mmt(A, B, a, c, b, out)``              out = A Bᵀ, A (a, c), B (b, c)
``eye_minus(M, q, c)``                   M ← I − c M (q × q)
``solve(q, M, rhs)``                     rhs ← M⁻¹ rhs (M is overwritten); returns ST_OK, or
                                         ST_SINGULAR at a zero pivot (per row)
``expm(q, Z, E, T, U)``                  E = exp(Z) (T, U: work)
``where``, ``clip``, ``maximum``         elementwise, as in NumPy
``exp``, ``sqrt``, ``absolute``          elementwise
``norm(a, n)``                           Euclidean norm per row, without overflow
``isfinite``, ``isnan``                  elementwise
``not_``, ``and_``, ``or_``              elementwise logic
``any_(b)``, ``count_(b)``               over the rows: any, how many (one row: b, int(b))
``sumsq(a, n)``                          Σ a[i]² per row
=======================================  ==========================================================
"""

from __future__ import annotations

import ast
import functools
import inspect
import math
import textwrap
import threading
import types
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.linalg.lapack import dgesv as _gesv

from ...errors import ThetahatError
from ...model.set_geometry import safe_norm
from ..status import Status

__all__ = ["ARRAYS", "NUMPY", "NUMPY_ROW", "PRIMITIVES", "AliasingError", "bind", "bound",
           "check_aliasing"]

FloatArray = NDArray[np.float64]

#: The names every back end binds.
PRIMITIVES = ("get", "put", "get2", "put2", "copy", "axpy", "fill", "mv", "mm", "mmt",
              "eye_minus", "solve", "expm", "where", "clip", "maximum", "exp", "sqrt",
              "absolute", "norm", "isfinite", "isnan", "not_", "and_", "or_", "any_", "count_",
              "sumsq")


def _get(a: FloatArray, i: int) -> Any:
    return a[..., i]


def _put(a: FloatArray, i: int, val: Any) -> None:
    a[..., i] = val


def _get2(M: FloatArray, i: int, j: int) -> Any:
    return M[..., i, j]


def _put2(M: FloatArray, i: int, j: int, val: Any) -> None:
    M[..., i, j] = val


def _copy(n: int, a: FloatArray, ao: int, out: FloatArray, oo: int) -> None:
    out[..., oo:oo + n] = a[..., ao:ao + n]


def _axpy(n: int, c: Any, a: FloatArray, ao: int, out: FloatArray, oo: int) -> None:
    if isinstance(c, float) and c == 1.0:
        out[..., oo:oo + n] += a[..., ao:ao + n]
        return
    if np.ndim(c):
        c = np.asarray(c)[..., None]
    out[..., oo:oo + n] += c * a[..., ao:ao + n]


def _fill(M: FloatArray, val: float) -> None:
    M[...] = val


def _product(M: FloatArray, xs: FloatArray) -> FloatArray:
    """M x for M (a, b), (1, a, b) or (B, a, b) and x (b,) or (B, b)."""
    if M.ndim == 2:
        return M @ xs if xs.ndim == 1 else xs @ M.T
    if M.shape[0] == 1:
        return xs @ M[0].T
    if xs.ndim == 1:
        return M @ xs
    return np.matmul(M, xs[..., None])[..., 0]


def _mv(M: FloatArray, a: int, b: int, x: FloatArray, xo: int, out: FloatArray, oo: int,
        acc: int) -> None:
    res = _product(M, x[..., xo:xo + b])
    if acc == 0:
        out[..., oo:oo + a] = res
    elif acc > 0:
        out[..., oo:oo + a] += res
    else:
        out[..., oo:oo + a] -= res


def _squeeze_to(res: FloatArray, ndim: int) -> FloatArray:
    """Drop a leading axis of length 1 that a shared (1, a, b) operand added."""
    return res[0] if res.ndim > ndim else res


def _mm(A: FloatArray, B: FloatArray, a: int, c: int, b: int, out: FloatArray, ro: int,
        co: int, acc: int) -> None:
    res = _squeeze_to(np.matmul(A, B), out.ndim)
    if acc == 0:
        out[..., ro:ro + a, co:co + b] = res
    else:
        out[..., ro:ro + a, co:co + b] += res


def _mmt(A: FloatArray, B: FloatArray, a: int, c: int, b: int, out: FloatArray) -> None:
    out[...] = _squeeze_to(np.matmul(A, np.swapaxes(B, -1, -2)), out.ndim)


def _eye_minus(M: FloatArray, q: int, c: float) -> None:
    M *= -c
    idx = np.arange(q)
    M[..., idx, idx] += 1.0


def _solve(q: int, M: FloatArray, rhs: FloatArray) -> Any:
    """rhs ← M⁻¹ rhs; the status (:class:`~thetahat.estimation.status.Status`) per row: a zero
    pivot of LAPACK's LU (info > 0) is ``SINGULAR`` and leaves NaN in that row's rhs."""
    if M.ndim == 2:                     # one row: LAPACK's gesv (np.linalg.solve costs ~4 µs)
        _, _, x, info = _gesv(M, rhs)
        if info > 0:
            rhs[...] = np.nan
            return int(Status.SINGULAR)
        rhs[...] = x
        return int(Status.OK)
    status = np.full(M.shape[:-2], int(Status.OK))
    try:
        rhs[...] = np.linalg.solve(M, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:       # some row is singular: find it, row by row
        for i in np.ndindex(*M.shape[:-2]):
            _, _, x, info = _gesv(M[i], rhs[i])
            if info > 0:
                rhs[i] = np.nan
                status[i] = int(Status.SINGULAR)
            else:
                rhs[i] = x
    return status


def _expm(q: int, Z: FloatArray, E: FloatArray, T: FloatArray, U: FloatArray) -> None:
    E[...] = scipy.linalg.expm(Z)


def _norm(a: FloatArray, n: int) -> Any:
    return safe_norm(a)


def _any(b: Any) -> bool:
    if isinstance(b, (bool, np.bool_)):
        return bool(b)
    return bool(b.any())


def _count(b: Any) -> int:
    if isinstance(b, (bool, np.bool_)):
        return int(b)
    return int(np.count_nonzero(b))


def _clip(a: Any, lo: Any, hi: Any) -> Any:
    return np.minimum(np.maximum(a, lo), hi)


def _sumsq(a: FloatArray, n: int) -> Any:
    if a.ndim == 1:
        return float(np.dot(a, a))
    return np.einsum("...i,...i->...", a, a)


#: The NumPy bindings of :data:`PRIMITIVES`.
NUMPY: Mapping[str, Any] = types.MappingProxyType({
    "get": _get, "put": _put, "get2": _get2, "put2": _put2, "copy": _copy, "axpy": _axpy,
    "fill": _fill, "mv": _mv, "mm": _mm, "mmt": _mmt, "eye_minus": _eye_minus,
    "solve": _solve, "expm": _expm, "where": np.where, "clip": _clip, "maximum": np.maximum,
    "exp": np.exp, "sqrt": np.sqrt, "absolute": np.absolute, "norm": _norm, "isfinite": np.isfinite,
    "isnan": np.isnan, "not_": np.logical_not, "and_": np.logical_and,
    "or_": np.logical_or, "any_": _any, "count_": _count, "sumsq": _sumsq})


def _row_put(a: FloatArray, i: int, val: Any) -> None:
    a[i] = val


def _row_put2(M: FloatArray, i: int, j: int, val: Any) -> None:
    M[i, j] = val


def _row_mv(M: FloatArray, a: int, b: int, x: FloatArray, xo: int, out: FloatArray, oo: int,
            acc: int) -> None:
    res = M @ x[xo:xo + b]
    if acc == 0:
        out[oo:oo + a] = res
    elif acc > 0:
        out[oo:oo + a] += res
    else:
        out[oo:oo + a] -= res


def _row_mm(A: FloatArray, B: FloatArray, a: int, c: int, b: int, out: FloatArray, ro: int,
            co: int, acc: int) -> None:
    if acc == 0:
        out[ro:ro + a, co:co + b] = A @ B
    else:
        out[ro:ro + a, co:co + b] += A @ B


def _row_axpy(n: int, c: Any, a: FloatArray, ao: int, out: FloatArray, oo: int) -> None:
    out[oo:oo + n] += c * a[ao:ao + n]


def _row_copy(n: int, a: FloatArray, ao: int, out: FloatArray, oo: int) -> None:
    out[oo:oo + n] = a[ao:ao + n]


def _row_eye_minus(M: FloatArray, q: int, c: float) -> None:
    M *= -c
    M.flat[::q + 1] += 1.0


def _row_where(c: Any, a: Any, b: Any) -> Any:
    return a if c else b


def _row_clip(a: Any, lo: Any, hi: Any) -> Any:
    return min(max(a, lo), hi)                  # NaN in a stays NaN, as with np.clip


#: The NumPy bindings for one row (vectors (size,), matrices (a, b)): the element primitives
#: on scalars, the block ones on 2-D arrays. Same meaning as :data:`NUMPY` on one row, with
#: less dispatch per call (the Python step runs one row per call).
NUMPY_ROW: Mapping[str, Any] = types.MappingProxyType({
    **NUMPY, "get": lambda a, i: a[i], "put": _row_put, "get2": lambda M, i, j: M[i, j],
    "put2": _row_put2, "copy": _row_copy, "axpy": _row_axpy, "mv": _row_mv, "mm": _row_mm,
    "eye_minus": _row_eye_minus, "where": _row_where, "clip": _row_clip,
    "isfinite": math.isfinite, "isnan": math.isnan, "not_": lambda a: not a,
    "and_": lambda a, b: bool(a and b), "or_": lambda a, b: bool(a or b),
    "any_": bool, "count_": lambda b: 1 if b else 0})


#: The array parameters of the block primitives, by position, and which of them are written.
#: The back ends differ where a written array is also read through another argument (NumPy
#: computes the product first, the scalar loops write as they go: ``mv(M, …, x, …, x, …)``
#: gives [2, 1] in one and [2, 2] in the other), so the formulas may not do that: see
#: :func:`check_aliasing`.
ARRAYS: Mapping[str, tuple[tuple[int, ...], tuple[int, ...]]] = types.MappingProxyType({
    "copy": ((1, 3), (3,)), "axpy": ((2, 4), (4,)), "mv": ((0, 3, 5), (5,)),
    "mm": ((0, 1, 5), (5,)), "mmt": ((0, 1, 5), (5,)), "solve": ((1, 2), (1, 2)),
    "expm": ((1, 2, 3, 4), (2, 3, 4))})


class AliasingError(ThetahatError, ValueError):
    """A formula passes one array as a written argument of a primitive and as another of its
    arguments (the back ends would disagree)."""


@functools.cache
def _aliasing_problems(code: types.CodeType, source: str) -> tuple[str, ...]:
    problems = []
    for node in ast.walk(ast.parse(textwrap.dedent(source))):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id in ARRAYS):
            continue
        arrays, written = ARRAYS[node.func.id]
        names = {i: ast.unparse(node.args[i]) for i in arrays if i < len(node.args)}
        for w in written:
            clash = [i for i, text in names.items() if i != w and text == names.get(w)]
            if clash:
                problems.append(f"{code.co_name}, line {node.lineno}: {ast.unparse(node)} "
                                f"passes {names[w]} as argument {w + 1} (written) and "
                                f"{', '.join(str(i + 1) for i in clash)}")
    return tuple(dict.fromkeys(problems))


def check_aliasing(fn: Callable[..., Any]) -> None:
    """Refuse a formula that passes one array as a written argument of a primitive and as
    another of its arguments (the same expression twice; :data:`ARRAYS`).

    Run where the formulas are bound (:func:`bind`) and emitted
    (:func:`~thetahat.estimation.observer.kernel_source.kernel_source`), so that every back end
    computes the same thing.

    Parameters
    ----------
    fn : function
        A formula (its source is read).

    Raises
    ------
    AliasingError
        The calls that alias, with their lines.

    Examples
    --------
    >>> def bad(M, x):
    ...     mv(M, 2, 2, x, 0, x, 0, 0)  # noqa: F821
    >>> check_aliasing(bad)
    Traceback (most recent call last):
    ...
    thetahat.estimation.kernels.primitives.AliasingError: ...passes x as argument 6 (written) and 4...
    """
    try:
        source = inspect.getsource(fn)
    except (OSError, TypeError):        # no source (built in a string): nothing to check
        return
    problems = _aliasing_problems(fn.__code__, source)
    if problems:
        raise AliasingError("a formula aliases an output of a primitive with another of its "
                            "arguments (the back ends would disagree); use a work buffer: "
                            + "; ".join(problems))


def bind(functions: Mapping[str, Callable[..., Any]], names: Mapping[str, Any]
         ) -> dict[str, Any]:
    """The formula ``functions`` rebuilt with the globals ``names`` (and each other).

    Parameters
    ----------
    functions : mapping of str to function
        Formula functions (their code objects are reused, their module globals are not).
    names : mapping of str to object
        The back end's primitives, the model functions and the constants the formulas read.

    Returns
    -------
    dict
        The namespace: ``names`` plus the rebound functions under their keys.

    Raises
    ------
    AliasingError
        A function aliases a primitive's output with another argument
        (:func:`check_aliasing`).

    Examples
    --------
    >>> import numpy as np
    >>> def norm2(a):
    ...     return sumsq(a, 2)        # a free name, bound below  # noqa: F821
    >>> env = bind({"norm2": norm2}, NUMPY)
    >>> env["norm2"](np.array([[3.0, 4.0], [1.0, 0.0]])).tolist()
    [25.0, 1.0]
    """
    env: dict[str, Any] = dict(names)
    for key, fn in functions.items():
        check_aliasing(fn)
        code = fn.__code__
        env[key] = types.FunctionType(code, env, code.co_name, fn.__defaults__, None)
    return env


#: Namespaces kept by :func:`bound` (one per owner in use).
_BOUND_KEPT = 128
_bound: OrderedDict[tuple[int, Any], tuple[object, dict[str, Any]]] = OrderedDict()
_bound_lock = threading.Lock()


def bound(owner: object, key: Any, functions: Mapping[str, Callable[..., Any]],
          names: Callable[[], Mapping[str, Any]]) -> dict[str, Any]:
    """:func:`bind` once per ``(owner, key)``: the namespace is kept while the owner is in use.

    Parameters
    ----------
    owner : object
        What the bindings close over (a law, a perturbation); kept alive with the namespace.
    key : hashable
        Distinguishes bindings of one owner (e.g. the state layout).
    functions : mapping of str to function
    names : callable
        Builds the names on a miss.

    Returns
    -------
    dict
        As :func:`bind`.

    Examples
    --------
    >>> def twice(a):
    ...     return 2.0 * a
    >>> owner = object()
    >>> env = bound(owner, None, {"twice": twice}, lambda: NUMPY)
    >>> bound(owner, None, {"twice": twice}, lambda: NUMPY) is env
    True
    """
    k = (id(owner), key)
    with _bound_lock:
        hit = _bound.get(k)
        if hit is not None and hit[0] is owner:
            _bound.move_to_end(k)
            return hit[1]
    env = bind(functions, names())
    with _bound_lock:
        _bound[k] = (owner, env)
        if len(_bound) > _BOUND_KEPT:
            _bound.popitem(last=False)
    return env
