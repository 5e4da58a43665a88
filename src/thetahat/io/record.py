"""A record as read, and what a reader needs to know of the model to read one.

:class:`DataRecord` holds t, u and y as read from a file; :class:`RecordSpec` is what a reader
asks of the model — the names of its inputs, outputs, states and parameters, its dimensions
and the optional ``[data]`` mapping (a :class:`~thetahat.modelfile.ModelSpec` has all of them;
the readers import nothing from the model files).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from ..model.system import PerturbedLinearSystem

__all__ = ["DataRecord", "MISSING_CELLS", "RecordSpec", "column_candidates"]

FloatArray = NDArray[np.float64]


class RecordSpec(Protocol):
    """What the readers and writers read of a model (a ``ModelSpec`` has it)."""

    @property
    def system(self) -> PerturbedLinearSystem:
        """The plant: its m, r, k."""
        ...

    @property
    def input_names(self) -> tuple[str, ...]:
        """One name per input."""
        ...

    @property
    def output_names(self) -> tuple[str, ...]:
        """One name per output."""
        ...

    @property
    def state_names(self) -> tuple[str, ...]:
        """One name per state."""
        ...

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """One name per parameter."""
        ...

    @property
    def data(self) -> object | None:
        """The ``[data]`` mapping (:class:`~thetahat.io.mapping.DataMapping`), or None."""
        ...


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


def column_candidates(spec: RecordSpec) -> list[list[str]]:
    """The accepted names of each data column: ``[["t"], [u names...]..., [y names...]...]``.

    Each input may be named as in the model, ``u1``, ``u2``, … or ``u`` when m = 1; each output
    likewise with ``y``. The first name found in a header is used.

    Parameters
    ----------
    spec : RecordSpec
        The model; its ``input_names`` and ``output_names`` give the column names.

    Returns
    -------
    list of list of str
        1 + m + r lists, in the order t, u₁ … u_m, y₁ … y_r: the accepted names of each
        column, the model's name first.

    Examples
    --------
    >>> from thetahat.modelfile import EXAMPLE_MODEL, loads_model
    >>> from thetahat.io.record import column_candidates
    >>> column_candidates(loads_model(EXAMPLE_MODEL))
    [['t'], ['u', 'u1'], ['y', 'y1']]
    """
    return [["t"]] + _aliases(spec.input_names, "u") + _aliases(spec.output_names, "y")


