"""A small numpydoc reader for the docstring meta-test: sections and the names they document.

numpydoc's own parser needs Sphinx; the meta-test needs only the section layout::

    Parameters
    ----------
    name : type
        description
    a, b : type

A section starts at a title line followed by a line of dashes of the same length; an entry of
Parameters / Returns / ... starts at the section's base indentation, its description is
indented further.
"""

from __future__ import annotations

import inspect
import re

#: numpydoc section titles (numpydoc's style guide).
SECTIONS = ("Parameters", "Returns", "Yields", "Receives", "Other Parameters", "Raises",
            "Warns", "Warnings", "See Also", "Notes", "References", "Examples", "Attributes",
            "Methods")

_ENTRY = re.compile(r"^(?P<names>\*{0,2}[A-Za-z_][\w]*(?:\s*,\s*\*{0,2}[A-Za-z_][\w]*)*)"
                    r"(?:\s*:\s*(?P<type>.*))?$")


def sections(doc: str) -> dict[str, list[str]]:
    """The lines of every section of a cleaned docstring, by title ('' for the summary)."""
    lines = inspect.cleandoc(doc).splitlines()
    out: dict[str, list[str]] = {"": []}
    current = ""
    i = 0
    while i < len(lines):
        line = lines[i]
        title = line.strip()
        underline = lines[i + 1].strip() if i + 1 < len(lines) else ""
        if title in SECTIONS and underline and set(underline) == {"-"} \
                and len(underline) == len(title):
            if title in out:
                raise ValueError(f"section {title!r} appears twice")
            current = title
            out[current] = []
            i += 2
            continue
        out[current].append(line)
        i += 1
    return out


def items(lines: list[str]) -> list[str]:
    """The entry lines of a section: its non-blank lines at the base indentation."""
    body = [ln for ln in lines if ln.strip()]
    if not body:
        return []
    base = min(len(ln) - len(ln.lstrip()) for ln in body)
    return [ln.strip() for ln in body if len(ln) - len(ln.lstrip()) == base]


def entries(lines: list[str]) -> list[tuple[tuple[str, ...], str | None]]:
    """(names, type) of each entry of a Parameters-like section (``name : type`` lines)."""
    out = []
    for ln in items(lines):
        m = _ENTRY.match(ln)
        if m is None:
            continue
        names = tuple(n.strip().lstrip("*") for n in m.group("names").split(","))
        out.append((names, m.group("type")))
    return out


def documented_names(doc: str, titles: tuple[str, ...] = ("Parameters", "Other Parameters")
                     ) -> set[str]:
    """Every name documented in the given sections."""
    secs = sections(doc)
    return {n for t in titles for names, _ in entries(secs.get(t, [])) for n in names}
