"""The tutorial page runs: every ```bash block of docs/tutorial.md, in order, in one empty folder.

Slow (it compiles the kernels of a new model and runs three estimators): kept out of the
default run; ``make docs`` runs it (``pytest -m slow tests/test_tutorial.py``).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"
#: A fenced shell block of a page: ```bash … ``` at the start of a line.
SHELL_BLOCK = re.compile(r"^```bash\n(.*?)^```$", re.MULTILINE | re.DOTALL)
#: Per block: generous against a cold numba cache on a loaded 2-core machine (a warm block
#: takes seconds; compiling a new model's kernels up to about a minute).
BLOCK_TIMEOUT_S = 600


def shell_blocks(text: str) -> list[str]:
    """The bodies of the ```bash blocks of a Markdown page, in order."""
    return [m.group(1) for m in SHELL_BLOCK.finditer(text)]


def test_shell_blocks_found():
    """The extraction itself: the tutorial's blocks, each ending in a newline, none empty."""
    page = "x\n```bash\necho a\n```\n```python\nprint(1)\n```\n```bash\nls\n\npwd\n```\n"
    assert shell_blocks(page) == ["echo a\n", "ls\n\npwd\n"]
    blocks = shell_blocks(TUTORIAL.read_text(encoding="utf-8"))
    assert len(blocks) >= 7 and all(b.strip() for b in blocks)
    joined = "\n".join(blocks)
    for step in ("thetahat analyze", "thetahat estimate", "--method paper", "--method guarded",
                 "thetahat codegen", "fleet", "--data cart_log.csv", "--delimiter ';'",
                 "cart_log.parquet", "cart_log.mat", "[data]", "scale = 0.001",
                 "offset = -0.25", "t = { rate = 200.0 }", "[data.segments]",
                 "--samples train", "--summary train.json", "validate_free_run"):
        assert step in joined, f"the tutorial no longer runs {step!r}"


@pytest.mark.slow
def test_tutorial_commands_run(tmp_path):
    """Each block exits 0 (``set -e``: any failing command fails it); together they write the
    files the page talks about."""
    if shutil.which("bash") is None:
        pytest.skip("no bash")
    if shutil.which("cc") is None and not os.environ.get("CC"):
        pytest.skip("no C compiler for the codegen step")
    pytest.importorskip("numba")  # without it the guarded runs take minutes in Python
    pytest.importorskip("pyarrow")  # section 8 writes and reads a Parquet log (the data extra)
    env = dict(os.environ)
    # `python` and `thetahat` are this interpreter's (the venv's), first on the path.
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    src = Path(__file__).resolve().parents[1] / "src"
    env["PYTHONPATH"] = os.pathsep.join([str(src), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    for i, block in enumerate(shell_blocks(TUTORIAL.read_text(encoding="utf-8")), 1):
        done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", block], cwd=tmp_path,
                              env=env, capture_output=True, text=True,
                              timeout=BLOCK_TIMEOUT_S)
        assert done.returncode == 0, (f"tutorial block {i} failed ({done.returncode}):\n"
                                      f"{block}\n--- stdout\n{done.stdout}\n"
                                      f"--- stderr\n{done.stderr}")
    for name in ("cart.toml", "cart_log.csv", "est_paper.csv", "est_guarded.csv",
                 "fleet_results.csv", "est_c.csv", "est_auto_c.csv", "est_eu.csv",
                 "est_parquet.csv", "est_mat.csv", "est_train.csv", "train.json"):
        assert (tmp_path / name).is_file(), name
    rows = (tmp_path / "fleet_results.csv").read_text().splitlines()
    assert len(rows) == 4 and all(",ok," in r for r in rows[1:]), rows
