"""Meta-tests: the public API is documented, and every docstring example runs."""

from __future__ import annotations

import doctest
import importlib
import inspect
import pkgutil

import pytest

import thetahat


def _public_callables():
    for name in thetahat.__all__:
        obj = getattr(thetahat, name)
        if inspect.isfunction(obj):
            yield name, obj
        elif inspect.isclass(obj) and not issubclass(obj, (Exception, Warning)):
            yield name, obj


@pytest.mark.parametrize("name, obj", list(_public_callables()), ids=lambda v: str(v)[:40])
def test_public_parameters_documented(name, obj):
    doc = inspect.getdoc(obj) or ""
    assert doc.strip(), f"{name} has no docstring"
    target = obj if inspect.isfunction(obj) else obj.__init__
    if target is object.__init__:
        return
    try:
        sig = inspect.signature(target)
    except (TypeError, ValueError):
        return
    missing = [p for p in sig.parameters if p not in ("self", "cls", "args", "kwargs")
               and p not in doc]
    assert not missing, f"{name}: parameters {missing} are not documented"


def _modules():
    for info in pkgutil.walk_packages(thetahat.__path__, prefix="thetahat."):
        if info.name.endswith(("__main__", ".cli")):
            continue
        yield info.name


@pytest.mark.parametrize("modname", sorted(_modules()))
def test_docstring_examples_run(modname):
    mod = importlib.import_module(modname)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for test in finder.find(mod, modname):
        runner.run(test)
    assert runner.failures == 0, f"{runner.failures} doctest failure(s) in {modname}"
