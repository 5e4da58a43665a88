"""A C99 printer for the step's formulas: the restricted subset, specialised per call.

The formulas of :mod:`~thetahat.estimation.observer.formulas` and
:mod:`~thetahat.estimation.observer.laws.formulas`, printed for the ``"scalar"`` target
(:meth:`~thetahat.estimation.kernels.printer.Program.printed`: blocks as loops, views as
offsets, the vocabulary as syntax), are loops, subscripts, arithmetic, comparisons,
``if``/``while`` and calls of other formulas — the same print the numba kernel compiles. :class:`CUnit` prints them as C, the way numba compiles them: each function
is *specialised* for the arguments of a call (monomorphised), starting from the calls the
generated step makes (:meth:`CUnit.call`).

Values the printer tracks (:class:`Const`, :class:`Arr`, :class:`Scal`, and Python tuples of
them):

* compile-time values (the dimensions, offsets, flags such as ``foh`` or ``second``, the
  plan's tuples of constant arrays) are folded: an ``if`` on a constant prints its taken branch
  only, a call on constants that returns a constant becomes that constant;
* arrays are flat C arrays, row-major, with their shape known at print time (``M[i, j]`` is
  ``M[i * cols + j]``); constant data are ``static const`` arrays at file scope, the rest
  (state, samples, work buffers) are parameters;
* runtime scalars are typed C locals (``real_t``, ``int`` for integers and booleans), declared
  at the top of their function and initialised.

Stage 2's kernels (numba's subset: :mod:`~thetahat.estimation.statistical.ekf_kernels`) also
allocate work arrays, copy blocks, read shapes and return arrays: each allocation is a local
C array of the size the specialisation fixes (:mod:`.c_arrays`), a returned array is written
through an output parameter, and a local that a specialisation left only written is dropped.

A specialised function keeps only the parameters its body uses (so ``-Wextra`` finds no
unused parameter), returns ``int``, ``real_t`` or nothing, or writes a returned tuple through
pointers. No heap, no recursion (the formulas have none), no mutable file-scope state.
"""

from __future__ import annotations

import ast
import functools
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import UnsupportedError
from .c_arrays import ALLOCATIONS, allocation_lines, copy_lines, prune, region, shape_of
from .c_syntax import BINOPS, CMP_FOLD, CMPS, FOLD, HELPERS, analysis, identifiers
from .c_values import (INT, REAL, Arr, CFunction, Const, Fn, Scal, c_type, join,
                       real_literal, specialisation_key)

__all__ = ["CUnit", "UNROLL"]

#: Loops with constant bounds are written out while the iterations of the nest written out
#: stay at most this many: their indices fold to constants, as in numba's (LLVM's) full
#: unrolling of the same loops, which gcc -O2 does not do; the bound keeps the code size of
#: larger models in check. Measured on LuGre (benchmarks/bench_codegen.py, one run each): 0.88×
#: the per-step cost of the hand-written C the printer replaced, against 1.16× without.
UNROLL = 16
#: Names that must not be C identifiers of locals (C keywords and <math.h> macros).
_RESERVED = frozenset({
    "auto", "break", "case", "char", "const", "continue", "default", "do", "double", "else",
    "enum", "extern", "float", "for", "goto", "if", "inline", "int", "long", "register",
    "restrict", "return", "short", "signed", "sizeof", "static", "struct", "switch",
    "typedef", "union", "unsigned", "void", "volatile", "while", "isfinite", "isnan", "isinf",
    "exp", "expf", "sqrt", "fabs", "y0", "y1", "j0", "j1", "jn", "yn", "real_t"})


#: NumPy's and math's special values, by the names <math.h> gives them.
_SPECIAL = {"inf": Const(math.inf, "INFINITY"), "nan": Const(math.nan, "NAN")}


class CUnit:
    """One C translation unit of specialised formula functions.

    Parameters
    ----------
    functions : mapping of str to ast.FunctionDef
        The formulas, hooks and scalar functions printed for the scalar target, by name.
    constants : mapping of str to Const
        The names the formulas read as constants (NX, …, BOUND_SQ, FAR, …).
    model : callable
        ``model(name, args) -> (C name, C argument texts)`` for a model function call
        (g_val, g_dx, dg_dy, dg_dtheta, theta_star, m_matrix) or None if ``name`` is not one.
    real : {"double", "float"}

    Notes
    -----
    A formula that writes into an array passed as constant data adds its name to
    :attr:`written_globals`: that array is scratch, and the unit must be printed again with it
    as a buffer (:mod:`.c_derive` does).

    Examples
    --------
    >>> import ast
    >>> src = "def twice(a, n):\\n    for i in range(n):\\n        a[i] = 2.0 * a[i]\\n"
    >>> fn = ast.parse(src).body[0]
    >>> unit = CUnit({"twice": fn}, {}, lambda name, args: None, "double")
    >>> f = unit.call("twice", [Arr("buf", (3,)), Const(3)])
    >>> f.name, f.args
    ('f_twice', ['buf'])
    >>> print(unit.source().split("\\n")[0])
    static void f_twice(real_t a[])
    """

    def __init__(self, functions: Mapping[str, ast.FunctionDef], constants: Mapping[str, Any],
                 model: Callable[[str, Sequence[Any] | None], tuple[str, list[str]] | None],
                 real: str) -> None:
        self.functions = dict(functions)
        self.constants = dict(constants)
        self.model = model
        self.real = real
        self.done: dict[Any, CFunction] = {}
        self.texts: list[str] = []
        self.names: dict[str, int] = {}
        self.helpers: set[str] = set()
        self.written_globals: set[str] = set()
        self.model_calls: set[str] = set()

    # ------------------------------------------------------------------ public
    def call(self, name: str, args: Sequence[Any]) -> CFunction:
        """Specialise ``name`` for ``args`` (printed once per specialisation).

        Parameters
        ----------
        name : str
        args : sequence
            :class:`Const`, :class:`Arr`, :class:`Scal` or tuples of them.

        Returns
        -------
        CFunction
        """
        fdef = self.functions.get(name)
        if fdef is None:
            raise UnsupportedError(f"the C printer has no definition of {name}")
        key = (name, tuple(specialisation_key(a) for a in args))
        hit = self.done.get(key)
        if hit is not None:
            return CFunction(hit.name, self._args_of(hit, args), hit.result)
        count = self.names.get(name, 0) + 1
        self.names[name] = count
        cname = f"f_{name}" if count == 1 else f"f_{name}_{count}"
        printer = _FunctionPrinter(self, fdef, args, cname)
        fn = printer.run()
        self.done[key] = fn
        return CFunction(fn.name, self._args_of(fn, args), fn.result)

    def source(self) -> str:
        """The helpers used and the specialised functions, callees first."""
        helpers = [HELPERS[h].replace("REAL", REAL).replace(
            "FABS", "fabs" if self.real == "double" else "fabsf") for h in sorted(self.helpers)]
        return "\n".join(helpers + self.texts)

    # ------------------------------------------------------------------ internal
    @staticmethod
    def _args_of(fn: CFunction, args: Sequence[Any]) -> list[str]:
        """The caller's C arguments for the kept parameters (paths into ``args``)."""
        out = []
        for path in fn.args:
            value: Any = args
            for index in path.split("."):
                value = value[int(index)]
            out.append(value.name if isinstance(value, Arr) else value.text)
        return out

    def literal(self, value: Any) -> str:
        if isinstance(value, bool):
            return "1" if value else "0"
        if isinstance(value, (int, np.integer)):
            return str(int(value))
        return real_literal(value, self.real)




@dataclass
class _Local:
    ctype: str


@dataclass
class _FunctionPrinter:
    unit: CUnit
    fdef: ast.FunctionDef
    args: Sequence[Any]
    cname: str
    env: dict[str, Any] = field(default_factory=dict)
    params: list[tuple[str, str, str]] = field(default_factory=list)   # (decl, c name, path)
    locals: dict[str, _Local] = field(default_factory=dict)
    lines: list[str] = field(default_factory=list)
    result: Any = None
    assigned: dict[str, int] = field(default_factory=dict)
    returns_tuple: bool = False
    only_const_return: bool = True
    unrolled: int = 1
    arrays: dict[str, int] = field(default_factory=dict)    # local C arrays: name → size
    pending: list[str] = field(default_factory=list)        # C before the statement
    stop: bool = False                                      # a folded branch returned
    pad: str = "    "
    target: str = "a"                                       # the name being assigned

    # ------------------------------------------------------------------ setup
    def run(self) -> CFunction:
        self.assigned, self.returns_tuple = analysis(self.fdef)
        names = [a.arg for a in self.fdef.args.args]
        if len(names) != len(self.args):
            raise UnsupportedError(f"{self.fdef.name} takes {len(names)} arguments, "
                                   f"given {len(self.args)}")
        for i, (pname, value) in enumerate(zip(names, self.args)):
            self.env[pname] = self._bind(pname, value, str(i))
        body = self._block(self.fdef.body, 1)
        if isinstance(self.result, Const) and self.only_const_return:
            return CFunction(self.cname, [], self.result)
        body, dead = prune(body, [*self.locals, *self.arrays])
        for name in dead:
            self.locals.pop(name, None)
            self.arrays.pop(name, None)
        used = set(identifiers("\n".join(body)))
        kept = [(decl, path) for decl, cname, path in self.params if cname in used]
        decls = [decl for decl, _ in kept]
        result = self.result
        if isinstance(result, Const):
            result = c_type(result)
        if self.returns_tuple:
            decls += [f"real_t ret{i}[]" if isinstance(t, Arr) else f"{t} *ret{i}"
                      for i, t in enumerate(result)]
            rtype = "void"
        elif isinstance(result, Arr):
            decls.append("real_t ret[]")
            rtype = "void"
        else:
            rtype = "void" if result is None else result
        head = f"static {rtype} {self.cname}({', '.join(decls) or 'void'})"
        local_lines = [f"    {loc.ctype} {name} = 0;" for name, loc in self.locals.items()]
        local_lines += [f"    real_t {name}[{max(size, 1)}];"
                        for name, size in self.arrays.items()]
        self.unit.texts.append("\n".join([head, "{", *local_lines, *body, "}", ""]))
        return CFunction(self.cname, [path for _, path in kept],
                         tuple(result) if self.returns_tuple else (result or "void"))

    def _new_array(self, shape: tuple[int, ...]) -> Arr:
        """A fresh local C array of ``shape`` (fixed size, declared at the function's top),
        named after the name being assigned where it is free."""
        taken = set(self.locals) | set(self.arrays) | {p[1] for p in self.params}
        base = self._c_name(self.target)
        name, count = base, 1
        while name in taken or name == "ret" or name in self.unit.constants:
            count += 1
            name = f"{base}_{count}"
        size = 1
        for d in shape:
            size *= d
        self.arrays[name] = size
        return Arr(name, shape)

    def _region(self, node: ast.expr) -> Any:
        """The block a ``.copy()`` copies (:func:`.c_arrays.region`)."""
        if isinstance(node, ast.Subscript):
            arr = self._array(node.value)
            parts = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            index: list[tuple[Any, ...]] = []
            for e in parts:
                if isinstance(e, ast.Slice):
                    if e.step is not None:
                        raise UnsupportedError("a copied block needs a unit step")
                    index.append(("slice", None if e.lower is None else self._expr(e.lower),
                                  None if e.upper is None else self._expr(e.upper)))
                else:
                    index.append(("at", self._expr(e)))
            return region(arr, index, self._text)
        arr = self._array(node)
        return region(arr, [("slice", None, None)] * len(arr.shape), self._text)

    def _bind(self, pname: str, value: Any, path: str) -> Any:
        """The callee's view of an argument: runtime parts become parameters (a named
        tuple's field a binding leaves None stays None: nothing to pass)."""
        if value is None or isinstance(value, (Const, Fn)) or (isinstance(value, Arr)
                                                               and value.glob):
            return value
        if isinstance(value, tuple):
            taken = {p[1] for p in self.params}
            # an element keeps the caller's name (w_F, law_3) where it is one
            items = [self._bind(v.name if isinstance(v, Arr) and v.name.isidentifier()
                                and v.name not in taken else f"{pname}_{i}", v, f"{path}.{i}")
                     for i, v in enumerate(value)]
            return type(value)(*items) if hasattr(value, "_fields") else tuple(items)
        cname = self._c_name(pname)
        if isinstance(value, Arr):
            self.params.append((f"real_t {cname}[]", cname, path))
            return Arr(cname, value.shape)
        if isinstance(value, Scal):
            self.params.append((f"{value.ctype} {cname}", cname, path))
            return Scal(cname, value.ctype)
        raise UnsupportedError(f"cannot pass {value!r} to {self.fdef.name}")

    @staticmethod
    def _c_name(name: str) -> str:
        return f"{name}_" if name in _RESERVED else name

    # ------------------------------------------------------------------ statements
    def _block(self, stmts: Sequence[ast.stmt], depth: int) -> list[str]:
        """The statements' C; stops after a return, also one in a branch a constant chose
        (:attr:`stop` says whether it did)."""
        out: list[str] = []
        ended = False
        for st in stmts:
            saved, self.pending = self.pending, []
            self.pad, self.stop = "    " * depth, False
            lines = self._stmt(st, depth)
            out += self.pending + lines
            self.pending = saved
            ended = isinstance(st, ast.Return) or (isinstance(st, ast.If) and self.stop)
            if ended:
                break
        self.stop = ended
        return out

    def _stmt(self, st: ast.stmt, depth: int) -> list[str]:
        pad = "    " * depth
        if isinstance(st, ast.Expr):
            if isinstance(st.value, ast.Constant):          # docstring
                return []
            value = self._expr(st.value)
            if isinstance(value, Scal):
                self.only_const_return = False
                return [f"{pad}{value.text};"] if "(" in value.text else []
            return []
        if isinstance(st, ast.Assign):
            return self._assign(st, pad)
        if isinstance(st, ast.AnnAssign):
            raise UnsupportedError("annotated assignments are outside the formulas' subset")
        if isinstance(st, ast.AugAssign):
            self.only_const_return = False
            op = BINOPS[type(st.op)]
            value = self._expr(st.value)
            if isinstance(st.target, ast.Name):
                name = st.target.id
                loc = self.locals.get(name)
                if loc is None:
                    raise UnsupportedError(f"{name} is updated before it is assigned")
                return [f"{pad}{self._use(name)} {op}= {self._text(value)};"]
            target = self._subscript(st.target, store=True)
            return [f"{pad}{target} {op}= {self._text(value)};"]
        if isinstance(st, ast.For):
            return self._for(st, depth)
        if isinstance(st, ast.While):
            self.only_const_return = False
            test = self._text(self._expr(st.test))
            return [f"{pad}while ({test}) {{", *self._block(st.body, depth + 1), f"{pad}}}"]
        if isinstance(st, ast.If):
            test = self._expr(st.test)
            if isinstance(test, Const):
                return self._block(st.body if test.value else st.orelse, depth)
            self.only_const_return = False
            pending, self.pending = self.pending, []
            lines = [f"{pad}if ({test.text}) {{", *self._block(st.body, depth + 1)]
            if st.orelse:
                lines += [f"{pad}}} else {{", *self._block(st.orelse, depth + 1)]
            self.pending, self.stop = pending, False
            return lines + [f"{pad}}}"]
        if isinstance(st, ast.Return):
            return self._return(st, pad)
        if isinstance(st, ast.Pass):
            return []
        raise UnsupportedError(f"{type(st).__name__} is outside the formulas' subset "
                               f"(in {self.fdef.name})")

    def _assign(self, st: ast.Assign, pad: str) -> list[str]:
        if len(st.targets) != 1:
            raise UnsupportedError("chained assignment is outside the formulas' subset")
        target = st.targets[0]
        self.target = target.id if isinstance(target, ast.Name) else "a"
        if isinstance(target, ast.Tuple):
            if isinstance(st.value, ast.Call):               # a function returning a tuple
                return self._tuple_call(target, st.value, pad)
            value = (tuple(self._expr(e) for e in st.value.elts)
                     if isinstance(st.value, ast.Tuple) else self._expr(st.value))
            if not isinstance(value, tuple) or len(value) != len(target.elts):
                raise UnsupportedError("tuple assignment needs a tuple of the same length")
            lines: list[str] = []
            for t, v in zip(target.elts, value):
                lines += self._store(t, v, pad)
            return lines
        return self._store(target, self._expr(st.value), pad)

    def _store(self, target: ast.expr, value: Any, pad: str) -> list[str]:
        if isinstance(target, ast.Subscript):
            self.only_const_return = False
            return [f"{pad}{self._subscript(target, store=True)} = {self._text(value)};"]
        if not isinstance(target, ast.Name):
            raise UnsupportedError("assignment target outside the formulas' subset")
        name = target.id
        once = self.assigned.get(name, 0) == 1 and name not in self.locals
        if once and isinstance(value, (Const, Arr, tuple, Fn)):
            self.env[name] = value                          # compile-time: no C code
            return []
        if isinstance(value, (Arr, tuple, Fn)):
            raise UnsupportedError(f"{name} is rebound to an array in {self.fdef.name}")
        self.only_const_return = False
        ctype = c_type(value)
        loc = self.locals.get(name)
        if loc is None:
            cname = self._c_name(name)
            if cname in self.locals or any(p[1] == cname for p in self.params):
                raise UnsupportedError(f"local {name} clashes in {self.fdef.name}")
            self.locals[name] = _Local(ctype)
            self.env[name] = Scal(cname, ctype)
        elif loc.ctype == INT and ctype == REAL:
            raise UnsupportedError(f"{name} changes from an integer to a real in "
                                   f"{self.fdef.name}")
        return [f"{pad}{self._use(name)} = {self._text(value)};"]

    def _use(self, name: str) -> str:
        return self._c_name(name)

    def _for(self, st: ast.For, depth: int) -> list[str]:
        pad = "    " * depth
        it = st.iter
        if not (isinstance(it, ast.Call) and isinstance(it.func, ast.Name)
                and it.func.id == "range" and isinstance(st.target, ast.Name)):
            raise UnsupportedError("only `for name in range(...)` is in the formulas' subset")
        bounds = [self._expr(a) for a in it.args]
        start, stop, step = ((Const(0), bounds[0], Const(1)) if len(bounds) == 1 else
                             (bounds[0], bounds[1], Const(1)) if len(bounds) == 2 else bounds)
        if not isinstance(step, Const) or step.value == 0:
            raise UnsupportedError("range() needs a constant, nonzero step")
        if (isinstance(start, Const) and isinstance(stop, Const)
                and len(range(start.value, stop.value, step.value)) == 0):
            return []
        self.only_const_return = False
        name = st.target.id
        if (isinstance(start, Const) and isinstance(stop, Const) and not st.orelse
                and len(range(start.value, stop.value, step.value)) * self.unrolled <= UNROLL):
            return self._unrolled(st, range(start.value, stop.value, step.value), depth)
        if name not in self.locals:
            self.locals[name] = _Local(INT)
            self.env[name] = Scal(self._c_name(name), INT)
        elif self.locals[name].ctype != INT:
            raise UnsupportedError(f"loop variable {name} is also a real in {self.fdef.name}")
        i = self._use(name)
        cmp = "<" if step.value > 0 else ">"
        inc = f"++{i}" if step.value == 1 else f"{i} += {step.value}"
        head = f"{pad}for ({i} = {self._text(start)}; {i} {cmp} {self._text(stop)}; {inc}) {{"
        if st.orelse:
            raise UnsupportedError("for ... else is outside the formulas' subset")
        return [head, *self._block(st.body, depth + 1), f"{pad}}}"]

    def _unrolled(self, st: ast.For, values: range, depth: int) -> list[str]:
        """A loop of a few constant iterations, written out (its indices fold)."""
        assert isinstance(st.target, ast.Name)
        name = st.target.id
        saved = self.env.get(name)
        lines: list[str] = []
        self.unrolled *= len(values)
        for value in values:
            self.env[name] = Const(value)
            lines += self._block(st.body, depth)
        self.unrolled //= len(values)
        if saved is None:
            self.env.pop(name, None)
        else:
            self.env[name] = saved
        return lines

    def _return(self, st: ast.Return, pad: str) -> list[str]:
        if st.value is None:
            self.only_const_return = False
            return [f"{pad}return;"]
        if self.returns_tuple:
            self.only_const_return = False
            if not isinstance(st.value, ast.Tuple):
                raise UnsupportedError(f"{self.fdef.name} returns tuples and non-tuples")
            values = [self._expr(e) for e in st.value.elts]
            types = [Arr("", v.shape) if isinstance(v, Arr) else c_type(v) for v in values]
            if self.result is None:
                self.result = types
            else:
                self.result = [a if isinstance(a, Arr) or isinstance(b, Arr) else join(a, b)
                               for a, b in zip(self.result, types)]
            lines = []
            for i, v in enumerate(values):
                lines += (copy_lines(f"ret{i}", region(v, [("slice", None, None)]
                                                       * len(v.shape), self._text), pad)
                          if isinstance(v, Arr) else [f"{pad}*ret{i} = {self._text(v)};"])
            return lines + [f"{pad}return;"]
        value = self._expr(st.value)
        if isinstance(value, Arr):
            self.only_const_return = False
            self.result = Arr("", value.shape)
            whole = region(value, [("slice", None, None)] * len(value.shape), self._text)
            return copy_lines("ret", whole, pad) + [f"{pad}return;"]
        if isinstance(value, Const):
            if self.result is None and self.only_const_return:
                self.result = value
                return [f"{pad}return {self._text(value)};"]
            ctype = c_type(value)
        else:
            self.only_const_return = False
            ctype = value.ctype
        prev = self.result
        if isinstance(prev, Const):
            prev = c_type(prev)
        self.result = ctype if prev is None else join(prev, ctype)
        return [f"{pad}return {self._text(value)};"]

    def _tuple_call(self, target: ast.Tuple, call: ast.Call, pad: str) -> list[str]:
        self.only_const_return = False
        fn = self._callee(call)
        names = [t.id for t in target.elts if isinstance(t, ast.Name)]
        if len(names) != len(target.elts) or not isinstance(fn.result, tuple):
            raise UnsupportedError("a tuple is assigned from a call that does not return one")
        outs = []
        for name, ctype in zip(names, fn.result):
            if isinstance(ctype, Arr):
                if self.assigned.get(name, 0) != 1:
                    raise UnsupportedError(f"{name} is rebound to an array in "
                                           f"{self.fdef.name}")
                self.target = name
                arr = self._new_array(ctype.shape)
                self.env[name] = arr
                outs.append(arr.name)
                continue
            if name not in self.locals:
                self.locals[name] = _Local(ctype)
                self.env[name] = Scal(self._c_name(name), ctype)
            outs.append("&" + self._use(name))
        return [f"{pad}{fn.name}({', '.join([*fn.args, *outs])});"]

    # ------------------------------------------------------------------ expressions
    def _text(self, value: Any) -> str:
        if isinstance(value, Const):
            return value.text if value.text is not None else self.unit.literal(value.value)
        if isinstance(value, Scal):
            return value.text
        raise UnsupportedError(f"{value!r} is not a scalar (in {self.fdef.name})")

    def _expr(self, node: ast.expr) -> Any:
        if isinstance(node, ast.Constant):
            if isinstance(node.value, (bool, int, float)):
                return Const(node.value)
            raise UnsupportedError(f"constant {node.value!r} is outside the formulas' subset")
        if isinstance(node, ast.Name):
            return self._name(node.id)
        if isinstance(node, ast.BinOp):
            return self._binop(node)
        if isinstance(node, ast.UnaryOp):
            v = self._expr(node.operand)
            if isinstance(node.op, ast.Not):
                if isinstance(v, Const):
                    return Const(not v.value)
                return Scal(f"!({v.text})", INT)
            if isinstance(node.op, ast.USub):
                if isinstance(v, Const):
                    return Const(-v.value, None if v.text is None else f"(-{v.text})")
                return Scal(f"-({v.text})", v.ctype)
            if isinstance(node.op, ast.UAdd):
                return v
        if isinstance(node, ast.Compare):
            return self._compare(node)
        if isinstance(node, ast.BoolOp):
            return self._boolop(node)
        if isinstance(node, ast.IfExp):
            test = self._expr(node.test)
            if isinstance(test, Const):
                return self._expr(node.body if test.value else node.orelse)
            a, b = self._expr(node.body), self._expr(node.orelse)
            ctype = join(c_type(a), c_type(b))
            return Scal(f"({test.text} ? {self._text(a)} : {self._text(b)})", ctype)
        if isinstance(node, ast.Subscript):
            return self._load_subscript(node)
        if isinstance(node, ast.Attribute):
            return self._attribute(node)
        if isinstance(node, ast.Call):
            return self._call(node)
        if isinstance(node, ast.Tuple):
            return tuple(self._expr(e) for e in node.elts)
        raise UnsupportedError(f"{type(node).__name__} is outside the formulas' subset "
                               f"(in {self.fdef.name})")

    def _name(self, name: str) -> Any:
        if name in self.env:
            value = self.env[name]
            return value
        if name in self.unit.constants:
            return self.unit.constants[name]
        if name in ("True", "False"):
            return Const(name == "True")
        if name in self.unit.functions or self.unit.model(name, None) is not None:
            return Fn(name)
        raise UnsupportedError(f"{name} is not bound for the C step (in {self.fdef.name})")

    def _binop(self, node: ast.BinOp) -> Any:
        a, b = self._expr(node.left), self._expr(node.right)
        op = type(node.op)
        if isinstance(a, Const) and isinstance(b, Const) and a.text is None and b.text is None:
            return Const(FOLD[op](a.value, b.value))
        if op is ast.Pow:
            if isinstance(b, Const) and b.value == 2:
                t = self._text(a)
                if not isinstance(a, Scal) or not a.text.isidentifier():
                    t = f"({t})"
                return Scal(f"{t} * {t}", REAL)
            raise UnsupportedError("only the square ** 2 is in the formulas' subset")
        unit = {ast.Add: 0, ast.Sub: 0, ast.Mult: 1}.get(op)
        for const, other, on_right in ((b, a, True), (a, b, False)):
            if (unit is not None and isinstance(const, Const) and const.text is None
                    and const.value == unit and (on_right or op is not ast.Sub)
                    and (isinstance(const.value, int) or c_type(other) == REAL)):
                return other
        ta, tb = c_type(a), c_type(b)
        ctype = join(ta, tb)
        left, right = self._paren(a), self._paren(b)
        if op is ast.Div:
            ctype = REAL
            if ta == INT and tb == INT:
                left = f"(real_t){left}"
        elif op is ast.FloorDiv:
            if ctype != INT:
                raise UnsupportedError("// on reals is outside the formulas' subset")
            return Scal(f"({left} / {right})", INT)
        elif op is ast.BitAnd and ctype != INT:
            raise UnsupportedError("& on reals is outside the formulas' subset")
        return Scal(f"({left} {BINOPS[op]} {right})", ctype)

    def _paren(self, value: Any) -> str:
        text = self._text(value)
        if isinstance(value, Const) and text.startswith("-"):
            return f"({text})"
        return text

    def _compare(self, node: ast.Compare) -> Any:
        if len(node.ops) != 1:
            raise UnsupportedError("chained comparisons are outside the formulas' subset")
        a, b = self._expr(node.left), self._expr(node.comparators[0])
        op = type(node.ops[0])
        if isinstance(a, Const) and isinstance(b, Const):
            return Const(bool(CMP_FOLD[op](a.value, b.value)))
        return Scal(f"({self._paren(a)} {CMPS[op]} {self._paren(b)})", INT)

    def _boolop(self, node: ast.BoolOp) -> Any:
        is_and = isinstance(node.op, ast.And)
        parts: list[str] = []
        for e in node.values:
            v = self._expr(e)
            if isinstance(v, Const):
                if bool(v.value) != is_and:                 # False in and, True in or
                    if any(re.search(r"\bf_\w*\(", part) for part in parts):
                        raise UnsupportedError("a call whose result a constant decides")
                    return Const(not is_and)
                continue
            parts.append(v.text)
        if not parts:
            return Const(is_and)
        return Scal("(" + (" && " if is_and else " || ").join(parts) + ")", INT)

    def _array(self, node: ast.expr) -> Arr:
        value = self._expr(node)
        if not isinstance(value, Arr):
            raise UnsupportedError(f"{ast.unparse(node)} is not an array (in {self.fdef.name})")
        return value

    def _index(self, arr: Arr, sl: ast.expr) -> str:
        if isinstance(sl, ast.Tuple):
            if len(arr.shape) != 2 or len(sl.elts) != 2:
                raise UnsupportedError(f"{arr.name}: a 2-D index of a {arr.shape} array")
            i, j = (self._expr(e) for e in sl.elts)
            cols = arr.shape[1]
            if isinstance(i, Const) and isinstance(j, Const):
                return str(i.value * cols + j.value)
            if isinstance(i, Const):
                row = i.value * cols
                return f"{row} + {self._paren(j)}" if row else self._text(j)
            return f"{self._paren(i)} * {cols} + {self._paren(j)}"
        index = self._expr(sl)
        if len(arr.shape) != 1:
            raise UnsupportedError(f"{arr.name}: a 1-D index of a {arr.shape} array")
        return self._text(index)

    def _subscript(self, node: ast.expr, store: bool) -> str:
        if not isinstance(node, ast.Subscript):
            raise UnsupportedError("assignment target outside the formulas' subset")
        arr = self._array(node.value)
        if store and arr.glob:
            self.unit.written_globals.add(arr.name)     # scratch, not data: printed again
        return f"{arr.name}[{self._index(arr, node.slice)}]"

    def _load_subscript(self, node: ast.Subscript) -> Any:
        base = self._expr(node.value)
        if isinstance(base, tuple):
            if isinstance(node.slice, ast.Slice):
                lo = self._expr(node.slice.lower) if node.slice.lower else Const(None)
                hi = self._expr(node.slice.upper) if node.slice.upper else Const(None)
                if node.slice.step is not None or not all(
                        isinstance(v, Const) for v in (lo, hi)):
                    raise UnsupportedError("a tuple slice needs constant bounds")
                return tuple(base[lo.value:hi.value])
            index = self._expr(node.slice)
            if not isinstance(index, Const):
                raise UnsupportedError("a tuple index must be a constant")
            return base[index.value]
        if isinstance(base, Arr):
            return Scal(f"{base.name}[{self._index(base, node.slice)}]", REAL)
        raise UnsupportedError(f"{ast.unparse(node)} is outside the formulas' subset")

    def _attribute(self, node: ast.Attribute) -> Any:
        if (isinstance(node.value, ast.Name) and node.value.id in ("np", "math")
                and node.attr in _SPECIAL):
            return _SPECIAL[node.attr]
        base = self._expr(node.value)
        if isinstance(base, tuple) and hasattr(base, "_fields"):
            return getattr(base, node.attr)
        if isinstance(base, Arr) and node.attr == "size":
            return Const(base.size)
        if isinstance(base, Arr) and node.attr == "shape":
            return tuple(Const(d) for d in base.shape)
        raise UnsupportedError(f"{ast.unparse(node)} is outside the formulas' subset")

    def _call(self, node: ast.Call) -> Any:
        func = node.func
        if isinstance(func, ast.Attribute):
            if isinstance(func.value, ast.Name) and func.value.id == "math":
                (a,) = (self._expr(e) for e in node.args)
                if func.attr == "isfinite":
                    if isinstance(a, Const):
                        return Const(math.isfinite(a.value))
                    return Scal(f"isfinite({a.text})", INT)
                if func.attr in ("exp", "sqrt", "ceil"):
                    suffix = "" if self.unit.real == "double" else "f"
                    return Scal(f"{func.attr}{suffix}({self._text(a)})", REAL)
            if (isinstance(func.value, ast.Name) and func.value.id == "np"
                    and func.attr in ALLOCATIONS):
                (arg,) = node.args
                shape = shape_of(self._expr(arg))
                shape = (shape[0], shape[0]) if func.attr == "eye" else shape
                arr = self._new_array(shape)
                self.pending += allocation_lines(func.attr, arr.name, shape, self.pad)
                return arr
            if func.attr == "copy" and not node.args:
                src = self._region(func.value)
                arr = self._new_array(src.shape)
                self.pending += copy_lines(arr.name, src, self.pad)
                return arr
            if func.attr == "reshape":
                arr = self._array(func.value)
                (n,) = (self._expr(e) for e in node.args)
                if not isinstance(n, Const) or n.value != arr.size:
                    raise UnsupportedError("reshape only flattens")
                return Arr(arr.name, (arr.size,), arr.glob)
            raise UnsupportedError(f"{ast.unparse(func)} is outside the formulas' subset")
        if not isinstance(func, ast.Name):
            raise UnsupportedError(f"{ast.unparse(func)} is outside the formulas' subset")
        name = func.id
        if name in ("max", "min"):
            values = [self._expr(e) for e in node.args]
            acc = values[0]
            for b in values[1:]:
                acc = self._extremum(name, acc, b)
            return acc
        if name in ("int", "float"):
            (a,) = (self._expr(e) for e in node.args)
            if isinstance(a, Const) and a.text is None:
                return Const(int(a.value) if name == "int" else float(a.value))
            ctype = INT if name == "int" else REAL
            return Scal(f"({ctype})({self._text(a)})", ctype)
        if name == "abs":
            (a,) = (self._expr(e) for e in node.args)
            if isinstance(a, Const):
                return Const(abs(a.value))
            return Scal(f"{'fabs' if self.unit.real == 'double' else 'fabsf'}({a.text})",
                        REAL)
        fn = self._callee(node)
        if isinstance(fn.result, Const):
            return fn.result
        if isinstance(fn.result, Arr):                      # written through ``ret``
            self.only_const_return = False
            arr = self._new_array(fn.result.shape)
            self.pending.append(f"{self.pad}{fn.name}({', '.join([*fn.args, arr.name])});")
            return arr
        if isinstance(fn.result, tuple):
            raise UnsupportedError(f"{name} returns a tuple: assign it to names")
        self.only_const_return = False
        text = f"{fn.name}({', '.join(fn.args)})"
        return Scal(text, fn.result if fn.result != "void" else INT)

    def _extremum(self, name: str, a: Any, b: Any) -> Any:
        """Python's max/min of two scalars (the first on ties and NaN)."""
        if isinstance(a, Const) and isinstance(b, Const):
            return Const(max(a.value, b.value) if name == "max" else min(a.value, b.value))
        helper = name if join(c_type(a), c_type(b)) == REAL else "i" + name
        self.unit.helpers.add(helper)
        return Scal(f"py_{helper}({self._text(a)}, {self._text(b)})",
                    REAL if helper == name else INT)

    def _callee(self, node: ast.Call) -> CFunction:
        func = node.func
        assert isinstance(func, ast.Name)
        target = self._name(func.id)
        if not isinstance(target, Fn):
            raise UnsupportedError(f"{func.id} is not a function (in {self.fdef.name})")
        args = [self._expr(a) for a in node.args]
        model = self.unit.model(target.name, args)
        if model is not None:
            self.unit.model_calls.add(target.name)
            cname, cargs = model
            return CFunction(cname, cargs, INT)
        fn = self.unit.call(target.name, args)
        return fn
