"""Progress of long runs: a ``progress(done, total)`` callback for ``run`` and ``estimate``.

:func:`reporter` returns a callback that drives a tqdm bar when tqdm is installed (an optional
extra, never required) and otherwise prints a line at most every ``LINE_EVERY`` seconds, so a
10⁶-sample estimate is never silent.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

__all__ = ["reporter", "LINE_EVERY"]

#: Seconds between two plain progress lines (without tqdm).
LINE_EVERY = 2.0


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
             use_tqdm: bool = True) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that reports to ``stream`` (default stderr).

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
