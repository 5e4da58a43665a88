"""Meta-tests: the public API is documented, and every docstring example runs."""

from __future__ import annotations

import doctest
import importlib
import inspect
import pkgutil

import pytest

import thetahat

from numpydoc_sections import documented_names, entries, items, sections


def _modules():
    for info in pkgutil.walk_packages(thetahat.__path__, prefix="thetahat."):
        if info.name.endswith(("__main__", ".cli")):
            continue
        yield info.name


def _public_callables():
    """Functions and classes of ``thetahat.__all__`` and of every module's ``__all__``
    (those defined in that module), each once."""
    seen = set()
    owners = [("thetahat", thetahat)] + [(m, importlib.import_module(m)) for m in
                                          sorted(_modules())]
    for modname, mod in owners:
        for name in getattr(mod, "__all__", ()):
            obj = getattr(mod, name, None)
            if id(obj) in seen or not (inspect.isfunction(obj) or (
                    inspect.isclass(obj) and not issubclass(obj, (Exception, Warning)))):
                continue
            if modname != "thetahat" and getattr(obj, "__module__", None) != modname:
                continue
            seen.add(id(obj))
            yield f"{obj.__module__}.{name}", obj


def _signature(obj):
    target = obj if inspect.isfunction(obj) else obj.__init__
    if target is object.__init__:
        return None
    try:
        return inspect.signature(target)
    except (TypeError, ValueError):
        return None


@pytest.mark.parametrize("name, obj", list(_public_callables()), ids=lambda v: str(v)[:60])
def test_public_parameters_documented(name, obj):
    """numpydoc, parsed: every parameter has an entry in Parameters (classes: or Attributes),
    and a function that returns something has a Returns (or Yields) section."""
    doc = inspect.getdoc(obj) or ""
    assert doc.strip(), f"{name} has no docstring"
    secs = sections(doc)
    sig = _signature(obj)
    if sig is None:
        return
    titles = ("Parameters", "Other Parameters") + (("Attributes",) if inspect.isclass(obj)
                                                   else ())
    have = documented_names(doc, titles)
    missing = [p for p in sig.parameters if p not in ("self", "cls", "args", "kwargs")
               and p not in have]
    assert not missing, f"{name}: parameters {missing} have no numpydoc entry"
    if inspect.isfunction(obj) and sig.return_annotation not in (None, "None",
                                                                  inspect.Signature.empty):
        assert "Returns" in secs or "Yields" in secs, f"{name}: no Returns section"
        assert items(secs.get("Returns", secs.get("Yields", []))), \
            f"{name}: the Returns section documents nothing"


def test_numpydoc_reader_finds_sections_and_entries():
    """The reader on a known docstring: grouped names, types, continuation lines skipped."""
    doc = """Summary.

    Parameters
    ----------
    a, b : float
        Two numbers; ``c : int`` in a description is not an entry.
    c
        Untyped.

    Returns
    -------
    ndarray, shape (n,)
    """
    secs = sections(doc)
    assert set(secs) == {"", "Parameters", "Returns"}
    assert entries(secs["Parameters"]) == [(("a", "b"), "float"), (("c",), None)]
    assert documented_names(doc) == {"a", "b", "c"}
    assert items(secs["Returns"]) == ["ndarray, shape (n,)"]


#: Modules whose examples need an optional extra: their doctests skip without it.
EXAMPLES_NEED = {"thetahat.plotting": "matplotlib", "thetahat.estimation.kernel_cache": "numba"}


@pytest.mark.parametrize("modname", sorted(_modules()))
def test_docstring_examples_run(modname):
    if modname in EXAMPLES_NEED:
        pytest.importorskip(EXAMPLES_NEED[modname])
    mod = importlib.import_module(modname)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for test in finder.find(mod, modname):
        runner.run(test)
    assert runner.failures == 0, f"{runner.failures} doctest failure(s) in {modname}"
