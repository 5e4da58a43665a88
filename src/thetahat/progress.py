"""Progress of long runs: the named stages of a job for a person, and the callbacks estimators
call.

:class:`Stages` reports the stages of one job (``thetahat estimate``: load model, read,
estimate, trust report, write) on a stream, stderr by default:

* on a terminal (mode ``"live"``) one line per stage, drawn as soon as the stage starts and
  redrawn in place every :data:`REFRESH_S` seconds by a background thread: the stage's number
  and name, what it has counted (samples, fits) and its share, the time spent in it and, once
  something has been counted, an estimate of the time left in it; a finished stage keeps its
  line with its time; the job ends with one line of totals;
* elsewhere (a pipe, a log file: ``"final"``) only that last line: the total time and the
  time of each stage;
* ``"quiet"``: nothing.

The callbacks the estimators take, both ``callback(done, total)``:

* **samples**, ``progress(done, total)`` — ``done`` of ``total`` samples processed (the
  observer's ``run`` calls it every ``PROGRESS_EVERY`` samples and at the end). A
  :class:`Stages` is such a callback: it counts the samples of its current stage.
* **fits**, :data:`FitProgress` ``fit_progress(done, total)`` — called by a statistical
  estimator's ``run`` (``"mle"``'s MAP fits, ``"guarded"``'s re-anchoring fits) with
  ``(0, total)`` before its first fit and ``(done, total)`` after each: ``total`` the fits its
  schedule places on the record, known in advance and constant within a run (0: none),
  ``done`` increasing to ``total``; an estimator whose total could not be known in advance
  would pass 0 (the line then shows the fits done, with no share or time left).
  :meth:`Stages.fits` is such a callback, and :meth:`Stages.fit_stage` makes one that counts
  them in a stage of their own; the live line then shows the fits and estimates the time left
  from them.

:func:`reporter` is the plain sample callback for library code (a tqdm bar or lines).

This module imports only the standard library and :mod:`thetahat.errors`: the command line
shows its first line before the model's libraries (SymPy, SciPy) load.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Literal, TextIO

from .errors import OptionError

__all__ = ["FitProgress", "LINE_EVERY", "MODES", "REFRESH_S", "SampleProgress", "StageTime",
           "Stages", "reporter"]

#: Seconds between two plain progress lines of :func:`reporter` (without tqdm).
LINE_EVERY = 2.0
#: Seconds between two redraws of a live :class:`Stages` line.
REFRESH_S = 0.25
#: The modes of :class:`Stages`; ``"auto"`` is ``"live"`` on a terminal, else ``"final"``.
MODES = ("auto", "live", "final", "quiet")

#: ``progress(done, total)``: ``done`` of ``total`` samples processed.
SampleProgress = Callable[[int, int], None]
#: ``fit_progress(done, total)``: ``done`` fits finished of ``total`` planned (0: none, or
#: unknown).
FitProgress = Callable[[int, int], None]


@dataclass(frozen=True, slots=True)
class StageTime:
    """A finished stage of a :class:`Stages`.

    Parameters
    ----------
    name : str
        The stage's name.
    seconds : float
        Its wall time (s).

    Examples
    --------
    >>> from thetahat.progress import StageTime
    >>> StageTime("read", 1.25)
    StageTime('read', 1.250 s)
    """

    name: str
    seconds: float

    def __repr__(self) -> str:
        return f"StageTime({self.name!r}, {self.seconds:.3f} s)"


class _Stage:
    """The stage in progress: its counts (mutable, read by the drawing thread)."""

    def __init__(self, index: int, name: str, total: int | None, unit: str, start: float
                 ) -> None:
        self.index, self.name, self.unit, self.start = index, name, unit, start
        self.total, self.done = total, 0
        self.fits_done, self.fits_total = 0, 0
        self.note = ""


def _count(done: int, total: int | None, unit: str) -> str:
    if not total:
        return f"{done:,} {unit}" if done else ""
    return f"{done:,}/{total:,} {unit} ({100.0 * done / total:.0f} %)"


def _seconds(s: float) -> str:
    if s < 60:
        return f"{s:.1f} s"
    minutes, s = divmod(int(round(s)), 60)
    return f"{minutes} min {s:02d} s" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"


class Stages:
    """The stages of one job, reported to a person as they run.

    Parameters
    ----------
    plan : sequence of str, optional
        The names of the stages to come, in order: the lines number them ``[k/K]``.
    stream : file, optional
        Where to write (default ``sys.stderr``).
    mode : {"auto", "live", "final", "quiet"}
        ``"live"``: a line per stage, redrawn in place (a terminal); ``"final"``: only the
        line of totals; ``"quiet"``: nothing; ``"auto"`` (default): ``"live"`` when
        ``stream`` is a terminal, else ``"final"``.
    title : str
        The lines' prefix.
    refresh : float
        Seconds between redraws of a live line.

    Notes
    -----
    Use it as a context manager: leaving the block stops the drawing thread and, without an
    error, writes the line of totals (:meth:`finish`); with an error, a live line is ended so
    that the error message starts a line of its own, and no totals are written. The object
    itself is the estimators' ``progress(done, total)`` callback (samples of the current
    stage), :meth:`fits` their ``fit_progress(done, total)`` (fits of the current stage) and
    :meth:`fit_stage` one that counts the fits in a stage of their own.

    Examples
    --------
    >>> import io
    >>> from thetahat.progress import Stages
    >>> out = io.StringIO()                              # not a terminal: the final line only
    >>> with Stages(plan=("read", "estimate"), stream=out) as stages:
    ...     stages.stage("read")
    ...     stages.stage("estimate", total=1000)
    ...     stages(1000, 1000)                           # the estimator's progress callback
    >>> out.getvalue().startswith("thetahat: done in "), out.getvalue().count(chr(10))
    (True, 1)
    >>> [t.name for t in stages.times]
    ['read', 'estimate']
    """

    def __init__(self, plan: tuple[str, ...] | list[str] = (), *, stream: TextIO | None = None,
                 mode: str = "auto", title: str = "thetahat",
                 refresh: float = REFRESH_S) -> None:
        if mode not in MODES:
            raise OptionError(f"Stages: unknown mode {mode!r}; expected one of {list(MODES)}.")
        self.stream = sys.stderr if stream is None else stream
        if mode == "auto":
            mode = "live" if _is_terminal(self.stream) else "final"
        self.mode, self.title, self.refresh, self.plan = mode, title, refresh, tuple(plan)
        self.times: list[StageTime] = []
        self._start = time.monotonic()
        self._current: _Stage | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._finished = False

    # --- what the job calls ------------------------------------------------------------------

    def stage(self, name: str, total: int | None = None, unit: str = "samples") -> None:
        """End the current stage (its line keeps its time) and start ``name``.

        ``total`` is the count the stage will reach in ``unit`` (``None``: not counted)."""
        with self._lock:
            now = time.monotonic()
            self._end_current(now)
            index = len(self.times) + 1
            self._current = _Stage(index, name, total, unit, now)
            self._draw(now)
        if self.mode == "live" and self._thread is None:
            self._thread = threading.Thread(target=self._redraw, name="thetahat-progress",
                                            daemon=True)
            self._thread.start()

    def advance(self, n: int = 1) -> None:
        """Count ``n`` more units of the current stage."""
        stage = self._current
        if stage is not None:
            stage.done += n

    def __call__(self, done: int, total: int) -> None:
        """``progress(done, total)``: ``done`` of ``total`` units of the current stage."""
        stage = self._current
        if stage is not None:
            stage.done, stage.total = done, total

    def fits(self, done: int, total: int) -> None:
        """``fit_progress(done, total)``: ``done`` fits finished, ``total`` planned (0 when
        unknown), in the current stage."""
        stage = self._current
        if stage is not None:
            stage.fits_done, stage.fits_total = done, total

    def fit_stage(self, name: str = "fits") -> FitProgress:
        """A ``fit_progress(done, total)`` callback whose first call starts stage ``name``
        (ending the current one: e.g. the samples of stage 1) and whose calls count its fits
        (:meth:`fits`)."""
        started = False

        def fit_progress(done: int, total: int) -> None:
            nonlocal started
            if not started:
                started = True
                self.stage(name, unit="fits")
            self.fits(done, total)
        return fit_progress

    def note(self, text: str) -> None:
        """Add ``text`` to the current stage's line (e.g. what was read)."""
        stage = self._current
        if stage is not None:
            stage.note = text

    def finish(self) -> None:
        """End the last stage and write the line of totals (not in ``"quiet"`` mode)."""
        self._stop_thread()
        with self._lock:
            if self._finished:
                return
            self._finished = True
            now = time.monotonic()
            self._end_current(now)
            if self.mode != "quiet":
                parts = ", ".join(f"{t.name} {_seconds(t.seconds)}" for t in self.times)
                self._write(f"{self.title}: done in {_seconds(now - self._start)}"
                            + (f": {parts}" if parts else "") + "\n")

    def __enter__(self) -> Stages:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if kind is None:
            self.finish()
            return
        self._stop_thread()
        with self._lock:
            self._finished = True
            if self.mode == "live" and self._current is not None:
                self._write("\n")                 # the error message on a line of its own
            self._current = None

    # --- drawing -----------------------------------------------------------------------------

    def _line(self, stage: _Stage, now: float, *, final: bool) -> str:
        numbered = (f"[{stage.index}/{max(len(self.plan), stage.index)}] "
                    if self.plan else "")
        parts = [f"{self.title}: {numbered}{stage.name}"]
        count = _count(stage.done, None if final else stage.total, stage.unit)
        fits = _count(stage.fits_done, None if final else stage.fits_total, "fits")
        parts += [p for p in (stage.note, count, fits) if p]
        spent = now - stage.start
        parts.append(_seconds(spent))
        if not final:
            left = _left(stage, spent)
            if left is not None:
                parts.append(f"about {_seconds(left)} left")
        return " · ".join(parts)

    def _draw(self, now: float) -> None:
        """Redraw the current stage's live line (call with the lock held)."""
        if self.mode == "live" and self._current is not None:
            self._write("\r" + _fit(self._line(self._current, now, final=False), self.stream)
                        + "\x1b[K")

    def _end_current(self, now: float) -> None:
        """Record the current stage's time; a live line is left with its final text."""
        stage = self._current
        if stage is None:
            return
        self.times.append(StageTime(stage.name, now - stage.start))
        if self.mode == "live":
            self._write("\r" + _fit(self._line(stage, now, final=True), self.stream)
                        + "\x1b[K\n")
        self._current = None

    def _redraw(self) -> None:
        while not self._stop.wait(self.refresh):
            with self._lock:
                if not self._finished:
                    self._draw(time.monotonic())

    def _stop_thread(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):      # a closed stream, a gone terminal: progress is
            pass                            # never worth failing the job for


def _left(stage: _Stage, spent: float) -> float | None:
    """Time left in a stage from its fits when counted, else from its samples."""
    for done, total in ((stage.fits_done, stage.fits_total), (stage.done, stage.total)):
        if done > 0 and total and total >= done:
            return spent * (total - done) / done
    return None


def _is_terminal(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def _fit(line: str, stream: TextIO) -> str:
    """``line`` cut to the terminal's width, so that ``\\r`` redraws it in place."""
    try:
        width = os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, ValueError, OSError):
        return line
    if width <= 0:                          # a terminal that does not know its size
        return line
    return line if len(line) < width else line[:max(width - 2, 1)] + "…"


class _Lines:
    """Plain-text progress: a line every LINE_EVERY seconds and one at the end."""

    def __init__(self, what: str, stream: TextIO) -> None:
        self.what, self.stream = what, stream
        self.start = self.last = time.monotonic()

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done < total and now - self.last < LINE_EVERY:
            return
        self.last = now
        pct = 100.0 * done / total if total else 100.0
        print(f"thetahat: {self.what}: {done}/{total} samples ({pct:.0f} %, "
              f"{now - self.start:.1f} s)", file=self.stream, flush=True)


class _Bar:
    """tqdm progress bar, closed when the last sample is reached."""

    def __init__(self, tqdm: Any, what: str, stream: TextIO) -> None:
        self.tqdm, self.what, self.stream = tqdm, what, stream
        self.bar: Any = None

    def __call__(self, done: int, total: int) -> None:
        if self.bar is None:
            self.bar = self.tqdm(total=total, desc=f"thetahat: {self.what}", unit="sample",
                                 file=self.stream, leave=False)
        self.bar.update(done - self.bar.n)
        if done >= total:
            self.bar.close()


def reporter(what: str, *, stream: TextIO | None = None,
             use_tqdm: bool = True) -> SampleProgress:
    """A ``progress(done, total)`` callback that reports to ``stream`` (default stderr).

    For library code that runs one estimator; the command line reports its jobs with
    :class:`Stages`.

    Parameters
    ----------
    what : str
        Names the work in the report (e.g. "estimate").
    stream : file, optional
        Where to write (default ``sys.stderr``).
    use_tqdm : bool, default True
        Use a tqdm bar when tqdm is installed; otherwise, or with False, plain lines at most
        every ``LINE_EVERY`` seconds and at the end.

    Returns
    -------
    callable
        ``progress(done, total)``.

    Examples
    --------
    >>> import io
    >>> from thetahat.progress import reporter
    >>> out = io.StringIO()
    >>> progress = reporter("estimate", stream=out, use_tqdm=False)
    >>> progress(0, 10); progress(10, 10)
    >>> out.getvalue().splitlines()[-1].startswith("thetahat: estimate: 10/10 samples (100 %")
    True
    """
    target = sys.stderr if stream is None else stream
    if use_tqdm:
        try:
            from tqdm import tqdm
        except ImportError:
            pass
        else:
            return _Bar(tqdm, what, target)
    return _Lines(what, target)
