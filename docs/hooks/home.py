"""The home page's table of pages lists every page of the navigation.

docs/index.md has a "Pages" table, one row per page with what the page covers (written by
hand: a title alone does not say it). :func:`missing` compares it with mkdocs.yml's ``nav``:
every page of the navigation except the home page itself and the API reference pages (the
table links their overview, api.md, which links them) must have a row. As a hook (mkdocs.yml
``hooks``) it warns for each missing page, which fails the strict build.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from typing import Any

HOME = "index.md"
#: The pages the overview api.md links; the home table needs only the overview.
REFERENCE = "reference/"
#: A row of the "Pages" table: its first cell is a link to a page.
ROW = re.compile(r"^\|\s*\[[^\]]+\]\((?P<page>[^)#\s]+\.md)(?:#[^)]*)?\)\s*\|", re.MULTILINE)

log = logging.getLogger("mkdocs.plugins.thetahat.home")


def nav_pages(nav: Any) -> Iterator[str]:
    """The page paths of an mkdocs ``nav`` (as mkdocs.yml's YAML gives it), in order."""
    if isinstance(nav, str):
        yield nav
    elif isinstance(nav, dict):
        for value in nav.values():
            yield from nav_pages(value)
    elif isinstance(nav, list):
        for item in nav:
            yield from nav_pages(item)


def table_section(index_text: str) -> str:
    """The "## Pages" section of the home page (up to the next heading)."""
    match = re.search(r"^## Pages\n(?P<body>.*?)(?=^#|\Z)", index_text, re.MULTILINE | re.DOTALL)
    return match["body"] if match else ""


def missing(nav: Any, index_text: str) -> list[str]:
    """The pages of ``nav`` that need a row in the home page's table and have none."""
    rows = {m["page"] for m in ROW.finditer(table_section(index_text))}
    return [page for page in nav_pages(nav)
            if page != HOME and not page.startswith(REFERENCE) and page not in rows]


# --- mkdocs hook ----------------------------------------------------------------------------

def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """On the home page: warn for each page of the navigation its table leaves out."""
    if page.file.src_uri == HOME:
        for path in missing(config["nav"], markdown):
            log.warning("%s: the Pages table has no row for %s (mkdocs.yml nav)", HOME, path)
    return markdown
