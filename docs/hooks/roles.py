"""Sphinx/numpydoc roles in docstrings, rewritten into the site's own cross-references.

The docstrings follow numpydoc and name other objects with Sphinx roles (:class:`X`,
:meth:`~a.b.c`, :func:`title <a.b>`, :mod:`.sibling`, :data:, :attr:, :exc:, :obj:). MkDocs
does not know them, so :func:`translate` turns each into an autorefs link
``[`text`][canonical.path]`` when the name resolves to an object the site renders, and into plain
code ``text`` when it does not (an external name such as ``numpy.random.Generator``, a private
helper, a module the reference does not show); the second kind is reported, never dropped.

:class:`RolesExtension` is the griffe extension mkdocs.yml loads for mkdocstrings: once the
package is loaded it gives module constants their Sphinx ``#:`` comments as docstrings (so the
reference shows them and :data: links reach them), then rewrites every docstring, resolving short names the way Sphinx does: from
the documented object outwards (its members, its class, its module, the enclosing packages),
then the package root, then a unique suffix match over the package. A role the pattern below
does not recognise survives as raw text, and the ``roles_check`` hook fails the strict build
on it.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

#: A role: :name:`body` or :py:name:`body`; the body may span lines, never a backtick.
ROLE = re.compile(r":(?:py:)?(?P<role>class|meth|func|mod|attr|data|const|exc|obj)"
                  r":`(?P<body>[^`]+)`")
#: Anything that looks like a role, recognised by the pattern above or not (the check).
RAW_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:`")
#: The same, as MkDocs renders it in HTML: the backticks became <code>.
RAW_ROLE_HTML = re.compile(r":[a-z]+(?::[a-z]+)?:<code>")
#: A ``::: identifier`` line of a page and its indented options: the object is rendered, and
#: everything public in it unless the options say ``members: false``.
DIRECTIVE = re.compile(r"^:::\s+(?P<ident>[\w.]+)[ \t]*\n(?P<options>(?:[ \t]+\S.*\n?)*)",
                       re.MULTILINE)
NO_MEMBERS = re.compile(r"^\s*members:\s*(?:false|\[\s*\])\s*$", re.MULTILINE)

log = logging.getLogger("mkdocs.plugins.thetahat.roles")


def parse(body: str) -> tuple[str, str, bool]:
    """Split a role's body into (shown text, target, whether to link).

    ``title <target>`` gives both explicitly; ``~a.b.c`` shows ``c``; ``!name`` is not linked;
    a trailing ``()`` is kept in the text and dropped from the target.
    """
    body = " ".join(body.split())
    explicit = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^<>]+)>", body)
    if explicit:
        return explicit["title"], _dotted(explicit["target"]), True
    name = body.replace(" ", "")  # a name broken over two lines of the docstring
    if name.startswith("!"):
        return name[1:], _dotted(name[1:]), False
    if name.startswith("~"):
        return name[1:].lstrip(".").rsplit(".", 1)[-1], _dotted(name[1:]), True
    return name, _dotted(name), True


def _dotted(target: str) -> str:
    return target.replace(" ", "").removesuffix("()")


def translate(text: str, resolve: Callable[[str], str | None]) -> tuple[str, list[str]]:
    """Rewrite every role of ``text``; return the new text and the targets left unresolved.

    ``resolve(target)`` returns the canonical dotted path of a rendered object, or None.
    """
    unresolved: list[str] = []

    def one(match: re.Match[str]) -> str:
        shown, target, link = parse(match["body"])
        path = resolve(target) if link else None
        if path is None:
            if link:
                unresolved.append(target)
            return f"`{shown}`"
        return f"[`{shown}`][{path}]"

    return ROLE.sub(one, text), unresolved


def rendered_identifiers(docs_dir: Path) -> list[tuple[str, bool]]:
    """The ``::: identifier`` directives of the pages under ``docs_dir``: (identifier, whether
    its members are rendered too)."""
    found: list[tuple[str, bool]] = []
    for page in sorted(docs_dir.rglob("*.md")):
        text = page.read_text(encoding="utf-8")
        found += [(m["ident"], not NO_MEMBERS.search(m["options"]))
                  for m in DIRECTIVE.finditer(text)]
    return found


# --- griffe: the loaded package -------------------------------------------------------------

def _target(obj: Any) -> Any:
    """The object an alias points to (None when it leaves the loaded packages)."""
    if not getattr(obj, "is_alias", False):
        return obj
    try:
        return obj.final_target
    except Exception:  # griffe's AliasResolutionError/CyclicAliasError: an external name
        return None


def _shown(obj: Any) -> bool:
    """Whether mkdocstrings renders a member (mkdocs.yml: filters ["!^_"], no undocumented)."""
    return not obj.name.startswith("_") and not obj.is_alias and obj.has_docstring


def _rendered_paths(root: Any, members: bool = True) -> Iterator[str]:
    """Canonical paths of ``root`` and of the members mkdocstrings renders under it."""
    yield root.path
    for member in root.members.values() if members else ():
        if _shown(member) and not member.is_module:
            yield from _rendered_paths(member)


def _documented(root: Any) -> Iterator[Any]:
    """Every non-alias object under ``root`` (root included) that has a docstring."""
    if root.docstring is not None:
        yield root
    for member in root.members.values():
        if not member.is_alias:
            yield from _documented(member)


def _lookup(scope: Any, name: str) -> Any:
    """``scope[name]`` (dotted) with aliases followed, or None: a missing member, or an alias
    on the way that leaves the loaded packages."""
    try:
        return _target(scope[name])
    except Exception:  # KeyError, or griffe's alias resolution errors
        return None


def make_resolver(owner: Any, package: Any, rendered: set[str],
                  by_name: dict[str, list[Any]]) -> Callable[[str], str | None]:
    """Sphinx-like resolution of a target named in ``owner``'s docstring (see the module)."""
    scopes: list[Any] = []
    node = owner
    while node is not None:
        if node.is_class or node.is_module:
            scopes.append(node)
        node = node.parent

    def resolve(target: str) -> str | None:
        name = target.lstrip(".")
        if not name:
            return None
        found = None
        root_name = package.name
        if name == root_name:
            found = package
        elif name.startswith(root_name + "."):
            found = _lookup(package, name[len(root_name) + 1:])
        for scope in scopes:
            if found is not None:
                break
            found = _lookup(scope, name)
        if found is None:
            tail = name.rsplit(".", 1)[-1]
            matches = {o.path: o for o in by_name.get(tail, ())
                       if o.path == name or o.path.endswith("." + name)}
            if len(matches) == 1:
                found = next(iter(matches.values()))
        if found is None or found.path not in rendered:
            return None
        return str(found.path)

    return resolve


def doc_comments(package: Any) -> int:
    """Give each module-level attribute without a docstring the Sphinx ``#:`` comment lines
    just above it, as its docstring (griffe reads only string docstrings); return how many."""
    from griffe import Docstring

    count = 0
    for module in _modules(package):
        lines = module.lines
        for attr in module.members.values():
            if (attr.is_alias or not attr.is_attribute or attr.docstring is not None
                    or not attr.lineno):
                continue
            comment: list[str] = []
            row = attr.lineno - 2  # the line above, 0-based
            while row >= 0 and lines[row].startswith("#:"):
                comment.insert(0, lines[row][2:].strip())
                row -= 1
            if comment:
                attr.docstring = Docstring("\n".join(comment), parent=attr)
                count += 1
    return count


def _modules(root: Any) -> Iterator[Any]:
    yield root
    for member in root.members.values():
        if not member.is_alias and member.is_module:
            yield from _modules(member)


def translate_package(package: Any, identifiers: Iterable[tuple[str, bool]]
                      ) -> dict[str, list[str]]:
    """Rewrite the docstrings of a loaded griffe package in place; return, per object path,
    the targets that stayed plain code. ``identifiers``: :func:`rendered_identifiers`."""
    rendered: set[str] = set()
    for ident, members in identifiers:
        if ident == package.name or ident.startswith(package.name + "."):
            obj = package if ident == package.name else _lookup(package,
                                                                 ident[len(package.name) + 1:])
            if obj is not None:
                rendered.update(_rendered_paths(obj, members))
    objects = list(_documented(package))
    by_name: dict[str, list[Any]] = {}
    for obj in objects:
        by_name.setdefault(obj.name, []).append(obj)
    unresolved: dict[str, list[str]] = {}
    for obj in objects:
        docstring = obj.docstring
        if not ROLE.search(docstring.value):
            continue
        new, missed = translate(docstring.value, make_resolver(obj, package, rendered, by_name))
        docstring.value = new
        docstring.__dict__.pop("parsed", None)  # a cached parse of the old text
        if missed:
            unresolved[obj.path] = missed
    return unresolved


try:
    from griffe import Extension
except ImportError:  # the docs extra is absent: translate/parse still work
    Extension = object  # type: ignore[assignment,misc]


class RolesExtension(Extension):  # type: ignore[misc,valid-type]
    """Griffe extension (mkdocs.yml, mkdocstrings ``extensions``): see the module docstring.

    Parameters
    ----------
    docs_dir : str
        The pages' folder, searched for ``::: identifier`` directives.
    """

    def __init__(self, docs_dir: str = "docs") -> None:
        super().__init__()
        self.docs_dir = Path(docs_dir)

    def on_package(self, *, pkg: Any, **kwargs: Any) -> None:
        """Read the ``#:`` comments, then rewrite the roles of every docstring of ``pkg``."""
        doc_comments(pkg)
        unresolved = translate_package(pkg, rendered_identifiers(self.docs_dir))
        targets = sorted({t for ts in unresolved.values() for t in ts})
        if targets:
            log.info("roles: %d name(s) not rendered on the site, shown as code: %s",
                     len(targets), ", ".join(targets))

    def on_package_loaded(self, *, pkg: Any, **kwargs: Any) -> None:
        """The same hook under its griffe 1 name (translating twice changes nothing)."""
        self.on_package(pkg=pkg, **kwargs)


# --- mkdocs hook (mkdocs.yml ``hooks``): the strict build fails on a raw role ---------------

def on_post_page(output: str, page: Any, config: Any) -> str:
    """Warn (an error under ``strict``) when a built page still shows a raw role."""
    for match in RAW_ROLE_HTML.finditer(output):
        context = output[match.start():match.start() + 80].split("\n", 1)[0]
        log.warning("%s: raw role left in the HTML: %s", page.file.src_uri, context)
    return output
