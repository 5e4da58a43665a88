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
``[data]`` does not name keeps the default naming of :func:`column_candidates`.

Which samples to estimate from: engineers hold a test segment back. ``[data.segments]`` names
segments of the record, each ``[start, stop]`` (0-based sample indices, half-open: the samples
start, start + 1, …, stop − 1), and ``samples`` says which ones the estimators read: a
segment's name, a ``[start, stop]`` pair, or ``"all"`` (the default)::

    [data]
    samples = "train"
    [data.segments]
    train = [40650, 105712]
    test = [105712, 127400]

:func:`select_samples` resolves the choice (the command line's ``--samples`` overrides the
file's); :func:`~thetahat.io.datafile.read_data` returns the chosen samples, t as in the file.

The mapping is one step of the one reader (:func:`thetahat.io.datafile.read_data`), for CSV,
Parquet and MATLAB files alike: :func:`select_columns` picks the columns (each used once, each
present once), the file's cells are checked as for any record, and the scale and offset are
applied *before* the checks of the values (finite, no overflow or underflow, t strictly
increasing). :class:`RecordLayout` is all a reader needs of a model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ArgumentTypeError, ModelFileError

__all__ = ["ALL_SAMPLES", "DataMapping", "RecordLayout", "Signal", "column_candidates",
           "parse_data_table", "select_columns", "select_samples"]

FloatArray = NDArray[np.float64]
_SIGNAL_KEYS = ("column", "scale", "offset")
_RATE_KEYS = ("rate", "start")
_DATA_KEYS = ("t", "u", "y", "samples", "segments")
#: The choice of ``samples`` that reads every sample of the record (the default).
ALL_SAMPLES = "all"


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
    segments : tuple of (str, int, int)
        The named segments ``(name, start, stop)`` of ``[data.segments]``, in the file's
        order (0-based, half-open).
    samples : str or (int, int)
        The samples the estimators read: a segment's name, (start, stop), or "all".
    """

    t: Signal | None
    rate: float | None
    start: float
    u: tuple[Signal | None, ...]
    y: tuple[Signal | None, ...]
    segments: tuple[tuple[str, int, int], ...] = ()
    samples: str | tuple[int, int] = ALL_SAMPLES

    def segment(self, name: str) -> tuple[int, int]:
        """(start, stop) of a named segment.

        Parameters
        ----------
        name : str

        Returns
        -------
        (int, int)

        Raises
        ------
        ModelFileError
            No segment of that name (the message lists them).
        """
        for label, start, stop in self.segments:
            if label == name:
                return start, stop
        known = [label for label, _, _ in self.segments]
        raise ModelFileError(f"no segment {name!r} in the model file's [data.segments]; it "
                             f"names {known or 'none'} (or give samples as START:STOP, or "
                             f"{ALL_SAMPLES!r}).")


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
    segments = _segments(table.get("segments", {}), fail)
    samples = _samples(table.get("samples", ALL_SAMPLES), "samples", fail)
    if isinstance(samples, str) and samples != ALL_SAMPLES \
            and samples not in [name for name, _, _ in segments]:
        raise fail(f"samples = {samples!r} names no segment of [data.segments] "
                   f"({[name for name, _, _ in segments] or 'none given'}); give one of "
                   f"them, [START, STOP] or {ALL_SAMPLES!r}.")
    return DataMapping(t=t_signal, rate=rate, start=start,
                       u=_signals(table.get("u"), input_names, "u", fail),
                       y=_signals(table.get("y"), output_names, "y", fail),
                       segments=segments, samples=samples)


def _pair(value: Any, where: str, fail: Callable[[str], ModelFileError]) -> tuple[int, int]:
    """[start, stop]: two whole numbers, 0 <= start < stop."""
    ok = (isinstance(value, (list, tuple)) and len(value) == 2
          and all(isinstance(v, int) and not isinstance(v, bool) for v in value))
    if not ok or not 0 <= value[0] < value[1]:
        raise fail(f"{where}: expected [START, STOP], two whole numbers with 0 <= START < STOP "
                   f"(0-based sample indices, STOP excluded); got {value!r}.")
    return int(value[0]), int(value[1])


def _segments(value: Any, fail: Callable[[str], ModelFileError]
              ) -> tuple[tuple[str, int, int], ...]:
    if not isinstance(value, Mapping):
        raise fail(f"segments: expected a table of names to [START, STOP], e.g. "
                   f"[data.segments] train = [0, 5000]; got {value!r}.")
    out = []
    for name, pair in value.items():
        if name == ALL_SAMPLES:
            raise fail(f"segments: {ALL_SAMPLES!r} means the whole record; give the segment "
                       f"another name.")
        out.append((str(name), *_pair(pair, f"segments.{name}", fail)))
    return tuple(out)


def _samples(value: Any, where: str, fail: Callable[[str], ModelFileError]
             ) -> str | tuple[int, int]:
    if isinstance(value, str) and value:
        return value
    if isinstance(value, (list, tuple)):
        return _pair(value, where, fail)
    raise fail(f"{where}: expected a segment's name, [START, STOP] or {ALL_SAMPLES!r}; got "
               f"{value!r}.")


def select_samples(mapping: DataMapping | None, N: int,
                   choice: str | tuple[int, int] | None = None, *,
                   where: str = "the record") -> tuple[int, int]:
    """Which samples of a record of N samples to read: (start, stop), 0-based, half-open.

    Parameters
    ----------
    mapping : DataMapping or None
        The model file's ``[data]`` (its ``samples`` and ``segments``); None: no table.
    N : int
        The record's number of samples.
    choice : str or (int, int), optional
        Overrides the file's ``samples``: a segment's name, ``"START:STOP"`` (either may be
        left out: ``"1000:"``), (start, stop), or "all". Default: the file's ``samples``.
    where : str
        Names the record in messages.

    Returns
    -------
    (int, int)

    Raises
    ------
    ModelFileError
        An unknown segment, a malformed ``START:STOP``, or a segment beyond the record's N
        samples or of fewer than two samples.

    Examples
    --------
    >>> from thetahat.errors import ModelFileError
    >>> from thetahat.io.mapping import parse_data_table, select_samples
    >>> m = parse_data_table({"samples": "train", "segments": {"train": [10, 60]}},
    ...                      ["u"], ["y"], ModelFileError)
    >>> select_samples(m, 100), select_samples(m, 100, "all"), select_samples(m, 100, "50:")
    ((10, 60), (0, 100), (50, 100))
    >>> select_samples(m, 40)
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: the record: samples 'train' = [10, 60) go beyond its 40 samples; ...
    """
    if choice is None:
        choice = ALL_SAMPLES if mapping is None else mapping.samples
    label = repr(choice)
    if isinstance(choice, str) and choice != ALL_SAMPLES and ":" in choice:
        head, _, tail = choice.partition(":")
        try:
            start = int(head) if head.strip() else 0
            stop = int(tail) if tail.strip() else N
        except ValueError:
            raise ModelFileError(f"samples {choice!r}: expected START:STOP, two whole numbers "
                                 f"(0-based, STOP excluded; either may be left out), a "
                                 f"segment's name or {ALL_SAMPLES!r}.") from None
    elif isinstance(choice, str):
        if choice == ALL_SAMPLES:
            return 0, N
        if mapping is None:
            raise ModelFileError(f"samples {choice!r}: the model file has no [data.segments] "
                                 f"to name; give START:STOP or {ALL_SAMPLES!r}.")
        start, stop = mapping.segment(choice)
    else:
        start, stop = (int(v) for v in choice)
    if not 0 <= start < stop or stop - start < 2:
        raise ModelFileError(f"{where}: samples {label} = [{start}, {stop}): expected "
                             f"0 <= START < STOP with at least two samples.")
    if stop > N:
        raise ModelFileError(f"{where}: samples {label} = [{start}, {stop}) go beyond its {N} "
                             f"samples; check [data.segments] (0-based, STOP excluded) or "
                             f"the record.")
    return start, stop


# ---------------------------------------------------------------------------------------------
# What a reader needs of a model, and which column is which signal
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class RecordLayout:
    """What the readers and writers need of a model: the names of its signals, the number of
    components of φ, the ``[data]`` mapping and the model's slowest time constant.

    A :class:`~thetahat.modelfile.ModelSpec` builds one (``spec.layout``); the readers import
    nothing from the model files.

    Attributes
    ----------
    input_names, output_names : tuple of str
        One name per input (m) and per output (r): the default column names.
    state_names, parameter_names : tuple of str
        The names of x and θ (the columns of the estimates a writer writes).
    k : int
        Components of φ.
    data : DataMapping or None
        The ``[data]`` table (None: the default column names).
    time_scale : float or None
        The model's slowest time constant in seconds (``1 / min |λ(A)|`` over the nonzero
        eigenvalues), used to flag a time column that is not in seconds; None when unknown.

    Examples
    --------
    >>> from thetahat.io.mapping import RecordLayout
    >>> layout = RecordLayout(input_names=("u",), output_names=("y",))
    >>> layout.m, layout.r
    (1, 1)
    """

    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    state_names: tuple[str, ...] = ()
    parameter_names: tuple[str, ...] = ()
    k: int = 1
    data: DataMapping | None = None
    time_scale: float | None = None

    def __post_init__(self) -> None:
        for field in ("input_names", "output_names", "state_names", "parameter_names"):
            names = getattr(self, field)
            if not isinstance(names, tuple) or not all(isinstance(n, str) for n in names):
                raise ArgumentTypeError(f"RecordLayout.{field} must be a tuple of str; got "
                                        f"{names!r}.")
        if not self.output_names:
            raise ModelFileError("RecordLayout: a record needs at least one output name.")
        if self.data is not None and (len(self.data.u), len(self.data.y)) != (self.m, self.r):
            raise ModelFileError(f"RecordLayout: the [data] mapping has {len(self.data.u)} "
                                 f"input(s) and {len(self.data.y)} output(s), the names "
                                 f"{self.m} and {self.r}.")

    @property
    def m(self) -> int:
        """Number of inputs."""
        return len(self.input_names)

    @property
    def r(self) -> int:
        """Number of outputs."""
        return len(self.output_names)


def _aliases(names: tuple[str, ...], letter: str) -> list[list[str]]:
    out = []
    for i, name in enumerate(names):
        alts = [name, f"{letter}{i + 1}"] + ([letter] if len(names) == 1 else [])
        out.append(list(dict.fromkeys(alts)))
    return out


def column_candidates(layout: RecordLayout) -> list[list[str]]:
    """The accepted names of each data column: ``[["t"], [u names...]..., [y names...]...]``.

    Each input may be named as in the model, ``u1``, ``u2``, … or ``u`` when m = 1; each output
    likewise with ``y``. Used for a signal the ``[data]`` table does not map.

    Parameters
    ----------
    layout : RecordLayout

    Returns
    -------
    list of list of str
        1 + m + r lists, in the order t, u₁ … u_m, y₁ … y_r: the accepted names of each
        column, the model's name first.

    Examples
    --------
    >>> from thetahat.io.mapping import RecordLayout, column_candidates
    >>> column_candidates(RecordLayout(input_names=("tau",), output_names=("q",)))
    [['t'], ['tau', 'u1', 'u'], ['q', 'y1', 'y']]
    """
    return ([["t"]] + _aliases(layout.input_names, "u")
            + _aliases(layout.output_names, "y"))


def _roles(layout: RecordLayout) -> list[str]:
    return (["t"] + [f"u ({n})" if layout.m > 1 else "u" for n in layout.input_names]
            + [f"y ({n})" if layout.r > 1 else "y" for n in layout.output_names])


def _data_line(role: str, names: Sequence[str], taken: set[str]) -> str:
    """The ``[data]`` line that maps ``role`` to a column of the file no signal takes yet,
    for messages."""
    key = role.split(" ")[0]
    example = next((n for n in names if n and n not in taken), "NAME")
    return f'{key} = "{example}"'


def select_columns(names: Sequence[str], layout: RecordLayout, where: str, *,
                   kind: str = "column", listing: str | None = None) -> list[Signal | None]:
    """Which of a file's columns (or variables) are t, u₁…u_m and y₁…y_r.

    A signal mapped by ``[data]`` is taken by its name; the others by
    :func:`column_candidates`. The first entry is None when ``[data]`` gives a ``rate``
    instead of a time column.

    Parameters
    ----------
    names : sequence of str
        The file's column or variable names, in order.
    layout : RecordLayout
    where : str
        Names the file (and line) in messages.
    kind : {"column", "variable"}
    listing : str, optional
        What the file has, for messages (default: the names).

    Returns
    -------
    list of (Signal or None)
        1 + m + r signals, in the order t, u…, y….

    Raises
    ------
    ModelFileError
        A used name appears more than once in the file; a signal is missing (the message
        shows the ``[data]`` line to add); two accepted names of one signal are both present;
        one column is used for two signals.

    Examples
    --------
    >>> from thetahat.io.mapping import RecordLayout, select_columns
    >>> layout = RecordLayout(input_names=("u",), output_names=("y",))
    >>> [s.column for s in select_columns(["y", "t", "u"], layout, "data file d.csv")]
    ['t', 'u', 'y']
    >>> select_columns(["t", "u", "q"], layout, "data file d.csv")
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: data file d.csv: missing column 'y' or 'y1' ...
    """
    mapping = layout.data
    mapped: list[Signal | None] = ([mapping.t, *mapping.u, *mapping.y] if mapping is not None
                                   else [None] * (1 + layout.m + layout.r))
    rate = mapping is not None and mapping.rate is not None
    shown = listing if listing is not None else ", ".join(repr(n) for n in names)
    present = set(names)
    wanted = {s.column for s in mapped if s is not None}
    wanted |= {a for alts in column_candidates(layout) for a in alts}
    twice = sorted({n for n in names if n in wanted and names.count(n) > 1})
    if twice:
        raise ModelFileError(f"{where}: the {kind}(s) {twice} appear more than once; rename "
                             f"or drop the copies.")
    out: list[Signal | None] = []
    for i, (signal, alts, role) in enumerate(zip(mapped, column_candidates(layout),
                                                 _roles(layout))):
        if i == 0 and rate:
            out.append(None)
        elif signal is not None:
            if signal.column not in present:
                raise ModelFileError(f"{where}: no {kind} {signal.column!r} (mapped to {role} "
                                     f"by the model file's [data] table); the file has "
                                     f"{shown}.")
            out.append(signal)
        else:
            found = [a for a in alts if a in present]
            if not found:
                raise ModelFileError(
                    f"{where}: missing {kind} {' or '.join(repr(a) for a in alts)} (the "
                    f"{role} signal); the file has {shown}. If the file names it otherwise, "
                    f"map it in the model file's [data] table, e.g. add the line "
                    f"'{_data_line(role, names, wanted)}' under [data].")
            if len(found) > 1:
                raise ModelFileError(f"{where}: the {kind}s {found} name the same signal "
                                     f"({role}); keep one of them.")
            out.append(Signal(found[0]))
    used: dict[str, str] = {}
    for signal, role in zip(out, _roles(layout)):
        if signal is None:
            continue
        if signal.column in used:
            raise ModelFileError(f"{where}: the {kind} {signal.column!r} is used for both "
                                 f"{used[signal.column]} and {role}; each signal needs a "
                                 f"{kind} of its own (check the [data] table).")
        used[signal.column] = role
    return out
