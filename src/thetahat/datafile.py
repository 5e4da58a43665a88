"""Data files for ``thetahat estimate``: read t, u, y from CSV and write the estimates as CSV."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .errors import ModelFileError
from .estimation.observer import ObserverResult
from .modelfile import ModelSpec

__all__ = ["DataRecord", "column_candidates", "read_data", "estimate_columns", "write_estimates"]

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


def column_candidates(spec: ModelSpec) -> list[list[str]]:
    """The accepted names of each data column: ``[["t"], [u names...]..., [y names...]...]``.

    Each input may be named as in the model, ``u1``, ``u2``, … or ``u`` when m = 1; each output
    likewise with ``y``. The first name found in a header is used.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.datafile import column_candidates
    >>> column_candidates(loads_model(EXAMPLE_MODEL))
    [['t'], ['u', 'u1'], ['y', 'y1']]
    """
    return [["t"]] + _aliases(spec.input_names, "u") + _aliases(spec.output_names, "y")


def read_data(path: str | Path, spec: ModelSpec) -> DataRecord:
    """Read a CSV record (header row; columns t, inputs, outputs) for a model's estimator.

    Parameters
    ----------
    path : str or Path
        CSV file with a header. Required columns: ``t``; each input under its name in the
        model (``[perturbation] u``) or ``u1``, ``u2``, … (``u`` when m = 1); each output
        under its name or ``y1``, … (``y`` when r = 1). Order is free; other columns are
        ignored; blank lines are skipped.
    spec : ModelSpec

    Returns
    -------
    DataRecord

    Raises
    ------
    ModelFileError
        The file cannot be read, a column is missing, a value is not a number or is NaN or
        inf (the message gives the line and the column), a row has the wrong number of
        fields, or t is not strictly increasing.

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
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = [(i + 1, row) for i, row in enumerate(csv.reader(fh))]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ModelFileError(f"cannot read data file {path}: {exc}") from exc
    rows = [(line, row) for line, row in rows if row and any(c.strip() for c in row)]
    if not rows:
        raise ModelFileError(f"data file {path} is empty; expected a header row such as "
                             f"t,{','.join(spec.input_names + spec.output_names)}.")
    header_line, header = rows[0]
    header = [h.strip() for h in header]
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
    if not rows[1:]:
        raise ModelFileError(f"data file {path} has a header but no data rows.")
    data = np.empty((len(rows) - 1, len(index)))
    for r, (line, row) in enumerate(rows[1:]):
        if len(row) != len(header):
            raise ModelFileError(f"data file {path}, line {line}: {len(row)} fields, but the "
                                 f"header has {len(header)}.")
        for c, j in enumerate(index):
            cell = row[j].strip()
            try:
                value = float(cell)
            except ValueError:
                raise ModelFileError(f"data file {path}, line {line}, column "
                                     f"{header[j]!r}: {cell!r} is not a number.") from None
            if not math.isfinite(value):
                raise ModelFileError(f"data file {path}, line {line}, column "
                                     f"{header[j]!r}: {cell} is not finite; the estimator "
                                     f"needs every sample (remove or fill the row).")
            data[r, c] = value
    t = data[:, 0]
    steps = np.diff(t)
    if steps.size and not np.all(steps > 0):
        r = int(np.argmax(steps <= 0)) + 1
        raise ModelFileError(f"data file {path}, line {rows[1 + r][0]}: t = {float(t[r])!r} does not "
                             f"increase (previous t = {float(t[r - 1])!r}); t must be strictly "
                             f"increasing.")
    m = spec.system.m
    cols = tuple(header[j] for j in index)
    return DataRecord(t=t, u=data[:, 1:1 + m], y=data[:, 1 + m:], columns=cols,
                      source=str(path))


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
