"""The ``[data]`` table: which variables or columns of a record are t, u and y, and in what units.

A real log rarely has columns named ``t``, ``u``, ``y`` in the model's units. The optional
``[data]`` table of a model file maps them::

    [data]
    t = "t"                                  # the variable or column holding the time (s)
    u = { column = "vir", scale = 35.15 }    # u = 35.15 · vir (N from V)
    y = "qm"                                 # y = qm

Each of ``t``, ``u``, ``y`` is a *signal*: a name (string), or a table with ``column`` (the
name) and optionally ``scale`` (default 1) and ``offset`` (default 0), giving
``value = scale · raw + offset``. With m > 1 inputs ``u`` is a list of m signals, in the order
of ``[perturbation] u`` (likewise ``y`` with r > 1 outputs); one signal may also be given as a
one-element list. ``t`` may instead be ``{ rate = 1000 }`` (Hz, optional ``start`` in s,
default 0) for records without a time vector: t_k = start + k / rate. A signal that
``[data]`` does not name keeps the default naming of :func:`thetahat.io.record.column_candidates`.

The mapping applies to CSV, Parquet and MATLAB (:mod:`thetahat.io.matfile`) files alike: a
mapped variable must exist, be real and numeric, be a vector (a MATLAB row or column vector,
or a column) with as many samples as the others, and be finite (an output may be NaN under
``nan_policy="skip"``); t must be strictly increasing. Each failure raises a
:class:`~thetahat.errors.ModelFileError` naming the variable and listing the ones the file has.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ModelFileError

from .record import MISSING_CELLS, DataRecord, RecordSpec, column_candidates

__all__ = ["DataMapping", "Signal", "parse_data_table", "read_mapped"]

FloatArray = NDArray[np.float64]
_SIGNAL_KEYS = ("column", "scale", "offset")
_RATE_KEYS = ("rate", "start")
_DATA_KEYS = ("t", "u", "y")


@dataclass(frozen=True, slots=True)
class Signal:
    """One mapped signal: ``value = scale · file[column] + offset``.

    Attributes
    ----------
    column : str
        The variable (MAT) or column (CSV, Parquet) name.
    scale, offset : float
    """

    column: str
    scale: float = 1.0
    offset: float = 0.0

    def apply(self, raw: FloatArray) -> FloatArray:
        """The signal in the model's units.

        Parameters
        ----------
        raw : ndarray, shape (N,)
            The file's values.

        Returns
        -------
        ndarray, shape (N,)

        Examples
        --------
        >>> import numpy as np
        >>> from thetahat.io.mapping import Signal
        >>> Signal("vir", scale=2.0, offset=1.0).apply(np.array([0.0, 1.0])).tolist()
        [1.0, 3.0]
        """
        if self.scale == 1.0 and self.offset == 0.0:
            return raw
        return self.scale * raw + self.offset


@dataclass(frozen=True, slots=True)
class DataMapping:
    """The ``[data]`` table, read: the signals for t, each input and each output.

    Attributes
    ----------
    t : Signal or None
        The time column, or None when ``rate`` is given or the default ``t`` is used.
    rate : float or None
        Sample rate (Hz) when the record has no time vector.
    start : float
        t of the first sample when ``rate`` is given (s).
    u, y : tuple of (Signal or None)
        One entry per input (m) and per output (r); None keeps the default column names.
    """

    t: Signal | None
    rate: float | None
    start: float
    u: tuple[Signal | None, ...]
    y: tuple[Signal | None, ...]


def _number(value: Any, where: str, fail: Callable[[str], ModelFileError], *,
            positive: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0):
        raise fail(f"{where}: expected a finite {'positive ' if positive else ''}number; got "
                   f"{value!r}.")
    return float(value)


def _signal(value: Any, where: str, fail: Callable[[str], ModelFileError]) -> Signal:
    if isinstance(value, str) and value:
        return Signal(value)
    if isinstance(value, Mapping):
        unknown = [k for k in value if k not in _SIGNAL_KEYS]
        if unknown:
            raise fail(f"{where}: unknown key(s) {unknown}; a signal has {list(_SIGNAL_KEYS)}.")
        column = value.get("column")
        if not isinstance(column, str) or not column:
            raise fail(f"{where}: expected column = \"NAME\" (the variable or column in the "
                       f"data file); got {column!r}.")
        scale = _number(value.get("scale", 1.0), f"{where} scale", fail)
        if scale == 0:
            raise fail(f"{where} scale: 0 would erase the signal; give a non-zero factor.")
        return Signal(column, scale, _number(value.get("offset", 0.0), f"{where} offset", fail))
    raise fail(f"{where}: expected a variable name such as \"qm\" or a table such as "
               f"{{ column = \"vir\", scale = 35.15, offset = 0.0 }}; got {value!r}.")


def _signals(value: Any, names: Sequence[str], key: str,
             fail: Callable[[str], ModelFileError]) -> tuple[Signal | None, ...]:
    if value is None:
        return (None,) * len(names)
    entries = value if isinstance(value, list) else [value]
    if len(entries) != len(names):
        raise fail(f"{key}: expected {len(names)} signal(s), one per name in [perturbation] "
                   f"{key} {list(names)}; got {len(entries)}.")
    return tuple(_signal(e, f"{key}[{i}] ({n})" if len(names) > 1 else key, fail)
                 for i, (e, n) in enumerate(zip(entries, names)))


def parse_data_table(table: Any, input_names: Sequence[str], output_names: Sequence[str],
                     fail: Callable[[str], ModelFileError]) -> DataMapping:
    """Read a ``[data]`` table (see the module docstring) into a :class:`DataMapping`.

    Parameters
    ----------
    table : mapping
        The table as parsed from TOML or JSON.
    input_names, output_names : sequence of str
        The model's input (m) and output (r) names, in order.
    fail : callable
        Builds the exception for a message (the model-file reader passes one that names the
        file and the table).

    Returns
    -------
    DataMapping

    Raises
    ------
    ModelFileError
        (Built by ``fail``.) Unknown key, wrong number of signals, a signal that is neither a
        name nor a table, a non-numeric or zero scale, ``rate`` not positive.

    Examples
    --------
    >>> from thetahat.errors import ModelFileError
    >>> from thetahat.io.mapping import parse_data_table
    >>> m = parse_data_table({"t": "t", "u": {"column": "vir", "scale": 35.15}, "y": "qm"},
    ...                      ["tau"], ["q"], ModelFileError)
    >>> m.u
    (Signal(column='vir', scale=35.15, offset=0.0),)
    >>> parse_data_table({"t": {"rate": 1000}}, ["tau"], ["q"], ModelFileError).rate
    1000.0
    """
    if not isinstance(table, Mapping):
        raise fail(f"expected a table with keys {list(_DATA_KEYS)}; got {table!r}.")
    unknown = [k for k in table if k not in _DATA_KEYS]
    if unknown:
        raise fail(f"unknown key(s) {unknown}; expected only {list(_DATA_KEYS)}.")
    t_value = table.get("t")
    t_signal, rate, start = None, None, 0.0
    if isinstance(t_value, Mapping) and "rate" in t_value:
        extra = [k for k in t_value if k not in _RATE_KEYS]
        if extra:
            raise fail(f"t: with rate, only {list(_RATE_KEYS)} are allowed; got {extra}.")
        rate = _number(t_value["rate"], "t rate (Hz)", fail, positive=True)
        start = _number(t_value.get("start", 0.0), "t start (s)", fail)
    elif t_value is not None:
        t_signal = _signal(t_value, "t", fail)
    return DataMapping(t=t_signal, rate=rate, start=start,
                       u=_signals(table.get("u"), input_names, "u", fail),
                       y=_signals(table.get("y"), output_names, "y", fail))


# ---------------------------------------------------------------------------------------------
# Columns of a file, by name
# ---------------------------------------------------------------------------------------------

class _Columns:
    """A file's variables or columns: their names, and each one as a checked float vector."""

    def __init__(self, path: Path, kind: str, raw: Mapping[str, Any],
                 fetch: Callable[[str], Any]) -> None:
        self.path, self.kind, self.raw, self._fetch = path, kind, raw, fetch

    def listing(self) -> str:
        if self.kind == "variable":
            from .matfile import describe_variables
            return describe_variables(dict(self.raw))
        return ", ".join(repr(n) for n in self.raw)

    def fail(self, name: str, message: str) -> ModelFileError:
        return ModelFileError(f"data file {self.path}, {self.kind} {name!r}: {message}; the "
                              f"file has {self.listing()}.")

    def vector(self, name: str) -> FloatArray:
        if name not in self.raw:
            return _raise(ModelFileError(f"data file {self.path}: no {self.kind} {name!r}; "
                                         f"the file has {self.listing()}."))
        value = self._fetch(name)
        arr = value if isinstance(value, np.ndarray) else np.asarray(value, dtype=object)
        if arr.dtype.kind == "c":
            raise self.fail(name, f"complex values ({arr.dtype}); the estimator needs real "
                                  f"signals (map the real part to a variable of its own)")
        if arr.dtype.kind not in "fiub":
            raise self.fail(name, f"not numeric (a {arr.dtype} array: text, a cell array or "
                                  f"a struct, or a ragged column)")
        if arr.ndim > 2 or (arr.ndim == 2 and min(arr.shape) > 1):
            raise self.fail(name, f"a {'×'.join(map(str, arr.shape))} array, not a vector; "
                                  f"save each signal as a row or column vector")
        return np.asarray(arr, dtype=np.float64).ravel()


def _raise(exc: ModelFileError) -> FloatArray:
    raise exc


def _mat_columns(path: Path) -> _Columns:
    from .matfile import read_mat_variables

    variables = read_mat_variables(path)
    return _Columns(path, "variable", variables, variables.__getitem__)


def _parquet_columns(path: Path) -> _Columns:
    try:
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise ModelFileError("reading Parquet needs pyarrow: pip install 'thetahat[data]'"
                             ) from exc
    try:
        table = pq.read_table(path)
    except (OSError, ValueError) as exc:       # pyarrow's ArrowInvalid derives from ValueError
        raise ModelFileError(f"cannot read data file {path}: {exc}") from exc

    def fetch(name: str) -> Any:
        try:
            return np.asarray(table.column(name).to_numpy(zero_copy_only=False))
        except (TypeError, ValueError) as exc:
            raise ModelFileError(f"data file {path}, column {name!r}: cannot be read as "
                                 f"numbers ({exc}).") from exc
    return _Columns(path, "column", {n: None for n in table.column_names}, fetch)


def _csv_columns(path: Path, wanted: Sequence[str]) -> _Columns:
    """The wanted columns of a CSV file (header row; blank lines skipped), read cell by cell
    with messages naming the line; empty or NaN-like cells read as NaN (checked later)."""

    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = (r for r in csv.reader(fh) if r and any(c.strip() for c in r))
            header = [h.strip() for h in next(rows, [])]
            if not header:
                raise ModelFileError(f"data file {path} is empty; expected a header row.")
            index = {n: header.index(n) for n in wanted if n in header}
            values: dict[str, list[float]] = {n: [] for n in index}
            for line, row in enumerate(rows, start=2):
                if len(row) != len(header):
                    raise ModelFileError(f"data file {path}, data row {line - 1}: {len(row)} "
                                         f"fields, but the header has {len(header)}.")
                for n, j in index.items():
                    cell = row[j].strip()
                    try:
                        values[n].append(math.nan if cell.lower() in MISSING_CELLS
                                         else float(cell))
                    except ValueError:
                        raise ModelFileError(f"data file {path}, data row {line - 1}, column "
                                             f"{n!r}: {cell!r} is not a number.") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ModelFileError(f"cannot read data file {path}: {exc}") from exc
    raw = {n: np.array(values[n]) if n in values else None for n in header}
    return _Columns(path, "column", raw, raw.__getitem__)


# ---------------------------------------------------------------------------------------------
# Reading a record through the mapping
# ---------------------------------------------------------------------------------------------

def _choose(columns: _Columns, signal: Signal | None, alternatives: list[str]) -> Signal:
    if signal is not None:
        return signal
    found = [a for a in alternatives if a in columns.raw]
    if not found:
        raise ModelFileError(f"data file {columns.path}: no {columns.kind} "
                             f"{' or '.join(repr(a) for a in alternatives)}; the file has "
                             f"{columns.listing()}. Name the ones to use in the model file's "
                             f"[data] table, e.g. y = \"qm\".")
    return Signal(found[0])


def read_mapped(path: str | Path, spec: RecordSpec, *, nan_policy: str = "raise") -> DataRecord:
    """Read a CSV, Parquet or MATLAB record through the model's ``[data]`` table.

    Without a ``[data]`` table (``spec.data is None``) the default names of
    :func:`~thetahat.io.record.column_candidates` are used (t, the model's input and output
    names, ``u1``…, ``y1``…).

    Parameters
    ----------
    path : str or Path
        A ``.mat`` (MATLAB v4–v7), ``.parquet`` (needs pyarrow) or CSV file.
    spec : RecordSpec
        The model; ``spec.data`` is its ``[data]`` table.
    nan_policy : {"raise", "skip"}
        ``"skip"`` keeps NaN outputs as dropouts; t and the inputs must always be finite.

    Returns
    -------
    DataRecord
        t, u and y in the model's units (scale and offset applied); ``columns`` names the
        variables used (``rate=... Hz`` for a generated t).

    Raises
    ------
    ModelFileError
        A mapped or default variable is missing, not numeric, complex, not a vector, of a
        different length than the others, or not finite; t is not strictly increasing; the
        file cannot be read (a MATLAB v7.3 file: see :func:`thetahat.io.matfile.read_mat_variables`).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np, scipy.io
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.io.mapping import read_mapped
    >>> spec = loads_model(EXAMPLE_MODEL + '[data]\\nu = {column = "volts", scale = 2.0}\\n'
    ...                    'y = {column = "pos_mm", scale = 1e-3}\\n')
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "log.mat"
    >>> scipy.io.savemat(path, {"t": [0.0, 0.01], "volts": [1.0, 2.0], "pos_mm": [5.0, 7.0]})
    >>> record = read_mapped(path, spec)
    >>> record.u.ravel().tolist(), record.y.ravel().tolist()
    ([2.0, 4.0], [0.005, 0.007])
    """
    from ..estimation.records import check_nan_policy

    check_nan_policy(nan_policy)
    path = Path(path)
    mapping = spec.data if spec.data is not None else DataMapping(
        t=None, rate=None, start=0.0, u=(None,) * spec.system.m, y=(None,) * spec.system.r)
    alternatives = column_candidates(spec)
    m = spec.system.m
    suffix = path.suffix.lower()
    if suffix == ".mat":
        columns = _mat_columns(path)
    elif suffix == ".parquet":
        columns = _parquet_columns(path)
    else:
        named = [s.column for s in (mapping.t, *mapping.u, *mapping.y) if s is not None]
        columns = _csv_columns(path, named + [a for alts in alternatives for a in alts])
    signals = [_choose(columns, s, alts)
               for s, alts in zip((*mapping.u, *mapping.y), alternatives[1:])]
    t_signal = None if mapping.rate is not None else _choose(columns, mapping.t,
                                                             alternatives[0])
    data = [(s, columns.vector(s.column)) for s in
            ([t_signal] if t_signal is not None else []) + signals]
    N = data[0][1].size
    for s, raw in data:
        if raw.size != N:
            raise columns.fail(s.column, f"{raw.size} samples, but {data[0][0].column!r} has "
                                         f"{N}; every mapped signal needs one value per sample")
    if N < 2:
        raise ModelFileError(f"data file {path}: {N} sample(s); the estimator needs at least 2.")
    for i, (s, raw) in enumerate(data):
        output = i - (t_signal is not None) >= m
        bad = ~np.isfinite(raw)
        if output and nan_policy == "skip":
            bad &= ~np.isnan(raw)
        if bad.any():
            k = int(np.argmax(bad))
            hint = (" (a NaN output is a dropout: pass --nan-policy skip)" if output else
                    "; the estimator needs every t and input sample")
            raise columns.fail(s.column, f"sample {k} is {raw[k]}, not finite{hint}")
    values = [s.apply(raw) for s, raw in data]
    t = (mapping.start + np.arange(N) / mapping.rate if mapping.rate is not None
         else values.pop(0))
    steps = np.diff(t)
    if not np.all(steps > 0):
        k = int(np.argmax(~(steps > 0))) + 1
        name = t_signal.column if t_signal is not None else "t"
        raise ModelFileError(f"data file {path}, {columns.kind} {name!r}: t does not increase "
                             f"at sample {k} (t = {t[k]!r} after {t[k - 1]!r}); t must be "
                             f"strictly increasing.")
    used = tuple([f"rate={mapping.rate:g} Hz"] if t_signal is None else []) + tuple(
        s.column for s, _ in data)
    u = np.column_stack(values[:m]) if m else np.zeros((N, 0))
    y = np.column_stack(values[m:])
    return DataRecord(t=np.ascontiguousarray(t, dtype=np.float64), u=u, y=y, columns=used,
                      source=str(path))
