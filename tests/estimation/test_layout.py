"""The layout of :mod:`thetahat.estimation`: three subpackages, each importing only what its
docstring allows, and the 0.2 flat module paths still importing (with a warning)."""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path

import pytest

import thetahat.estimation as estimation

PACKAGE = Path(estimation.__file__).parent


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the modules a file imports (relative imports resolved)."""
    pkg = ".".join(path.relative_to(PACKAGE.parent.parent).with_suffix("").parts[:-1])
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            names.add(mod)
            names.update(f"{mod}.{a.name}" for a in node.names)
    return names


@pytest.mark.parametrize("sub", ["paper", "kernels"])
def test_observer_and_kernels_never_import_the_statistical_estimators(sub: str) -> None:
    # The subpackages' docstrings: the paper's observer and the back ends sit below the
    # statistical estimators, which build on them; an import the other way is a layering error.
    files = sorted((PACKAGE / sub).glob("*.py"))
    assert len(files) > 3
    offenders = {f.name: sorted(m for m in imported_modules(f)
                                if m.startswith("thetahat.estimation.statistical"))
                 for f in files}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_every_estimation_module_lives_in_one_subpackage() -> None:
    flat = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__"}
    assert flat == {"protocol", "results"}
    for sub in ("paper", "kernels", "statistical"):
        doc = importlib.import_module(f"thetahat.estimation.{sub}").__doc__
        assert doc and "may import" in doc


@pytest.mark.parametrize("name", sorted(estimation.MOVED))
def test_flat_paths_of_0_2_name_the_moved_module(name: str) -> None:
    old = f"thetahat.estimation.{name}"
    new = importlib.import_module(f"thetahat.estimation.{estimation.MOVED[name]}.{name}")
    assert (PACKAGE / estimation.MOVED[name] / f"{name}.py").is_file()
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=estimation.MOVED[name]):
        module = importlib.import_module(old)
    assert module is new
    assert module.__name__ == new.__name__          # one object, its own name kept
