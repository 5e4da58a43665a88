"""The import graph of thetahat: the layers of pyproject's import-linter contracts, no cycle
between modules, every package saying what it may import, and the 0.2 paths gone."""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

import pytest

import thetahat

ROOT = Path(__file__).resolve().parents[1]


def _graph():
    grimp = pytest.importorskip("grimp", reason="grimp comes with import-linter (typecheck extra)")
    return grimp.build_graph("thetahat", include_external_packages=False)


def test_the_contracts_of_pyproject_are_kept() -> None:
    """import-linter's layers contracts (the tool CI runs as `lint-imports`)."""
    pytest.importorskip("importlinter", reason="import-linter is in the typecheck extra")
    from importlinter.application.use_cases import lint_imports
    from importlinter.application.app_config import settings  # noqa: F401  (configures it)
    import importlinter.configuration

    importlinter.configuration.configure()
    cwd = Path.cwd()
    try:
        import os
        os.chdir(ROOT)                               # lint-imports reads ./pyproject.toml
        assert lint_imports(config_filename="pyproject.toml") is True
    finally:
        os.chdir(cwd)


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative: no
    recursion limit to raise)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    for root in list(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_no_module_imports_itself_through_others() -> None:
    """No import cycle between modules, counting imports inside functions and under
    TYPE_CHECKING (a package's __init__ counts as a module)."""
    graph = _graph()
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    assert _cycles(edges) == []


def test_the_cycle_finder_finds_a_cycle() -> None:
    """The check above can fail: two modules importing each other are one cycle."""
    assert _cycles({"a": {"b"}, "b": {"a", "c"}, "c": set()}) == [["a", "b"]]


def test_every_package_says_what_lives_there_and_what_it_may_import() -> None:
    packages = [m.name for m in pkgutil.walk_packages(thetahat.__path__, "thetahat.")
                if m.ispkg]
    assert len(packages) >= 10
    for name in packages:
        doc = importlib.import_module(name).__doc__
        assert doc and len(doc.split()) >= 15, f"{name} has no docstring saying what it holds"
    for name in ("thetahat.estimation.observer", "thetahat.estimation.kernels",
                 "thetahat.estimation.statistical", "thetahat.codegen", "thetahat.io"):
        assert "may import" in importlib.import_module(name).__doc__


@pytest.mark.parametrize("old", ["thetahat.estimation.mle", "thetahat.estimation.paper",
                                 "thetahat.estimation.kernels.compiled", "thetahat.datafile"])
def test_the_paths_of_0_3_are_gone(old: str) -> None:
    """0.x: a moved name moves (CHANGELOG.md), no alias hook serves the old path."""
    sys.modules.pop(old, None)
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(old)
    assert old in (ROOT / "CHANGELOG.md").read_text()
