"""The documentation site: its equations, its home page and, once built, every page of it.

The first tests exercise the build hooks (docs/hooks/equations.py, docs/hooks/home.py) on
known input; they need the docs extra's converter (latex2mathml) or PyYAML and skip without.
The ``test_built_*`` tests read the site ``make docs`` writes to build/site (it runs them after
``mkdocs build``); without a built site they skip.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SITE = ROOT / "build" / "site"
#: Equations of the site when this test was written: 53 on 10 pages of docs/*.md and the
#: docstrings reference/estimation shows, and 2 of structure/zeros.py on
#: reference/structure-design. More may come; fewer means some were lost on the way.
MIN_EQUATIONS = 55
#: Where a formula is written in Markdown: $$…$$ (display) or $…$ (inline), outside code.
SOURCE_MATH = re.compile(r"\$\$.+?\$\$|(?<![\\$])\$(?!\s)(?:[^$\n]|\n(?!\s*\n))+?(?<![\s\\])\$(?!\d)",
                         re.DOTALL)
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]+`")


def _hook(name: str):
    path = ROOT / "docs" / "hooks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"docs_{name}_hook", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# --- the equations hook ---------------------------------------------------------------------

def test_matrix_becomes_a_fenced_table():
    """The tutorial's kind of formula: a bmatrix is a MathML table of its rows and cells whose
    brackets are stretchy fences around it (not raw TeX, not text-sized brackets)."""
    pytest.importorskip("latex2mathml")
    eq = _hook("equations")
    out = eq.render(r"A = \begin{bmatrix} 0 & 1 \\ 0 & -c/M \end{bmatrix}", display=True)
    assert out.startswith('<div class="equation"><math') and "\\" not in out
    assert out.count("<mtr>") == 2 and out.count("<mtd>") == 4
    fences = re.findall(r'<mo fence="true" stretchy="true" form="(\w+)">(.)</mo>', out)
    assert fences == [("prefix", "["), ("postfix", "]")]
    assert re.search(r'form="prefix">\[</mo><mtable>.*</mtable><mo [^>]*>\]</mo></mrow>', out)


def test_aligned_rows_and_equation_numbers():
    """aligned: one table row per line and no literal & (latex2mathml 3.81 keeps it in
    ``aligned``); a \\tag becomes the number at the margin, out of the formula."""
    pytest.importorskip("latex2mathml")
    eq = _hook("equations")
    out = eq.render(r"\begin{aligned} \dot x &= Ax + E\phi, \\ y &= Cx \end{aligned}", True)
    assert out.count("<mtr>") == 2 and "&amp;" not in out and ">&<" not in out
    tagged = eq.render(r"\dot{\hat\theta} = u_\theta \tag{8}", display=True)
    assert tagged.endswith('</math><span class="eqno">(8)</span></div>')
    assert "(8)" not in tagged.split("</math>")[0]
    inline = eq.render(r"\varepsilon^{i} < 1", display=False)
    assert inline.startswith('<math xmlns="http://www.w3.org/1998/Math/MathML" '
                             'display="inline">') and "&lt;" in inline


def test_formula_the_converter_cannot_read_is_an_error():
    """An unknown command would pass through as \\name, a broken one raises: both are an
    EquationError naming the formula, and the mark is kept for the build to report."""
    pytest.importorskip("latex2mathml")
    eq = _hook("equations")
    with pytest.raises(eq.EquationError, match=r"does not know \\nosuch"):
        eq.render(r"x = \nosuch{y}", display=False)
    with pytest.raises(eq.EquationError, match="cannot convert"):
        eq.render(r"\frac{a}{", display=True)
    page = ('<p><span class="arithmatex">\\(x_1\\)</span> and '
            '<span class="arithmatex">\\(\\nosuch\\)</span></p>')
    out, count, errors = eq.convert_marks(page)
    assert count == 1 and len(errors) == 1 and out.count("arithmatex") == 1


def test_raw_tex_found_in_text_not_in_code():
    """The check the build and the site tests use: TeX in a page's text is found; the same
    characters inside code, pre and math are not."""
    eq = _hook("equations")
    for raw in ("<p>where $x_1$ is</p>", "<p>\\(a\\)</p>", "<p>\\[a\\]</p>",
                "<p>\\begin{bmatrix}</p>", "<p>.. math::</p>"):
        assert eq.raw_tex(raw), raw
    for fine in ("<pre><code>echo $x_1 $y_2\n\\begin{x}</code></pre>",
                 "<p><code>$THETAHAT_CACHE_DIR</code> costs $5 or $10</p>",
                 "<math><mi>\\(</mi></math>"):
        assert not eq.raw_tex(fine), fine


# --- the home page's table of pages ---------------------------------------------------------

def test_home_table_lists_every_page():
    """Every page of mkdocs.yml's nav (the API pages through their overview) has a row in the
    home page's Pages table; a table without one of them is caught."""
    yaml = pytest.importorskip("yaml")
    home = _hook("home")
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))["nav"]
    index = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    pages = list(home.nav_pages(nav))
    assert len(pages) > 25 and "guarded.md" in pages and "reference/model.md" in pages
    assert home.missing(nav, index) == []
    row = next(line for line in index.splitlines() if line.startswith("| [Guaranteed"))
    assert home.missing(nav, index.replace(row + "\n", "")) == ["guarded.md"]


# --- the built site -------------------------------------------------------------------------

def _built_pages() -> dict[str, str]:
    if not (SITE / "index.html").is_file():
        pytest.skip("no built site in build/site: `make docs` builds it, then runs these")
    return {p.relative_to(SITE).as_posix(): p.read_text(encoding="utf-8")
            for p in sorted(SITE.rglob("*.html")) if p.name != "404.html"}


def _source_formulas(page: Path) -> int:
    """The formulas a Markdown page writes, counted in its source (code removed)."""
    text = INLINE_CODE.sub("", FENCE.sub("", page.read_text(encoding="utf-8")))
    return len(SOURCE_MATH.findall(text))


def test_remote_assets_found():
    """The offline check: scripts, stylesheets and images from another host are found; local
    ones and plain links to other sites are not."""
    offline = _hook("offline")
    page = ('<script src="https://cdn.example/mathjax.js"></script><script src="js/x.js">'
            '<link rel="stylesheet" href="//cdn.example/hl.css"><link href="css/a.css">'
            '<img src="http://example.org/a.png"><a href="https://example.org">x</a>')
    assert offline.remote_assets(page) == ["https://cdn.example/mathjax.js",
                                           "//cdn.example/hl.css", "http://example.org/a.png"]


def test_built_site_reads_offline_with_no_raw_tex():
    """Offline reading: no page loads anything from another host (no MathJax or KaTeX, no
    highlight.js), and none shows TeX raw ($…$, \\(, \\[, \\begin{, .. math::) outside
    code."""
    eq = _hook("equations")
    offline = _hook("offline")
    pages = _built_pages()
    remote = {name: offline.remote_assets(html) for name, html in pages.items()}
    assert not any(remote.values()), {k: v for k, v in remote.items() if v}
    assert (SITE / offline.HIGHLIGHT_CSS).is_file()
    raw = {name: eq.raw_tex(html) for name, html in pages.items()}
    assert not any(raw.values()), {k: v for k, v in raw.items() if v}
    left = [name for name, html in pages.items() if 'class="arithmatex"' in html]
    assert not left, f"formulas not converted on {left}"


def test_built_site_every_equation_is_mathml():
    """Each formula of a page's Markdown is one <math> element on the built page (counted
    independently in the source), the docstrings' formulas are on the reference pages, and
    no MathML holds a TeX command the converter did not understand."""
    pages = _built_pages()
    counts = {name: html.count("<math ") for name, html in pages.items()}
    for source in sorted((ROOT / "docs").glob("*.md")):
        built = source.with_suffix(".html").name
        assert counts.get(built, 0) == _source_formulas(source), (built, counts.get(built))
    assert counts["reference/estimation.html"] >= 6
    assert counts["reference/structure-design.html"] >= 2
    assert sum(counts.values()) >= MIN_EQUATIONS, counts
    for name, html in pages.items():
        for mathml in re.findall(r"<math .*?</math>", html, re.DOTALL):
            assert not re.search(r"\\[A-Za-z]+", re.sub(r"<[^>]+>", "", mathml)), (name,
                                                                                 mathml)
    tutorial = pages["tutorial.html"]
    assert tutorial.count("<mtable>") >= 4  # A, B, E, C of the cart


def test_built_home_table_links_every_page():
    """The home page's table, as built, links every top-level page of the site."""
    pages = _built_pages()
    links = set(re.findall(r'<td><a href="([^"#]+)"', pages["index.html"]))
    top = {name for name in pages if "/" not in name and name not in ("index.html",)}
    assert top <= links, top - links


# --- the stored benchmark results the gallery draws from ------------------------------------

#: benchmarks/bench_guarded.py --results: written by `make bench`, read by the gallery.
GUARDED_RESULTS = ROOT / "benchmarks" / "results" / "guarded_crlb.json"
#: The stored curves have 4 significant digits (bench_guarded.STORED_DIGITS): a rounding step.
STORED_RELATIVE = 1e-3


def test_stored_guarded_results_are_a_full_run():
    """The results the gallery's CRLB figure is drawn from are those of the full benchmark
    (every scenario, 20 seeds × 20 s), each curve complete, and they obey what the figure
    shows: the Cramér–Rao bound never grows as data accumulates, and on the nominal scenario
    the guarded estimator is at the bound (the README's 0.87 ± 0.1; 0.6–1.5 allows the
    seed-to-seed spread of a rerun)."""
    import json

    stored = json.loads(GUARDED_RESULTS.read_text(encoding="utf-8"))
    assert stored["seeds"] >= 20 and stored["t_end"] >= 20
    names = {"nominal", "theta_hat0=0.05", "theta_hat0=1", "wrong_x_hat0",
             "overconfident_prior", "weak_input(u*0.3)", "fs=500", "alpha2x0.8(model error)"}
    assert set(stored["curves"]) == names == set(stored["scenarios"])
    for name, curve in stored["curves"].items():
        t, bound = curve["t"], curve["sqrt_crlb"]
        assert {"guarded", "mle", "ekf", "paper"} <= set(curve), name
        assert all(len(v) == len(t) > 100 for v in curve.values()), name
        assert all(a < b for a, b in zip(t, t[1:])), name
        assert all(b <= a * (1 + STORED_RELATIVE) for a, b in zip(bound, bound[1:])), name
    nominal = stored["scenarios"]["nominal"]["guarded"]
    assert 0.6 < nominal["rmse_over_crlb"] < 1.5 and nominal["in_Theta"]
