"""A record as read: :class:`DataRecord` holds t, u and y in the model's units, the columns used
and the file they came from; :data:`MISSING_CELLS` are the cells read as a missing sample."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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
    """

    t: FloatArray
    u: FloatArray
    y: FloatArray
    columns: tuple[str, ...]
    source: str

    def __repr__(self) -> str:
        return (f"DataRecord(N={self.t.size}, columns={list(self.columns)}, "
                f"source={self.source!r})")


#: Cells read as a missing output sample under ``nan_policy="skip"`` (besides NaN itself).
MISSING_CELLS = ("", "nan", "na", "n/a", "null", "none")
