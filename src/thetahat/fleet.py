"""Fleet estimation: one model file, many logged records (CSV or Parquet), one row per record.

A drive maker estimates the friction of every motor in a fleet from logged data. The records
are independent, so :func:`estimate_many` hands them to :func:`thetahat.engine.run_keyed` in
chunks (in this process, or on a Dask cluster); within a chunk, records with the same sampling
instants run together through :func:`~thetahat.estimation.batch_run.run_batch`. A record that
cannot be read or estimated gets its reason in ``status`` and never stops the others.

Per record (a row of :class:`FleetResult`):

``file``, ``status``
    The path, and ``"ok"`` or the failure (``"ModelFileError: ... line 7 ..."``).
``n_samples``, ``t_end``
    Length of the record.
``theta_hat_<name>``
    θ̂ at the end of the record.
``theta_hat_<name>_se``
    Standard error of θ̂ over the final fifth of the record by batch means (10 batches):
    how much θ̂ still moves, not a Cramér–Rao bound.
``t_settle_<name>``
    First time after which θ̂ stays within 1 % of its final value — of |θ̂(t_end)|, but at
    least of Θ's half-width, so that a θ near 0 has a meaningful band.
``warnings``
    Warnings raised while estimating that record, ``"; "``-separated.
"""

from __future__ import annotations

import functools
import glob
import math
import warnings
from collections.abc import Hashable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from .datafile import DataRecord, column_candidates, read_data
from .engine import run_keyed
from .errors import MissingExtraError, ModelFileError, OptionError
from .estimation.batch_run import run_batch
from .estimation.records import check_nan_policy
from .model.paramset import Box
from .modelfile import (ESTIMATION_METHODS, ModelSpec, build_observer, load_model, loads_model,
                        run_estimator)
from .spec import Hold
from .studies.metrics import time_to_within

__all__ = ["DATA_SUFFIXES", "FleetResult", "SETTLE_BAND", "estimate_many", "fleet_files",
           "read_parquet"]

FloatArray = NDArray[np.float64]

#: Record formats a fleet may hold.
DATA_SUFFIXES = (".csv", ".parquet")
#: Relative band of the settling time (1 %, the accuracy the examples aim for).
SETTLE_BAND = 0.01
#: Fraction of the record at its end over which the standard error is computed.
TAIL_FRACTION = 0.2
#: Batches of the batch-means standard error.
SE_BATCHES = 10


@dataclass(frozen=True, slots=True, eq=False)
class FleetResult:
    """One row per record, in the order of the files.

    Attributes
    ----------
    columns : tuple of str
        ``file, status, n_samples, t_end, theta_hat_<p>..., theta_hat_<p>_se...,
        t_settle_<p>..., warnings``.
    rows : tuple of dict
        One mapping column → value per record (NaN where a record failed).
    model : str
        The model file.
    """

    columns: tuple[str, ...]
    rows: tuple[dict[str, Any], ...]
    model: str

    @property
    def n_ok(self) -> int:
        """Records estimated."""
        return sum(r["status"] == "ok" for r in self.rows)

    @property
    def failed(self) -> dict[str, str]:
        """``{file: reason}`` of the records that failed."""
        return {r["file"]: r["status"] for r in self.rows if r["status"] != "ok"}

    def theta_hat(self) -> FloatArray:
        """Final θ̂ of every record, shape (n_files, p) (NaN rows for failures)."""
        names = [c for c in self.columns if c.startswith("theta_hat_") and not c.endswith("_se")]
        return np.array([[r[c] for c in names] for r in self.rows], dtype=np.float64)

    def to_dataframe(self) -> Any:
        """The rows as a :class:`pandas.DataFrame` (needs pandas)."""
        try:
            import pandas as pd
        except ImportError as exc:
            raise MissingExtraError("FleetResult.to_dataframe needs pandas: pip install "
                              "'thetahat[data]'") from exc
        return pd.DataFrame(list(self.rows), columns=list(self.columns))

    def write(self, path: str | Path) -> Path:
        """Write the table as CSV or Parquet (by suffix; Parquet needs pyarrow).

        Raises
        ------
        ModelFileError
            Unknown suffix, or the file cannot be written.
        """
        path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            if path.suffix == ".csv":
                _write_csv(path, self)
            elif path.suffix == ".parquet":
                _write_parquet(path, self)
            else:
                raise ModelFileError(f"results file {path}: the suffix must be .csv or "
                                     f".parquet; got {path.suffix!r}.")
        except OSError as exc:
            raise ModelFileError(f"cannot write results to {path}: {exc}") from exc
        return path

    def __repr__(self) -> str:
        return (f"FleetResult(files={len(self.rows)}, ok={self.n_ok}, "
                f"failed={len(self.rows) - self.n_ok}, model={self.model!r})")


def _write_csv(path: Path, result: FleetResult) -> None:
    import csv

    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(result.columns)
        for r in result.rows:
            w.writerow([repr(v) if isinstance(v, float) else v
                        for v in (r[c] for c in result.columns)])


def _write_parquet(path: Path, result: FleetResult) -> None:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise MissingExtraError("writing Parquet needs pyarrow: pip install 'thetahat[data]', "
                             "or write .csv") from exc
    table = pa.table({c: [r[c] for r in result.rows] for c in result.columns})
    pq.write_table(table, path)


def fleet_files(data: str | Path | Iterable[str | Path]) -> list[Path]:
    """The records of a fleet: a directory (its .csv and .parquet files), a glob pattern, or
    a list of paths; sorted by name (lists keep their order).

    Parameters
    ----------
    data : str, Path or iterable of str or Path
        A directory (its files with a suffix in :data:`DATA_SUFFIXES`, not recursive), a glob
        pattern (``**`` recurses; only files match), any other path as one file, or a list
        of paths (taken as given, not checked).

    Returns
    -------
    list of Path
        The record files.

    Raises
    ------
    ModelFileError
        Nothing matches.
    """
    if isinstance(data, (str, Path)):
        p = Path(data)
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in DATA_SUFFIXES)
        elif glob.has_magic(str(data)):
            files = sorted(Path(f) for f in glob.glob(str(data), recursive=True)
                           if Path(f).is_file())
        else:
            files = [p]
    else:
        files = [Path(f) for f in data]
    if not files:
        raise ModelFileError(f"no data files in {data}: expected a directory with .csv or "
                             f".parquet files, or a glob such as 'logs/*.csv'.")
    return files


def read_parquet(path: str | Path, spec: ModelSpec, *, nan_policy: str = "raise") -> DataRecord:
    """Read a Parquet record with the columns of :func:`~thetahat.datafile.read_data`.

    Parameters
    ----------
    path : str or Path
        Parquet file (needs pyarrow). Required columns as for
        :func:`~thetahat.datafile.read_data` (see
        :func:`~thetahat.datafile.column_candidates`); other columns are ignored. Every
        value must be finite (outputs may be NaN under ``nan_policy="skip"``), and t
        strictly increasing over at least two rows.
    spec : ModelSpec
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
        pyarrow missing, unreadable file, a missing column, a non-finite value, or t not
        strictly increasing.
    """
    try:
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise ModelFileError("reading Parquet needs pyarrow: pip install 'thetahat[data]'"
                             ) from exc
    path = Path(path)
    try:
        table = pq.read_table(path)
    except (OSError, ValueError) as exc:       # pyarrow's ArrowInvalid derives from ValueError
        raise ModelFileError(f"cannot read data file {path}: {exc}") from exc
    names = table.column_names
    cols = []
    for alts in column_candidates(spec):
        found = [a for a in alts if a in names]
        if not found:
            raise ModelFileError(f"data file {path}: missing column "
                                 f"{' or '.join(repr(a) for a in alts)}; it has {names}.")
        cols.append(found[0])
    try:
        data = np.column_stack([np.asarray(table.column(c).to_numpy(), dtype=np.float64)
                                for c in cols])
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"data file {path}: a column is not numeric: {exc}") from exc
    check_nan_policy(nan_policy)
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
    return DataRecord(t=data[:, 0], u=data[:, 1:1 + m], y=data[:, 1 + m:], columns=tuple(cols),
                      source=str(path))


def _read(path: str, spec: ModelSpec, nan_policy: str) -> DataRecord:
    if path.lower().endswith(".parquet") and spec.data is None:
        return read_parquet(path, spec, nan_policy=nan_policy)
    return read_data(path, spec, nan_policy=nan_policy)


@functools.lru_cache(maxsize=4)
def _spec(text: str, syntax: str, source: str) -> ModelSpec:
    return loads_model(text, syntax=syntax, source=source)


def _summary(spec: ModelSpec, t: FloatArray, theta_hat: FloatArray) -> dict[str, Any]:
    row: dict[str, Any] = {"n_samples": int(t.size), "t_end": float(t[-1])}
    box = cast(Box, spec.system.parameter_set)        # a model file's Θ is always a Box
    half_width = (np.asarray(box.upper) - np.asarray(box.lower)) / 2
    N = t.size
    tail = theta_hat[N - max(SE_BATCHES, int(TAIL_FRACTION * N)):]
    means = np.array([b.mean(axis=0) for b in np.array_split(tail, SE_BATCHES)])
    se = means.std(axis=0, ddof=1) / math.sqrt(SE_BATCHES)
    for i, name in enumerate(spec.parameter_names):
        final = float(theta_hat[-1, i])
        row[f"theta_hat_{name}"] = final
        row[f"theta_hat_{name}_se"] = float(se[i])
        scale = max(abs(final), half_width[i])
        row[f"t_settle_{name}"] = time_to_within(t, theta_hat[:, i] - final + scale, scale,
                                                 SETTLE_BAND)
    return row


def _failure(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".replace("\n", " ")


def _estimate_chunk(paths: list[str], *, model: tuple[str, str, str], hold: str,
                    method: str, nan_policy: str) -> list[tuple[Hashable, dict[str, Any]]]:
    """One task: read the records; the paper's observer runs records with equal sampling
    instants as one batch, the two-stage methods run record by record."""
    spec = _spec(*model)
    out: dict[str, dict[str, Any]] = {}
    records: dict[str, tuple[DataRecord, list[str]]] = {}
    for p in paths:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                records[p] = (_read(p, spec, nan_policy), [str(w.message) for w in caught])
            except Exception as exc:       # a bad file is reported, never stops the others
                out[p] = {"status": _failure(exc), "warnings": ""}
    if method != "paper":
        for p in records:
            _estimate_one(spec, p, records[p], hold, method, nan_policy, out)
        return [(p, out[p]) for p in paths]
    groups: dict[bytes, list[str]] = {}
    for p, (rec, _) in records.items():
        groups.setdefault(rec.t.tobytes(), []).append(p)
    for members in groups.values():
        _estimate_group(spec, members, records, hold, nan_policy, out)
    return [(p, out[p]) for p in paths]


def _estimate_one(spec: ModelSpec, path: str, record: tuple[DataRecord, list[str]], hold: str,
                  method: str, nan_policy: str, out: dict[str, dict[str, Any]]) -> None:
    rec, read_warnings = record
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            res = run_estimator(spec, rec.t, rec.u, rec.y, hold=cast(Hold, hold),
                                nan_policy=nan_policy, method=method)
        except Exception as exc:           # a record that fails is reported, never stops others
            out[path] = {"status": _failure(exc), "warnings": "; ".join(read_warnings)}
            return
    row = {"status": "ok", **_summary(spec, rec.t, np.asarray(res.theta_hat))}
    row["warnings"] = "; ".join(dict.fromkeys(read_warnings + [str(w.message) for w in caught]))
    out[path] = row


def _estimate_group(spec: ModelSpec, members: list[str],
                    records: dict[str, tuple[DataRecord, list[str]]], hold: str,
                    nan_policy: str, out: dict[str, dict[str, Any]]) -> None:
    t = records[members[0]][0].t
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            obs = build_observer(spec, nan_policy=nan_policy)
            s0 = obs.init(x_hat0=spec.estimator.x_hat0, theta_hat0=spec.estimator.theta_hat0)
            res = run_batch(obs, t, np.stack([records[p][0].u for p in members]),
                            np.stack([records[p][0].y for p in members]), hold=hold,
                            state0=s0)
        except Exception as exc:
            if len(members) > 1:           # find the record at fault: run them one by one
                for p in members:
                    _estimate_group(spec, [p], records, hold, nan_policy, out)
                return
            out[members[0]] = {"status": _failure(exc),
                               "warnings": "; ".join(records[members[0]][1])}
            return
    batch_warnings = [str(w.message) for w in caught]
    for i, p in enumerate(members):
        row = {"status": "ok", **_summary(spec, t, np.asarray(res.theta_hat[i]))}
        row["warnings"] = "; ".join(dict.fromkeys(records[p][1] + batch_warnings))
        out[p] = row


def estimate_many(model: str | Path, data: str | Path | Iterable[str | Path], *,
                  scheduler: Any = None, chunk_size: int | None = None, hold: str = "zoh",
                  method: str | None = None, nan_policy: str = "raise",
                  progress: bool = True) -> FleetResult:
    """Run a model file's estimator on every record of a fleet; one row per record.

    Parameters
    ----------
    model : str or Path
        Model file (TOML or JSON), as for ``thetahat estimate``.
    data : str, Path or iterable of paths
        A directory (its .csv and .parquet files), a glob (``"logs/**/*.parquet"``) or a
        list of files. Columns as for :func:`~thetahat.datafile.read_data`.
    scheduler : None, str or dask.distributed.Client
        Where to run (:func:`thetahat.engine.run_keyed`): None here, or a Dask cluster.
    chunk_size : int, optional
        Records per task (default: about 16 tasks). Results do not depend on it beyond
        rounding (records that share their sampling instants run as one batch).
    hold : {"zoh", "foh"}
        Sample hold between samples.
    method : {"paper", "guarded", "mle"}, optional
        The estimator (default: the file's ``[estimator] method``, else ``"paper"``), as for
        :func:`~thetahat.modelfile.assembly.run_estimator`. The paper's observer runs the
        records that share their sampling instants as one batch; the two-stage methods run
        record by record.
    nan_policy : {"raise", "skip"}
        ``"skip"``: a NaN output sample is a dropout the estimator predicts over;
        ``"raise"``: such a record fails (its row says where).
    progress : bool
        Progress bar (tqdm) on long runs.

    Returns
    -------
    FleetResult

    Raises
    ------
    ModelFileError
        The model file is bad or no data file matches (a bad *data* file is a row, not an
        error).
    OptionError
        Unknown ``method`` or ``nan_policy``.
    EngineError
        The scheduler cannot be reached.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np
    >>> from thetahat.fleet import estimate_many
    >>> from thetahat.modelfile import EXAMPLE_MODEL
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "model.toml").write_text(EXAMPLE_MODEL)
    >>> t = np.arange(0.0, 2.0, 0.01)
    >>> np.savetxt(d / "a.csv", np.c_[t, np.sin(t), 0 * t], delimiter=",", header="t,u,y",
    ...            comments="")
    >>> _ = (d / "b.csv").write_text("t,u,y\\n0,1,oops\\n")
    >>> res = estimate_many(d / "model.toml", [d / "a.csv", d / "b.csv"])
    >>> res.n_ok, res.failed[str(d / "b.csv")].split(":")[0]
    (1, 'ModelFileError')
    """
    source = Path(model)
    try:
        text = source.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"cannot read model file {source}: {exc}") from exc
    syntax = "json" if source.suffix.lower() == ".json" else "toml"
    spec = load_model(source)                      # errors in the model stop here, once
    how = spec.estimator.method if method is None else method
    if how not in ESTIMATION_METHODS:
        raise OptionError(f"method must be one of {list(ESTIMATION_METHODS)}; got {how!r}.")
    check_nan_policy(nan_policy)
    files = [str(f) for f in fleet_files(data)]
    task = functools.partial(_estimate_chunk, model=(text, syntax, str(source)), hold=hold,
                             method=how, nan_policy=nan_policy)
    results = run_keyed(task, files, files, scheduler=scheduler, chunk_size=chunk_size,
                        label="estimate", progress=progress)
    names = spec.parameter_names
    columns = (("file", "status", "n_samples", "t_end")
               + tuple(f"theta_hat_{n}" for n in names)
               + tuple(f"theta_hat_{n}_se" for n in names)
               + tuple(f"t_settle_{n}" for n in names) + ("warnings",))
    nan_row = {c: float("nan") for c in columns}
    rows = tuple({**nan_row, "n_samples": 0, **results[f], "file": f} for f in files)
    return FleetResult(columns=columns, rows=rows, model=str(source))
