"""The formulas' language: a small subset of Python over named blocks, read once for every printer.

The step's formulas (:mod:`~thetahat.estimation.observer.formulas`,
:mod:`~thetahat.estimation.observer.laws.formulas`) are plain functions in this subset:

* **views** name a block of an array: ``x_hat, z = s[0:NX], s[NX:NX + NK]`` (1-D), or are
  passed as arguments (``g_dx(v, x_hat, theta_hat, g, Gx)``);
* **block statements** assign a block: ``F[:] = P.L @ xz + P.Bv @ v``, ``F_x += P.E @ g``,
  ``Nm[0:NX, 0:NX] = P.E @ Gx``, ``M[:] = eye(q) - c * (Phi1 @ Nm)``, ``W.zc[:] = 0.0``: sums
  and differences of blocks, scalars, matrix–vector and matrix–matrix products (``A @ x``,
  ``A @ B``, ``A @ B.T``) and ``eye(q)``;
* **element statements** read and write entries (``thn[i] = ts[i] - thn[i]``, ``Z[a, c]``),
  with the elementwise vocabulary of :mod:`~thetahat.estimation.kernels.primitives` (``where``,
  ``clip``, ``isfinite``, …), ``for … in range(…)``, ``if``, ``while`` and ``return``.

An array parameter is declared in the numpydoc docstring, with its shape where a block
statement needs its length (``F : array, shape (NQ,)``); a parameter annotated with a tuple of
:mod:`~thetahat.estimation.kernels.kernel_args` has its fields' shapes from
:data:`~thetahat.estimation.kernels.kernel_args.SHAPES`. This module reads a function into a
:class:`Formula` (:func:`definition`: its source, once per process) and describes a block of an
array (:class:`Block`: its array, offset and shape); :mod:`~thetahat.estimation.kernels.printer`
prints formulas for their targets.
"""

from __future__ import annotations

import ast
import functools
import inspect
import re
import textwrap
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ...errors import ThetahatError, UnsupportedError
from .kernel_args import SHAPES

__all__ = ["AliasingError", "Block", "External", "Formula", "add", "const_node", "definition",
           "definitions", "everything", "is_int", "name_node", "same", "slice_bounds",
           "source_tree", "sub"]


class AliasingError(ThetahatError, ValueError):
    """A block statement reads, inside a product, the array it writes (the targets would
    disagree)."""


@dataclass(frozen=True)
class Formula:
    """One function of the subset, parsed.

    Attributes
    ----------
    name : str
        The name it is printed under.
    node : ast.FunctionDef
        Its definition (never modified: printers copy it).
    arrays : mapping of str to tuple of ast.expr or None
        Its array parameters, with their declared shapes (None: undeclared).
    tuples : mapping of str to str
        Its parameters that are named tuples of kernel_args, by type name.
    origin : str
        Where it is defined (for messages and the printed header).
    """

    name: str
    node: ast.FunctionDef
    arrays: Mapping[str, tuple[ast.expr, ...] | None]
    tuples: Mapping[str, str]
    origin: str

    @property
    def params(self) -> tuple[str, ...]:
        return tuple(a.arg for a in self.node.args.args)


@dataclass(frozen=True)
class External:
    """A function the formulas call that a target defines itself (the model functions, a
    hook printed from SymPy).

    Attributes
    ----------
    params : tuple of str
        Its parameters.
    viewed : frozenset of str
        Those that take views (an array and an offset in the scalar target).
    """

    params: tuple[str, ...]
    viewed: frozenset[str] = frozenset()


_PARAM_LINE = re.compile(r"^\s*([A-Za-z_]\w*(?:\s*,\s*[A-Za-z_]\w*)*)\s*:\s*(.+?)\s*$")
_SHAPE = re.compile(r"shape\s*\(([^)]*)\)")


def _declared(doc: str | None) -> dict[str, tuple[ast.expr, ...] | None]:
    """The array parameters a numpydoc docstring declares, with their shapes."""
    out: dict[str, tuple[ast.expr, ...] | None] = {}
    if not doc:
        return out
    lines = textwrap.dedent(doc).splitlines()
    inside = False
    for i, line in enumerate(lines):
        if line.strip() == "Parameters" and i + 1 < len(lines) and set(lines[i + 1].strip()) == {"-"}:
            inside = True
            continue
        if inside and i + 1 < len(lines) and lines[i + 1].strip() and set(
                lines[i + 1].strip()) == {"-"} and line.strip():
            break                                   # the next section
        match = _PARAM_LINE.match(line) if inside and not line.startswith(" ") else None
        if match is None or not match.group(2).startswith("array"):
            continue
        shape = _SHAPE.search(match.group(2))
        dims: tuple[ast.expr, ...] | None = None
        if shape is not None:
            tree = ast.parse(f"({shape.group(1)},)" if "," not in shape.group(1)
                             else f"({shape.group(1)})", mode="eval").body
            dims = tuple(tree.elts) if isinstance(tree, ast.Tuple) else (tree,)
        for name in re.split(r"\s*,\s*", match.group(1)):
            out[name] = dims
    return out


def _formula(node: ast.FunctionDef, name: str, origin: str) -> Formula:
    tuples: dict[str, str] = {}
    for a in node.args.args:
        ann = a.annotation
        type_name = ann.id if isinstance(ann, ast.Name) else (
            ann.value if isinstance(ann, ast.Constant) and isinstance(ann.value, str) else None)
        if type_name is not None and type_name in SHAPES:
            tuples[a.arg] = type_name
    arrays = _declared(ast.get_docstring(node))
    params = {a.arg for a in node.args.args}
    unknown = set(arrays) - params
    if unknown:
        raise UnsupportedError(f"{origin}: the docstring declares {sorted(unknown)}, which "
                               "are not parameters")
    return Formula(name=name, node=node, arrays=arrays, tuples=tuples, origin=origin)


@functools.cache
def source_tree(fn: Callable[..., Any]) -> ast.FunctionDef:
    """The syntax tree of a function's source (read once per process; do not modify it).

    Parameters
    ----------
    fn : function
        Defined in a file (``inspect.getsource`` reads it).

    Returns
    -------
    ast.FunctionDef

    Raises
    ------
    UnsupportedError
        The source is not a plain function definition.

    Examples
    --------
    >>> from thetahat.estimation.observer import formulas
    >>> source_tree(formulas.phi_hat).name
    'phi_hat'
    """
    node = ast.parse(textwrap.dedent(inspect.getsource(fn))).body[0]
    if not isinstance(node, ast.FunctionDef):
        raise UnsupportedError(f"{fn!r} is not a plain function definition")
    return node


def definition(fn: Callable[..., Any], name: str | None = None) -> Formula:
    """A function of the subset, read from its source (once per process).

    Parameters
    ----------
    fn : function
        Defined in a file, at module level.
    name : str, optional
        The name to print it under (default its own).

    Returns
    -------
    Formula

    Examples
    --------
    >>> from thetahat.estimation.observer import formulas
    >>> f = definition(formulas.observer_forcing)
    >>> ast.unparse(f.arrays["Gx"][1]), f.tuples["P"]
    ('NX', 'PlanArrays')
    """
    fn = getattr(fn, "py_func", fn)
    return _formula(source_tree(fn), name or fn.__name__, f"{fn.__module__}.{fn.__qualname__}")


def definitions(source: str, origin: str) -> dict[str, Formula]:
    """The functions of a source text in the subset (generated hooks), by name; parsed, never
    executed.

    Parameters
    ----------
    source : str
    origin : str
        What generated it (for messages).

    Returns
    -------
    dict of str to Formula

    Examples
    --------
    >>> sorted(definitions("def f(a):\\n    return a\\n", "doc"))
    ['f']
    """
    out = {}
    for node in ast.parse(textwrap.dedent(source)).body:
        if isinstance(node, ast.FunctionDef):
            out[node.name] = _formula(node, node.name, f"{origin}.{node.name}")
    return out


# ----------------------------------------------------------------------------- expressions
def const_node(value: Any) -> ast.expr:
    """The syntax of a constant.

    Parameters
    ----------
    value : int, float or bool

    Returns
    -------
    ast.expr

    Examples
    --------
    >>> ast.unparse(const_node(0))
    '0'
    """
    return ast.Constant(value)


def name_node(ident: str, ctx: ast.expr_context | None = None) -> ast.Name:
    """The syntax of a name (read, unless ``ctx`` says otherwise).

    Parameters
    ----------
    ident : str
    ctx : ast.Load, ast.Store or None

    Returns
    -------
    ast.Name

    Examples
    --------
    >>> ast.unparse(name_node("NX"))
    'NX'
    """
    return ast.Name(ident, ctx or ast.Load())


def is_int(node: ast.expr, value: int) -> bool:
    """Whether ``node`` is the integer constant ``value``.

    Parameters
    ----------
    node : ast.expr
    value : int

    Returns
    -------
    bool

    Examples
    --------
    >>> is_int(const_node(0), 0), is_int(const_node(0.0), 0)
    (True, False)
    """
    return isinstance(node, ast.Constant) and node.value == value and type(node.value) is int


def same(a: ast.expr, b: ast.expr) -> bool:
    """Whether two expressions are written alike.

    Parameters
    ----------
    a, b : ast.expr

    Returns
    -------
    bool

    Examples
    --------
    >>> same(name_node("s"), name_node("s")), same(name_node("s"), name_node("out"))
    (True, False)
    """
    return ast.dump(a) == ast.dump(b)


def add(a: ast.expr, b: ast.expr) -> ast.expr:
    """a + b, with a zero dropped and integer constants folded.

    Parameters
    ----------
    a, b : ast.expr

    Returns
    -------
    ast.expr

    Examples
    --------
    >>> ast.unparse(add(const_node(0), name_node("i"))), ast.unparse(add(const_node(2), const_node(3)))
    ('i', '5')
    """
    if is_int(a, 0):
        return b
    if is_int(b, 0):
        return a
    if (isinstance(a, ast.Constant) and isinstance(b, ast.Constant)
            and type(a.value) is int and type(b.value) is int):
        return const_node(a.value + b.value)
    return ast.BinOp(a, ast.Add(), b)


def sub(a: ast.expr, b: ast.expr) -> ast.expr:
    """a − b, with ``(b + c) − b`` = c, a zero dropped and integer constants folded.

    Parameters
    ----------
    a, b : ast.expr

    Returns
    -------
    ast.expr

    Examples
    --------
    >>> ast.unparse(sub(ast.parse("NX + NK", mode="eval").body, name_node("NX")))
    'NK'
    """
    if is_int(b, 0):
        return a
    if same(a, b):
        return const_node(0)
    if isinstance(a, ast.BinOp) and isinstance(a.op, ast.Add) and same(a.left, b):
        return a.right
    if (isinstance(a, ast.Constant) and isinstance(b, ast.Constant)
            and type(a.value) is int and type(b.value) is int):
        return const_node(a.value - b.value)
    return ast.BinOp(a, ast.Sub(), b)


def everything(node: ast.Subscript) -> bool:
    """Whether a subscript is ``x[:]`` (all of an array, whatever its rank).

    Parameters
    ----------
    node : ast.Subscript

    Returns
    -------
    bool

    Examples
    --------
    >>> everything(ast.parse("x[:]", mode="eval").body)
    True
    """
    sl = node.slice
    return (isinstance(sl, ast.Slice) and sl.lower is None and sl.upper is None
            and sl.step is None)


def slice_bounds(node: ast.Subscript) -> tuple[list[ast.expr], list[ast.expr | None]] | None:
    """(lows, highs) of a subscript made of slices only (``a[lo:hi]``, ``M[a:b, c:d]``).

    Parameters
    ----------
    node : ast.Subscript

    Returns
    -------
    tuple of lists, or None
        None when some index is not a slice (an entry, ``x[i]``); a missing high is None.

    Raises
    ------
    UnsupportedError
        A slice with a step.

    Examples
    --------
    >>> lows, highs = slice_bounds(ast.parse("s[NX:NX + NK]", mode="eval").body)
    >>> [ast.unparse(e) for e in lows + highs]
    ['NX', 'NX + NK']
    """
    parts = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
    if not all(isinstance(p, ast.Slice) for p in parts):
        return None
    lows, highs = [], []
    for p in parts:
        assert isinstance(p, ast.Slice)
        if p.step is not None:
            raise UnsupportedError(f"{ast.unparse(node)}: a block has no step")
        lows.append(p.lower or const_node(0))
        highs.append(p.upper)
    return lows, highs


# ----------------------------------------------------------------------------- blocks
@dataclass(frozen=True)
class Block:
    """An array, or a block of one, as the printers see it.

    Attributes
    ----------
    base : ast.expr
        The array that holds it (a name, or a field of a named tuple: ``P.E``).
    offset : tuple of ast.expr
        Its first entry in ``base``, per axis.
    shape : tuple of ast.expr or None
        Its length per axis (None: not declared).
    node : ast.expr
        How the formula names it (NumPy prints it so).
    rank : int or None
        Its number of axes (None: not declared).

    Examples
    --------
    >>> s = Block.whole(name_node("s"), None, rank=1)
    >>> z = s.part([name_node("NX")], [ast.parse("NX + NK", mode="eval").body], name_node("z"))
    >>> ast.unparse(z.offset[0]), ast.unparse(z.shape[0])
    ('NX', 'NK')
    """

    base: ast.expr
    offset: tuple[ast.expr, ...]
    shape: tuple[ast.expr, ...] | None
    node: ast.expr
    rank: int | None

    @classmethod
    def whole(cls, node: ast.expr, shape: tuple[ast.expr, ...] | None, rank: int | None = None,
              offset: ast.expr | None = None) -> Block:
        """All of the array ``node`` (at ``offset`` along its first axis: a view passed in)."""
        rank = len(shape) if shape is not None else rank
        zeros = (const_node(0),) * (rank or 1)
        if offset is not None:
            zeros = (offset,) + zeros[1:]
        return cls(node, zeros, shape, node, rank)

    def offsets(self, rank: int) -> tuple[ast.expr, ...]:
        """The offset per axis for ``rank`` axes (an array of undeclared rank has one)."""
        return self.offset[:rank] + (const_node(0),) * (rank - len(self.offset))

    def part(self, lows: Sequence[ast.expr], highs: Sequence[ast.expr | None],
             node: ast.expr) -> Block:
        """The block [lows:highs] of this one, named ``node``."""
        if self.rank is not None and len(lows) != self.rank:
            raise UnsupportedError(f"{ast.unparse(node)}: a {len(lows)}-D block of a "
                                   f"{self.rank}-D array")
        shape = []
        for axis, (lo, hi) in enumerate(zip(lows, highs)):
            if hi is None:
                if self.shape is None:
                    raise UnsupportedError(f"{ast.unparse(node)}: give the block's end")
                hi = self.shape[axis]
            shape.append(sub(hi, lo))
        offset = tuple(add(o, lo) for o, lo in zip(self.offsets(len(lows)), lows))
        return Block(self.base, offset, tuple(shape), node, len(lows))
