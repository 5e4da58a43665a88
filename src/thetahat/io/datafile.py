"""Data files: read a record (t, u, y) from CSV, Parquet or MATLAB, and write the estimates as
CSV or Parquet.

:func:`read_data` is the one reading entry point, for every format, with or without a
``[data]`` table: :func:`~thetahat.io.tables.open_table` reads the file's columns (checking
each cell for what it holds), :func:`~thetahat.io.mapping.select_columns` decides which are t,
u and y, and :func:`read_data` then applies the mapping's scale and offset and makes the checks
every record gets (finite values, t strictly increasing, at least two samples), in that order.
Only regular files are read, within :data:`thetahat.limits.MAX_DATA_FILE_BYTES`; outputs are
written atomically (:mod:`thetahat.safe_io`).
"""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import limits
from ..errors import (ArgumentTypeError, DimensionError, MissingExtraError, ModelFileError,
                      ThetahatWarning)
from ..estimation.protocol import EstimateResult
from ..estimation.records import check_nan_policy
from ..safe_io import atomic_path, check_writable, open_input
from .mapping import RecordLayout, Signal, select_columns, select_samples
from .record import DataRecord
from .tables import EXCEL_SUFFIXES, Table, arrow_csv, open_table

__all__ = ["CSV_CHUNK_ROWS", "DATA_SUFFIXES", "ESTIMATE_SUFFIXES", "read_data", "check_writable",
           "estimate_columns", "write_csv_table", "write_estimates", "write_parquet_table"]

#: Record formats by suffix (case-insensitive): what a fleet's folder or glob takes as records.
#: :func:`read_data` reads any other name as CSV.
DATA_SUFFIXES = (".csv", ".parquet", ".mat") + EXCEL_SUFFIXES
#: Formats :func:`write_estimates` writes (by suffix).
ESTIMATE_SUFFIXES = (".csv", ".parquet")

FloatArray = NDArray[np.float64]


def _check_layout(layout: Any) -> RecordLayout:
    if isinstance(layout, RecordLayout):
        return layout
    hint = (" (a model spec: pass spec.layout)" if isinstance(getattr(layout, "layout", None),
                                                               RecordLayout) else "")
    raise ArgumentTypeError(f"layout must be a thetahat.io.mapping.RecordLayout{hint}; got "
                            f"{type(layout).__name__}.")


def read_data(path: str | Path, layout: RecordLayout, *, nan_policy: str = "raise",
              delimiter: str | None = None,
              samples: str | tuple[int, int] | None = None) -> DataRecord:
    """Read a record for a model's estimator: CSV, Parquet or MATLAB, by the suffix.

    Parameters
    ----------
    path : str or Path
        A regular file: ``.mat`` (MATLAB v4–v7, :mod:`thetahat.io.matfile`), ``.parquet``
        (needs pyarrow; also a Parquet file under another name), ``.xlsx``, ``.xls`` and the
        other workbooks of :data:`~thetahat.io.tables.EXCEL_SUFFIXES` (the first sheet; needs
        python-calamine, else refused with "save as CSV"), anything else CSV with a
        header row (UTF-8, any line ending, separated by commas, semicolons or tabs, decimal
        commas when the separator is not a comma). Columns (or variables): ``t``, each input
        and each output under its name in the model, ``u1``…/``y1``… (``u``/``y`` for one),
        or as the model's ``[data]`` table maps them (:mod:`thetahat.io.mapping`). Other
        columns are ignored.
    layout : RecordLayout
        What the reader needs of the model (``spec.layout`` of a
        :class:`~thetahat.modelfile.ModelSpec`): the names and the ``[data]`` mapping.
    nan_policy : {"raise", "skip"}
        ``"skip"`` reads missing or NaN output samples as NaN (dropouts); ``"raise"`` refuses
        them. t and the inputs must always be complete and finite.
    delimiter : {",", ";", "\\t"}, optional
        The CSV separator; default: detected from the header.
    samples : str or (int, int), optional
        Which samples to return (:func:`~thetahat.io.mapping.select_samples`): a segment of
        the model file's ``[data.segments]`` by name, ``"START:STOP"``, (start, stop) or
        ``"all"``; default: the ``[data]`` table's ``samples`` (else all). Every sample of
        the file is checked either way.

    Returns
    -------
    DataRecord
        t, u and y in the model's units (the mapping's scale and offset applied), over the
        samples chosen (t as in the file).

    Raises
    ------
    ModelFileError
        The file is not a regular file or cannot be read; a column is missing, given twice,
        used twice or of the wrong kind (the message names it and what it holds); a value is
        not a number, not finite, or over- or underflows once scaled (the message gives the
        line, row or sample); t does not strictly increase; fewer than two samples; samples
        names no segment or goes beyond the record.
    InputLimitError
        The file, its declared rows or a compressed element exceeds :mod:`thetahat.limits`.
    ResourceLimitError
        The declared record would not fit in memory.
    MissingExtraError
        A Parquet file without pyarrow, or a workbook without python-calamine.
    OptionError
        Unknown ``nan_policy`` or ``delimiter``.
    ArgumentTypeError
        ``layout`` is not a :class:`~thetahat.io.mapping.RecordLayout`.

    Warns
    -----
    ThetahatWarning
        t holds whole numbers stepping by at least 1 and by at least half the model's
        slowest time constant (fewer than two samples per time constant): t looks like
        milliseconds or another unit, not seconds.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.io.datafile import read_data
    >>> from thetahat.io.mapping import RecordLayout
    >>> layout = RecordLayout(input_names=("u",), output_names=("y",))
    >>> csv_path = pathlib.Path(tempfile.mkdtemp()) / "data.csv"
    >>> _ = csv_path.write_text("t,u,y\\n0,0,0.1\\n0.01,0.5,0.2\\n")
    >>> read_data(csv_path, layout).t.tolist()
    [0.0, 0.01]
    >>> _ = csv_path.write_text("t;u;y\\r\\n0;0;0,1\\r\\n0,01;0,5;\\r\\n")   # a dropout
    >>> read_data(csv_path, layout, nan_policy="skip").y.ravel().tolist()
    [0.1, nan]
    """
    check_nan_policy(nan_policy)
    layout = _check_layout(layout)
    path = Path(path)
    with open_input(path, "data file", limits.MAX_DATA_FILE_BYTES) as raw:
        table = open_table(path, raw, delimiter=delimiter)
        signals = select_columns(table.names, layout, table.where, kind=table.kind,
                                 listing=table.listing())
        used = [s for s in signals if s is not None]
        raws = table.read([s.column for s in used])
        record = _record(table, layout, signals, raws, nan_policy)   # messages read lines
    start, stop = select_samples(layout.data, record.t.size, samples,
                                 where=f"data file {path}")
    return record.segment(start, stop)


def _record(table: Table, layout: RecordLayout, signals: list[Signal | None],
            raws: list[FloatArray], nan_policy: str) -> DataRecord:
    """The checks every record gets, once the columns are read."""
    used = [s for s in signals if s is not None]
    N = raws[0].size
    for s, raw in zip(used, raws):
        if raw.size != N:
            raise table.fail(s.column, f"{raw.size} samples, but {used[0].column!r} has {N}; "
                                       f"every signal needs one value per sample")
    m = layout.m
    offset = 1 if signals[0] is not None else 0
    values = []
    for i, (s, raw) in enumerate(zip(used, raws)):
        output = i - offset >= m
        values.append(_scaled(table, s, raw, output=output, skip=nan_policy == "skip"))
    if N < 2:                      # after the samples' own checks
        what = "a header but no data rows" if N == 0 else "one data row"
        raise ModelFileError(f"data file {table.path} has {N} sample(s) ({what}); an estimate "
                             f"needs a record of at least two samples.")
    mapping = layout.data
    if signals[0] is None and mapping is not None and mapping.rate is not None:
        with np.errstate(over="ignore"):
            t = mapping.start + np.arange(N) / mapping.rate
        if not np.all(np.isfinite(t)):
            raise ModelFileError(f"data file {table.path}: t = start + k / rate overflows at "
                                 f"{N} samples; check [data] t's rate and start.")
    else:
        t = values.pop(0)
    _check_time(table, signals[0], t, layout.time_scale)
    used_names = (([f"rate={mapping.rate:g} Hz"] if signals[0] is None and mapping is not None
                   else []) + [s.column for s in used])
    u = np.column_stack(values[:m]) if m else np.zeros((N, 0))
    y = np.column_stack(values[m:])
    return DataRecord(t=np.ascontiguousarray(t, dtype=np.float64), u=u, y=y,
                      columns=tuple(used_names), source=str(table.path))


def _scaled(table: Table, signal: Signal, raw: FloatArray, *, output: bool,
            skip: bool) -> FloatArray:
    """``scale · raw + offset``, after checking raw and before returning the result: every t
    and input sample finite, outputs finite or (under skip) NaN, no overflow to inf and no
    underflow of a nonzero sample to zero or a subnormal number."""
    bad = ~np.isfinite(raw)
    if output and skip:
        bad &= ~np.isnan(raw)
    if bad.any():
        k = int(np.argmax(bad))
        hint = ("; a missing or NaN output is a dropout: pass --nan-policy skip "
                "(nan_policy='skip') to predict over it" if output and np.isnan(raw[k]) else
                "; the estimator needs every t and input sample (remove or fill the row)")
        what = " (a missing or NaN sample)" if np.isnan(raw[k]) else ""
        raise ModelFileError(f"data file {table.path}, {table.position(k)}, {table.kind} "
                             f"{signal.column!r}: {float(raw[k])} is not finite{what}{hint}.")
    if signal.scale == 1.0 and signal.offset == 0.0:
        return raw
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        value = signal.scale * raw + signal.offset
    ok = np.isfinite(raw)
    over = ok & ~np.isfinite(value)
    tiny = np.finfo(np.float64).tiny
    under = ok & (raw != 0) & (np.abs(value) < tiny) & (signal.offset == 0.0)
    for mask, what in ((over, "overflows float64"), (under, "underflows to zero or a "
                                                            "subnormal number")):
        if mask.any():
            k = int(np.argmax(mask))
            raise ModelFileError(
                f"data file {table.path}, {table.position(k)}, {table.kind} {signal.column!r}: "
                f"{signal.scale!r} × {float(raw[k])!r} + {signal.offset:g} {what}; check the "
                f"[data] table's scale for {signal.column!r} (it converts the file's unit to "
                f"the model's).")
    return value


def _check_time(table: Table, signal: Signal | None, t: FloatArray,
                time_scale: float | None) -> None:
    """t strictly increasing; a warning when its step looks like milliseconds."""
    steps = np.diff(t)
    name = signal.column if signal is not None else "t"
    if not np.all(steps > 0):
        k = int(np.argmax(~(steps > 0))) + 1
        raise ModelFileError(f"data file {table.path}, {table.position(k)}: t = "
                             f"{float(t[k])!r} does not increase (previous t = "
                             f"{float(t[k - 1])!r}, {table.kind} {name!r}); t must be strictly "
                             f"increasing.")
    step = float(np.median(steps))
    if time_scale is not None and step >= 1.0 and step >= time_scale / 2 \
            and np.all(t == np.round(t)):
        warnings.warn(
            f"data file {table.path}: t steps by {step:g} (whole numbers): fewer than two "
            f"samples per time constant of the model (its slowest is {time_scale:.3g} s). Is "
            f"t in milliseconds or another unit? The estimator reads t in seconds; convert it "
            f"with the model file's [data] table, e.g. "
            f"t = {{ column = \"{name}\", scale = 1e-3 }}.",
            ThetahatWarning, stacklevel=4)


def estimate_columns(layout: RecordLayout, *, refined: bool) -> tuple[str, ...]:
    """Header of an estimates CSV: t, x_hat_<x>..., phi_hat_<i>..., theta_hat_<θ>...,
    and x_hat_refined_<x>... when ``refined``.

    Parameters
    ----------
    layout : RecordLayout
        The names of x and θ, and k.
    refined : bool
        Include the second observer's columns.

    Returns
    -------
    tuple of str

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.io.datafile import estimate_columns
    >>> estimate_columns(loads_model(EXAMPLE_MODEL).layout, refined=False)
    ('t', 'x_hat_x1', 'x_hat_x2', 'phi_hat_1', 'theta_hat_theta')
    """
    layout = _check_layout(layout)
    cols = ["t"] + [f"x_hat_{s}" for s in layout.state_names]
    cols += [f"phi_hat_{i + 1}" for i in range(layout.k)]
    cols += [f"theta_hat_{s}" for s in layout.parameter_names]
    if refined:
        cols += [f"x_hat_refined_{s}" for s in layout.state_names]
    return tuple(cols)


def write_estimates(path: str | Path, result: EstimateResult, layout: RecordLayout) -> None:
    """Write an :class:`~thetahat.estimation.protocol.EstimateResult` as CSV or Parquet, by suffix (header
    :func:`estimate_columns`), atomically: a failed write leaves an old file unchanged.

    CSV numbers are written so that reading the file back gives the same floats (the shortest
    decimal that rounds to the value, by pyarrow's CSV writer when pyarrow is installed;
    17 significant digits otherwise: :func:`write_csv_table`); Parquet holds the float64
    values themselves.

    Parameters
    ----------
    path : str or Path
        Output file, ``.csv`` or ``.parquet`` (its folder is created).
    result : EstimateResult
    layout : RecordLayout
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
    cols = estimate_columns(layout, refined=result.x_hat_refined is not None)
    arrays = [np.asarray(part, dtype=np.float64)[:, j] for part in parts
              for j in range(part.shape[1])]
    columns = dict(zip(cols, arrays))
    if path.suffix.lower() == ".parquet":
        write_parquet_table(path, columns)
    else:
        write_csv_table(path, columns)


#: Rows formatted at once by :func:`write_csv_table` without pyarrow (a few MB of text).
CSV_CHUNK_ROWS = 1 << 16
#: Numbers (rows × columns) from which :func:`write_csv_table` imports pyarrow's CSV writer:
#: below, importing it (0.2–0.9 s) costs more than it saves (formatting at ~1 µs a number).
CSV_ARROW_MIN_VALUES = 500_000


def write_csv_table(path: str | Path, columns: dict[str, Any]) -> None:
    """Write named float columns as CSV with a header, atomically, so that reading the file
    back gives the same floats.

    With pyarrow installed (the ``data`` extra) and at least :data:`CSV_ARROW_MIN_VALUES`
    numbers (or pyarrow already imported), its CSV writer formats every number as the shortest
    decimal that rounds back to it (about 0.5 million rows of five columns a second);
    otherwise the rows are formatted with 17 significant digits (``%.17g``), a block of
    :data:`CSV_CHUNK_ROWS` rows at a time (CPython's float formatting bounds that path to about
    a quarter of pyarrow's speed).

    Parameters
    ----------
    path : str or Path
        The output file (its folder is created).
    columns : dict of str to array_like (N,)
        Column name → float values, all of one length N.

    Raises
    ------
    DimensionError
        The columns differ in length, or one is not one-dimensional.
    FileAccessError
        The file cannot be written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np
    >>> from thetahat.io.datafile import write_csv_table
    >>> out = pathlib.Path(tempfile.mkdtemp()) / "table.csv"
    >>> x = np.array([0.1, 1 / 3, -2e-300])
    >>> write_csv_table(out, {"k": np.arange(3.0), "x": x})
    >>> out.read_text().splitlines()[0]
    'k,x'
    >>> bool(np.array_equal(np.loadtxt(out, delimiter=",", skiprows=1)[:, 1], x))
    True
    """
    names = list(columns)
    arrays = [np.asarray(columns[c], dtype=np.float64) for c in names]
    lengths = {a.shape for a in arrays}
    if len(lengths) > 1 or any(a.ndim != 1 for a in arrays):
        raise DimensionError(f"write_csv_table: every column must be one-dimensional and of "
                             f"one length; got shapes "
                             f"{ {c: a.shape for c, a in zip(names, arrays)} }.")
    header = (",".join(names) + "\n").encode()
    pa_csv = _arrow_csv(len(arrays) * (arrays[0].size if arrays else 0))
    if pa_csv is None:
        with atomic_path(path) as tmp:
            _write_csv_rows(tmp, header, arrays)
        return
    import pyarrow as pa
    table = pa.table({c: np.ascontiguousarray(a) for c, a in zip(names, arrays)})
    options = pa_csv.WriteOptions(include_header=False)       # the header as given: unquoted
    with atomic_path(path) as tmp, pa.OSFile(str(tmp), "wb") as sink:
        sink.write(header)
        pa_csv.write_csv(table, sink, write_options=options)


def _arrow_csv(values: int) -> Any:
    """``pyarrow.csv`` when installed and worth importing for ``values`` numbers, else None."""
    if values < CSV_ARROW_MIN_VALUES and "pyarrow.csv" not in sys.modules:
        return None
    return arrow_csv()


def _write_csv_rows(tmp: Path, header: bytes, arrays: list[FloatArray]) -> None:
    """The CSV rows without pyarrow: ``%.17g``, :data:`CSV_CHUNK_ROWS` rows per format."""
    row = ",".join(["%.17g"] * len(arrays)) + "\n"
    table = np.column_stack(arrays) if arrays else np.zeros((0, 0))
    with open(tmp, "wb") as f:
        f.write(header)
        for start in range(0, table.shape[0], CSV_CHUNK_ROWS):
            block = table[start:start + CSV_CHUNK_ROWS]
            f.write(((row * block.shape[0]) % tuple(block.ravel().tolist())).encode())


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
