"""Local arrays of the C printer (:mod:`.c_printer`): NumPy's allocations as fixed C arrays.

Stage 2's kernels (:mod:`~thetahat.estimation.statistical.ekf_kernels`,
:mod:`~thetahat.estimation.statistical.plant_kernel`) are written in numba's subset of Python:
besides the formulas' loops they allocate work arrays (``np.zeros((N, N))``, ``np.empty(n)``,
``np.eye(N)``), copy blocks (``s[:n].copy()``, ``P[n:, n:].copy()``, ``PHt[row].copy()``),
read shapes (``Phi.shape[0]``) and return arrays. Every shape is a compile-time constant of
the specialisation, so each allocation becomes a C array of fixed size declared at the top of
its function (no heap), filled where Python allocates it; a returned array is written through
an output parameter. This module prints the C of those operations; the printer decides where
they go.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from typing import Any

from ..errors import UnsupportedError
from .c_values import Arr, Const

__all__ = ["Region", "allocation_lines", "copy_lines", "prune", "region", "shape_of"]

#: NumPy's allocation functions the printer turns into local arrays.
ALLOCATIONS = ("zeros", "empty", "eye")


def shape_of(value: Any) -> tuple[int, ...]:
    """The shape an allocation's argument gives (a constant or a tuple of constants).

    Parameters
    ----------
    value : Const or tuple of Const

    Returns
    -------
    tuple of int

    Examples
    --------
    >>> shape_of((Const(2), Const(3))), shape_of(Const(4))
    ((2, 3), (4,))
    """
    items = value if isinstance(value, tuple) else (value,)
    if not all(isinstance(v, Const) and isinstance(v.value, int) for v in items):
        raise UnsupportedError("a local array needs a shape known when the C is printed")
    if len(items) not in (1, 2):
        raise UnsupportedError("local arrays are 1-D or 2-D")
    return tuple(int(v.value) for v in items)


def allocation_lines(kind: str, name: str, shape: tuple[int, ...], pad: str) -> list[str]:
    """The C that fills a fresh local array as ``np.<kind>`` does (``empty``: nothing).

    Parameters
    ----------
    kind : {"zeros", "empty", "eye"}
    name : str
        The C array.
    shape : tuple of int
    pad : str
        Indentation.

    Returns
    -------
    list of str

    Examples
    --------
    >>> allocation_lines("eye", "I", (2, 2), "")
    ['for (int q = 0; q < 4; ++q) I[q] = 0.0;', 'for (int q = 0; q < 2; ++q) I[q * 3] = 1.0;']
    """
    size = 1
    for d in shape:
        size *= d
    if kind == "empty" or size == 0:
        return []
    lines = [f"{pad}for (int q = 0; q < {size}; ++q) {name}[q] = 0.0;"]
    if kind == "eye":
        if len(shape) != 2 or shape[0] != shape[1]:
            raise UnsupportedError("np.eye of a non-square shape")
        n = shape[0]
        lines.append(f"{pad}for (int q = 0; q < {n}; ++q) {name}[q * {n + 1}] = 1.0;")
    return lines


class Region:
    """A block of a flat array: ``rows`` × ``cols`` entries from ``offset`` with row stride
    ``stride`` (a 1-D block has one row).

    Parameters
    ----------
    arr : Arr
    offset : str
        The C expression of the first entry's index.
    shape : tuple of int
        The block's shape (what ``.copy()`` allocates).
    stride : int
        The source's row length (2-D blocks).
    """

    __slots__ = ("arr", "offset", "shape", "stride")

    def __init__(self, arr: Arr, offset: str, shape: tuple[int, ...], stride: int) -> None:
        self.arr, self.offset, self.shape, self.stride = arr, offset, shape, stride

    def __repr__(self) -> str:
        return f"Region({self.arr.name}, offset={self.offset}, shape={self.shape})"


def _bounds(lo: Any, hi: Any, length: int) -> tuple[int, int]:
    for v in (lo, hi):
        if v is not None and not (isinstance(v, Const) and isinstance(v.value, int)):
            raise UnsupportedError("a copied block needs constant slice bounds")
    start = 0 if lo is None else lo.value
    stop = length if hi is None else hi.value
    start, stop, _ = slice(start, stop).indices(length)
    return start, max(stop, start)


def region(arr: Arr, index: Sequence[Any], text: Any) -> Region:
    """The block ``arr[index]`` names: slices with constant bounds, or a row of a 2-D array.

    Parameters
    ----------
    arr : Arr
    index : sequence
        Per axis: ``("slice", lo, hi)`` (lo, hi Const or None) or ``("at", value)`` (a
        Const or Scal row index; 2-D arrays, first axis only).
    text : callable
        ``text(value) -> str``: the C of a scalar value.

    Returns
    -------
    Region

    Examples
    --------
    >>> r = region(Arr("P", (4, 4)), [("slice", Const(2), None), ("slice", Const(2), None)],
    ...            str)
    >>> r.offset, r.shape
    ('10', (2, 2))
    """
    if len(index) != len(arr.shape):
        if len(arr.shape) == 2 and len(index) == 1 and index[0][0] == "at":
            index = [index[0], ("slice", None, None)]
        else:
            raise UnsupportedError(f"{arr.name}: a block of a {arr.shape} array")
    if len(arr.shape) == 1:
        if index[0][0] != "slice":
            raise UnsupportedError(f"{arr.name}: an element is not a block")
        a, b = _bounds(index[0][1], index[0][2], arr.shape[0])
        return Region(arr, str(a), (b - a,), b - a)
    cols = arr.shape[1]
    c0, c1 = (_bounds(index[1][1], index[1][2], cols) if index[1][0] == "slice"
              else (-1, -1))
    if c0 < 0:
        raise UnsupportedError(f"{arr.name}: only rows and constant blocks are copied")
    if index[0][0] == "at":
        row = index[0][1]
        if isinstance(row, Const):
            return Region(arr, str(row.value * cols + c0), (c1 - c0,), cols)
        return Region(arr, f"({text(row)}) * {cols} + {c0}", (c1 - c0,), cols)
    r0, r1 = _bounds(index[0][1], index[0][2], arr.shape[0])
    return Region(arr, str(r0 * cols + c0), (r1 - r0, c1 - c0), cols)


def copy_lines(name: str, src: Region, pad: str) -> list[str]:
    """The C that copies block ``src`` into the local array ``name`` (row-major).

    Parameters
    ----------
    name : str
    src : Region
    pad : str

    Returns
    -------
    list of str

    Examples
    --------
    >>> copy_lines("x", Region(Arr("s", (3,)), "0", (2,), 2), "")
    ['for (int q = 0; q < 2; ++q) x[q] = s[0 + q];']
    """
    a = src.arr.name
    if len(src.shape) == 1:
        if src.shape[0] == 0:
            return []
        return [f"{pad}for (int q = 0; q < {src.shape[0]}; ++q) "
                f"{name}[q] = {a}[{src.offset} + q];"]
    rows, cols = src.shape
    if rows * cols == 0:
        return []
    return [f"{pad}for (int q = 0; q < {rows}; ++q) for (int c = 0; c < {cols}; ++c) "
            f"{name}[q * {cols} + c] = {a}[{src.offset} + q * {src.stride} + c];"]


#: A call with side effects (a printed function or the model's): its line is never dropped.
_EFFECT = re.compile(r"\b(f_\w+|rhs_jac)\(")


def _writes_only(line: str, name: str) -> bool:
    """Whether ``line`` is a statement that only stores into ``name`` (an element or the
    scalar), computing nothing with side effects."""
    m = re.fullmatch(r"\s*(?:for \(int q[^)]*\) (?:for \(int c[^)]*\) )?)?"
                     rf"{re.escape(name)}(?:\[[^=]*\])? [-+*/]?= (.*);", line)
    return m is not None and _EFFECT.search(line) is None


def prune(body: list[str], names: Iterable[str]) -> tuple[list[str], set[str]]:
    """Drop the locals among ``names`` that are only ever stored into (dead after a
    specialisation folded their readers away), with their stores; to a fixed point.

    Parameters
    ----------
    body : list of str
        A function's lines.
    names : iterable of str
        Its local scalars and arrays.

    Returns
    -------
    body : list of str
    removed : set of str

    Examples
    --------
    >>> body, dead = prune(["    a = (real_t)s / ns;", "    b = 2.0;", "    c[0] = b;",
    ...                     "    f_g(c);"], ["a", "b", "c"])
    >>> body, sorted(dead)
    (['    b = 2.0;', '    c[0] = b;', '    f_g(c);'], ['a'])
    """
    removed: set[str] = set()
    pending = set(names)
    changed = True
    while changed:
        changed = False
        for name in sorted(pending - removed):
            word = re.compile(rf"(?<![\w>.]){re.escape(name)}\b")
            mentions = [i for i, line in enumerate(body) if word.search(line)]
            if all(_writes_only(body[i], name) for i in mentions):
                drop = set(mentions)
                body = [line for i, line in enumerate(body) if i not in drop]
                removed.add(name)
                changed = True
    return body, removed
