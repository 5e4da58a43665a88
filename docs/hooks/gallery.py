"""The gallery: each figure of the site, the command that draws it, and what it shows.

:data:`GALLERY` is the one place a figure is declared. ``make docs`` runs this file as a script,
which runs every entry's command (in order, from the repository's root) to write the figures
into docs/figures; MkDocs then loads it as a hook (mkdocs.yml ``hooks``) that writes the page
gallery.md from the same table, and fails the strict build when a declared figure is missing.
Adding a figure is one line in :data:`GALLERY`.

Commands are written as a user types them. ``python`` and ``thetahat`` are run with the
interpreter that runs this script (``python -m thetahat``), so ``make docs`` uses its venv.
"""

from __future__ import annotations

import logging
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

ROOT = Path(__file__).resolve().parents[2]
FIGURES = "docs/figures"


class Entry(NamedTuple):
    """One figure: its file under docs/figures, the command that writes it, a title and a
    caption (Markdown)."""

    figure: str
    command: str
    title: str
    caption: str


#: The figures, in the order of the page. A command may read what an earlier one wrote.
GALLERY: tuple[Entry, ...] = (
    Entry("lugre.png",
          "python examples/lugre_demo.py --no-show --out docs/figures",
          "The paper's Fig. 1: DC motor with LuGre friction",
          "Fig. 1 of the paper, reproduced: the DC motor with LuGre friction (Sec. VIII). "
          "Measured speed y with ω̂ of both observers, the bristle deflection η̂, and θ̂ = α̂0 "
          "converging to 0.28 inside Θ = [0.05, 1]. The script also writes the record it "
          "simulated, lugre_data.csv, which the entries below read."),
    Entry("two_inertia.png",
          "python examples/two_inertia_demo.py --no-show --out docs/figures",
          "A MIMO example: the two-inertia drive",
          "A MIMO example: the two-inertia drive with two friction parameters (F_m, F_l) and "
          "chains of lengths (2, 3) in the SCB. Outputs, φ̂, and θ̂ with Θ and a ±1 % band."),
    Entry("sweep.png",
          "thetahat sweep --eps 1 0.3 0.1 --seeds 2 --out docs/figures",
          "The ε sweep of Sec. VII",
          "Tuning ε on the LuGre example, from ε = 1 down: the time θ̂ needs to stay within 1 %, "
          "the largest and the RMS error of θ̂ over the second half, and the RMS error of the "
          "states from both observers, per ε for each noise seed (dots) and their median "
          "(line). The title line says down to which ε every seed stayed stable."),
    Entry("estimate_paper.png",
          "thetahat estimate examples/lugre.toml docs/figures/lugre_data.csv --method paper "
          "--no-progress --plot docs/figures/estimate_paper.png -o build/estimates_paper.csv",
          "A logged record through the command line: the paper's estimator",
          "The paper's estimator run by the command line on a logged record (t, u, y): the "
          "model file examples/lugre.toml on the record of the first entry."),
    Entry("estimate_guarded.png",
          "thetahat estimate examples/lugre.toml docs/figures/lugre_data.csv --method guarded "
          "--no-progress --plot docs/figures/estimate_guarded.png -o build/estimates_guarded.csv",
          "The same record: the guarded estimator",
          "The same record through the guarded two-stage estimator "
          "([Guaranteed and efficient](guarded.md)): the paper's observer as stage 1, an EKF "
          "re-anchored by MAP fits as stage 2, the output kept within the guard's band of "
          "stage 1. θ̂ is within 1 % of α0 = 0.28 after a fraction of a second instead of "
          "about ten."),
    Entry("emps.png",
          "thetahat demo emps --out docs/figures",
          "A real machine: the EMPS benchmark",
          "θ̂(t) of the paper's estimator, the guarded estimator and the MAP fits on the "
          "measured EMPS record (Janot, Gautier & Brunot 2019) against the published IDIM-LS "
          "values ± 3σ, and the closed loop simulated with θ̂ against the measured position "
          "and force ([Real data: EMPS](real-data-emps.md))."),
    Entry("guarded_crlb.png",
          "python benchmarks/bench_guarded.py --only nominal 'alpha2x0.8(model error)' "
          "--seeds 3 --t-end 10 --no-cost --jobs 1 --figure docs/figures/guarded_crlb.png",
          "The guarded estimator against the Cramér–Rao bound",
          "The RMS over noise seeds of θ̂ − θ for the guarded estimator, the MAP fits (mle), a "
          "joint EKF (filterpy) and the paper's estimator, against √CRLB(t) (dashed), on the "
          "nominal LuGre scenario and with a model error (the plant's α2 is 0.8 times the "
          "model's), where every estimator settles off by the bias the wrong model causes. A "
          "short run of the benchmark (3 seeds, 10 s, two of its eight scenarios; "
          "`python benchmarks/bench_guarded.py` runs them all)."),
)

PAGE_HEAD = """# Gallery

Every figure of this site, with the command that drew it. `make docs` runs these commands
(from the repository's root, in this order) before it builds the pages, so each figure here is
the one the current code draws. The table lives in `docs/hooks/gallery.py`.
"""

log = logging.getLogger("mkdocs.plugins.thetahat.gallery")


def argv(command: str) -> list[str]:
    """The command as an argument vector, ``python``/``thetahat`` run by this interpreter."""
    words = shlex.split(command)
    if words[0] == "python":
        return [sys.executable, *words[1:]]
    if words[0] == "thetahat":
        return [sys.executable, "-m", "thetahat", *words[1:]]
    return words


def page(entries: tuple[Entry, ...] = GALLERY) -> str:
    """The Markdown of the gallery page."""
    parts = [PAGE_HEAD]
    for entry in entries:
        parts.append(f"## {entry.title}\n\n![{entry.title}](figures/{entry.figure})\n\n"
                     f"{entry.caption}\n\n```bash\n{entry.command}\n```\n")
    return "\n".join(parts)


def draw(entries: tuple[Entry, ...] = GALLERY) -> None:
    """Run every entry's command from the repository's root; stop at the first that fails."""
    (ROOT / FIGURES).mkdir(parents=True, exist_ok=True)
    (ROOT / "build").mkdir(exist_ok=True)
    for entry in entries:
        start = time.perf_counter()
        print(f"gallery: {entry.command}", flush=True)
        subprocess.run(argv(entry.command), cwd=ROOT, check=True)
        if not (ROOT / FIGURES / entry.figure).is_file():
            raise SystemExit(f"gallery: {entry.command!r} did not write "
                             f"{FIGURES}/{entry.figure}")
        print(f"gallery:   {entry.figure} in {time.perf_counter() - start:.1f} s", flush=True)


# --- mkdocs hook --------------------------------------------------------------------------

def on_files(files: Any, config: Any) -> Any:
    """Add gallery.md, generated from :data:`GALLERY`, to the site's files."""
    from mkdocs.structure.files import File

    docs_dir = Path(config["docs_dir"])
    for entry in GALLERY:
        if not (docs_dir / "figures" / entry.figure).is_file():
            log.warning("gallery: figures/%s is missing: run `make docs` (it runs `%s`)",
                        entry.figure, entry.command)
    files.append(File.generated(config, "gallery.md", content=page()))
    return files


if __name__ == "__main__":
    draw()
