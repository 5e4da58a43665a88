"""The site reads offline: everything a page loads comes with the site.

Engineers read these pages on plant networks without internet. Equations are MathML written
at build time (docs/hooks/equations.py) and code is coloured at build time by Pygments
(``pymdownx.highlight`` in mkdocs.yml, the theme's highlight.js from a CDN switched off). This
hook (mkdocs.yml ``hooks``) writes the Pygments colours as the stylesheet
``stylesheets/highlight.css`` (mkdocs.yml ``extra_css``), and under ``strict`` fails the build
when a page loads a script, a stylesheet or an image from another host (:func:`remote_assets`).
Links to other sites are not assets: they are fine.
"""

from __future__ import annotations

import logging
import re
from typing import Any

HIGHLIGHT_CSS = "stylesheets/highlight.css"
#: The Pygments style of the code blocks (a light one, as the theme is light).
STYLE = "default"
#: An element that makes the browser fetch something when the page loads, from an absolute URL.
REMOTE = re.compile(r"<(?:script|img|iframe|source)\b[^>]*\bsrc=[\"'](?P<url>(?:https?:)?//[^\"']+)"
                    r"|<link\b[^>]*\bhref=[\"'](?P<href>(?:https?:)?//[^\"']+)", re.IGNORECASE)

log = logging.getLogger("mkdocs.plugins.thetahat.offline")


def highlight_css(style: str = STYLE) -> str:
    """The stylesheet of Pygments' ``style`` for ``pymdownx.highlight``'s ``.highlight``."""
    from pygments.formatters import HtmlFormatter

    return HtmlFormatter(style=style).get_style_defs(".highlight") + "\n"


def remote_assets(page_html: str) -> list[str]:
    """The URLs of other hosts a page loads (scripts, stylesheets, images, frames)."""
    return [m["url"] or m["href"] for m in REMOTE.finditer(page_html)]


# --- mkdocs hook ----------------------------------------------------------------------------

def on_files(files: Any, config: Any) -> Any:
    """Add the Pygments stylesheet to the site's files."""
    from mkdocs.structure.files import File

    files.append(File.generated(config, HIGHLIGHT_CSS, content=highlight_css()))
    return files


def on_post_page(output: str, page: Any, config: Any) -> str:
    """Warn (an error under ``strict``) for each asset the page would fetch from the network."""
    for url in remote_assets(output):
        log.warning("%s: loads %s from the network; the site must read offline",
                    page.file.src_uri, url)
    return output
