"""Issue 36, a newcomer's first hour with a log: European CSV exports, Excel workbooks, and a
missing column that says how to map it."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from thetahat import errors as E
from thetahat.fleet import estimate_many, fleet_files
from thetahat.io.datafile import read_data
from thetahat.modelfile import EXAMPLE_MODEL, loads_model
from xlsx_writer import write_xlsx

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
LAYOUT = loads_model(EXAMPLE_MODEL).layout
#: Models besides LuGre with one and with two outputs.
MODELS = ["prop1", "two_inertia", "heater", "actuator"]


def _spec(name: str):
    return loads_model((EXAMPLES / f"{name}.toml").read_text(encoding="utf-8"), source=name)


def _table(spec, n: int = 40) -> tuple[list[str], np.ndarray]:
    rng = np.random.default_rng(36)
    names = ["t", *spec.input_names, *spec.output_names]
    t = np.arange(n) * 0.01
    return names, np.column_stack([t] + [rng.normal(size=n) for _ in names[1:]])


def _write(path: Path, names: list[str], table: np.ndarray, sep: str, decimal: str) -> Path:
    rows = [sep.join(names)] + [sep.join(f"{v:.17g}".replace(".", decimal) for v in row)
                                for row in table]
    path.write_text("\r\n".join(rows) + "\r\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("sep,decimal", [(";", ","), ("\t", ","), ("\t", "."), (";", ".")],
                         ids=["semicolon-comma", "tab-comma", "tab-point", "semicolon-point"])
def test_european_exports_read_as_the_comma_separated_file(tmp_path, model, sep, decimal):
    """A European spreadsheet's export (semicolons or tabs, decimal commas) gives the same
    float64 arrays as the same table written with commas and points."""
    spec = _spec(model)
    names, table = _table(spec)
    plain = read_data(_write(tmp_path / "plain.csv", names, table, ",", "."), spec.layout)
    other = read_data(_write(tmp_path / "export.csv", names, table, sep, decimal), spec.layout)
    for a in ("t", "u", "y"):
        np.testing.assert_array_equal(getattr(other, a), getattr(plain, a))
    np.testing.assert_array_equal(plain.y, table[:, 1 + spec.layout.m:])


def test_mixed_decimal_marks_are_refused(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text("t;u;y\n0;0,5;1\n0,01;1.234;2\n", encoding="utf-8")
    with pytest.raises(E.ModelFileError, match=r"line 2 writes decimals with a comma and line "
                                               r"3 with a point.*thousands separator"):
        read_data(path, LAYOUT)


def test_a_forced_wrong_delimiter_names_the_right_one(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text("t;u;y\n0;0;1\n0,01;1;2\n", encoding="utf-8")
    with pytest.raises(E.ModelFileError, match=re.escape(
            "the header (t;u;y); the header is one field, which looks separated by a "
            "semicolon: pass delimiter=';' (--delimiter)")):
        read_data(path, LAYOUT, delimiter=",")
    assert read_data(path, LAYOUT, delimiter=";").t.tolist() == [0.0, 0.01]
    with pytest.raises(E.OptionError, match="delimiter must be one of"):
        read_data(path, LAYOUT, delimiter="|")


def test_decimal_comma_in_a_comma_separated_file_is_explained(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text('t,u,y\n0,"0,5",1\n0.01,1,2\n', encoding="utf-8")
    with pytest.raises(E.ModelFileError, match="'0,5' is not a number \\(a decimal comma in a "
                                               "comma-separated file"):
        read_data(path, LAYOUT)


@pytest.mark.parametrize("model", ["prop1", "two_inertia", "heater"])
def test_missing_column_names_the_data_table_and_the_line(tmp_path, model):
    spec = _spec(model)
    names, table = _table(spec)
    names[-1] = "sensor_7"
    path = _write(tmp_path / "d.csv", names, table, ",", ".")
    with pytest.raises(E.ModelFileError) as info:
        read_data(path, spec.layout)
    message = str(info.value)
    y = spec.output_names[-1]
    assert f"missing column '{y}'" in message and "the file has the header" in message
    assert "model file's [data] table" in message and "'y = " in message
    # the line it shows, added to the model file, reads the record
    line = re.search(r"add the line '(.+?)' under \[data\]", message).group(1)
    if spec.layout.r > 1:
        line = "y = [" + ", ".join(f'"{n}"' for n in names[1 + spec.layout.m:]) + "]"
    fixed = loads_model((EXAMPLES / f"{model}.toml").read_text(encoding="utf-8")
                        + f"\n[data]\n{line}\n", source=model)
    np.testing.assert_array_equal(read_data(path, fixed.layout).y[:, -1], table[:, -1])


# --- workbooks ----------------------------------------------------------------------------------

def _rows(names, table):
    return [names] + [list(map(float, row)) for row in table]


@pytest.mark.parametrize("model", ["prop1", "two_inertia", "heater"])
def test_xlsx_reads_as_the_csv(tmp_path, model):
    pytest.importorskip("python_calamine", reason="workbooks need the data extra")
    spec = _spec(model)
    names, table = _table(spec)
    book = read_data(write_xlsx(tmp_path / "log.xlsx", _rows(names, table)), spec.layout)
    csv = read_data(_write(tmp_path / "log.csv", names, table, ",", "."), spec.layout)
    for a in ("t", "u", "y"):
        np.testing.assert_array_equal(getattr(book, a), getattr(csv, a))


XLSX_REFUSED = [
    ("boolean", lambda r: r[3].__setitem__(2, True), "column 'y': row 4 holds a boolean"),
    ("text", lambda r: r[3].__setitem__(1, "n/v"), "column 'u': row 4 holds the text 'n/v'"),
    ("empty input", lambda r: r[3].__setitem__(1, None), "row 4, column 'u': nan is not finite"),
]


@pytest.mark.parametrize("name,spoil,words", XLSX_REFUSED, ids=[c[0] for c in XLSX_REFUSED])
def test_xlsx_cells_are_checked_like_csv_cells(tmp_path, name, spoil, words):
    pytest.importorskip("python_calamine", reason="workbooks need the data extra")
    rows = _rows(*_table(_spec("prop1")))
    spoil(rows)
    with pytest.raises(E.ModelFileError, match=re.escape(words)):
        read_data(write_xlsx(tmp_path / "log.xlsx", rows), LAYOUT)


def test_xlsx_dropout_under_skip(tmp_path):
    pytest.importorskip("python_calamine", reason="workbooks need the data extra")
    rows = _rows(*_table(_spec("prop1")))
    rows[5][2] = None
    rec = read_data(write_xlsx(tmp_path / "log.xlsx", rows), LAYOUT, nan_policy="skip")
    assert np.flatnonzero(np.isnan(rec.y[:, 0])).tolist() == [4]


def test_workbook_without_the_extra_says_save_as_csv(tmp_path, monkeypatch):
    """Without python-calamine, a real .xlsx (or one renamed .csv) is refused with the fix,
    not with "'utf-8' codec can't decode byte"."""
    monkeypatch.setitem(sys.modules, "python_calamine", None)
    rows = _rows(*_table(_spec("prop1")))
    for name in ("log.xlsx", "log.csv"):
        path = write_xlsx(tmp_path / name, rows)
        with pytest.raises(E.MissingExtraError, match=r"is an Excel or OpenDocument workbook.*"
                                                      r"python-calamine.*save the sheet as CSV"):
            read_data(path, LAYOUT)
    (tmp_path / "old.xls").write_bytes(b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1" + bytes(504))
    with pytest.raises(E.MissingExtraError, match="save the sheet as CSV"):
        read_data(tmp_path / "old.xls", LAYOUT)


def test_damaged_workbook_is_a_typed_error(tmp_path):
    pytest.importorskip("python_calamine", reason="workbooks need the data extra")
    data = bytearray(write_xlsx(tmp_path / "log.xlsx",
                                _rows(*_table(_spec("prop1")))).read_bytes())
    data[len(data) // 2:len(data) // 2 + 40] = bytes(40)
    (tmp_path / "log.xlsx").write_bytes(bytes(data))
    with pytest.raises(E.ModelFileError, match="as a workbook.*save the sheet as CSV"):
        read_data(tmp_path / "log.xlsx", LAYOUT)


def test_fleet_folder_takes_workbooks(tmp_path):
    pytest.importorskip("python_calamine", reason="workbooks need the data extra")
    model = tmp_path / "m.toml"
    model.write_text(EXAMPLE_MODEL, encoding="utf-8")
    d = tmp_path / "logs"
    d.mkdir()
    t = np.arange(150) * 0.01
    table = np.c_[t, np.sin(t), 0.1 * np.cos(t)]
    write_xlsx(d / "a.xlsx", _rows(["t", "u", "y"], table))
    _write(d / "b.csv", ["t", "u", "y"], table, ";", ",")
    assert [p.name for p in fleet_files(d)] == ["a.xlsx", "b.csv"]
    res = estimate_many(model, d, progress=False)
    assert res.n_ok == 2
    assert res.rows[0]["theta_hat_theta"] == res.rows[1]["theta_hat_theta"]   # same record


def test_fleet_passes_the_delimiter_to_every_record(tmp_path):
    model = tmp_path / "m.toml"
    model.write_text(EXAMPLE_MODEL, encoding="utf-8")
    d = tmp_path / "logs"
    d.mkdir()
    t = np.arange(150) * 0.01
    _write(d / "a.csv", ["t", "u", "y"], np.c_[t, np.sin(t), 0.1 * np.cos(t)], ";", ".")
    assert estimate_many(model, d, delimiter=";", progress=False).n_ok == 1
    forced = estimate_many(model, d, delimiter=",", progress=False)
    assert "looks separated by a semicolon" in forced.failed[str(d / "a.csv")]
    with pytest.raises(E.OptionError, match="delimiter must be one of"):
        estimate_many(model, d, delimiter="|", progress=False)
