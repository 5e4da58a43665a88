"""Printing the formulas for a target: the scalar loops of numba and C, NumPy for a row or a batch.

:class:`Program` holds a set of formulas (:mod:`~thetahat.estimation.kernels.subset`) printed
together — the calls between them resolved — and prints each for a target, resolving every
view and block at print time:

* ``"scalar"`` (one row of scalars: the numba kernel, and the input of the C printer of
  :mod:`thetahat.codegen`): a block statement becomes loops over its entries, with a local
  per product entry summed in the order of the indices; a view is its array and an offset
  (``x_hat[i]`` → ``s[i]``, ``theta_hat[i]`` → ``s[NQ + i]``), and a parameter that receives
  views takes the offset as a further parameter ``<name>_at``; the vocabulary becomes syntax
  or the scalar functions of :mod:`~thetahat.estimation.kernels.scalar_primitives`;
* ``"row"`` (NumPy, one row): the formula as written, the vocabulary bound to Python and
  NumPy functions;
* ``"batch"`` (NumPy, rows on a leading axis): entries and blocks along the last axes
  (``x[i]`` → ``x[..., i]``), products batched
  (:func:`~thetahat.estimation.kernels.primitives.product`, …).

A block statement may not read, inside a product, the array it writes, nor another part of
it (NumPy computes the product first, the loops write as they go): every target raises
:class:`~thetahat.estimation.kernels.subset.AliasingError`.
"""

from __future__ import annotations

import ast
import copy
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from ...errors import UnsupportedError
from .kernel_args import SHAPES
from .subset import (AliasingError, Block, External, Formula, add, const_node, everything,
                     is_int, name_node, same, slice_bounds, sub)

__all__ = ["BUILTINS", "Program", "TARGETS"]

#: The targets a program prints for.
TARGETS = ("scalar", "row", "batch")

#: Names the printed code may use without a binding.
BUILTINS = frozenset({"range", "min", "max", "abs", "len", "bool", "int", "float", "math",
                      "np", "True", "False", "None"})


class Program:
    """A set of formulas printed together (the calls between them resolved).

    Parameters
    ----------
    formulas : mapping of str to Formula
        By the name they are called under.
    externals : mapping of str to External, optional
        Functions the target defines (model functions, printed hooks).
    aliases : mapping of str to str, optional
        Names that call a formula under another name (``law_step`` → the law's formula).

    Examples
    --------
    >>> from thetahat.estimation.kernels.subset import definition
    >>> from thetahat.estimation.observer import formulas
    >>> prog = Program({"phi_hat": definition(formulas.phi_hat)})
    >>> print(ast.unparse(prog.printed("phi_hat", "scalar")).splitlines()[-1].strip())
    phi[i_1] = g[i_1] + s[NX + i_1]
    >>> print(ast.unparse(prog.printed("phi_hat", "batch")).splitlines()[-1].strip())
    phi[...] = g + s[..., NX:NX + NK]
    """

    def __init__(self, formulas: Mapping[str, Formula],
                 externals: Mapping[str, External] | None = None,
                 aliases: Mapping[str, str] | None = None) -> None:
        self.formulas = dict(formulas)
        self.externals = dict(externals or {})
        self.aliases = dict(aliases or {})
        self.viewed = self._viewed()
        self._printed: dict[tuple[str, str], ast.FunctionDef] = {}

    def callee(self, name: str) -> tuple[tuple[str, ...], frozenset[str]] | None:
        """(parameters, those that take views) of a formula or external called ``name``."""
        name = self.aliases.get(name, name)
        if name in self.formulas:
            return self.formulas[name].params, frozenset(self.viewed[name])
        if name in self.externals:
            ext = self.externals[name]
            return ext.params, ext.viewed
        return None

    def _viewed(self) -> dict[str, set[str]]:
        """The parameters of each formula that some call passes a view (to a fixpoint)."""
        viewed: dict[str, set[str]] = {name: set() for name in self.formulas}
        views = {name: _view_names(f) for name, f in self.formulas.items()}
        changed = True
        while changed:
            changed = False
            for name, f in self.formulas.items():
                local = views[name] | viewed[name]
                for node in ast.walk(f.node):
                    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)):
                        continue
                    target = self.aliases.get(node.func.id, node.func.id)
                    if target not in self.formulas:
                        continue
                    params = self.formulas[target].params
                    for p, arg in zip(params, node.args):
                        if _is_view(arg, local) and p not in viewed[target]:
                            viewed[target].add(p)
                            changed = True
        return viewed

    def printed(self, name: str, target: str) -> ast.FunctionDef:
        """Formula ``name`` printed for ``target`` (see the module docstring).

        Parameters
        ----------
        name : str
        target : {"scalar", "row", "batch"}

        Returns
        -------
        ast.FunctionDef
            Its docstring dropped; printed once per program and target (read it, do not
            modify it).

        Raises
        ------
        UnsupportedError
            The formula leaves the subset (the message says where).
        AliasingError
            A product reads the array its statement writes.
        """
        if target not in TARGETS:
            raise UnsupportedError(f"target must be one of {TARGETS}; got {target!r}")
        hit = self._printed.get((name, target))
        if hit is None:
            hit = self._printed[name, target] = _Printer(self, self.formulas[name],
                                                         target).function()
        return hit

    def free_names(self, names: Iterable[str], target: str) -> set[str]:
        """The names the printed formulas ``names`` read that none of them defines."""
        out: set[str] = set()
        printed = set(names)
        for name in printed:
            fn = self.printed(name, target)
            bound = {a.arg for a in fn.args.args} | {
                n.id for n in ast.walk(fn) if isinstance(n, ast.Name)
                and isinstance(n.ctx, ast.Store)}
            out |= {n.id for n in ast.walk(fn) if isinstance(n, ast.Name)
                    and isinstance(n.ctx, ast.Load) and n.id not in bound}
        return out - printed - BUILTINS

    def closure(self, roots: Iterable[str]) -> list[str]:
        """``roots`` and the formulas they call, transitively (each once, callees first)."""
        order: list[str] = []

        def visit(name: str) -> None:
            if name in order or name not in self.formulas:
                return
            for node in ast.walk(self.formulas[name].node):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                    visit(self.aliases.get(node.func.id, node.func.id))
            order.append(name)

        for root in roots:
            visit(root)
        return order


def _view_names(f: Formula) -> set[str]:
    """Names a formula binds to a block of an array (``x = s[0:NX]``)."""
    out = set()
    for node in ast.walk(f.node):
        if isinstance(node, ast.Assign):
            pairs: list[tuple[ast.expr, ast.expr]] = []
            for t in node.targets:
                if isinstance(t, ast.Tuple) and isinstance(node.value, ast.Tuple):
                    pairs += list(zip(t.elts, node.value.elts))
                else:
                    pairs.append((t, node.value))
            for t, v in pairs:
                if (isinstance(t, ast.Name) and isinstance(v, ast.Subscript)
                        and slice_bounds(v) is not None):
                    out.add(t.id)
    return out


def _is_view(arg: ast.expr, views: set[str]) -> bool:
    return ((isinstance(arg, ast.Subscript) and slice_bounds(arg) is not None)
            or (isinstance(arg, ast.Name) and arg.id in views))


def _call(func: str | ast.expr, *args: ast.expr) -> ast.Call:
    return ast.Call(name_node(func) if isinstance(func, str) else func, list(args), [])


def _attr(base: str, attr: str) -> ast.Attribute:
    return ast.Attribute(name_node(base), attr, ast.Load())


#: The vocabulary per target: a function of the printed arguments giving the expression.
_SYNTAX: dict[str, dict[str, Callable[..., ast.expr]]] = {
    "scalar": {
        "where": lambda c, a, b: ast.IfExp(c, a, b),
        "clip": lambda a, lo, hi: _call("min", _call("max", a, lo), hi),
        "isfinite": lambda a: _call(_attr("math", "isfinite"), a),
        "isnan": lambda a: _call("isnan", a),
        "exp": lambda a: _call("exp", a),
        "not_": lambda a: ast.UnaryOp(ast.Not(), a),
        "and_": lambda a, b: ast.BoolOp(ast.And(), [a, b]),
        "or_": lambda a, b: ast.BoolOp(ast.Or(), [a, b]),
        "any_": lambda b: b,
        "count_": lambda b: ast.IfExp(b, const_node(1), const_node(0)),
    },
    "row": {
        "where": lambda c, a, b: ast.IfExp(c, a, b),
        "clip": lambda a, lo, hi: _call("min", _call("max", a, lo), hi),
        "isfinite": lambda a: _call(_attr("math", "isfinite"), a),
        "isnan": lambda a: _call(_attr("math", "isnan"), a),
        "exp": lambda a: _call(_attr("np", "exp"), a),
        "not_": lambda a: ast.UnaryOp(ast.Not(), a),
        "and_": lambda a, b: ast.BoolOp(ast.And(), [a, b]),
        "or_": lambda a, b: ast.BoolOp(ast.Or(), [a, b]),
        "any_": lambda b: b,
        "count_": lambda b: ast.IfExp(b, const_node(1), const_node(0)),
    },
    "batch": {
        "where": lambda c, a, b: _call(_attr("np", "where"), c, a, b),
        "clip": lambda a, lo, hi: _call("clip", a, lo, hi),
        "isfinite": lambda a: _call(_attr("np", "isfinite"), a),
        "isnan": lambda a: _call(_attr("np", "isnan"), a),
        "exp": lambda a: _call(_attr("np", "exp"), a),
        "not_": lambda a: _call(_attr("np", "logical_not"), a),
        "and_": lambda a, b: _call(_attr("np", "logical_and"), a, b),
        "or_": lambda a, b: _call(_attr("np", "logical_or"), a, b),
        "any_": lambda b: _call("any_rows", b),
        "count_": lambda b: _call("count_rows", b),
    },
}

#: Vocabulary on whole arrays, sized from the arguments' shapes in the scalar target: name →
#: (index of the argument whose length is prepended, NumPy row name, NumPy batch name).
_SIZED = {"solve": (1, "solve_row", "solve_rows"), "expm": (0, "expm", "expm"),
          "norm": (0, "norm", "norm"), "sumsq": (0, "sumsq_row", "sumsq_rows")}


@dataclass
class _Printer:
    program: Program
    formula: Formula
    target: str
    arrays: dict[str, Block] = field(default_factory=dict)
    tuples: dict[str, str] = field(default_factory=dict)
    named: set[str] = field(default_factory=set)
    counter: int = 0

    # ------------------------------------------------------------------ setup
    def function(self) -> ast.FunctionDef:
        f = self.formula
        node = copy.deepcopy(f.node)
        viewed = self.program.viewed.get(f.name, set())
        args = []
        for a in node.args.args:
            a.annotation = None
            args.append(a)
            if a.arg in f.tuples:
                self.tuples[a.arg] = f.tuples[a.arg]
            elif a.arg in f.arrays or a.arg in viewed:
                shape = f.arrays.get(a.arg)
                at = a.arg + "_at" if a.arg in viewed else None
                self.arrays[a.arg] = Block.whole(name_node(a.arg), shape, 1 if at else None,
                                            name_node(at) if at else None)
                if at and self.target == "scalar":
                    args.append(ast.arg(at))
            if a.arg in viewed and a.arg not in f.arrays:
                raise UnsupportedError(f"{f.origin}: {a.arg} receives views; declare it "
                                       "an array in the docstring")
        node.args.args = args
        node.returns = None
        node.decorator_list = []
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            body = body[1:]
        node.body = self.block(body) or [ast.Pass()]
        return ast.fix_missing_locations(node)

    def fail(self, node: ast.AST, what: str) -> UnsupportedError:
        return UnsupportedError(f"{self.formula.origin}: {ast.unparse(node)}: {what}")

    def fresh(self, stem: str) -> str:
        self.counter += 1
        return f"{stem}_{self.counter}"

    # ------------------------------------------------------------------ arrays
    def array(self, node: ast.expr) -> Block | None:
        """The array or block an expression denotes, or None (a scalar, a tuple, …)."""
        if isinstance(node, ast.Name):
            return self.arrays.get(node.id)
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in self.tuples):
            shape = SHAPES[self.tuples[node.value.id]].get(node.attr)
            if shape is None:
                return None
            return Block.whole(node, tuple(name_node(d) for d in shape))
        if isinstance(node, ast.Subscript):
            parts = slice_bounds(node)
            if parts is None:
                return None
            base = self.array(node.value)
            if base is None:
                return None
            if everything(node):                  # x[:]: all of it, whatever its rank
                return Block(base.base, base.offset, base.shape, node, base.rank)
            return base.part(parts[0], parts[1], node)
        return None

    # ------------------------------------------------------------------ statements
    def block(self, stmts: Sequence[ast.stmt]) -> list[ast.stmt]:
        out: list[ast.stmt] = []
        for st in stmts:
            out += self.stmt(st)
        return out

    def stmt(self, st: ast.stmt) -> list[ast.stmt]:
        if isinstance(st, ast.Assign):
            return self.assign(st)
        if isinstance(st, ast.AugAssign):
            target = self.array(st.target)
            if target is not None:
                return self.block_statement(st.target, target, type(st.op), st.value)
            return [ast.AugAssign(self.store(st.target), st.op, self.expr(st.value))]
        if isinstance(st, ast.Expr):
            return [ast.Expr(self.expr(st.value))]
        if isinstance(st, ast.If):
            return [ast.If(self.expr(st.test), self.block(st.body) or [ast.Pass()],
                           self.block(st.orelse))]
        if isinstance(st, ast.For):
            return [ast.For(st.target, self.expr(st.iter), self.block(st.body) or [ast.Pass()],
                            self.block(st.orelse))]
        if isinstance(st, ast.While):
            return [ast.While(self.expr(st.test), self.block(st.body) or [ast.Pass()],
                              self.block(st.orelse))]
        if isinstance(st, ast.Return):
            return [ast.Return(None if st.value is None else self.expr(st.value))]
        if isinstance(st, ast.Pass):
            return []
        raise self.fail(st, "outside the formulas' subset")

    def assign(self, st: ast.Assign) -> list[ast.stmt]:
        if len(st.targets) != 1:
            raise self.fail(st, "chained assignment is outside the subset")
        target = st.targets[0]
        if isinstance(target, ast.Subscript) and slice_bounds(target) is not None:
            arr = self.array(target)
            if arr is None:
                raise self.fail(target, "a block of something that is not a known array")
            return self.block_statement(target, arr, None, st.value)
        pairs = (list(zip(target.elts, st.value.elts))
                 if isinstance(target, ast.Tuple) and isinstance(st.value, ast.Tuple)
                 and len(target.elts) == len(st.value.elts) else None)
        if pairs is not None and all(isinstance(t, ast.Name) for t, _ in pairs):
            kinds = [self.array(v) is not None for _, v in pairs]
            if all(kinds):
                out: list[ast.stmt] = []
                for t, v in pairs:
                    out += self.assign(ast.Assign([t], v))
                return out
            if any(kinds):
                raise self.fail(st, "arrays and scalars in one assignment")
        if isinstance(target, ast.Name):
            arr = self.array(st.value)
            if arr is not None:                 # a name for an array or a block
                if target.id in self.named or target.id in self.formula.params:
                    raise self.fail(st, "a name is bound to an array twice")
                self.named.add(target.id)
                node = name_node(target.id)
                self.arrays[target.id] = Block(arr.base, arr.offset, arr.shape, node, arr.rank)
                if self.target == "scalar":
                    return []
                return [ast.Assign([name_node(target.id, ast.Store())],
                                   self.numpy_array(st.value))]
            if target.id in self.arrays:
                raise self.fail(st, "a block's name is rebound to a value")
        return [ast.Assign([self.expr(target)], self.expr(st.value))]

    # ------------------------------------------------------------------ blocks
    def block_statement(self, target_node: ast.expr, target: Block,
                        op: type[ast.operator] | None, value: ast.expr) -> list[ast.stmt]:
        """``target op= value`` over a block (op None: assignment)."""
        if target.shape is None:
            raise self.fail(target_node, "the block's shape is not known: declare the array's "
                            "shape in the docstring")
        self.check_aliasing(target_node, target, value)
        if self.target == "scalar":
            return self.loops(target, op, value)
        rank = len(target.shape)
        if isinstance(target_node, ast.Name):      # x += …: in place on the view
            lhs: ast.Name | ast.Subscript = name_node(target_node.id, ast.Store())
        else:
            sub = self.numpy_array(target_node, whole=True)
            if not isinstance(sub, ast.Subscript):
                raise self.fail(target_node, "a block statement writes a block")
            lhs = ast.Subscript(sub.value, sub.slice, ast.Store())
        rhs = self.numpy_block(value, rank)
        if op is None:
            return [ast.Assign([lhs], rhs)]
        return [ast.AugAssign(lhs, op(), rhs)]

    def check_aliasing(self, target_node: ast.expr, target: Block, value: ast.expr) -> None:
        """Refuse a block statement whose value reads the written array in a product, at
        another offset, or entry by entry."""
        for operand, how in self.operands(value, ""):
            arr = self.array(operand)
            if arr is None:                         # an entry: x[i] of the written array?
                arr = self.array(operand.value) if isinstance(operand, ast.Subscript) else None
                how = how or " entry by entry"
            if arr is None or not same(arr.base, target.base):
                continue
            if how or not all(same(a, b) for a, b in zip(arr.offset, target.offset)):
                raise AliasingError(
                    f"{self.formula.origin}: {ast.unparse(target_node)} is written by a "
                    f"statement that reads {ast.unparse(operand)}{how or ' at another offset'}"
                    " (the targets would disagree); use a work buffer")

    def operands(self, node: ast.expr, how: str) -> Iterable[tuple[ast.expr, str]]:
        """The arrays and entries a block expression reads (``how``: in a product)."""
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.MatMult):
            right = node.right.value if (isinstance(node.right, ast.Attribute)
                                         and node.right.attr == "T") else node.right
            yield from self.operands(node.left, " in a product")
            yield from self.operands(right, " in a product")
        elif self.array(node) is not None:
            yield node, how
        elif isinstance(node, ast.Subscript):
            yield node, how
            yield from self.operands(node.slice, how)
        else:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.expr):
                    yield from self.operands(child, how)

    def loops(self, target: Block, op: type[ast.operator] | None, value: ast.expr
              ) -> list[ast.stmt]:
        assert target.shape is not None
        idx = [self.fresh(s) for s in "ij"[:len(target.shape)]]
        pre: list[ast.stmt] = []
        element = self.element(value, idx, pre, len(target.shape))
        index = [add(o, name_node(i)) for o, i in zip(target.offset, idx)]
        sub_ = index[0] if len(index) == 1 else ast.Tuple(index, ast.Load())
        lhs = ast.Subscript(copy.deepcopy(target.base), sub_, ast.Store())
        body: list[ast.stmt] = pre + [ast.Assign([lhs], element) if op is None
                                      else ast.AugAssign(lhs, op(), element)]
        for i, n in reversed(list(zip(idx, target.shape))):
            body = [ast.For(name_node(i, ast.Store()), _call("range", copy.deepcopy(n)), body, [])]
        return body

    def at(self, arr: Block, idx: Sequence[ast.expr]) -> ast.expr:
        index = [add(o, i) for o, i in zip(arr.offsets(len(idx)), idx)]
        return ast.Subscript(copy.deepcopy(arr.base),
                             index[0] if len(index) == 1 else ast.Tuple(index, ast.Load()),
                             ast.Load())

    def element(self, node: ast.expr, idx: Sequence[str], pre: list[ast.stmt],
                rank: int) -> ast.expr:
        """Entry ``idx`` of a block expression (products summed into locals in ``pre``)."""
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.MatMult):
            return self.product(node, idx, pre, rank)
        if isinstance(node, ast.BinOp):
            return ast.BinOp(self.element(node.left, idx, pre, rank), node.op,
                             self.element(node.right, idx, pre, rank))
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return ast.UnaryOp(ast.USub(), self.element(node.operand, idx, pre, rank))
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id == "eye"):
            if rank != 2:
                raise self.fail(node, "eye(q) is a matrix")
            return ast.IfExp(ast.Compare(name_node(idx[0]), [ast.Eq()], [name_node(idx[1])]),
                             const_node(1.0), const_node(0.0))
        arr = self.array(node)
        if arr is not None:
            if arr.rank != rank:
                raise self.fail(node, f"a {arr.rank}-D operand of a {rank}-D block")
            return self.at(arr, [name_node(i) for i in idx])
        return self.expr(node)

    def product(self, node: ast.BinOp, idx: Sequence[str], pre: list[ast.stmt],
                rank: int) -> ast.expr:
        """Σ_l A[i, l] x[l] (rank 1) or Σ_l A[i, l] B[l, j] (rank 2, B or Bᵀ) into a local."""
        A = self.array(node.left)
        right, transposed = node.right, False
        if isinstance(right, ast.Attribute) and right.attr == "T":
            right, transposed = right.value, True
        B = self.array(right)
        if A is None or B is None:
            raise self.fail(node, "a product of arrays or blocks only")
        if rank == 1:
            if B.shape is None:
                raise self.fail(node, "the vector's length is not known")
            inner = B.shape[0]
        elif A.shape is not None and len(A.shape) == 2:
            inner = A.shape[1]
        elif B.shape is not None:
            inner = B.shape[1] if transposed else B.shape[0]
        else:
            raise self.fail(node, "the inner dimension is not known")
        l_ = name_node(self.fresh("l"))
        t = self.fresh("t")
        i = name_node(idx[0])
        if rank == 1:
            b = self.at(B, [l_])
        else:
            b = self.at(B, [name_node(idx[1]), l_] if transposed else [l_, name_node(idx[1])])
        term = ast.BinOp(self.at(A, [i, l_]), ast.Mult(), b)
        pre += [ast.Assign([name_node(t, ast.Store())], const_node(0.0)),
                ast.For(name_node(l_.id, ast.Store()), _call("range", copy.deepcopy(inner)),
                        [ast.AugAssign(name_node(t, ast.Store()), ast.Add(), term)], [])]
        return name_node(t)

    # ------------------------------------------------------------------ NumPy blocks
    def numpy_array(self, node: ast.expr, whole: bool = False) -> ast.expr:
        """An array expression in NumPy (a block along the last axes in the batch target);
        ``whole``: ``x[:]`` for all of a named array."""
        if isinstance(node, ast.Subscript):
            parts = slice_bounds(node)
            if parts is not None:
                base = self.numpy_array(node.value)
                if whole and everything(node):
                    index: ast.expr = ast.Constant(Ellipsis)
                    return ast.Subscript(base, index, ast.Load())
                slices: list[ast.expr] = [ast.Slice(lo, hi) for lo, hi in zip(*parts)]
                if self.target == "batch":
                    slices = [ast.Constant(Ellipsis), *slices]
                index = slices[0] if len(slices) == 1 else ast.Tuple(slices, ast.Load())
                return ast.Subscript(base, index, ast.Load())
        return copy.deepcopy(node)

    def numpy_block(self, node: ast.expr, rank: int) -> ast.expr:
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.MatMult):
            right, transposed = node.right, False
            if isinstance(right, ast.Attribute) and right.attr == "T":
                right, transposed = right.value, True
            a, b = self.numpy_array(node.left), self.numpy_array(right)
            if self.target == "row":
                return ast.BinOp(a, ast.MatMult(), ast.Attribute(b, "T", ast.Load())
                                 if transposed else b)
            if transposed:
                b = _call("transpose", b)
            return _call("product" if rank == 1 else "matmul", a, b)
        if isinstance(node, ast.BinOp):
            return ast.BinOp(self.numpy_block(node.left, rank), node.op,
                             self.numpy_block(node.right, rank))
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return ast.UnaryOp(ast.USub(), self.numpy_block(node.operand, rank))
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id == "eye"):
            return _call("identity", *(self.expr(a) for a in node.args))
        if self.array(node) is not None:
            return self.numpy_array(node)
        return self.expr(node)

    # ------------------------------------------------------------------ expressions
    def expr(self, node: ast.expr) -> ast.expr:
        """A scalar expression (or a call, or an argument) printed for the target."""
        if isinstance(node, ast.Subscript):
            return self.subscript(node)
        if isinstance(node, ast.Call):
            return self.call(node)
        if isinstance(node, ast.BinOp):
            if isinstance(node.op, ast.MatMult):
                raise self.fail(node, "a product outside a block statement")
            return ast.BinOp(self.expr(node.left), node.op, self.expr(node.right))
        if isinstance(node, ast.UnaryOp):
            return ast.UnaryOp(node.op, self.expr(node.operand))
        if isinstance(node, ast.BoolOp):
            return ast.BoolOp(node.op, [self.expr(v) for v in node.values])
        if isinstance(node, ast.Compare):
            return ast.Compare(self.expr(node.left), node.ops,
                               [self.expr(c) for c in node.comparators])
        if isinstance(node, ast.IfExp):
            return ast.IfExp(self.expr(node.test), self.expr(node.body), self.expr(node.orelse))
        if isinstance(node, ast.Tuple):
            return ast.Tuple([self.expr(e) for e in node.elts], node.ctx)
        if isinstance(node, (ast.Name, ast.Constant, ast.Attribute)):
            if self.target == "scalar" and self.array(node) is not None:
                arr = self.array(node)
                assert arr is not None
                if not all(is_int(o, 0) for o in arr.offset):
                    raise self.fail(node, "a block used as a value (pass it to a call or "
                                    "index it)")
                return copy.deepcopy(arr.base)
            return copy.deepcopy(node)
        raise self.fail(node, "outside the formulas' subset")

    def store(self, node: ast.expr) -> ast.Name | ast.Attribute | ast.Subscript:
        """An element or a name written by an assignment."""
        out = self.expr(node)
        if not isinstance(out, (ast.Name, ast.Attribute, ast.Subscript)):
            raise self.fail(node, "not a target")
        return out

    def subscript(self, node: ast.Subscript) -> ast.expr:
        arr = self.array(node.value)
        if slice_bounds(node) is not None:
            if arr is None:                          # a slice of a tuple: W[17:]
                return ast.Subscript(self.expr(node.value), node.slice, node.ctx)
            raise self.fail(node, "a block used as a value")
        index = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
        idx = [self.expr(i) for i in index]
        if arr is None:
            if self.target == "batch" and isinstance(node.value, ast.Name) and \
                    node.value.id in self.formula.params:
                raise self.fail(node, "an entry of a parameter not declared an array")
            return ast.Subscript(self.expr(node.value),
                                 idx[0] if len(idx) == 1 else ast.Tuple(idx, ast.Load()),
                                 node.ctx)
        if arr.rank is not None and len(idx) != arr.rank:
            raise self.fail(node, f"{len(idx)} indices of a {arr.rank}-D array")
        if self.target == "scalar":
            out = self.at(arr, idx)
            assert isinstance(out, ast.Subscript)
            return ast.Subscript(out.value, out.slice, node.ctx)
        if self.target == "batch":
            idx = [ast.Constant(Ellipsis), *idx]
        return ast.Subscript(copy.deepcopy(arr.node),
                             idx[0] if len(idx) == 1 else ast.Tuple(idx, ast.Load()), node.ctx)

    def call(self, node: ast.Call) -> ast.expr:
        if node.keywords:
            raise self.fail(node, "keyword arguments are outside the subset")
        func = node.func
        if not isinstance(func, ast.Name):
            return ast.Call(self.expr(func), [self.expr(a) for a in node.args], [])
        name = func.id
        if name == "eye":
            raise self.fail(node, "eye(q) belongs in a block statement")
        if name in _SIZED:
            return self.sized(node)
        syntax = _SYNTAX[self.target].get(name)
        if syntax is not None:
            return syntax(*(self.expr(a) for a in node.args))
        callee = self.program.callee(name)
        if callee is None:
            return ast.Call(name_node(name), [self.expr(a) for a in node.args], [])
        params, viewed = callee
        if len(params) != len(node.args):
            raise self.fail(node, f"{name} takes {len(params)} arguments")
        args: list[ast.expr] = []
        for p, a in zip(params, node.args):
            arr = self.array(a)
            if self.target != "scalar":
                args.append(self.numpy_array(a) if arr is not None else self.expr(a))
            elif p in viewed:
                if arr is None:
                    raise self.fail(a, f"{name} takes a view as {p}")
                if arr.rank not in (None, 1):
                    raise self.fail(a, "only 1-D blocks are passed as views")
                args += [copy.deepcopy(arr.base), copy.deepcopy(arr.offset[0])]
            elif arr is not None:
                if not all(is_int(o, 0) for o in arr.offset):
                    raise self.fail(a, f"{name} takes a whole array as {p}")
                args.append(copy.deepcopy(arr.base))
            else:
                args.append(self.expr(a))
        return ast.Call(name_node(name), args, [])

    def sized(self, node: ast.Call) -> ast.expr:
        position, row, batch = _SIZED[node.func.id]  # type: ignore[attr-defined]
        arrays = [self.array(a) for a in node.args]
        if self.target != "scalar":
            args = [self.numpy_array(a) if arr is not None else self.expr(a)
                    for a, arr in zip(node.args, arrays)]
            return _call(row if self.target == "row" else batch, *args)
        args = []
        for a, arr in zip(node.args, arrays):
            if arr is None or not all(is_int(o, 0) for o in arr.offset):
                raise self.fail(a, f"{node.func.id} takes whole arrays")  # type: ignore[attr-defined]
            args.append(copy.deepcopy(arr.base))
        sized = arrays[position]
        if sized is None or sized.shape is None:
            raise self.fail(node, "the array's shape is not known: declare it in the docstring")
        return _call(node.func.id, copy.deepcopy(sized.shape[0]), *args)  # type: ignore[attr-defined]
