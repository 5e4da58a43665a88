"""A record as read: :class:`DataRecord` holds t, u and y in the model's units, the columns used
and the file they came from; :data:`MISSING_CELLS` are the cells read as a missing sample."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import IndexOutOfRangeError

__all__ = ["DataRecord", "MISSING_CELLS"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True, repr=False)
class DataRecord:
    """Samples read by :func:`~thetahat.io.datafile.read_data`.

    Attributes
    ----------
    t : ndarray, shape (N,)
    u : ndarray, shape (N, m)
    y : ndarray, shape (N, r)
    columns : tuple of str
        The columns or variables used, in the order t, u..., y... (``rate=... Hz`` for a t
        generated from ``[data] t = { rate = ... }``).
    source : str
    samples : (int, int) or None
        The samples of the file held, [start, stop) (0-based), when a segment was chosen
        (``[data] samples``, :meth:`segment`); None: the whole file.
    """

    t: FloatArray
    u: FloatArray
    y: FloatArray
    columns: tuple[str, ...]
    source: str
    samples: tuple[int, int] | None = None

    def segment(self, start: int, stop: int) -> DataRecord:
        """Samples [start, stop) of this record (0-based, half-open), t unchanged.

        Parameters
        ----------
        start, stop : int
            Indices into this record.

        Returns
        -------
        DataRecord
            ``self`` for the whole record; otherwise the segment, its ``samples`` in the
            file's indices.

        Raises
        ------
        IndexOutOfRangeError
            Not 0 <= start < stop <= N, or fewer than two samples.

        Examples
        --------
        >>> import numpy as np
        >>> from thetahat.io.record import DataRecord
        >>> rec = DataRecord(np.arange(5.0), np.zeros((5, 1)), np.ones((5, 1)), ("t", "u", "y"),
        ...                  "d.csv")
        >>> rec.segment(1, 4)
        DataRecord(N=3, columns=['t', 'u', 'y'], source='d.csv', samples=[1, 4))
        """
        N = self.t.size
        if not 0 <= start < stop <= N or stop - start < 2:
            raise IndexOutOfRangeError(f"segment [{start}, {stop}) of a record of {N} samples: "
                                       f"expected 0 <= start < stop <= {N}, at least two "
                                       f"samples.")
        if (start, stop) == (0, N):
            return self
        first = 0 if self.samples is None else self.samples[0]
        return DataRecord(t=self.t[start:stop], u=self.u[start:stop], y=self.y[start:stop],
                          columns=self.columns, source=self.source,
                          samples=(first + start, first + stop))

    def __repr__(self) -> str:
        cut = ("" if self.samples is None
               else f", samples=[{self.samples[0]}, {self.samples[1]})")
        return (f"DataRecord(N={self.t.size}, columns={list(self.columns)}, "
                f"source={self.source!r}{cut})")


#: Cells read as a missing output sample under ``nan_policy="skip"`` (besides NaN itself).
MISSING_CELLS = ("", "nan", "na", "n/a", "null", "none")
