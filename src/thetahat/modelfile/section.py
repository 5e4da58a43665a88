"""One section of a model file, read against its table of keys, with messages that name the key.

A :class:`Section` holds the section's value from the file and its
:class:`~thetahat.modelfile.keys.Table`: it refuses keys the table does not list, requires the
keys it marks required, fills in its literal defaults and checks a value by its type
(numbers, booleans, choices by the row alone; vectors, names, matrices and poles with the
sizes the rest of the file gives). Every problem is a :class:`~thetahat.errors.ModelFileError`
that names the file, the section and the key.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ModelFileError
from .keys import TYPES, Table

__all__ = ["Section", "is_number", "show"]

FloatArray = NDArray[np.float64]


def show(value: Any) -> str:
    """A value as a message quotes it: its repr, cut at 60 characters.

    Parameters
    ----------
    value : object

    Returns
    -------
    str

    Examples
    --------
    >>> show("x" * 100)[-5:]
    'xx...'
    """
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def is_number(value: Any) -> bool:
    """An int or a float, not a bool.

    Parameters
    ----------
    value : object

    Returns
    -------
    bool

    Examples
    --------
    >>> is_number(1), is_number(True), is_number("1")
    (True, False, False)
    """
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class Section:
    """One table of a file, read against its :class:`~thetahat.modelfile.keys.Table`.

    Parameters
    ----------
    source : str
        The file's name (the messages start with it).
    keys : Table
        The section's keys.
    value : object
        The section as parsed from the file (must be a table).

    Raises
    ------
    ModelFileError
        ``value`` is not a table.

    Examples
    --------
    >>> from thetahat.modelfile.keys import SCENARIO
    >>> sec = Section("m.toml", SCENARIO, {"t_end": 5.0})
    >>> sec.number("t_end"), sec.number("fs"), sec.choice("method")
    (5.0, 100.0, 'Radau')
    >>> Section("m.toml", SCENARIO, {"fs": -1.0}).number("fs")
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: model file m.toml: [scenario] fs: expected a finite positive number; got -1.0.
    """

    def __init__(self, source: str, keys: Table, value: Any) -> None:
        if not isinstance(value, Mapping):
            raise ModelFileError(f"model file {source}: [{keys.section}] must be a table; got "
                                 f"{show(value)}.")
        self.source, self.keys, self.value = source, keys, value

    @property
    def name(self) -> str:
        """The section's name, as in ``[estimator.second]``."""
        return self.keys.section

    def as_form(self, keys: Table) -> Section:
        """The same section read against another form's table (``[parameter_set]``).

        Parameters
        ----------
        keys : Table

        Returns
        -------
        Section
        """
        return Section(self.source, keys, self.value)

    def fail(self, key: str | None, message: str) -> ModelFileError:
        """The error of a key (or of the section, ``key=None``).

        Parameters
        ----------
        key : str or None
        message : str
            What is wrong and what to do.

        Returns
        -------
        ModelFileError
        """
        where = f"[{self.name}]" + (f" {key}" if key else "")
        return ModelFileError(f"model file {self.source}: {where}: {message}")

    def check_keys(self) -> None:
        """Refuse a key the section's table does not list (it is usually a typo).

        Raises
        ------
        ModelFileError
            Naming the unknown keys and the allowed ones.
        """
        allowed = self.keys.names()
        unknown = [k for k in self.value if k not in allowed]
        if unknown:
            raise self.fail(None, f"unknown key(s) {unknown}; expected only {list(allowed)}.")

    def has(self, key: str) -> bool:
        """The file gives ``key``.

        Parameters
        ----------
        key : str

        Returns
        -------
        bool
        """
        return key in self.value

    def get(self, key: str) -> Any:
        """The file's value of ``key``, else the table's literal default (else None).

        Parameters
        ----------
        key : str

        Returns
        -------
        object
        """
        if key in self.value:
            return self.value[key]
        row = self.keys[key]
        return copy.deepcopy(row.default) if row.literal else None

    def require(self, key: str, what: str | None = None) -> Any:
        """The file's value of ``key``, which must be given.

        Parameters
        ----------
        key : str
        what : str, optional
            What is expected, for the message (default: the key's type).

        Returns
        -------
        object

        Raises
        ------
        ModelFileError
            The key is missing.
        """
        if key not in self.value:
            raise self.fail(key, f"missing; expected {what or TYPES[self.keys[key].type]}.")
        return self.value[key]

    def number(self, key: str) -> float:
        """A number, checked by the key's type (``number``, ``positive number``,
        ``non-negative number``); the table's default when absent.

        Parameters
        ----------
        key : str

        Returns
        -------
        float

        Raises
        ------
        ModelFileError
            Not a finite number, or out of the type's range; missing without a default.
        """
        row = self.keys[key]
        if key not in self.value and row.literal:
            return float(row.default)
        v = self.require(key, "a number")
        positive = row.type in ("positive number", "positive number or auto")
        non_negative = row.type == "non-negative number"
        if not (is_number(v) and math.isfinite(v) and (not positive or v > 0)
                and (not non_negative or v >= 0)):
            auto = " or 'auto'" if row.type.endswith(" or auto") else ""
            raise self.fail(key, f"expected a finite {'positive ' if positive else ''}number"
                                 f"{' >= 0' if non_negative else ''}{auto}; got {show(v)}.")
        return float(v)

    def boolean(self, key: str) -> bool:
        """``true`` or ``false``; the table's default when absent.

        Parameters
        ----------
        key : str

        Returns
        -------
        bool

        Raises
        ------
        ModelFileError
            Anything else (``1``, ``"yes"``).
        """
        v = self.get(key)
        if not isinstance(v, bool):
            raise self.fail(key, f"expected true or false; got {show(v)}.")
        return v

    def choice(self, key: str) -> str:
        """One of the key's choices; the table's default when absent.

        Parameters
        ----------
        key : str

        Returns
        -------
        str

        Raises
        ------
        ModelFileError
            Another value, or missing when required.
        """
        row = self.keys[key]
        v = self.require(key, f"one of {list(row.choices)}") if row.required else self.get(key)
        if v not in row.choices:
            raise self.fail(key, f"unknown {key} {show(v)}; expected one of "
                                 f"{list(row.choices)}.")
        return str(v)

    def vector(self, key: str, size: int, what: str) -> FloatArray:
        """``size`` finite numbers (one number when ``size`` is 1).

        Parameters
        ----------
        key : str
        size : int
        what : str
            What they are, for the message.

        Returns
        -------
        ndarray, shape (size,)

        Raises
        ------
        ModelFileError
            Missing, not numbers, not finite or the wrong count.
        """
        v = self.require(key, f"{size} number(s) ({what})")
        if is_number(v):
            v = [v]
        if not isinstance(v, list) or not all(is_number(e) for e in v):
            raise self.fail(key, f"expected a list of {size} number(s) ({what}); got "
                                 f"{show(v)}.")
        if len(v) != size:
            raise self.fail(key, f"expected {size} number(s) ({what}); got {len(v)}.")
        arr = np.array(v, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise self.fail(key, f"entries must be finite; got {v}.")
        return arr

    def names(self, key: str, what: str, *, allow_empty: bool) -> tuple[str, ...]:
        """A list of names (a single name may be given as a string).

        Parameters
        ----------
        key : str
        what : str
            What they name, for the message.
        allow_empty : bool
            ``[]`` is allowed (no inputs).

        Returns
        -------
        tuple of str

        Raises
        ------
        ModelFileError
            Missing, not strings, or empty when not allowed.
        """
        v = self.require(key, f"a list of names ({what})")
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list) or not all(isinstance(e, str) for e in v):
            raise self.fail(key, f"expected a list of names ({what}); got {show(v)}.")
        if not v and not allow_empty:
            raise self.fail(key, f"expected at least one name ({what}); got [].")
        return tuple(v)

    def matrix(self, key: str, rows: int, cols: int | None, what: str) -> FloatArray:
        """A matrix as a nested list of rows of finite numbers, of a given shape.

        Parameters
        ----------
        key : str
        rows : int
        cols : int or None
            None: any number of columns.
        what : str
            What it is, for the message (``"n × n with n = 2 states"``).

        Returns
        -------
        ndarray, shape (rows, cols)
            ``[]`` gives (rows, 0) when ``cols`` is 0.

        Raises
        ------
        ModelFileError
            Missing, ragged, non-finite or of the wrong shape.
        """
        v = self.require(key, f"a {what} matrix as a nested list of rows of numbers")
        if v == [] and rows > 0 and cols == 0:
            return np.zeros((rows, 0))
        if not isinstance(v, list) or not v or not all(isinstance(row, list) for row in v):
            raise self.fail(key, f"expected a {what} matrix as a nested list of rows, e.g. "
                                 f"[[1.0, 0.0], [0.0, 1.0]]; got {show(v)}.")
        lengths = [len(row) for row in v]
        if len(set(lengths)) != 1:
            raise self.fail(key, f"rows have different lengths {lengths}; a matrix needs "
                                 f"equal rows.")
        for i, row in enumerate(v):
            for j, e in enumerate(row):
                if not is_number(e) or not math.isfinite(e):
                    raise self.fail(key, f"entry [{i}][{j}] = {show(e)} is not a finite "
                                         f"number.")
        arr = np.array(v, dtype=np.float64)
        want = (rows, lengths[0] if cols is None else cols)
        if arr.shape != want:
            raise self.fail(key, f"expected shape {want} ({what}); got {arr.shape}.")
        return arr

    def poles(self, key: str) -> Any:
        """Real poles: a list (type ``poles``) or one list per chain (``pole lists``).

        Parameters
        ----------
        key : str

        Returns
        -------
        tuple of float, tuple of tuple of float, or None
            None when absent (the design's defaults).

        Raises
        ------
        ModelFileError
            Not lists of finite numbers.
        """
        if key not in self.value:
            return None
        nested = self.keys[key].type == "pole lists"
        v = self.value[key]
        lists = v if nested else [v]
        ok = isinstance(v, list) and all(isinstance(p, list) and p and
                                         all(is_number(e) and math.isfinite(e) for e in p)
                                         for p in lists)
        if not ok:
            example = "[[-1.0, -2.0, -3.0]] (one list per chain)" if nested else "[-1.0, -2.0]"
            raise self.fail(key, f"expected real poles as {example}; got {show(v)}.")
        return tuple(tuple(float(e) for e in p) for p in v) if nested else \
            tuple(float(e) for e in v)
