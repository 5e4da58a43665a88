"""One error hierarchy, actually raised: no bare builtin exception leaves src/thetahat.

Every exception that leaves the public API or the CLI must be a ThetahatError subclass (that
also derives from the matching builtin), so that ``except ThetahatError`` is complete. This
test walks the source with :mod:`ast` and fails on any ``raise ValueError(...)``,
``raise TypeError``, ... in the package, wherever it is.
"""

from __future__ import annotations

import ast
import builtins
import inspect
from pathlib import Path

import pytest

import thetahat
from thetahat import errors

SRC = Path(thetahat.__file__).resolve().parent

#: Every builtin exception class (ValueError, TypeError, RuntimeError, NotImplementedError,
#: MemoryError, RecursionError, ...): none may be raised directly.
BUILTIN_EXCEPTIONS = {name for name, obj in vars(builtins).items()
                      if inspect.isclass(obj) and issubclass(obj, BaseException)}

#: Re-raised builtins that are not errors of ours (the CLI's argparse exit, Ctrl-C), and the
#: AttributeError that a module's ``__getattr__`` (PEP 562, thetahat's lazy names) must raise for
#: an unknown name: ``hasattr`` and ``from thetahat import X`` rely on exactly that type.
ALLOWED = {"SystemExit", "KeyboardInterrupt", "StopIteration", "GeneratorExit", "AttributeError"}


def _raised_name(node: ast.Raise) -> str | None:
    exc = node.exc
    if isinstance(exc, ast.Call):
        exc = exc.func
    return exc.id if isinstance(exc, ast.Name) else None


def _bare_builtin_raises() -> list[str]:
    found = []
    for path in sorted(SRC.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Raise) and node.exc is not None:
                name = _raised_name(node)
                if name in BUILTIN_EXCEPTIONS and name not in ALLOWED:
                    found.append(f"{path.relative_to(SRC)}:{node.lineno}: raise {name}")
    return found


def test_the_walk_finds_a_bare_raise(tmp_path):
    """The detector itself works (a test that cannot fail proves nothing)."""
    tree = ast.parse("def f():\n    raise ValueError('x')\n")
    raises = [n for n in ast.walk(tree) if isinstance(n, ast.Raise)]
    assert _raised_name(raises[0]) == "ValueError" and "ValueError" in BUILTIN_EXCEPTIONS


def test_no_bare_builtin_raise_in_the_package():
    found = _bare_builtin_raises()
    assert not found, "raise a ThetahatError subclass instead:\n" + "\n".join(found)


@pytest.mark.parametrize("name", errors.__all__)
def test_every_error_is_a_thetahat_error_and_a_builtin(name):
    cls = getattr(errors, name)
    if issubclass(cls, Warning):
        assert issubclass(cls, errors.ThetahatWarning) or cls is errors.ThetahatWarning
        return
    assert issubclass(cls, errors.ThetahatError)
    if cls is not errors.ThetahatError:
        builtin_bases = [b for b in cls.__mro__ if b.__name__ in BUILTIN_EXCEPTIONS
                         and b not in (Exception, BaseException, object)]
        assert builtin_bases, f"{name} derives from no builtin it refines"
