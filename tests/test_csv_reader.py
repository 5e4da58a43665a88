"""The CSV reader's fast paths: pyarrow's multi-threaded reader (large files, when installed)
gives numpy's floats to the bit, and every file it refuses goes to numpy's reader and the
careful one as before."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np
import pytest

from thetahat.io import tables
from thetahat.io.tables import open_table

#: Files that differ only in what a reader might get wrong: the byte-order mark, line
#: endings, blank lines, blanks around cells, the separator, number syntax, NaN, and cells or
#: rows that are not numbers (the careful reader then decides).
FILES = {
    "plain": b"t,u,y\n0,1,2\n1,2,3\n2,3,4\n",
    "bom_crlf": "\ufefft,u,y\r\n0,1,2\r\n1,2,3\r\n2,3,4\r\n".encode(),
    "cr": b"t,u,y\r0,1,2\r1,2,3\r2,3,4\r",
    "blank_lines": b"t,u,y\n0,1,2\n\n1,2,3\n2,3,4\n\n",
    "blanks_in_cells": b"t,u,y\n0, 1,2\n1,2 ,3\n2,3,4\n",
    "nan": b"t,u,y\n0,nan,2\n1,2,3\n2,3,4\n",
    "empty_cell": b"t,u,y\n0,,2\n1,2,3\n2,3,4\n",
    "quoted": b't,u,y\n0,"1.5",2\n1,2,3\n2,3,4\n',
    "trailing_separator": b"t,u,y\n0,1,2,\n1,2,3,\n2,3,4,\n",
    "semicolon_points": b"t;u;y\n0;1.5;2\n1;2;3\n2;3;4\n",
    "semicolon_commas": b"t;u;y\n0;1,5;2\n1;2;3\n2;3;4\n",
    "tab_syntax": b"t\tu\ty\n0\t1e5\t+.5\n1\t-2.\t3\n2\t3\t4\n",
    "ragged": b"t,u,y\n0,1\n1,2,3\n2,3,4\n",
    "t_decreasing": b"t,u,y\n0,1,2\n3,2,3\n2,3,4\n",
    "hex": b"t,u,y\n0,0x10,2\n1,2,3\n2,3,4\n",
    "long_digits": (b"t,u,y\n0,0.100000000000000005551115123125782702118158340454101562500001,2\n"
                    b"1,1e-320,3\n2,1.7976931348623157e308,4\n"),
}


def _read(raw: bytes, monkeypatch, arrow: bool) -> list[np.ndarray] | str:
    """The columns t, u, y as :class:`~thetahat.io.tables.CsvTable` reads them, or the
    error's type and message; ``arrow``: pyarrow's reader whatever the size, else hidden."""
    with monkeypatch.context() as m:
        if arrow:
            m.setattr(tables, "CSV_ARROW_MIN_BYTES", 0)
        else:
            m.setitem(sys.modules, "pyarrow.csv", None)
        table = open_table(Path("record.csv"), io.BufferedReader(io.BytesIO(raw)))
        try:
            return table.read(["t", "u", "y"])
        except Exception as exc:           # noqa: BLE001 — the error itself is compared
            return f"{type(exc).__name__}: {exc}"


def _same(a: list[np.ndarray] | str, b: list[np.ndarray] | str) -> bool:
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return all(x.tobytes() == y.tobytes() for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("name", sorted(FILES))
def test_pyarrows_reader_reads_what_numpys_reads(name, monkeypatch):
    pytest.importorskip("pyarrow.csv")
    raw = FILES[name]
    assert _same(_read(raw, monkeypatch, arrow=True), _read(raw, monkeypatch, arrow=False))


def test_pyarrows_reader_is_the_one_used_on_a_large_file(tmp_path, monkeypatch):
    """Floats whose 17-digit and shortest forms differ, subnormals and the largest double,
    2¹⁸ rows: pyarrow reads them (it is called and returns the table) to numpy's bits."""
    pytest.importorskip("pyarrow.csv")
    rng = np.random.default_rng(3)
    N = 1 << 18
    u = rng.standard_normal(N) * 10.0 ** rng.integers(-300, 300, N)
    u[:4] = [5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, 0.1]
    y = rng.standard_normal(N) / 3.0
    path = tmp_path / "record.csv"
    np.savetxt(path, np.c_[np.arange(N) * 1e-3, u, y], delimiter=",", header="t,u,y",
               comments="", fmt="%.17g")
    assert path.stat().st_size >= tables.CSV_ARROW_MIN_BYTES
    used = []
    real = tables.CsvTable._arrow

    def spy(self):
        out = real(self)
        used.append(out is not None)
        return out

    monkeypatch.setattr(tables.CsvTable, "_arrow", spy)
    with open(path, "rb") as f:
        columns = open_table(path, f).read(["t", "u", "y"])
    assert used == [True]
    reference = np.loadtxt(path, delimiter=",", skiprows=1)
    for j, col in enumerate(columns):
        assert col.tobytes() == np.ascontiguousarray(reference[:, j]).tobytes()
