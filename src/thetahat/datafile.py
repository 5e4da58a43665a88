"""Data files for ``thetahat estimate``: read t, u, y from CSV and write the estimates as CSV."""

from __future__ import annotations

import csv
import math
import os
import warnings
from array import array
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import ModelFileError
from .estimation.observer import ObserverResult
from .estimation.records import check_nan_policy
from .modelfile import ModelSpec

__all__ = ["DataRecord", "column_candidates", "read_data", "check_writable", "estimate_columns",
           "write_estimates"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, repr=False)
class DataRecord:
    """Samples read by :func:`read_data`.

    Attributes
    ----------
    t : ndarray, shape (N,)
    u : ndarray, shape (N, m)
    y : ndarray, shape (N, r)
    columns : tuple of str
        The CSV columns used, in the order t, u..., y....
    source : str
    """

    t: FloatArray
    u: FloatArray
    y: FloatArray
    columns: tuple[str, ...]
    source: str

    def __repr__(self) -> str:
        return (f"DataRecord(N={self.t.size}, columns={list(self.columns)}, "
                f"source={self.source!r})")


def _aliases(names: tuple[str, ...], letter: str) -> list[list[str]]:
    out = []
    for i, name in enumerate(names):
        alts = [name, f"{letter}{i + 1}"] + ([letter] if len(names) == 1 else [])
        out.append(list(dict.fromkeys(alts)))
    return out


#: Cells read as a missing output sample under ``nan_policy="skip"`` (besides NaN itself).
MISSING_CELLS = ("", "nan", "na", "n/a", "null", "none")


def column_candidates(spec: ModelSpec) -> list[list[str]]:
    """The accepted names of each data column: ``[["t"], [u names...]..., [y names...]...]``.

    Each input may be named as in the model, ``u1``, ``u2``, … or ``u`` when m = 1; each output
    likewise with ``y``. The first name found in a header is used.

    Parameters
    ----------
    spec : ModelSpec
        The model; its ``input_names`` and ``output_names`` give the column names.

    Returns
    -------
    list of list of str
        1 + m + r lists, in the order t, u₁ … u_m, y₁ … y_r: the accepted names of each
        column, the model's name first.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.datafile import column_candidates
    >>> column_candidates(loads_model(EXAMPLE_MODEL))
    [['t'], ['u', 'u1'], ['y', 'y1']]
    """
    return [["t"]] + _aliases(spec.input_names, "u") + _aliases(spec.output_names, "y")


def read_data(path: str | Path, spec: ModelSpec, *, nan_policy: str = "raise") -> DataRecord:
    """Read a CSV record (header row; columns t, inputs, outputs) for a model's estimator.

    MATLAB (``.mat``) and Parquet files, and any file when the model has a ``[data]`` table,
    are read by :func:`thetahat.data_mapping.read_mapped` instead.

    The file is read as UTF-8 (a byte-order mark, as Excel writes, is accepted), with any line
    ending (LF, CRLF), row by row into float64 columns: memory is O(N) in the samples only.

    Parameters
    ----------
    path : str or Path
        CSV file with a header. Required columns: ``t``; each input under its name in the
        model (``[perturbation] u``) or ``u1``, ``u2``, … (``u`` when m = 1); each output
        under its name or ``y1``, … (``y`` when r = 1). Order is free; other columns are
        ignored; blank lines are skipped.
    spec : ModelSpec
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
        The file cannot be read, a column is missing, a value is not a number or is NaN or
        inf (the message gives the line and the column), a row has the wrong number of
        fields, or t is not strictly increasing.
    OptionError
        Unknown ``nan_policy``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.datafile import read_data
    >>> spec = loads_model(EXAMPLE_MODEL)
    >>> csv_path = pathlib.Path(tempfile.mkdtemp()) / "data.csv"
    >>> _ = csv_path.write_text("t,u,y\\n0,0,0.1\\n0.01,0.5,0.2\\n")
    >>> read_data(csv_path, spec).y.ravel().tolist()
    [0.1, 0.2]
    >>> _ = csv_path.write_text("t,u,y\\r\\n0,0,0.1\\r\\n0.01,0.5,\\r\\n")   # a dropout
    >>> read_data(csv_path, spec, nan_policy="skip").y.ravel().tolist()
    [0.1, nan]
    """
    check_nan_policy(nan_policy)
    path = Path(path)
    if spec.data is not None or path.suffix.lower() in (".mat", ".parquet"):
        from .data_mapping import read_mapped          # [data] table, MATLAB and Parquet files
        return read_mapped(path, spec, nan_policy=nan_policy)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            return _read_rows(path, csv.reader(fh), spec, nan_policy)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ModelFileError(f"cannot read data file {path}: {exc}") from exc


def _fast_columns(path: Path, header_line: int, width: int,
                  index: list[int]) -> NDArray[np.float64] | None:
    """The selected columns by numpy's C reader, or None when the file needs the careful
    row-by-row reader (quoted or non-numeric cells, NaN, ragged rows, t not increasing), which
    then gives the message with the line and the column."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = np.loadtxt(path, delimiter=",", skiprows=header_line, dtype=np.float64,
                              ndmin=2, encoding="utf-8-sig", comments=None)
    except (ValueError, OSError, UnicodeDecodeError):
        return None
    if data.shape[0] == 0 or data.shape[1] != width:
        return None
    cols = data[:, index]
    if not np.isfinite(cols).all() or not np.all(np.diff(cols[:, 0]) > 0):
        return None
    return np.ascontiguousarray(cols)


def _read_rows(path: Path, reader: Any, spec: ModelSpec, nan_policy: str) -> DataRecord:
    header_line, header = 0, None
    for line, row in enumerate(reader, start=1):
        if row and any(c.strip() for c in row):
            header_line, header = line, [h.strip() for h in row]
            break
    if header is None:
        raise ModelFileError(f"data file {path} is empty; expected a header row such as "
                             f"t,{','.join(spec.input_names + spec.output_names)}.")
    wanted = column_candidates(spec)
    index = []
    for alts in wanted:
        found = [h for h in alts if h in header]
        if not found:
            raise ModelFileError(
                f"data file {path}: missing column {' or '.join(repr(a) for a in alts)} in the "
                f"header (line {header_line}: {','.join(header)}); expected t, then the "
                f"inputs {list(spec.input_names)} and the outputs {list(spec.output_names)}.")
        index.append(header.index(found[0]))
    m = spec.system.m
    cols = tuple(header[j] for j in index)
    fast = _fast_columns(path, header_line, len(header), index)
    if fast is not None:
        return DataRecord(t=fast[:, 0].copy(), u=fast[:, 1:1 + m].copy(),
                          y=fast[:, 1 + m:].copy(), columns=cols, source=str(path))
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


def _cell(path: Path, line: int, column: str, text: str, *, output: bool,
          skip: bool) -> float:
    cell = text.strip()
    if output and skip and cell.lower() in MISSING_CELLS:
        return math.nan
    try:
        value = float(cell)
    except ValueError:
        hint = (" (an empty output cell is a dropout: pass --nan-policy skip)"
                if output and cell == "" else "")
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


def check_writable(path: str | Path) -> Path:
    """Check, before any work, that an output file can be written (without creating it).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Path

    Raises
    ------
    ModelFileError
        ``path`` is a directory, an existing file that is not writable, or lies in a folder
        that cannot be created or written.

    Examples
    --------
    >>> import tempfile
    >>> from thetahat.datafile import check_writable
    >>> check_writable(tempfile.mkdtemp())
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: cannot write ...: it is a directory; give a file name...
    """
    path = Path(path)
    if path.is_dir():
        raise ModelFileError(f"cannot write {path}: it is a directory; give a file name, e.g. "
                             f"{path / 'estimates.csv'}.")
    if path.exists():
        if not os.access(path, os.W_OK):
            raise ModelFileError(f"cannot write {path}: the file is not writable.")
        return path
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise ModelFileError(f"cannot write {path}: {folder} is not a writable folder; choose "
                             f"another output path (-o).")
    return path


def estimate_columns(spec: ModelSpec, *, refined: bool) -> tuple[str, ...]:
    """Header of an estimates CSV: t, x_hat_<x>..., phi_hat_<i>..., theta_hat_<θ>...,
    and x_hat_refined_<x>... when ``refined``.

    Parameters
    ----------
    spec : ModelSpec
    refined : bool
        Include the second observer's columns.

    Returns
    -------
    tuple of str

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.datafile import estimate_columns
    >>> estimate_columns(loads_model(EXAMPLE_MODEL), refined=False)
    ('t', 'x_hat_x1', 'x_hat_x2', 'phi_hat_1', 'theta_hat_theta')
    """
    cols = ["t"] + [f"x_hat_{s}" for s in spec.state_names]
    cols += [f"phi_hat_{i + 1}" for i in range(spec.system.k)]
    cols += [f"theta_hat_{s}" for s in spec.parameter_names]
    if refined:
        cols += [f"x_hat_refined_{s}" for s in spec.state_names]
    return tuple(cols)


def write_estimates(path: str | Path, result: ObserverResult, spec: ModelSpec) -> None:
    """Write an :class:`ObserverResult` as CSV (header :func:`estimate_columns`).

    Numbers are written with 17 significant digits, so reading the file back gives the
    same floats.

    Parameters
    ----------
    path : str or Path
        Output file (its folder is created).
    result : ObserverResult
    spec : ModelSpec
        For the column names.

    Raises
    ------
    ModelFileError
        The file cannot be written.
    """
    parts = [result.t[:, None], result.x_hat, result.phi_hat, result.theta_hat]
    if result.x_hat_refined is not None:
        parts.append(result.x_hat_refined)
    cols = estimate_columns(spec, refined=result.x_hat_refined is not None)
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(path, np.hstack(parts), delimiter=",", header=",".join(cols), comments="",
                   fmt="%.17g")
    except OSError as exc:
        raise ModelFileError(f"cannot write estimates to {path}: {exc}") from exc
