"""Equations rendered at build time: every formula of the site becomes MathML in the HTML.

The pages and the docstrings write TeX between ``$…$`` (inline) and ``$$…$$`` (display).
``pymdownx.arithmatex`` (mkdocs.yml, generic mode) keeps Markdown away from it and marks it
``<span class="arithmatex">\\(…\\)</span>`` or ``<div class="arithmatex">\\[…\\]</div>``; this
hook (mkdocs.yml ``hooks``) replaces each mark with the MathML that ``latex2mathml`` writes, so
the site needs no script and no network to show an equation (browsers draw MathML natively;
docs/stylesheets/equations.css aligns tables and equation numbers).

Two corrections to latex2mathml 3.81, applied to the TeX before converting:

- ``aligned`` (used inside display math, where a reader of the docstring expects it) is
  converted as ``align*``: latex2mathml renders ``aligned``'s ``&`` as a literal character;
- a display equation's ``\\tag{…}`` becomes its equation number at the right margin, as in the
  paper, instead of text run into the formula.

Under ``strict`` a formula the converter rejects, a TeX command it does not know (it would pass
through as ``\\name``) and TeX left raw on a page (``$…$``, ``\\(``, ``\\[``, ``\\begin{``,
a reStructuredText ``.. math::``) fail the build: :func:`raw_tex` finds the last kind.
"""

from __future__ import annotations

import html
import logging
import re
from typing import Any
from xml.etree.ElementTree import Element, tostring

#: An arithmatex mark: the TeX inside is HTML-escaped and wrapped in \\(…\\) or \\[…\\].
MARK = re.compile(r'<(?P<tag>span|div) class="arithmatex">(?P<tex>.*?)</(?P=tag)>', re.DOTALL)
#: \\tag{…} of a display equation (no nested braces in the paper's numbers: 3a, 8, 14).
TAG = re.compile(r"\\tag\*?\{(?P<number>[^{}]*)\}")
#: A TeX command name; inside the converter's output it means the command was not understood.
COMMAND = re.compile(r"\\[A-Za-z]+")
#: A matrix's opening bracket and its closing one (bmatrix, pmatrix, Bmatrix, vmatrix, Vmatrix).
OPENING = {"[": "]", "(": ")", "{": "}", "|": "|", "\u2016": "\u2016"}
#: Elements whose text is code or already rendered: raw TeX inside them is not a defect.
EXEMPT = re.compile(r"<(?P<tag>pre|code|math|script|style|textarea)\b.*?</(?P=tag)>",
                    re.DOTALL | re.IGNORECASE)
#: TeX left unrendered in the text of a page: a $…$ span with TeX in it, \\( or \\[ delimiters,
#: an environment, or reStructuredText's math directive.
RAW_TEX = re.compile(r"\$[^$<>\n]*[\\^_{}][^$<>\n]*\$|\\\(|\\\[|\\begin\{|\.\. math::")

log = logging.getLogger("mkdocs.plugins.thetahat.equations")


class EquationError(ValueError):
    """A formula latex2mathml cannot convert, or converts with a command it does not know."""


def _unwrap(tex: str) -> str:
    """The TeX of an arithmatex mark without its \\(…\\) or \\[…\\] delimiters."""
    tex = html.unescape(tex).strip()
    for left, right in (("\\(", "\\)"), ("\\[", "\\]")):
        if tex.startswith(left) and tex.endswith(right):
            return tex[len(left):-len(right)].strip()
    return tex


def render(tex: str, display: bool) -> str:
    """The HTML of one formula: a ``<math>`` element, and for a display formula with a
    ``\\tag`` the number beside it.

    Raises
    ------
    EquationError
        When latex2mathml fails on ``tex`` or leaves a TeX command in its output.
    """
    from latex2mathml.converter import convert_to_element

    numbers = [m["number"] for m in TAG.finditer(tex)] if display else []
    body = TAG.sub("", tex) if display else tex
    body = body.replace("{aligned}", "{align*}")
    try:
        tree = convert_to_element(body, display="block" if display else "inline")
    except Exception as exc:  # latex2mathml's own exceptions share no base class
        raise EquationError(f"latex2mathml cannot convert {tex!r}: "
                            f"{type(exc).__name__} {exc}") from exc
    for element in tree.iter():
        # latex2mathml stores characters as entity text (&#x0005B;) and unescapes the whole
        # serialised string, which would let a < of \text{} through as markup: characters
        # here, and ElementTree escapes what it must.
        if element.text:
            element.text = html.unescape(element.text)
    _fence_matrices(tree)
    unknown = sorted({c for e in tree.iter() if e.text for c in COMMAND.findall(e.text)})
    if unknown:
        raise EquationError(f"latex2mathml does not know {', '.join(unknown)} in {tex!r}")
    mathml = tostring(tree, encoding="unicode")
    if not display:
        return mathml
    number = "".join(f'<span class="eqno">({html.escape(n)})</span>' for n in numbers)
    return f'<div class="equation">{mathml}{number}</div>'


def _fence_matrices(tree: Element) -> None:
    """Make a matrix's brackets stretch to its height: latex2mathml writes them as plain
    ``<mo>`` siblings of the ``<mtable>``, which MathML draws at text size in a longer row.
    Each (opening mo, mtable, closing mo) becomes its own row of a prefix and a postfix fence."""
    for parent in list(tree.iter()):
        children = list(parent)
        for i in range(len(children) - 2):
            left, table, right = children[i:i + 3]
            if (left.tag == "mo" and left.text in OPENING and table.tag == "mtable"
                    and right.tag == "mo" and right.text == OPENING[left.text]):
                row = Element("mrow")
                for mo, form in ((left, "prefix"), (right, "postfix")):
                    mo.attrib.update(fence="true", stretchy="true", form=form)
                index = list(parent).index(left)
                for child in (left, table, right):
                    parent.remove(child)
                    row.append(child)
                parent.insert(index, row)


def convert_marks(page_html: str) -> tuple[str, int, list[str]]:
    """Replace every arithmatex mark of a page's HTML by MathML; return the new HTML, the
    number of formulas converted and the errors (a failed formula keeps its mark)."""
    errors: list[str] = []
    count = 0

    def one(match: re.Match[str]) -> str:
        nonlocal count
        try:
            out = render(_unwrap(match["tex"]), display=match["tag"] == "div")
        except EquationError as exc:
            errors.append(str(exc))
            return match.group(0)
        count += 1
        return out

    return MARK.sub(one, page_html), count, errors


def raw_tex(page_html: str) -> list[str]:
    """TeX left raw in the text of a page (outside code, scripts and MathML): each occurrence
    with a little context."""
    text = EXEMPT.sub(" ", page_html)
    return [text[max(0, m.start() - 30):m.end() + 30].replace("\n", " ")
            for m in RAW_TEX.finditer(text)]


# --- mkdocs hook ----------------------------------------------------------------------------

def on_page_content(html_text: str, page: Any, config: Any, files: Any) -> str:
    """Render the page's formulas (its Markdown and the docstrings it shows) as MathML."""
    out, _, errors = convert_marks(html_text)
    for error in errors:
        log.warning("%s: %s", page.file.src_uri, error)
    for context in raw_tex(out):
        log.warning("%s: TeX left raw in the HTML: …%s…", page.file.src_uri, context)
    return out
