"""Printed Python modules: the formulas for NumPy, kernels for numba, imported from the cache.

Every piece of generated Python in thetahat is printed here from syntax trees and imported
as a module file written under its content hash
(:func:`~thetahat.estimation.kernels.kernel_cache.load_module`); none is executed from a
string, and no function is rebuilt from another's code object.

* :func:`numpy_binding`: the formulas of a :class:`~thetahat.estimation.kernels.printer.Program`
  printed for NumPy (``"row"`` or ``"batch"``) as a module with one function, ``bind``, whose
  keyword parameters are the names the formulas read (the model functions, the law's hooks,
  the dimensions); ``bind(**names)`` returns the formulas closed over them. One module per
  set of formulas and target, one call of ``bind`` per owner (a perturbation, a law).
* :class:`ModuleText`: the text of a module of functions, constants and imports, each
  function a printed tree (the numba kernel of
  :mod:`~thetahat.estimation.observer.kernel_source`, stage 2's plant model of
  :mod:`~thetahat.estimation.statistical.plant_kernel`).
* :meth:`ModuleText.bound`: a module-level function written in numba's subset printed with
  its free names bound — the functions it calls printed beside it, a kernel of another printed
  module imported from there, numbers and arrays as exact literals, and the names the caller
  provides (stage 2's kernels over one model's printed plant model, the projection onto Θ of
  the observer's kernel); compiled once per machine (numba's ``cache=True``) when decorated.
"""

from __future__ import annotations

import ast
import builtins
import inspect
import math
import threading
import types
from collections import OrderedDict
from collections.abc import Callable, Collection, Hashable, Mapping, Sequence
from typing import Any

import numpy as np

from ...errors import MissingExtraError, ThetahatError
from . import primitives
from .kernel_cache import load_module, origin, register
from .printer import Program
from .subset import source_tree

__all__ = ["KernelSourceError", "ModuleText", "numpy_binding", "numpy_source"]

#: The start of numba's decorator line (:func:`_inlined` adds its ``inline`` option there).
NUMBA_JIT = "@numba.njit("
#: Modules a kernel may use by name, with the import line that binds them.
_MODULES = {id(math): ("math", "import math"), id(np): ("np", "import numpy as np")}

#: The NumPy functions a printed NumPy module imports (:mod:`.primitives`).
_HELPERS = tuple(name for name in primitives.__all__ if name != "VOCABULARY")


class KernelSourceError(ThetahatError, ValueError):
    """A kernel cannot be written out as module source (the caller compiles it in memory)."""


def _literal(value: Any) -> str | None:
    """Exact source of a number or a numeric array, or None."""
    if isinstance(value, (bool, np.bool_)):
        return repr(bool(value))
    if isinstance(value, (int, np.integer)):
        return repr(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return repr(v) if math.isfinite(v) else f"float({repr(v)!r})"
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        flat = ", ".join(_literal(v) or "" for v in value.ravel().tolist())
        return (f"np.array([{flat}], dtype=np.{value.dtype.name})"
                f".reshape({tuple(value.shape)!r})")
    return None


class ModuleText:
    """The text of a printed module: a docstring, imports, constants and functions.

    Parameters
    ----------
    doc : str
        The module's docstring (what generated it).
    decorator : str, optional
        The decorator line of every function added with :meth:`function` (default none).
    inline : collection of function, optional
        Functions that :meth:`bound` prints with numba's ``inline='always'`` when the
        decorator is numba's: small kernels called once per RK4 stage, whose loops over the
        state then unroll in their caller (``stage_jac``: the MAP fit's sweep 2× faster on the
        Silverbox model, measured once).

    Examples
    --------
    >>> text = ModuleText("Doc.")
    >>> text.constant("K", "2.0")
    >>> text.function(ast.parse("def f(x):\\n    return K * x\\n").body[0])
    >>> print(text.source())
    '''Doc.'''
    K = 2.0
    <BLANKLINE>
    <BLANKLINE>
    def f(x):
        return K * x
    <BLANKLINE>
    """

    def __init__(self, doc: str, decorator: str | None = None,
                 inline: Collection[Callable[..., Any]] = ()) -> None:
        self.doc = doc
        self.decorator = decorator
        self.inline = {id(getattr(fn, "py_func", fn)) for fn in inline}
        self.imports: dict[str, None] = {}
        self.constants: list[str] = []
        self.functions: list[str] = []
        self.names: dict[int, str] = {}
        self.values: dict[tuple[str, int], tuple[Any, str]] = {}

    def import_line(self, line: str) -> None:
        """Add an import (once)."""
        self.imports[line] = None

    def constant(self, name: str, text: str) -> None:
        """``name = text`` at module level."""
        self.constants.append(f"{name} = {text}")

    def function(self, node: ast.FunctionDef, decorator: str | None = None) -> None:
        """A printed function (decorated with ``decorator``, else the module's)."""
        line = decorator if decorator is not None else self.decorator
        self.functions.append((f"{line}\n" if line else "") + ast.unparse(node))

    def definition(self, fn: Callable[..., Any], decorator: str | None = None) -> None:
        """A module-level function of thetahat, printed as written (annotations and docstring
        dropped) under its own name: its free names are the printed module's."""
        self.function(_bare(source_tree(fn)), decorator)

    def text(self, text: str) -> None:
        """Source already printed (e.g. by SymPy's printer), as it is."""
        self.functions.append(text.rstrip("\n"))

    def source(self) -> str:
        """The module's text."""
        head = [f"'''{self.doc}'''", *self.imports, *self.constants]
        return "\n".join(head) + "".join(f"\n\n\n{f}" for f in self.functions) + "\n"

    # ------------------------------------------------------------------ bound functions
    def value(self, ident: str, value: Any, decorator: str | None = None,
              provided: Mapping[str, Any] | None = None) -> str:
        """The module-level name bound to ``value`` (emitting what it needs).

        A module (``math``, ``np``) is imported; a function printed in another module
        (registered, :func:`~thetahat.estimation.kernels.kernel_cache.origin`) is imported from
        it; a thetahat function is printed (:meth:`bound`); a number or a numeric array
        becomes a constant; a string is a name the module defines itself (used as it is).
        """
        if isinstance(value, str):
            return value
        if id(value) in _MODULES:
            alias, line = _MODULES[id(value)]
            self.import_line(line)
            return alias
        known = origin(value)
        if known is not None:
            module, name = known
            self.import_line(f"from {module} import {name}")
            return name
        if callable(value) and not isinstance(value, type):
            return self.bound(value, decorator, provided)
        seen = self.values.get((ident, id(value)))
        if seen is not None and seen[0] is value:
            return seen[1]
        text = _literal(value)
        if text is None:
            raise KernelSourceError(f"{ident!r} holds a {type(value).__name__}")
        if isinstance(value, np.ndarray):
            self.import_line("import numpy as np")
        name = f"{ident}_k{len(self.constants)}"
        self.constant(name, text)
        self.values[(ident, id(value))] = (value, name)
        return name

    def bound(self, fn: Any, decorator: str | None = None,
              provided: Mapping[str, Any] | None = None) -> str:
        """Print the module-level function ``fn`` and every function it calls, each free name
        bound to what it names; returns its name in the module.

        A free name is looked up in ``provided`` first (what this module gives the function:
        another printed module's kernel, an array, or a name the module defines), then in the
        globals of the function's own module; each value is emitted by :meth:`value`. Every
        function printed gets ``decorator`` (``"@numba.njit(...)"`` imports numba; None: plain
        Python). The same function printed twice is one definition.

        Raises
        ------
        KernelSourceError
            No source, a closure or a nested function, or a free name of another kind.
        """
        py = getattr(fn, "py_func", fn)
        if not isinstance(py, types.FunctionType):
            raise KernelSourceError(f"{fn!r} is not a Python function")
        if id(py) in self.names:
            return self.names[id(py)]
        if py.__closure__:
            raise KernelSourceError(f"{py.__name__} is a closure: kernels are module-level "
                                    "functions whose free names are bound when printed")
        try:
            node = _bare(source_tree(py))
        except (OSError, TypeError, SyntaxError, ThetahatError) as exc:
            raise KernelSourceError(f"no source for {py.__name__}: {exc}") from exc
        name = f"{py.__name__}_f{len(self.names)}"
        self.names[id(py)] = name
        given = provided or {}
        local = set(py.__code__.co_varnames) | set(py.__code__.co_cellvars)
        rename: dict[str, str] = {}
        for sub in ast.walk(node):
            if isinstance(sub, ast.FunctionDef | ast.Lambda) and sub is not node:
                raise KernelSourceError(f"{py.__name__} defines a nested function")
            if not isinstance(sub, ast.Name) or sub.id in local or sub.id in rename:
                continue
            if sub.id in given:
                rename[sub.id] = self.value(sub.id, given[sub.id], decorator, provided)
            elif sub.id in py.__globals__:
                rename[sub.id] = self.value(sub.id, py.__globals__[sub.id], decorator,
                                            provided)
            elif not hasattr(builtins, sub.id):
                raise KernelSourceError(f"{py.__name__}: unknown name {sub.id!r}")
        printed = _renamed(node, rename, name)
        self.function(printed, _inlined(decorator) if id(py) in self.inline else decorator or "")
        if decorator is not None and decorator.startswith("@numba."):
            self.import_line("import numba")
        return name


def _inlined(decorator: str | None) -> str:
    """``decorator`` with numba's ``inline='always'`` (the function's IR is typed into each
    caller's, so the caller's loops over its constant shapes unroll through it); other
    decorators as they are."""
    if decorator is None or not decorator.startswith(NUMBA_JIT):
        return decorator or ""
    return decorator.replace(NUMBA_JIT, NUMBA_JIT + "inline='always', ", 1)


class _Rename(ast.NodeTransformer):
    def __init__(self, rename: Mapping[str, str]) -> None:
        self.rename = rename

    def visit_Name(self, node: ast.Name) -> ast.Name:
        return ast.Name(self.rename.get(node.id, node.id), node.ctx)


def _bare(node: ast.FunctionDef) -> ast.FunctionDef:
    """A copy of ``node`` without annotations, decorators and docstring (they are not
    code)."""
    new = ast.parse(ast.unparse(node)).body[0]
    assert isinstance(new, ast.FunctionDef)
    args = new.args
    for a in [*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg]:
        if a is not None:
            a.annotation = None
    new.returns = None
    new.decorator_list = []
    if (new.body and isinstance(new.body[0], ast.Expr)
            and isinstance(new.body[0].value, ast.Constant)):
        new.body = new.body[1:] or [ast.Pass()]
    return new


def _renamed(node: ast.FunctionDef, rename: Mapping[str, str], name: str) -> ast.FunctionDef:
    """``node`` named ``name``, its free names renamed."""
    new = _Rename(rename).visit(node)
    assert isinstance(new, ast.FunctionDef)
    new.name = name
    return ast.fix_missing_locations(new)


# ------------------------------------------------------------------------------ NumPy
def numpy_source(program: Program, roots: Sequence[str], target: str) -> str:
    """The module text of ``roots`` (and the formulas they call) printed for NumPy.

    Parameters
    ----------
    program : Program
    roots : sequence of str
        The formulas wanted.
    target : {"row", "batch"}

    Returns
    -------
    str
        A module defining ``bind(*, <free names>)`` that returns the formulas by name.

    Examples
    --------
    >>> from thetahat.estimation.kernels.subset import definition
    >>> from thetahat.estimation.observer import formulas
    >>> text = numpy_source(Program({"phi_hat": definition(formulas.phi_hat)}), ["phi_hat"],
    ...                     "batch")
    >>> "def bind(*, NK, NX):" in text
    True
    """
    names = program.closure(roots)
    free = sorted(program.free_names(names, target) - set(_HELPERS))
    functions = [program.printed(name, target) for name in names]
    result = ast.Return(ast.Dict([ast.Constant(n) for n in names],
                                 [ast.Name(n, ast.Load()) for n in names]))
    params = f"*, {', '.join(free)}" if free else ""
    template = ast.parse(f"def bind({params}):\n    pass\n").body[0]
    assert isinstance(template, ast.FunctionDef)
    template.body = [*functions, result]
    bind = template
    text = ModuleText(f"Printed by thetahat.estimation.kernels.modules from "
                      f"{', '.join(names)} for NumPy ({target}): do not edit.")
    text.import_line("import math")
    text.import_line("import numpy as np")
    text.import_line(f"from thetahat.estimation.kernels.primitives import {', '.join(_HELPERS)}")
    text.function(ast.fix_missing_locations(bind))
    return text.source()


_factories: dict[tuple[int, tuple[str, ...], str], tuple[Program, Callable[..., Any]]] = {}
#: Bindings kept by :func:`numpy_binding` (one per owner in use).
_BOUND_KEPT = 128
_bound: OrderedDict[tuple[int, Hashable], tuple[object, dict[str, Any]]] = OrderedDict()
_lock = threading.Lock()


def _factory(program: Program, roots: tuple[str, ...], target: str) -> Callable[..., Any]:
    key = (id(program), roots, target)
    hit = _factories.get(key)
    if hit is not None and hit[0] is program:
        return hit[1]
    module = load_module(numpy_source(program, roots, target), f"thetahat_numpy_{target}")
    with _lock:
        _factories[key] = (program, module.bind)
    bind: Callable[..., Any] = module.bind
    return bind


def numpy_binding(owner: object, key: Hashable, program: Program, roots: Sequence[str],
                  target: str, names: Callable[[], Mapping[str, Any]]) -> dict[str, Any]:
    """The formulas ``roots`` printed for NumPy and bound to ``names()``, once per
    ``(owner, key)`` (kept while the owner is in use).

    Parameters
    ----------
    owner : object
        What the names close over (a perturbation, a law); kept alive with the binding.
    key : hashable
        Distinguishes bindings of one owner (besides the program, the roots and the target).
    program : Program
        Kept for the life of the process (a module-level one).
    roots : sequence of str
    target : {"row", "batch"}
    names : callable
        Builds the names on a miss: the free names of the printed formulas (more are
        ignored).

    Returns
    -------
    dict of str to function
        The printed formulas by name.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.kernels.subset import definition
    >>> from thetahat.estimation.observer import formulas
    >>> prog = Program({"phi_hat": definition(formulas.phi_hat)})
    >>> fns = numpy_binding(prog, None, prog, ["phi_hat"], "row", lambda: {"NX": 1, "NK": 1})
    >>> phi = np.empty(1)
    >>> fns["phi_hat"](np.array([2.0]), np.array([0.0, 0.5]), phi); phi.tolist()
    [2.5]
    """
    k = (id(owner), (key, id(program), tuple(roots), target))
    with _lock:
        hit = _bound.get(k)
        if hit is not None and hit[0] is owner:
            _bound.move_to_end(k)
            return hit[1]
    bind = _factory(program, tuple(roots), target)
    given = names()
    wanted = list(inspect.signature(bind).parameters)
    missing = sorted(set(wanted) - set(given))
    if missing:
        raise ThetahatError(f"the NumPy binding of {', '.join(roots)} lacks {missing}")
    functions: dict[str, Any] = bind(**{n: given[n] for n in wanted})
    with _lock:
        _bound[k] = (owner, functions)
        if len(_bound) > _BOUND_KEPT:
            _bound.popitem(last=False)
    return functions
