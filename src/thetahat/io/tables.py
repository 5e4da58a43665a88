"""The files a record is read from, as named columns: CSV, Parquet, MATLAB and workbooks.

:func:`open_table` looks at an open data file (its suffix and its first bytes) and returns a
:class:`Table`: the names of its columns (or variables) and a way to read some of them as
float64 vectors, each cell checked for what it holds. A table does not know the model: which
column is t, u or y is decided by :func:`thetahat.io.mapping.select_columns`, and the checks
every record gets (finite values, t increasing) are made once, by
:func:`thetahat.io.datafile.read_data`, whatever the format.
"""

from __future__ import annotations

import abc
import csv
import io
import itertools
import math
import os
import warnings
from array import array
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from .. import limits
from ..errors import InputLimitError, ModelFileError, ResourceLimitError
from .record import MISSING_CELLS

__all__ = ["CSV_ARROW_MIN_BYTES", "CSV_DELIMITERS", "EXCEL_SUFFIXES", "Table", "arrow_csv",
           "check_samples", "open_table"]

FloatArray = NDArray[np.float64]

#: Column separators a CSV may use (detected from the header when not given): a comma, a
#: semicolon (a European spreadsheet's export, whose decimals are commas) or a tab.
CSV_DELIMITERS = (",", ";", "\t")
_DELIMITER_NAMES = {",": "a comma", ";": "a semicolon", "\t": "a tab"}
#: Largest CSV with decimal commas read by numpy's fast reader (its text is held twice, once
#: with points); larger ones are read row by row.
_DECIMAL_COMMA_FAST_BYTES = 256 << 20
#: Smallest CSV (bytes) read by pyarrow's multi-threaded reader when it is installed: a
#: 58 MB file of 10⁶ rows took 0.14–0.32 s there against numpy's 0.93–1.0 s (two runs,
#: 2026-12-07), about 60 MB a second for numpy; importing pyarrow.csv took 0.05 s with a warm
#: disk (one run; the writer's CSV_ARROW_MIN_VALUES notes 0.2–0.9 s from a cold one), so
#: below a few MB numpy's reader is as fast.
CSV_ARROW_MIN_BYTES = 8 << 20
#: Copies of the read columns a reader may hold at once (the file's table, the float64
#: columns, the record): the memory checked before a large record is read.
_COPIES = 4


class Table(abc.ABC):
    """A data file's columns (or variables) by name (abstract: one subclass per format).

    Attributes
    ----------
    path : Path
    kind : {"column", "variable"}
    names : list of str
        The names, in the file's order.
    where : str
        Names the file (and the header's line) in messages.
    """

    def __init__(self, path: Path, kind: str, names: list[str], where: str) -> None:
        self.path, self.kind, self.names, self.where = path, kind, names, where

    def listing(self) -> str:
        """What the file has, for messages."""
        return ", ".join(repr(n) for n in self.names) if self.names else "(none)"

    @abc.abstractmethod
    def read(self, names: Sequence[str]) -> list[FloatArray]:
        """The named columns as float64 vectors (missing cells as NaN)."""

    def position(self, k: int) -> str:
        """Where sample ``k`` (0-based) is in the file, for messages."""
        return f"sample {k}"

    def fail(self, name: str, message: str) -> ModelFileError:
        """An error about one column, listing what the file has."""
        return ModelFileError(f"data file {self.path}, {self.kind} {name!r}: {message}; the "
                              f"file has {self.listing()}.")


def check_samples(path: Path, rows: int, columns: int) -> None:
    """Refuse a record whose declared number of rows exceeds the limits, before reading it.

    Parameters
    ----------
    path : Path
    rows : int
        Samples per column, as the file declares them.
    columns : int
        Columns that will be read.

    Raises
    ------
    InputLimitError
        ``rows`` exceeds :data:`thetahat.limits.MAX_DATA_SAMPLES`.
    ResourceLimitError
        The columns would not fit in memory (:func:`thetahat.limits.check_allocation`).
    """
    if rows > limits.MAX_DATA_SAMPLES:
        raise InputLimitError(f"data file {path} declares {rows} rows, more than the limit of "
                              f"{limits.MAX_DATA_SAMPLES} samples (thetahat.limits."
                              f"MAX_DATA_SAMPLES); split the record or raise the limit.")
    limits.check_allocation(_COPIES * 8.0 * rows * max(columns, 1),
                            f"reading the {rows} rows of data file {path}",
                            fix="split the record")


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------

def arrow_csv() -> Any:
    """``pyarrow.csv`` when pyarrow is installed (the ``data`` extra), else None.

    The CSV reader (:class:`CsvTable`, files of at least :data:`CSV_ARROW_MIN_BYTES`) and
    writer (:func:`thetahat.io.datafile.write_csv_table`) use it when it is there.

    Returns
    -------
    module or None

    Examples
    --------
    >>> from thetahat.io.tables import arrow_csv
    >>> arrow_csv() is None or callable(arrow_csv().read_csv)
    True
    """
    try:
        import pyarrow.csv as pa_csv
    except ImportError:
        return None
    return pa_csv


def _detect_delimiter(line: str) -> str:
    """The separator of a header line: the one of :data:`CSV_DELIMITERS` that splits it into
    the most fields (a comma when none does)."""
    counts = {d: len(next(csv.reader([line], delimiter=d), [])) for d in CSV_DELIMITERS}
    best = max(CSV_DELIMITERS, key=lambda d: (counts[d], d == ","))
    return best if counts[best] > 1 else ","


class CsvTable(Table):
    """A CSV file with a header row: UTF-8 (a byte-order mark is dropped), any line ending
    (LF, CRLF, CR), separated by a comma, a semicolon or a tab (detected from the header),
    decimals with a point, or with a comma when the separator is not a comma."""

    def __init__(self, path: Path, raw: IO[bytes], delimiter: str | None) -> None:
        if delimiter is not None and delimiter not in CSV_DELIMITERS:
            from ..errors import OptionError
            raise OptionError(f"delimiter must be one of {list(CSV_DELIMITERS)}; got "
                              f"{delimiter!r}.")
        self._raw = raw
        self._fh = io.TextIOWrapper(raw, encoding="utf-8-sig", newline="")
        self._lines: array[int] | None = None
        try:
            line_no, text = 0, ""
            for line_no, text in enumerate(self._fh, start=1):
                if text.strip():
                    break
            else:
                raise ModelFileError(f"data file {path} is empty; expected a header row "
                                     f"such as t,u,y.")
        except (OSError, UnicodeDecodeError) as exc:
            raise ModelFileError(f"cannot read data file {path}: {exc}; thetahat reads CSV "
                                 f"as UTF-8 (in Excel: Save As 'CSV UTF-8').") from exc
        self.delimiter = delimiter if delimiter is not None else _detect_delimiter(text)
        self.header_line = line_no
        header = [h.strip() for h in next(csv.reader([text], delimiter=self.delimiter))]
        super().__init__(path, "column", header,
                         f"data file {path}, line {line_no} (the header)")

    def listing(self) -> str:
        shown = self.delimiter.join(self.names)
        hint = ""
        if len(self.names) == 1:
            other = [d for d in CSV_DELIMITERS if d != self.delimiter and d in self.names[0]]
            if other:
                hint = (f"; the header is one field, which looks separated by "
                        f"{_DELIMITER_NAMES[other[0]]}: pass delimiter={other[0]!r} "
                        f"(--delimiter)")
        return f"the header ({shown}){hint}"

    def position(self, k: int) -> str:
        if self._lines is not None:
            return f"line {self._lines[k]}"
        try:                        # read by the fast path: find the line (only for a message)
            self._fh.seek(0)
            reader = csv.reader(self._fh, delimiter=self.delimiter)
            rows = (line for line, row in enumerate(reader, start=1)
                    if line > self.header_line and row and any(c.strip() for c in row))
            return f"line {next(itertools.islice(rows, k, None))}"
        except (OSError, ValueError, csv.Error, StopIteration):
            return f"data row {k + 1}"

    def read(self, names: Sequence[str]) -> list[FloatArray]:
        index = [self.names.index(n) for n in names]
        try:
            fast = self._fast(index)
            if fast is not None:
                return [np.ascontiguousarray(fast[:, j]) for j in range(len(index))]
            return self._careful(index)
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise ModelFileError(f"cannot read data file {self.path}: {exc}") from exc

    def _fast(self, index: list[int]) -> FloatArray | None:
        """The columns by pyarrow's reader (:meth:`_arrow`) or numpy's C reader, or None when
        the file needs the careful reader (quoted, empty or non-numeric cells, decimal commas,
        NaN or inf, ragged rows, t not increasing), which then gives the message with the
        line."""
        data = self._arrow()
        if data is None:
            data = self._numpy()
        if data is None or data.shape[0] < 2 or data.shape[1] != len(self.names):
            return None
        cols = data[:, index]
        if not np.isfinite(cols).all() or not np.all(np.diff(cols[:, 0]) > 0):
            return None
        return cols

    def _arrow(self) -> FloatArray | None:
        """Every column by pyarrow's CSV reader: a file of at least :data:`CSV_ARROW_MIN_BYTES`
        whose header is its first line, every cell a number (both readers round each decimal
        to the nearest float64, so the values are numpy's); None otherwise, or when pyarrow
        is not installed or refuses a cell (numpy's reader then decides)."""
        if self.header_line != 1 or self._size() < CSV_ARROW_MIN_BYTES:
            return None
        pa_csv = arrow_csv()
        if pa_csv is None:
            return None
        import pyarrow as pa
        names = [f"c{j}" for j in range(len(self.names))]
        try:
            self._fh.seek(0)
            self._raw.seek(0)
            table = pa_csv.read_csv(
                self._raw,
                read_options=pa_csv.ReadOptions(skip_rows=1, column_names=names),
                parse_options=pa_csv.ParseOptions(delimiter=self.delimiter, quote_char=False),
                convert_options=pa_csv.ConvertOptions(
                    column_types={c: pa.float64() for c in names}, null_values=[],
                    strings_can_be_null=False))
            return np.column_stack([table.column(c).to_numpy() for c in names])
        except (pa.ArrowException, ValueError, OSError):
            return None

    def _numpy(self) -> FloatArray | None:
        """Every column by ``numpy.loadtxt`` (decimal commas turned into points when the
        separator is not a comma and the file is small), or None."""
        try:
            self._fh.seek(0)
            source: Any = self._fh
            skip = self.header_line
            if self.delimiter != "," and self._size() <= _DECIMAL_COMMA_FAST_BYTES:
                for _ in range(self.header_line):
                    next(self._fh)
                body = self._fh.read()
                if "," in body:                         # decimal commas, and no point
                    if "." in body:
                        return None
                    source, skip = io.StringIO(body.replace(",", ".")), 0
                else:
                    self._fh.seek(0)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                data = np.loadtxt(source, delimiter=self.delimiter, skiprows=skip,
                                  dtype=np.float64, ndmin=2, comments=None)
        except (ValueError, OSError, UnicodeDecodeError, StopIteration):
            return None
        return np.asarray(data, dtype=np.float64)

    def _size(self) -> int:
        try:
            return os.fstat(self._raw.fileno()).st_size
        except (OSError, AttributeError, ValueError):
            return _DECIMAL_COMMA_FAST_BYTES + 1        # unknown: the row-by-row reader

    def _careful(self, index: list[int]) -> list[FloatArray]:
        self._fh.seek(0)
        reader = csv.reader(self._fh, delimiter=self.delimiter)
        for _ in range(self.header_line):
            next(reader)
        columns = [array("d") for _ in index]
        lines = array("q")
        comma, point = 0, 0
        for line, row in enumerate(reader, start=self.header_line + 1):
            if not row or not any(c.strip() for c in row):
                continue
            if len(row) != len(self.names):
                raise ModelFileError(f"data file {self.path}, line {line}: {len(row)} fields, "
                                     f"but the header has {len(self.names)} (separated by "
                                     f"{_DELIMITER_NAMES[self.delimiter]}).")
            for c, j in enumerate(index):
                value, mark = self._cell(line, self.names[j], row[j])
                columns[c].append(value)
                if mark == ",":
                    comma = comma or line
                elif mark == ".":
                    point = point or line
            lines.append(line)
            if len(lines) > limits.MAX_DATA_SAMPLES:
                check_samples(self.path, len(lines), len(index))
        if comma and point:
            raise ModelFileError(
                f"data file {self.path}: line {comma} writes decimals with a comma and line "
                f"{point} with a point; a number such as 1.234 could be 1234 (a thousands "
                f"separator): export the file with one decimal mark.")
        self._lines = lines
        return [np.frombuffer(col, dtype=np.float64).copy() for col in columns]

    def _cell(self, line: int, column: str, text: str) -> tuple[float, str]:
        """(value, decimal mark used); a missing cell is NaN."""
        cell = text.strip()
        if cell.lower() in MISSING_CELLS:
            return math.nan, ""
        mark = ""
        number = cell
        if self.delimiter != "," and "," in cell:
            mark, number = ",", cell.replace(",", ".", 1) if cell.count(",") == 1 else cell
        elif "." in cell:
            mark = "."
        value = _plain_float(number)
        if value is not None:
            return value, mark
        hint = (" (digit separators such as 1_000 are not accepted)" if "_" in cell else
                " (t must be in seconds, not a date or time)" if column == "t" and
                _is_datetime(cell) else
                " (a decimal comma in a comma-separated file: export it separated by "
                "semicolons, or with decimal points)" if self.delimiter == "," and "," in cell
                else "")
        raise ModelFileError(f"data file {self.path}, line {line}, column {column!r}: "
                             f"{cell!r} is not a number{hint}.")


def _plain_float(text: str) -> float | None:
    """The number a cell writes in plain decimal notation, or None (``float`` would also read
    ``1_000`` as 1000 and the full-width ``１`` or Arabic-Indic ``١`` as 1: digit separators
    and non-ASCII digits are refused, as the generated C harness refuses them)."""
    if "_" in text or not text.isascii():
        return None
    try:
        return float(text)
    except ValueError:
        return None


def _is_datetime(text: str) -> bool:
    try:
        np.datetime64(text)
    except ValueError:
        return False
    return True


# ---------------------------------------------------------------------------------------------
# Parquet
# ---------------------------------------------------------------------------------------------

def _arrow_kind(kind: Any) -> str | None:
    """What a non-numeric Arrow type holds, in words; None for numbers (int, float, decimal)."""
    import pyarrow as pa

    t = pa.types
    if t.is_integer(kind) or t.is_floating(kind) or t.is_decimal(kind):
        return None
    for test, words in ((t.is_boolean, "booleans (true/false)"),
                        (t.is_null, "no values (every entry is null)"),
                        (t.is_timestamp, "time stamps"), (t.is_date, "dates"),
                        (t.is_time, "times of day"), (t.is_duration, "durations"),
                        (t.is_dictionary, "categories (a dictionary-encoded column)"),
                        (t.is_string, "text"), (t.is_large_string, "text"),
                        (t.is_binary, "bytes"), (t.is_large_binary, "bytes"),
                        (t.is_list, "lists"), (t.is_large_list, "lists"),
                        (t.is_struct, "structs"), (t.is_map, "maps")):
        if test(kind):
            return words
    return f"values of type {kind}"


class ParquetTable(Table):
    """A Parquet file (needs pyarrow): its row count and column types are read from the
    metadata and checked before any column is."""

    def __init__(self, path: Path, raw: IO[bytes]) -> None:
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError as exc:
            from ..errors import MissingExtraError
            raise MissingExtraError(f"reading Parquet ({path}) needs pyarrow: pip install "
                                    f"'thetahat[data]', or export the record to CSV.") from exc
        self._pa = pa
        try:
            self._file = pq.ParquetFile(raw)
            schema = self._file.schema_arrow
            self.rows = int(self._file.metadata.num_rows)
        except (OSError, ValueError, pa.ArrowException) as exc:
            raise ModelFileError(f"cannot read data file {path} as Parquet: {exc}") from exc
        self._types = {f.name: f.type for f in schema}
        super().__init__(path, "column", list(schema.names), f"data file {path}")

    def position(self, k: int) -> str:
        return f"row {k}"

    def read(self, names: Sequence[str]) -> list[FloatArray]:
        check_samples(self.path, self.rows, len(names))
        for i, name in enumerate(names):
            what = _arrow_kind(self._types[name])
            temporal = what in ("time stamps", "dates", "durations")
            if what is not None and not (temporal and i == 0 and name == names[0]):
                raise self.fail(name, f"holds {what}, not numbers (booleans, text and dates "
                                      f"are not read as numbers; save the signal as float64)")
        try:
            table = self._file.read(columns=list(dict.fromkeys(names)))
        except (OSError, ValueError, self._pa.ArrowException) as exc:
            raise ModelFileError(f"cannot read data file {self.path}: {exc}") from exc
        except MemoryError as exc:
            raise ResourceLimitError(f"reading data file {self.path} ran out of memory; split "
                                     f"the record.") from exc
        if table.num_rows != self.rows:
            raise ModelFileError(f"data file {self.path}: {table.num_rows} rows read, but the "
                                 f"metadata declares {self.rows}: the file is damaged.")
        return [self._column(table.column(n), n) for n in names]

    def _column(self, column: Any, name: str) -> FloatArray:
        pa = self._pa
        kind = column.type
        if pa.types.is_timestamp(kind) or pa.types.is_date(kind) or pa.types.is_duration(kind):
            stamps = np.asarray(column.to_numpy(zero_copy_only=False),
                                dtype="timedelta64[ns]" if pa.types.is_duration(kind)
                                else "datetime64[ns]")
            if stamps.size == 0:
                return np.zeros(0)
            if np.isnat(stamps).any():
                k = int(np.argmax(np.isnat(stamps)))
                raise self.fail(name, f"the time stamp of row {k} is missing")
            return np.asarray((stamps - stamps[0]) / np.timedelta64(1, "ns") * 1e-9,
                              dtype=np.float64)
        try:
            return np.asarray(column.to_numpy(zero_copy_only=False), dtype=np.float64)
        except (TypeError, ValueError, pa.ArrowException) as exc:
            raise self.fail(name, f"cannot be read as numbers ({exc})") from exc


# ---------------------------------------------------------------------------------------------
# MATLAB
# ---------------------------------------------------------------------------------------------

class MatTable(Table):
    """A MATLAB v4/v5/v7 file: its variables (:mod:`thetahat.io.matfile`)."""

    def __init__(self, path: Path, raw: IO[bytes]) -> None:
        from .matfile import scan_mat

        self._raw = raw
        self._variables = scan_mat(path, raw)
        super().__init__(path, "variable", list(self._variables), f"data file {path}")

    def listing(self) -> str:
        return ", ".join(f"{n!r} ({v.describe()})" for n, v in self._variables.items()) \
            or "(none)"

    def read(self, names: Sequence[str]) -> list[FloatArray]:
        from .matfile import load_mat

        for name in names:
            problem = self._variables[name].problem()
            if problem:
                raise self.fail(name, problem)
        values = load_mat(self.path, self._raw, list(names), self._variables)
        return [self._vector(name, values[name]) for name in names]

    def _vector(self, name: str, value: Any) -> FloatArray:
        arr = value if isinstance(value, np.ndarray) else np.asarray(value, dtype=object)
        if arr.dtype.kind == "c":
            raise self.fail(name, f"complex values ({arr.dtype}); the estimator needs real "
                                  f"signals (map the real part to a variable of its own)")
        if arr.dtype.kind == "b":
            raise self.fail(name, "a logical (true/false) array, not numbers; save it as "
                                  "double(...)")
        if arr.dtype.kind not in "fiu":
            raise self.fail(name, f"not numeric (a {arr.dtype} array: text, a cell array or "
                                  f"a struct)")
        if arr.ndim > 2 or (arr.ndim == 2 and min(arr.shape) > 1):
            raise self.fail(name, f"a {'×'.join(map(str, arr.shape))} array, not a vector; "
                                  f"save each signal as a row or column vector")
        return np.asarray(arr, dtype=np.float64).ravel()


# ---------------------------------------------------------------------------------------------
# Excel and OpenDocument workbooks
# ---------------------------------------------------------------------------------------------

#: Workbook suffixes, read through python-calamine (the ``data`` extra).
EXCEL_SUFFIXES = (".xlsx", ".xlsm", ".xlsb", ".xls", ".ods")
_ZIP_MAGIC = b"PK\x03\x04"
_OLE_MAGIC = b"\xd0\xcf\x11\xe0"


def _check_zip(path: Path, raw: IO[bytes]) -> None:
    """Refuse a workbook whose parts declare more than the limits once decompressed."""
    import zipfile

    try:
        with zipfile.ZipFile(raw) as archive:
            expanded = sum(info.file_size for info in archive.infolist())
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ModelFileError(f"cannot read data file {path} as a workbook: {exc}; save the "
                             f"sheet as CSV.") from exc
    finally:
        raw.seek(0)
    if expanded > limits.MAX_DECOMPRESSED_BYTES:
        raise InputLimitError(f"data file {path}: the workbook's parts declare {expanded} "
                              f"bytes once decompressed, more than the limit of "
                              f"{limits.MAX_DECOMPRESSED_BYTES} (thetahat.limits."
                              f"MAX_DECOMPRESSED_BYTES); save the sheet as CSV.")


class ExcelTable(Table):
    """The first sheet of an Excel (``.xlsx``, ``.xls``, …) or OpenDocument workbook, read by
    python-calamine: its first non-empty row is the header. Number cells are read as numbers,
    empty cells as missing samples, text that is a plain number as that number; booleans,
    other text and dates are refused (a date or time t becomes seconds from its first
    sample)."""

    def __init__(self, path: Path, raw: IO[bytes], head: bytes) -> None:
        try:
            import python_calamine
        except ImportError as exc:
            from ..errors import MissingExtraError
            raise MissingExtraError(
                f"data file {path} is an Excel or OpenDocument workbook; reading it needs "
                f"python-calamine (pip install 'thetahat[data]'), or save the sheet as CSV "
                f"(Excel: File > Save As > 'CSV UTF-8').") from exc
        if head.startswith(_ZIP_MAGIC):
            _check_zip(path, raw)
        try:
            book = python_calamine.CalamineWorkbook.from_filelike(raw)
            self.sheets = list(book.sheet_names)
            rows = book.get_sheet_by_index(0).to_python(skip_empty_area=False)
        except MemoryError as exc:
            raise ResourceLimitError(f"reading data file {path} ran out of memory; save the "
                                     f"sheet as CSV.") from exc
        except Exception as exc:  # noqa: BLE001 - calamine's errors have no common base
            raise ModelFileError(f"cannot read data file {path} as a workbook: "
                                 f"{type(exc).__name__}: {exc}; save the sheet as CSV.") from exc
        start = next((i for i, row in enumerate(rows) if any(c not in ("", None) for c in row)),
                     None)
        if start is None:
            raise ModelFileError(f"data file {path}: the sheet {self.sheets[0]!r} is empty; "
                                 f"expected a header row such as t, u, y.")
        self._rows = [(i + 1, row) for i, row in enumerate(rows[start + 1:], start=start + 1)
                      if any(c not in ("", None) for c in row)]
        check_samples(path, len(self._rows), 1)
        self._lines: list[int] = [i for i, _ in self._rows]
        header = [str(c).strip() for c in rows[start]]
        super().__init__(path, "column", header, f"data file {path}, sheet "
                                                 f"{self.sheets[0]!r}, row {start + 1}")

    def listing(self) -> str:
        more = (f" (of the first sheet, {self.sheets[0]!r}; the workbook has "
                f"{len(self.sheets)} sheets: move the record to the first)"
                if len(self.sheets) > 1 else "")
        return super().listing() + more

    def position(self, k: int) -> str:
        return f"row {self._lines[k]}"

    def read(self, names: Sequence[str]) -> list[FloatArray]:
        out = []
        for n in names:
            j = self.names.index(n)
            cells = [row[j] if j < len(row) else "" for _, row in self._rows]
            out.append(self._column(n, cells, is_t=n == names[0]))
        return out

    def _column(self, name: str, cells: list[Any], *, is_t: bool) -> FloatArray:
        import datetime as dt

        if is_t and cells and all(isinstance(c, (dt.datetime, dt.timedelta)) for c in cells):
            first = cells[0]
            return np.array([(c - first).total_seconds() for c in cells], dtype=np.float64)
        values = np.empty(len(cells))
        for k, cell in enumerate(cells):
            if isinstance(cell, bool):
                raise self.fail(name, f"{self.position(k)} holds a boolean ({cell}), not a "
                                      f"number")
            if isinstance(cell, (int, float)):
                values[k] = cell
            elif cell in ("", None) or (isinstance(cell, str)
                                        and cell.strip().lower() in MISSING_CELLS):
                values[k] = math.nan
            elif isinstance(cell, str):
                number = _plain_float(cell)
                if number is None:
                    raise self.fail(name, f"{self.position(k)} holds the text {cell!r}, not a "
                                          f"number")
                values[k] = number
            else:
                raise self.fail(name, f"{self.position(k)} holds a date or time ({cell}), not "
                                      f"a number" + (" (t must be in seconds, or dates in "
                                                     "every row)" if is_t else ""))
        return values


# ---------------------------------------------------------------------------------------------
# Which reader
# ---------------------------------------------------------------------------------------------

#: The first bytes of a Parquet file.
_PARQUET_MAGIC = b"PAR1"


def open_table(path: Path, raw: IO[bytes], *, delimiter: str | None = None) -> Table:
    """The table of an open data file, by its suffix (``.mat``, ``.parquet``, a workbook's
    :data:`EXCEL_SUFFIXES`; anything else is CSV) and its first bytes (a Parquet file or a
    workbook under another name is read as what it is).

    Parameters
    ----------
    path : Path
        For the suffix and the messages.
    raw : binary file
        The file, opened by :func:`thetahat.safe_io.open_input` (a regular file within
        :data:`thetahat.limits.MAX_DATA_FILE_BYTES`).
    delimiter : {",", ";", "\\t"}, optional
        The CSV separator (default: detected from the header).

    Returns
    -------
    Table

    Raises
    ------
    ModelFileError
        The file cannot be read as its format (the message names the file).
    MissingExtraError
        A Parquet file without pyarrow, or a workbook without python-calamine (the message
        says to save it as CSV).
    """
    suffix = path.suffix.lower()
    head = raw.read(8)
    raw.seek(0)
    if suffix == ".mat":
        return MatTable(path, raw)
    if suffix == ".parquet" or head.startswith(_PARQUET_MAGIC):
        return ParquetTable(path, raw)
    if suffix in EXCEL_SUFFIXES or head.startswith((_ZIP_MAGIC, _OLE_MAGIC)):
        return ExcelTable(path, raw, head)
    return CsvTable(path, raw, delimiter)
