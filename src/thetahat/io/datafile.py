"""Data files for ``thetahat estimate``: read t, u, y from CSV or Parquet and write the
estimates as CSV or Parquet.

:func:`read_data` is the one reading entry point: it dispatches on the file's suffix. Only
regular files are read, within :data:`thetahat.limits.MAX_DATA_FILE_BYTES`; outputs are written
atomically (:mod:`thetahat.safe_io`).
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from array import array
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import limits
from ..errors import MissingExtraError, ModelFileError
from ..estimation.protocol import EstimateResult
from ..estimation.records import check_nan_policy
from .record import MISSING_CELLS, DataRecord, RecordSpec, column_candidates
from ..safe_io import atomic_path, check_regular, check_writable, open_input

__all__ = ["DATA_SUFFIXES", "ESTIMATE_SUFFIXES", "read_data",
           "read_csv", "read_parquet", "check_writable", "estimate_columns", "write_estimates",
           "write_parquet_table"]

#: Record formats :func:`read_data` reads (by suffix, case-insensitive).
DATA_SUFFIXES = (".csv", ".parquet")
#: Formats :func:`write_estimates` writes (by suffix).
ESTIMATE_SUFFIXES = (".csv", ".parquet")

FloatArray = NDArray[np.float64]


def read_data(path: str | Path, spec: RecordSpec, *, nan_policy: str = "raise") -> DataRecord:
    """Read a data record for a model's estimator: CSV, Parquet or MATLAB, by the suffix.

    Parameters
    ----------
    path : str or Path
        A regular file: ``.mat`` (MATLAB v4–v7, :func:`thetahat.io.mapping.read_mapped`),
        ``.parquet`` (needs pyarrow; :func:`read_parquet`), anything else is read as CSV
        (:func:`read_csv`). Columns: ``t``, the inputs and the outputs (see
        :func:`column_candidates`), or as the model's ``[data]`` table maps them (any format,
        through :func:`thetahat.io.mapping.read_mapped`).
    spec : RecordSpec
        The model whose estimator reads the record.
    nan_policy : {"raise", "skip"}
        ``"skip"`` reads missing or NaN output samples as NaN (dropouts); ``"raise"`` refuses
        them.

    Returns
    -------
    DataRecord

    Raises
    ------
    ModelFileError
        The file is not a regular file, cannot be read, or its content is invalid (the message
        says where).
    InputLimitError
        The file is larger than :data:`thetahat.limits.MAX_DATA_FILE_BYTES`.
    OptionError
        Unknown ``nan_policy``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.io.datafile import read_data
    >>> csv_path = pathlib.Path(tempfile.mkdtemp()) / "data.csv"
    >>> _ = csv_path.write_text("t,u,y\\n0,0,0.1\\n0.01,0.5,0.2\\n")
    >>> read_data(csv_path, loads_model(EXAMPLE_MODEL)).t.tolist()
    [0.0, 0.01]
    """
    check_nan_policy(nan_policy)
    path = check_regular(path, "data file", limits.MAX_DATA_FILE_BYTES)   # every format
    if spec.data is not None or path.suffix.lower() == ".mat":
        from .mapping import read_mapped          # a [data] table, or a MATLAB file
        return read_mapped(path, spec, nan_policy=nan_policy)
    if path.suffix.lower() == ".parquet":
        return read_parquet(path, spec, nan_policy=nan_policy)
    return read_csv(path, spec, nan_policy=nan_policy)


def read_csv(path: str | Path, spec: RecordSpec, *, nan_policy: str = "raise") -> DataRecord:
    """Read a CSV record (header row; columns t, inputs, outputs) for a model's estimator.

    Usually called through :func:`read_data`, which dispatches on the suffix.

    The file is read as UTF-8 (a byte-order mark, as Excel writes, is accepted), with any line
    ending (LF, CRLF), row by row into float64 columns: memory is O(N) in the samples only.

    Parameters
    ----------
    path : str or Path
        CSV file with a header. Required columns: ``t``; each input under its name in the
        model (``[perturbation] u``) or ``u1``, ``u2``, … (``u`` when m = 1); each output
        under its name or ``y1``, … (``y`` when r = 1). Order is free; other columns are
        ignored; blank lines are skipped. A column name may appear only once, and only one of
        the accepted names of a column may be present. Cells are plain decimal numbers
        (``1_000`` is refused). At least two rows.
    spec : RecordSpec
    nan_policy : {"raise", "skip"}
        ``"skip"`` reads empty or NaN output cells (measurement dropouts) as NaN, for the
        observer's ``nan_policy="skip"``; ``"raise"`` refuses them. Inputs and t must always
        be finite.

    Returns
    -------
    DataRecord

    Raises
    ------
    ModelFileError
        The file cannot be read or is not a regular file, a column is missing or given twice, a value is not a number or is NaN or
        inf (the message gives the line and the column), a row has the wrong number of
        fields, or t is not strictly increasing.
    InputLimitError
        The file is larger than :data:`thetahat.limits.MAX_DATA_FILE_BYTES`.
    OptionError
        Unknown ``nan_policy``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.io.datafile import read_csv
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> csv_path = pathlib.Path(tempfile.mkdtemp()) / "data.csv"
    >>> _ = csv_path.write_text("t,u,y\\n0,0,0.1\\n0.01,0.5,0.2\\n")
    >>> read_csv(csv_path, spec).y.ravel().tolist()
    [0.1, 0.2]
    >>> _ = csv_path.write_text("t,u,y\\r\\n0,0,0.1\\r\\n0.01,0.5,\\r\\n")   # a dropout
    >>> read_csv(csv_path, spec, nan_policy="skip").y.ravel().tolist()
    [0.1, nan]
    """
    check_nan_policy(nan_policy)
    path = Path(path)
    with open_input(path, "data file", limits.MAX_DATA_FILE_BYTES) as raw:
        try:
            fh = io.TextIOWrapper(raw, encoding="utf-8-sig", newline="")
            return _read_rows(path, fh, spec, nan_policy)
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise ModelFileError(f"cannot read data file {path}: {exc}") from exc


def _fast_columns(fh: Any, header_line: int, width: int,
                  index: list[int]) -> NDArray[np.float64] | None:
    """The selected columns by numpy's C reader, or None when the file needs the careful
    row-by-row reader (quoted or non-numeric cells, NaN, ragged rows, t not increasing, fewer
    than two rows), which then gives the message with the line and the column."""
    try:
        fh.seek(0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = np.loadtxt(fh, delimiter=",", skiprows=header_line, dtype=np.float64,
                              ndmin=2, comments=None)
    except (ValueError, OSError, UnicodeDecodeError):
        return None
    if data.shape[0] < 2 or data.shape[1] != width:
        return None
    cols = data[:, index]
    if not np.isfinite(cols).all() or not np.all(np.diff(cols[:, 0]) > 0):
        return None
    return np.ascontiguousarray(cols)


def _header(path: Path, reader: Any, spec: RecordSpec) -> tuple[int, list[str], list[int]]:
    """(line of the header, its names, the index of t, u..., y... in it)."""
    for line, row in enumerate(reader, start=1):
        if row and any(c.strip() for c in row):
            header_line, header = line, [h.strip() for h in row]
            break
    else:
        raise ModelFileError(f"data file {path} is empty; expected a header row such as "
                             f"t,{','.join(spec.input_names + spec.output_names)}.")
    cols = _find_columns(f"data file {path}, line {header_line}", header, spec)
    index = [header.index(c) for c in cols]
    return header_line, header, index


def _find_columns(where: str, names: list[str], spec: RecordSpec) -> list[str]:
    """The column names of t, u..., y... in a header: each present once, one name per signal."""
    twice = sorted({h for h in names if h and names.count(h) > 1})
    if twice:
        raise ModelFileError(f"{where}: the column(s) {twice} appear more than once in the "
                             f"header; rename or drop the copies.")
    cols = []
    for alts in column_candidates(spec):
        found = [h for h in alts if h in names]
        if not found:
            raise ModelFileError(
                f"{where}: missing column {' or '.join(repr(a) for a in alts)} in the header "
                f"({','.join(names)}); expected t, then the inputs {list(spec.input_names)} "
                f"and the outputs {list(spec.output_names)}.")
        if len(found) > 1:
            raise ModelFileError(f"{where}: the columns {found} name the same signal; keep one "
                                 f"of them.")
        cols.append(found[0])
    return cols


def _read_rows(path: Path, fh: Any, spec: RecordSpec, nan_policy: str) -> DataRecord:
    header_line, header, index = _header(path, csv.reader(fh), spec)
    m = spec.system.m
    cols = tuple(header[j] for j in index)
    fast = _fast_columns(fh, header_line, len(header), index)
    if fast is not None:
        return DataRecord(t=fast[:, 0].copy(), u=fast[:, 1:1 + m].copy(),
                          y=fast[:, 1 + m:].copy(), columns=cols, source=str(path))
    fh.seek(0)
    reader = csv.reader(fh)
    for _ in range(header_line):
        next(reader)
    columns = [array("d") for _ in index]
    lines = array("q")
    for line, row in enumerate(reader, start=header_line + 1):
        if not row or not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise ModelFileError(f"data file {path}, line {line}: {len(row)} fields, but the "
                                 f"header has {len(header)}.")
        for c, j in enumerate(index):
            columns[c].append(_cell(path, line, header[j], row[j], output=c > m,
                                    skip=nan_policy == "skip"))
        lines.append(line)
    if not lines:
        raise ModelFileError(f"data file {path} has a header but no data rows.")
    if len(lines) < 2:
        raise ModelFileError(f"data file {path} has one data row; an estimate needs a record "
                             f"of at least two samples.")
    data = np.column_stack([np.frombuffer(col, dtype=np.float64) for col in columns])
    t = data[:, 0]
    steps = np.diff(t)
    if steps.size and not np.all(steps > 0):
        r = int(np.argmax(steps <= 0)) + 1
        raise ModelFileError(f"data file {path}, line {lines[r]}: t = {float(t[r])!r} does not "
                             f"increase (previous t = {float(t[r - 1])!r}); t must be strictly "
                             f"increasing.")
    return DataRecord(t=t.copy(), u=data[:, 1:1 + m].copy(), y=data[:, 1 + m:].copy(),
                      columns=cols, source=str(path))


def _is_datetime(text: str) -> bool:
    try:
        np.datetime64(text)
    except ValueError:
        return False
    return True


def _cell(path: Path, line: int, column: str, text: str, *, output: bool,
          skip: bool) -> float:
    cell = text.strip()
    if output and skip and cell.lower() in MISSING_CELLS:
        return math.nan
    try:
        value = math.nan if "_" in cell else float(cell)   # float() reads 1_000 as 1000
        ok = "_" not in cell
    except ValueError:
        ok = False
    if not ok:
        hint = (" (an empty output cell is a dropout: pass --nan-policy skip)"
                if output and cell == "" else
                " (digit separators such as 1_000 are not accepted)" if "_" in cell else
                " (t must be in seconds, not a date or time)" if column == "t" and
                _is_datetime(cell) else "")
        raise ModelFileError(f"data file {path}, line {line}, column {column!r}: {cell!r} is "
                             f"not a number{hint}.") from None
    if math.isnan(value) and output and skip:
        return value
    if not math.isfinite(value):
        hint = ("; a NaN output is a dropout: pass --nan-policy skip (nan_policy='skip') to "
                "predict over it" if output and math.isnan(value) else
                "; the estimator needs every t and input sample (remove or fill the row)")
        raise ModelFileError(f"data file {path}, line {line}, column {column!r}: {cell} is "
                             f"not finite{hint}.")
    return value


def estimate_columns(spec: RecordSpec, *, refined: bool) -> tuple[str, ...]:
    """Header of an estimates CSV: t, x_hat_<x>..., phi_hat_<i>..., theta_hat_<θ>...,
    and x_hat_refined_<x>... when ``refined``.

    Parameters
    ----------
    spec : RecordSpec
    refined : bool
        Include the second observer's columns.

    Returns
    -------
    tuple of str

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.io.datafile import estimate_columns
    >>> estimate_columns(loads_model(EXAMPLE_MODEL), refined=False)
    ('t', 'x_hat_x1', 'x_hat_x2', 'phi_hat_1', 'theta_hat_theta')
    """
    cols = ["t"] + [f"x_hat_{s}" for s in spec.state_names]
    cols += [f"phi_hat_{i + 1}" for i in range(spec.system.k)]
    cols += [f"theta_hat_{s}" for s in spec.parameter_names]
    if refined:
        cols += [f"x_hat_refined_{s}" for s in spec.state_names]
    return tuple(cols)


def write_estimates(path: str | Path, result: EstimateResult, spec: RecordSpec) -> None:
    """Write an :class:`~thetahat.estimation.protocol.EstimateResult` as CSV or Parquet, by suffix (header
    :func:`estimate_columns`), atomically: a failed write leaves an old file unchanged.

    CSV numbers are written with 17 significant digits, so reading the file back gives the
    same floats; Parquet holds the float64 values themselves.

    Parameters
    ----------
    path : str or Path
        Output file, ``.csv`` or ``.parquet`` (its folder is created).
    result : EstimateResult
    spec : RecordSpec
        For the column names.

    Raises
    ------
    ModelFileError
        Unknown suffix.
    FileAccessError
        The file cannot be written.
    MissingExtraError
        ``.parquet`` without pyarrow.
    """
    path = check_writable(path, suffixes=ESTIMATE_SUFFIXES, what="estimates")
    parts = [result.t[:, None], result.x_hat, result.phi_hat, result.theta_hat]
    if result.x_hat_refined is not None:
        parts.append(result.x_hat_refined)
    cols = estimate_columns(spec, refined=result.x_hat_refined is not None)
    table = np.hstack(parts)
    if path.suffix.lower() == ".parquet":
        write_parquet_table(path, {c: table[:, i] for i, c in enumerate(cols)})
        return
    with atomic_path(path) as tmp:
        np.savetxt(tmp, table, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")


def write_parquet_table(path: str | Path, columns: dict[str, Any]) -> None:
    """Write named columns as a Parquet file, atomically (needs pyarrow).

    Parameters
    ----------
    path : str or Path
        The output file.
    columns : dict of str to sequence
        Column name → values (all of one length).

    Raises
    ------
    MissingExtraError
        pyarrow is not installed.
    FileAccessError
        The file cannot be written.
    """
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise MissingExtraError("writing Parquet needs pyarrow: pip install 'thetahat[data]', "
                                "or write .csv") from exc
    table = pa.table({c: list(v) if not isinstance(v, np.ndarray) else v
                      for c, v in columns.items()})
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)


def read_parquet(path: str | Path, spec: RecordSpec, *, nan_policy: str = "raise") -> DataRecord:
    """Read a Parquet record with the columns of :func:`read_csv`.

    Parameters
    ----------
    path : str or Path
        A regular Parquet file (needs pyarrow). Required columns as for :func:`read_csv`
        (see :func:`column_candidates`); other columns are ignored. Every value must be
        finite (outputs may be NaN or null under ``nan_policy="skip"``), and t strictly
        increasing over at least two rows. A timestamp or duration column t is converted to
        seconds from the first sample; booleans, dates in u or y and non-numbers are refused.
    spec : RecordSpec
        The model whose estimator reads the record (its input and output names).
    nan_policy : {"raise", "skip"}, optional
        ``"skip"`` keeps NaN outputs as dropouts for the observer's ``nan_policy="skip"``;
        ``"raise"`` refuses them.

    Returns
    -------
    DataRecord
        ``t (N,)``, ``u (N, m)``, ``y (N, r)`` in float64, the columns used and the source.

    Raises
    ------
    ModelFileError
        pyarrow missing, not a regular file, unreadable file, a missing column, a column that
        is not numeric, a non-finite value, or t not strictly increasing.
    InputLimitError
        The file is larger than :data:`thetahat.limits.MAX_DATA_FILE_BYTES`.
    """
    try:
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise ModelFileError("reading Parquet needs pyarrow: pip install 'thetahat[data]'"
                             ) from exc
    check_nan_policy(nan_policy)
    path = Path(path)
    with open_input(path, "data file", limits.MAX_DATA_FILE_BYTES) as fh:
        try:
            table = pq.read_table(fh)
        except (OSError, ValueError) as exc:   # pyarrow's ArrowInvalid derives from ValueError
            raise ModelFileError(f"cannot read data file {path}: {exc}") from exc
    cols = _find_columns(f"data file {path}", table.column_names, spec)
    data = np.column_stack([_parquet_column(path, table.column(c), c, is_t=i == 0)
                            for i, c in enumerate(cols)])
    m = spec.system.m
    bad = ~np.isfinite(data)
    if nan_policy == "skip":
        bad[:, 1 + m:] &= ~np.isnan(data[:, 1 + m:])       # a NaN output is a dropout
    if bad.any():
        i, j = (int(a[0]) for a in np.nonzero(bad))
        raise ModelFileError(f"data file {path}, row {i}, column {cols[j]!r}: {data[i, j]} is "
                             "not finite; the estimator needs every sample (a NaN output is "
                             "a dropout under nan_policy='skip').")
    if data.shape[0] < 2 or not np.all(np.diff(data[:, 0]) > 0):
        raise ModelFileError(f"data file {path}: t must be strictly increasing with at least "
                             "two rows.")
    return DataRecord(t=data[:, 0].copy(), u=data[:, 1:1 + m].copy(),
                      y=data[:, 1 + m:].copy(), columns=tuple(cols), source=str(path))


def _parquet_column(path: Path, column: Any, name: str, *, is_t: bool) -> FloatArray:
    """One Parquet column as float64 (nulls as NaN); t in seconds from its first sample when
    it holds timestamps or durations."""
    import pyarrow as pa

    kind = column.type
    if pa.types.is_timestamp(kind) or pa.types.is_duration(kind) or pa.types.is_date(kind):
        if not is_t:
            raise ModelFileError(f"data file {path}, column {name!r}: holds dates or times "
                                 f"({kind}); inputs and outputs must be numbers.")
        stamps = np.asarray(column.to_numpy(), dtype="datetime64[ns]"
                            if not pa.types.is_duration(kind) else "timedelta64[ns]")
        if stamps.size == 0:
            return np.zeros(0)
        if np.isnat(stamps).any():
            raise ModelFileError(f"data file {path}, column 't': a time stamp is missing.")
        return (stamps - stamps[0]) / np.timedelta64(1, "ns") * 1e-9
    if not (pa.types.is_integer(kind) or pa.types.is_floating(kind)
            or pa.types.is_decimal(kind) or pa.types.is_null(kind)):
        raise ModelFileError(f"data file {path}, column {name!r}: holds {kind} values; "
                             f"expected numbers (booleans and text are not read as numbers).")
    try:
        return np.asarray(column.to_numpy(zero_copy_only=False), dtype=np.float64)
    except (TypeError, ValueError, pa.ArrowException) as exc:
        raise ModelFileError(f"data file {path}, column {name!r}: not numeric: {exc}") from exc
