"""The model-file reference, generated from the tables the loader validates against.

:data:`thetahat.modelfile.keys.TABLES` holds one table per section of a model file (key, type,
default, example, description); the loader refuses a key that is not in its section's table and
takes its defaults from there. As a hook (mkdocs.yml ``hooks``), this file writes the page
reference/model-file.md from those tables at every build, so the page lists what the loader
accepts and cannot drift from it. :func:`page` is the whole page; ``python
docs/hooks/model_file.py`` prints it.
"""

from __future__ import annotations

from typing import Any

PATH = "reference/model-file.md"

HEAD = """# Model-file reference

A model file describes a system (1), its perturbation g, the parameter set Θ and the
estimator, in TOML (or JSON with the same structure): what `thetahat analyze`, `estimate`,
`sweep`, `tune` and `codegen` read, and `thetahat.modelfile.load_model` in Python. Each
section below is a table of the file; a key that its table does not list is refused (it is
usually a typo), and a key left out takes the default shown. Every problem is reported as a
`ModelFileError` that names the file, the section and the key.

This page is generated, at each build of the site, from the tables the loader validates
against (`thetahat.modelfile.keys`; docs/hooks/model_file.py writes it). Worked files:
`examples/*.toml` (`examples/emps.toml` has a `[data]` table); a model from scratch to C:
the [tutorial](../tutorial.md), whose section on [your own log](../tutorial.md#8-your-own-log)
covers `[data]`.
"""

TYPES_HEAD = """## Types

What a value of each type in the tables above looks like.

| type | a value is |
| --- | --- |
"""


def _cell(text: str) -> str:
    """Text for a table cell: a pipe would end the cell, a newline the row."""
    return text.replace("|", "\\|").replace("\n", " ")


def toml(value: Any) -> str:
    """A default value as it would be written in the file."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {toml(v)}" for k, v in value.items()) + " }" \
            if value else "{}"
    return repr(value)


def default(key: Any) -> str:
    """The default column: required, computed (in words) or the value."""
    from thetahat.modelfile.keys import Derived

    if key.required:
        return "**required**"
    if isinstance(key.default, Derived):
        return f"*{_cell(key.default.how)}*"
    return f"`{toml(key.default)}`"


def kind(key: Any) -> str:
    """The type column: the type, and a choice's values."""
    if key.choices:
        return "one of " + ", ".join(f'`"{c}"`' for c in key.choices)
    return key.type


def table(tab: Any) -> str:
    """One table of keys as Markdown."""
    rows = ["| key | type | default | example | description |",
            "| --- | --- | --- | --- | --- |"]
    for key in tab.keys:
        rows.append(f"| `{key.key}` | {kind(key)} | {default(key)} | `{_cell(key.example)}` | "
                    f"{_cell(key.description)} |")
    return "\n".join(rows) + "\n"


def _title(section: str) -> str:
    return "Top level" if section == "top level" else f"`[{section}]`"


def page(tables: Any = None) -> str:
    """The Markdown of the reference page (default: the loader's tables, read now)."""
    from thetahat.modelfile import keys

    tables = keys.TABLES if tables is None else tables
    what = {row.key: row.description for row in keys.TOP.keys}
    what["estimator.second"] = keys.ESTIMATOR["second"].description
    parts, seen = [HEAD], set()
    for tab in tables:
        if tab.section not in seen:
            seen.add(tab.section)
            intro = what.get(tab.section, "")
            parts.append(f"## {_title(tab.section)}\n" + (f"\n{intro}\n" if intro else ""))
        if tab.form:
            parts.append(f"### {tab.form[0].upper()}{tab.form[1:]}\n"
                         + (f"\n{tab.note}\n" if tab.note else ""))
        parts.append(table(tab))
    types = "".join(f"| {name} | {_cell(text)} |\n" for name, text in keys.TYPES.items())
    parts.append(TYPES_HEAD + types)
    return "\n".join(parts)


# --- mkdocs hook --------------------------------------------------------------------------

def on_files(files: Any, config: Any) -> Any:
    """Add reference/model-file.md, generated from the loader's tables, to the site's files."""
    from mkdocs.structure.files import File

    files.append(File.generated(config, PATH, content=page()))
    return files


if __name__ == "__main__":
    print(page())
