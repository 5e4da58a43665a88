"""The README is a front door: short, the two commands, the tutorial on its first screen, links
that lead somewhere, a figure the gallery draws and a model file that loads."""

from __future__ import annotations

import importlib.util
import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: The issue's bound: the README says what thetahat is and leads on; the tables live in
#: docs/results.md.
MAX_WORDS = 1500
#: What a first screen shows (a terminal or a repository page, before scrolling).
FIRST_SCREEN_LINES = 40
#: A Markdown link or image: [text](target) or ![alt](target).
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _text() -> str:
    return README.read_text(encoding="utf-8")


def test_short_with_the_two_commands_and_the_tutorial_first():
    text = _text()
    words = len(text.split())                       # as `wc -w` counts them
    assert words <= MAX_WORDS, f"README: {words} words; move the detail to docs/"
    assert "make demo" in text and "make test" in text
    first = "\n".join(text.splitlines()[:FIRST_SCREEN_LINES])
    targets = LINK.findall(first)
    assert "docs/tutorial.md" in targets and "docs/getting-started.md" in targets


def _slug(heading: str) -> str:
    """A heading's anchor as GitHub and MkDocs's toc make it (for these headings)."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_every_link_leads_to_a_file_and_heading_that_exist():
    """Relative links name files of the repository (and headings of them); the one figure is a
    committed copy (docs/images) of a figure the gallery draws (docs/figures is built, not
    committed), so the page shows it before any build."""
    spec = importlib.util.spec_from_file_location("docs_gallery_hook",
                                                  ROOT / "docs" / "hooks" / "gallery.py")
    gallery = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gallery)
    drawn = {f"docs/figures/{entry.figure}" for entry in gallery.GALLERY}
    figures = re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", _text())
    assert len(figures) == 1 and figures[0].startswith("docs/images/"), figures
    assert (ROOT / figures[0]).is_file()
    assert f"docs/figures/{Path(figures[0]).name}" in drawn        # the gallery draws it
    for target in LINK.findall(_text()):
        if target.startswith(("http://", "https://")) or target in drawn:
            continue
        path, _, anchor = target.partition("#")
        assert (ROOT / path).is_file(), target
        if anchor:
            headings = re.findall(r"^#+ (.+)$", (ROOT / path).read_text(encoding="utf-8"),
                                  re.MULTILINE)
            assert anchor in {_slug(h) for h in headings}, target


def test_the_model_of_bring_your_own_model_loads_and_passes_assumption_1():
    """The README's ten-line model file is a valid model whose design is stable: what
    `thetahat analyze cart.toml` reports (exit 0)."""
    from thetahat.modelfile import analyze_model, loads_model

    block = re.search(r"```toml\n(.*?)```", _text(), re.DOTALL)
    assert block is not None
    tomllib.loads(block.group(1))
    report = analyze_model(loads_model(block.group(1), source="README.md"))
    assert report.ok, report.verdict()
    assert "thetahat analyze cart.toml" in _text()
