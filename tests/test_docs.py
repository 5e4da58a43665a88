"""Meta-tests: the public API is documented, and every docstring example runs."""

from __future__ import annotations

import doctest
import importlib
import enum
import gc
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


@pytest.mark.parametrize("name, obj", [pytest.param(n, o, id=n) for n, o in _public_callables()])
def test_public_parameters_documented(name, obj):
    """numpydoc, parsed: every parameter has an entry in Parameters (classes: or Attributes),
    and a function that returns something has a Returns (or Yields) section."""
    doc = inspect.getdoc(obj) or ""
    assert doc.strip(), f"{name} has no docstring"
    secs = sections(doc)
    sig = _signature(obj)
    if sig is None or (inspect.isclass(obj) and issubclass(obj, enum.Enum)):
        return      # an Enum's signature is the Enum machinery's (value, *names), not its API
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
EXAMPLES_NEED = {"thetahat.plotting": "matplotlib", "thetahat.estimation.kernels.kernel_cache": "numba",
                 "thetahat.estimation.kernels.modules": "numba"}


@pytest.mark.parametrize("modname", sorted(_modules()))
def test_docstring_examples_run(modname):
    if modname in EXAMPLES_NEED:
        pytest.importorskip(EXAMPLES_NEED[modname])
    mod = importlib.import_module(modname)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for test in finder.find(mod, modname):
        # DocTestRunner.run resets pdb, whose linecache.checkcache() iterates over a snapshot
        # of linecache's keys; SymPy's lambdify registers its generated source there and a
        # weakref finalizer removes it when the function is collected, so a cyclic collection
        # during that loop raised KeyError (seen once in CI). No cyclic collection mid-run.
        gc.disable()
        try:
            runner.run(test)
        finally:
            gc.enable()
    assert runner.failures == 0, f"{runner.failures} doctest failure(s) in {modname}"


# --- the site's cross-references: Sphinx roles become autorefs links (docs/hooks/roles.py) ---

def _roles_hook():
    import importlib.util
    import pathlib
    path = pathlib.Path(__file__).resolve().parents[1] / "docs" / "hooks" / "roles.py"
    spec = importlib.util.spec_from_file_location("docs_roles_hook", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_roles_translate_each_form():
    """Every role form the docstrings use: plain, ~ (last part shown), explicit title, !
    (never linked), a name broken over two lines; resolved names become autorefs links,
    unresolved ones plain code, and are reported."""
    roles = _roles_hook()
    known = {"thetahat.a.B": "thetahat.a.B", "B": "thetahat.a.B", "thetahat.a.B.run":
             "thetahat.a.B.run", ".c": "thetahat.c"}
    text = ("See :class:`B`, :meth:`~thetahat.a.B.run`, :func:`the run <thetahat.a.B.run>`,\n"
            ":mod:`.c`, :class:`!B`, :py:class:`B`, :data:`thetahat.a.\n    B` and "
            ":class:`numpy.random.Generator`.")
    out, missed = roles.translate(text, known.get)
    assert out == ("See [`B`][thetahat.a.B], [`run`][thetahat.a.B.run], "
                   "[`the run`][thetahat.a.B.run],\n[`.c`][thetahat.c], `B`, [`B`][thetahat.a.B], "
                   "[`thetahat.a.B`][thetahat.a.B] and `numpy.random.Generator`.")
    assert missed == ["numpy.random.Generator"]
    assert not roles.RAW_ROLE.search(out)


def test_no_raw_role_survives_in_any_docstring():
    """The translation over every docstring of the package, loaded by griffe as mkdocstrings
    loads it (with the ``#:`` comments of constants as docstrings): afterwards no text that looks like a role (a broader pattern than the one
    translated) is left, and every thetahat name a page renders is linked, not shown as code."""
    griffe = pytest.importorskip("griffe")
    import pathlib
    roles = _roles_hook()
    root = pathlib.Path(__file__).resolve().parents[1]
    package = griffe.load("thetahat", search_paths=[str(root / "src")])
    assert roles.doc_comments(package) > 20  # the #: comments of constants, as the site reads
    before = sum(len(roles.ROLE.findall(o.docstring.value)) for o in roles._documented(package))
    unresolved = roles.translate_package(package, roles.rendered_identifiers(root / "docs"))
    left = {o.path: roles.RAW_ROLE.findall(o.docstring.value)
            for o in roles._documented(package) if roles.RAW_ROLE.search(o.docstring.value)}
    assert before > 100 and not left, left
    # A module a reference page renders is linked whenever a docstring names it.
    rendered_modules = {ident for ident, _ in roles.rendered_identifiers(root / "docs")}
    named = {t for ts in unresolved.values() for t in ts}
    assert not named & rendered_modules, named & rendered_modules
