"""Fleet estimation: one model file, many logged records (CSV or Parquet), one row per record.

A drive maker estimates the friction of every motor in a fleet from logged data. The records
are independent, so :func:`estimate_many` hands them to :func:`thetahat.engine.run_keyed` in
chunks (in this process, or on a Dask cluster); within a chunk, records with the same sampling
instants run on the fastest back end installed: one by one on the C printed from the
formulas (a C compiler) or numba's kernel (a group of at least ``COMPILE_MIN_SAMPLES``
samples), else together through :func:`~thetahat.estimation.observer.batch_run.run_batch` (NumPy; the
results agree to rounding, 1e-9 relative). A record that
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

import fnmatch
import functools
import glob
import math
import os
import re
import warnings
from collections.abc import Hashable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import limits
from .io.datafile import DATA_SUFFIXES, read_data, write_parquet_table
from .io.record import DataRecord
from .io.tables import CSV_DELIMITERS
from .engine import run_keyed
from .errors import ArgumentTypeError, MissingExtraError, ModelFileError, OptionError
from .estimation.observer.batch_run import run_batch
from .estimation.records import check_nan_policy
from .estimation.statistical.stage2_set import theta_bounds
from .modelfile import (ESTIMATION_METHODS, ModelSpec, build_observer, loads_model,
                        run_estimator, split_hold, start_x_hat)
from .safe_io import atomic_path, check_writable, read_text, same_file
from .studies.information import explain_nonfinite, stuck_parameters
from .studies.metrics import time_to_within

__all__ = ["DATA_SUFFIXES", "FleetResult", "RESULT_SUFFIXES", "SETTLE_BAND", "check_output",
           "estimate_many", "fleet_files", "is_glob"]

FloatArray = NDArray[np.float64]

#: Formats of the results table (:meth:`FleetResult.write`).
RESULT_SUFFIXES = (".csv", ".parquet")
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
        """Write the table as CSV or Parquet (by suffix; Parquet needs pyarrow), atomically.

        Parameters
        ----------
        path : str or Path
            ``.csv`` or ``.parquet``; it may not be the model file or one of the records.

        Returns
        -------
        Path

        Raises
        ------
        ModelFileError
            Unknown suffix, or the path is an input of the run.
        FileAccessError
            The file cannot be written (an old file there is left unchanged).
        """
        path = check_output(path, self.model, [r["file"] for r in self.rows])
        if path.suffix.lower() == ".parquet":
            write_parquet_table(path, {c: [_printable(r[c]) for r in self.rows]
                                       for c in self.columns})
        else:
            with atomic_path(path) as tmp:
                _write_csv(tmp, self)
        return path

    def __repr__(self) -> str:
        return (f"FleetResult(files={len(self.rows)}, ok={self.n_ok}, "
                f"failed={len(self.rows) - self.n_ok}, model={self.model!r})")


def _printable(value: Any) -> Any:
    """A string as valid UTF-8: the bytes of a file name that is not UTF-8 (which Python holds
    as surrogate escapes) written as ``\\xNN`` (``backslashreplace``); other values as they
    are."""
    if not isinstance(value, str):
        return value
    return value.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def _write_csv(path: Path, result: FleetResult) -> None:
    import csv

    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(result.columns)
        for r in result.rows:
            w.writerow([repr(v) if isinstance(v, float) else _printable(v)
                        for v in (r[c] for c in result.columns)])


def check_output(path: str | Path, model: str | Path, files: Iterable[str | Path],
                 data: str | Path | None = None) -> Path:
    """Check a fleet's results path before any work: a known suffix, writable, and neither the
    model, nor a record, nor a file the fleet as given would take as a record (the next run
    would read it): a record-like file in the fleet's folder, or a path its glob matches.

    Parameters
    ----------
    path : str or Path
        The results file (``.csv`` or ``.parquet``).
    model : str or Path
        The model file.
    files : iterable of str or Path
        The records.
    data : str or Path, optional
        The fleet as given (a folder or a glob is checked for the last rule).

    Returns
    -------
    Path

    Raises
    ------
    ModelFileError
        The path is refused; the message says why.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.fleet import check_output
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> check_output(d / "out" / "results.csv", d / "m.toml", [], str(d / "logs" / "*.csv"))
    PosixPath('...results.csv')
    >>> check_output(d / "logs" / "results.csv", d / "m.toml", [], str(d / "logs" / "*.csv"))
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: cannot write ...: the fleet's glob ... matches it, ...
    """
    files = list(files)
    out = check_writable(path, inputs=[model, *files], suffixes=RESULT_SUFFIXES,
                         what="results")
    if isinstance(data, (str, Path)):
        if Path(data).is_dir() and same_file(out.parent, data):
            raise ModelFileError(f"cannot write {out}: it lies in the fleet's folder {data}, "
                                 f"where the next run would read it as a record; write it "
                                 f"elsewhere (-o).")
        if is_glob(data) and _matches(str(data), out):
            raise ModelFileError(f"cannot write {out}: the fleet's glob {str(data)!r} matches "
                                 f"it, so the next run would read it as a record; write it "
                                 f"elsewhere (-o).")
    return out


def _is_record(path: Path) -> bool:
    """The one inclusion rule of folders and globs: a file (or a link to one) whose name is
    not hidden and whose suffix is a record format (:data:`DATA_SUFFIXES`)."""
    return (not path.name.startswith(".") and path.suffix.lower() in DATA_SUFFIXES
            and not path.is_dir())


#: Names that mark a folder as one partitioned Parquet dataset (pyarrow, Spark, Dask).
_DATASET_MARKERS = ("_metadata", "_common_metadata", "_SUCCESS")
_PART = re.compile(r"^part[-._]\d+")


def _dataset_reason(folder: Path) -> str | None:
    """Why a folder looks like one partitioned Parquet dataset, or None."""
    names = [e.name for e in folder.iterdir()]
    marker = [n for n in names if n in _DATASET_MARKERS]
    if marker:
        return f"it has {marker[0]}"
    hive = [n for n in names if "=" in n and (folder / n).is_dir()]
    if hive:
        return f"it has the partition folder {hive[0]}"
    parts = [n for n in names if n.lower().endswith(".parquet")]
    if len(parts) >= 2 and all(_PART.match(n) for n in parts):
        return f"its Parquet files are parts ({parts[0]}, …)"
    return None


def _matches(pattern: str, path: Path) -> bool:
    """Whether a glob pattern (``**`` for any folders) matches ``path`` (both made absolute)."""
    pat = Path(os.path.abspath(pattern)).parts
    target = Path(os.path.abspath(path)).parts

    def match(i: int, j: int) -> bool:
        if i == len(pat):
            return j == len(target)
        if pat[i] == "**":
            return any(match(i + 1, k) for k in range(j, len(target) + 1))
        return j < len(target) and fnmatch.fnmatchcase(target[j], pat[i]) and match(i + 1, j + 1)
    return match(0, 0)


def _walk(pattern: str) -> list[Path]:
    """The files a glob with ``**`` matches, each folder entered once (a symlink loop is not
    followed round), hidden names left out unless the pattern names them."""
    parts = Path(pattern).parts
    i = next((k for k, part in enumerate(parts) if glob.has_magic(part)), len(parts))
    root = Path(*parts[:i]) if i else Path(".")
    seen: set[tuple[int, int]] = set()
    out: list[Path] = []

    def entries(folder: Path, segment: str) -> list[Path]:
        try:
            names = sorted(os.listdir(folder))
        except OSError:
            return []
        return [folder / n for n in names if fnmatch.fnmatchcase(n, segment)
                and (segment.startswith(".") or not n.startswith("."))]

    def visit(folder: Path, rest: tuple[str, ...]) -> None:
        head, tail = rest[0], rest[1:]
        if head == "**":
            if tail:
                visit(folder, tail)
            else:
                out.extend(e for e in entries(folder, "*") if not e.is_dir())
            for sub in entries(folder, "*"):
                try:
                    st = sub.stat()
                except OSError:
                    continue
                if sub.is_dir() and (st.st_dev, st.st_ino) not in seen:
                    seen.add((st.st_dev, st.st_ino))
                    visit(sub, rest)
            return
        for e in entries(folder, head):
            if not tail:
                out.append(e)
            elif e.is_dir():
                visit(e, tail)

    try:
        st = root.stat()
    except OSError:
        return []
    seen.add((st.st_dev, st.st_ino))
    if parts[i:]:
        visit(root, parts[i:])
    return out


def _unique(paths: Iterable[Path]) -> list[Path]:
    """The paths in order, each file once (two names of one file, by symlinks or hard links,
    are one record)."""
    out, seen = [], set()
    for p in paths:
        try:
            st = p.stat()
            key: Hashable = (st.st_dev, st.st_ino)
        except OSError:
            key = os.path.abspath(p)
        if key not in seen:
            seen.add(key)
            out.append(p)
    return out


def fleet_files(data: str | Path | Iterable[str | Path]) -> list[Path]:
    """The records of a fleet: a folder, a glob pattern, or a list of paths.

    Parameters
    ----------
    data : str, Path or iterable of str or Path
        A folder (not recursive), a glob pattern (``**`` recurses; each folder is entered once,
        so a symlink loop is not followed round), any other path as one file, or a list of
        paths (taken as given). A folder and a glob take the same files: names that are not
        hidden, with a record suffix (:data:`DATA_SUFFIXES`: ``.csv``, ``.parquet``, ``.mat``),
        sorted by name. Every list is de-duplicated: two names of one file (a symlink, a hard
        link, a path given twice) are one record.

    Returns
    -------
    list of Path
        The record files.

    Raises
    ------
    ModelFileError
        Nothing matches (the message says what was left out), or the folder is one
        partitioned Parquet dataset (``_metadata``, ``key=value`` partition folders, ``part-0``
        files), which is one record, not a fleet.
    ArgumentTypeError
        ``data`` is neither a path nor an iterable of paths.

    Notes
    -----
    A path that exists is taken literally, even with ``[`` or ``*`` in its name; only a path
    that does not exist is read as a glob (:func:`is_glob`). Entries of a folder or a glob
    that are not regular files (a FIFO, a link to a device) are kept: reading them fails, and
    their row says why.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from thetahat.fleet import fleet_files
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> for name in ("b.csv", "a.mat", ".a.csv.tmp.csv", "notes.txt"):
    ...     _ = (d / name).write_text("")
    >>> (d / "loop").symlink_to(d)
    >>> [p.name for p in fleet_files(d)], [p.name for p in fleet_files(f"{d}/**/*")]
    (['a.mat', 'b.csv'], ['a.mat', 'b.csv'])
    """
    if isinstance(data, (str, Path)):
        p = Path(data)
        if p.is_dir():
            reason = _dataset_reason(p)
            if reason is not None:
                raise ModelFileError(
                    f"{p} looks like one partitioned Parquet dataset ({reason}), not a fleet "
                    f"of records: thetahat reads one record per file. Combine the parts into "
                    f"one file (pyarrow.parquet.write_table(pyarrow.dataset.dataset(DIR)."
                    f"to_table(), 'record.parquet')), or, if each part is a record of its "
                    f"own, move them out of the dataset.")
            found = sorted(p.iterdir())
        elif is_glob(data):
            found = sorted(_walk(str(data)) if "**" in str(data)
                           else (Path(f) for f in glob.glob(str(data))))
        else:
            return [p]
        files = _unique(f for f in found if _is_record(f))
        if not files:
            left = [f.name for f in found][:5]
            raise ModelFileError(
                f"no data files in {data!s:.200}: expected a folder or a glob of "
                f"{', '.join(DATA_SUFFIXES)} files"
                + (f" (left out: {', '.join(left)}{', …' if len(found) > 5 else ''})"
                   if left else "") + ", such as 'logs/*.csv'.")
        return files
    if isinstance(data, Iterable) and not isinstance(data, bytes):
        files = _unique(Path(f) for f in _paths(data))
        if not files:
            raise ModelFileError("no data files: the list of records is empty.")
        return files
    raise ArgumentTypeError(f"data must be a folder, a glob pattern or a list of paths; "
                            f"got {type(data).__name__}.")


def is_glob(data: str | Path) -> bool:
    """True when ``data`` is a glob pattern: it has ``*``, ``?`` or ``[`` and no file or folder
    of that exact name exists (brackets in a real file's name are taken literally).

    Parameters
    ----------
    data : str or Path

    Returns
    -------
    bool

    Examples
    --------
    >>> from thetahat.fleet import is_glob
    >>> is_glob("logs/*.csv"), is_glob("/")
    (True, False)
    """
    return glob.has_magic(str(data)) and not os.path.lexists(data)


def _paths(data: Iterable[Any]) -> list[str | Path]:
    out = list(data)
    for f in out:
        if not isinstance(f, (str, Path)):
            raise ArgumentTypeError(f"data: each record must be a path (str or Path); got "
                                    f"{type(f).__name__}.")
    return out


@functools.lru_cache(maxsize=4)
def _spec(text: str, syntax: str, source: str) -> ModelSpec:
    return loads_model(text, syntax=syntax, source=source)


def _summary(spec: ModelSpec, t: FloatArray, theta_hat: FloatArray) -> dict[str, Any]:
    row: dict[str, Any] = {"n_samples": int(t.size), "t_end": float(t[-1])}
    lower, upper = theta_bounds(spec.system.require_parameter_set("the fleet summary"))   # Θ's bounding box (any set)
    half_width = (upper - lower) / 2
    N = t.size
    tail = theta_hat[max(N - max(SE_BATCHES, int(TAIL_FRACTION * N)), 0):]
    if tail.shape[0] < SE_BATCHES:          # a record too short for batch means: no error bar
        se = np.full(theta_hat.shape[1], np.nan)
    else:
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


def _estimate_chunk(paths: list[str], *, model: tuple[str, str, str], hold: str | None,
                    method: str, nan_policy: str, delimiter: str | None = None,
                    noise_std: Any = None, window: int | str | None = None
                    ) -> list[tuple[Hashable, dict[str, Any]]]:
    """One task: read the records; the paper's observer runs records with equal sampling
    instants as one batch, the two-stage methods run record by record."""
    spec = _spec(*model)
    out: dict[str, dict[str, Any]] = {}
    records: dict[str, tuple[DataRecord, list[str]]] = {}
    for p in paths:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                records[p] = (read_data(p, spec.layout, nan_policy=nan_policy,
                                        delimiter=delimiter),
                              [str(w.message) for w in caught])
            except Exception as exc:       # a bad file is reported, never stops the others
                out[p] = {"status": _failure(exc), "warnings": ""}
    if method != "paper":
        for p in records:
            _estimate_one(spec, p, records[p], hold, method, nan_policy, out, noise_std,
                          window)
        return [(p, out[p]) for p in paths]
    groups: dict[bytes, list[str]] = {}
    for p, (rec, _) in records.items():
        groups.setdefault(rec.t.tobytes(), []).append(p)
    for members in groups.values():
        _estimate_group(spec, members, records, hold, nan_policy, out)
    return [(p, out[p]) for p in paths]


def _estimate_one(spec: ModelSpec, path: str, record: tuple[DataRecord, list[str]],
                  hold: str | None,
                  method: str, nan_policy: str, out: dict[str, dict[str, Any]],
                  noise_std: Any = None, window: int | str | None = None) -> None:
    rec, read_warnings = record
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            res = run_estimator(spec, rec.t, rec.u, rec.y, hold=hold,
                                nan_policy=nan_policy, method=method, noise_std=noise_std,
                                window=window)
        except Exception as exc:           # a record that fails is reported, never stops others
            out[path] = {"status": _failure(_explain(exc, spec, rec)),
                         "warnings": "; ".join(read_warnings)}
            return
    out[path] = _ok_row(spec, rec, np.asarray(res.x_hat), np.asarray(res.theta_hat),
                        read_warnings + [str(w.message) for w in caught])


def _explain(exc: BaseException, spec: ModelSpec, rec: DataRecord) -> BaseException:
    return explain_nonfinite(exc, spec.system, rec.t, rec.u, rec.y, start_x_hat(spec, rec.y),
                             spec.estimator.theta_hat0)


def _ok_row(spec: ModelSpec, rec: DataRecord, x_hat: FloatArray, theta_hat: FloatArray,
            notes: list[str]) -> dict[str, Any]:
    row = {"status": "ok", **_summary(spec, rec.t, theta_hat)}
    stuck = stuck_parameters(spec.system, rec.u, rec.y, x_hat, theta_hat, spec.parameter_names)
    row["warnings"] = "; ".join(dict.fromkeys(notes + ([stuck] if stuck else [])))
    return row


@dataclass(frozen=True)
class _Stacked:
    """x̂ and θ̂ of a group's records run one by one (as run_batch's result indexes them)."""

    x_hat: list[FloatArray]
    theta_hat: list[FloatArray]


def _group_runner(obs: Any, t: FloatArray, records: int) -> Any:
    """What runs a group of records that share ``t``: the fastest back end installed for the
    group's samples (:func:`~thetahat.estimation.drive.runner`); ``obs`` itself when none
    takes it, and the group then runs as one NumPy batch (``run_batch``)."""
    from .estimation.drive import runner
    return runner(obs, t, samples=records * t.size)


def _estimate_group(spec: ModelSpec, members: list[str],
                    records: dict[str, tuple[DataRecord, list[str]]], hold: str | None,
                    nan_policy: str, out: dict[str, dict[str, Any]]) -> None:
    t = records[members[0]][0].t
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            obs = build_observer(spec, nan_policy=nan_policy).with_run_options(
                hold=split_hold(hold, "paper")[0])
            s0s = [obs.init(x_hat0=start_x_hat(spec, records[p][0].y),
                            theta_hat0=spec.estimator.theta_hat0) for p in members]
            fast = _group_runner(obs, t, len(members))
            res: Any
            if fast is obs:
                res = run_batch(obs, t, np.stack([records[p][0].u for p in members]),
                                np.stack([records[p][0].y for p in members]),
                                state0=np.stack(s0s))
            else:
                runs = [fast.run(t, records[p][0].u, records[p][0].y, state0=s0)
                        for p, s0 in zip(members, s0s)]
                res = _Stacked(x_hat=[r.x_hat for r in runs],
                               theta_hat=[r.theta_hat for r in runs])
        except Exception as exc:
            if len(members) > 1:           # find the record at fault: run them one by one
                for p in members:
                    _estimate_group(spec, [p], records, hold, nan_policy, out)
                return
            rec = records[members[0]][0]
            out[members[0]] = {"status": _failure(_explain(exc, spec, rec)),
                               "warnings": "; ".join(records[members[0]][1])}
            return
    batch_warnings = [str(w.message) for w in caught]
    for i, p in enumerate(members):
        out[p] = _ok_row(spec, records[p][0], np.asarray(res.x_hat[i]),
                         np.asarray(res.theta_hat[i]), records[p][1] + batch_warnings)


def estimate_many(model: str | Path, data: str | Path | Iterable[str | Path], *,
                  scheduler: Any = None, chunk_size: int | None = None,
                  hold: str | None = None,
                  method: str | None = None, nan_policy: str = "raise",
                  progress: bool = True, delimiter: str | None = None,
                  noise_std: Any = None, window: int | str | None = None) -> FleetResult:
    """Run a model file's estimator on every record of a fleet; one row per record.

    Parameters
    ----------
    model : str or Path
        Model file (TOML or JSON), as for ``thetahat estimate``.
    data : str, Path or iterable of paths
        A directory (its .csv and .parquet files), a glob (``"logs/**/*.parquet"``) or a
        list of files. Columns as for :func:`~thetahat.io.datafile.read_data`.
    scheduler : None, str or dask.distributed.Client
        Where to run (:func:`thetahat.engine.run_keyed`): None here, or a Dask cluster.
    chunk_size : int, optional
        Records per task (default: about 16 tasks). Results do not depend on it beyond
        rounding (records that share their sampling instants run as one batch).
    hold : {"zoh", "foh", "bandlimited", "smooth"}, optional
        u between the samples, for every method
        (:func:`~thetahat.modelfile.holds.split_hold`; default: each method's own).
    method : {"paper", "guarded", "mle", "ekf"}, optional
        The estimator (default: the file's ``[estimator] method``, else ``"guarded"``), as for
        :func:`~thetahat.modelfile.assembly.run_estimator`. The paper's observer runs the
        records that share their sampling instants as one batch; the two-stage methods run
        record by record.
    nan_policy : {"raise", "skip"}
        ``"skip"``: a NaN output sample is a dropout the estimator predicts over;
        ``"raise"``: such a record fails (its row says where).
    progress : bool
        Progress bar (tqdm) on long runs.
    delimiter : {",", ";", "\\t"}, optional
        The CSV separator of every record; default: detected from each header.
    noise_std : float or array_like (r,), optional
        σ of the output noise for the statistical methods (default: estimated from each
        record, which needs 12 samples; ``thetahat estimate --noise-std``).
    window : {None, "auto"} or int, optional
        Bounded fits for ``guarded`` and ``mle`` (``thetahat estimate --window``;
        :func:`~thetahat.modelfile.run_estimator`).

    Returns
    -------
    FleetResult

    Raises
    ------
    ModelFileError
        The model file is bad, is not a regular file, or no data file matches (a bad, special
        or unreadable *data* file is a row, not an error).
    ArgumentTypeError
        ``model`` is not a path, or ``data`` is not a path, a pattern or a list of paths.
    OptionError
        Unknown ``method``, ``nan_policy`` or ``delimiter``.
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
    >>> noise = 1e-3 * np.random.default_rng(0).standard_normal(t.size)
    >>> np.savetxt(d / "a.csv", np.c_[t, np.sin(t), noise], delimiter=",", header="t,u,y",
    ...            comments="")
    >>> _ = (d / "b.csv").write_text("t,u,y\\n0,1,oops\\n")
    >>> res = estimate_many(d / "model.toml", [d / "a.csv", d / "b.csv"])
    >>> res.n_ok, res.failed[str(d / "b.csv")].split(":")[0]
    (1, 'ModelFileError')
    """
    if not isinstance(model, (str, Path)):
        raise ArgumentTypeError(f"model must be the path of a model file; got "
                                f"{type(model).__name__}.")
    source = Path(model)
    syntax = source.suffix.lower().lstrip(".")
    if syntax not in ("toml", "json"):
        raise ModelFileError(f"model file {source}: unknown type "
                             f"{source.suffix or '(no suffix)'!r}; use a .toml or .json file.")
    text = read_text(source, "model file", limits.MAX_MODEL_FILE_BYTES)
    spec = _spec(text, syntax, str(source))        # errors in the model stop here, once
    how = spec.estimator.method if method is None else method
    if how not in ESTIMATION_METHODS:
        raise OptionError(f"method must be one of {list(ESTIMATION_METHODS)}; got {how!r}.")
    check_nan_policy(nan_policy)
    split_hold(hold, how)                          # a hold the method cannot take: refused
    if window is not None:                         # refused once, not once per record
        from .estimation.statistical.window import WINDOW_MAX, check_window
        check_window("estimate_many", window, WINDOW_MAX, spec.system)
    if delimiter is not None and delimiter not in CSV_DELIMITERS:
        raise OptionError(f"delimiter must be one of {list(CSV_DELIMITERS)}; got "
                          f"{delimiter!r}.")
    files = [str(f) for f in fleet_files(data)]
    task = functools.partial(_estimate_chunk, model=(text, syntax, str(source)), hold=hold,
                             method=how, nan_policy=nan_policy, delimiter=delimiter,
                             noise_std=noise_std, window=window)
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
