"""The values the C printer tracks (:mod:`.c_printer`): constants, arrays, scalars, functions.

A formula's argument or expression is, at print time, a compile-time :class:`Const`, a flat
:class:`Arr` (constant data or a runtime buffer), a runtime :class:`Scal` (a C expression and
its type), a :class:`Fn` or a Python tuple of these (the plan tuples); a specialised function
is a :class:`CFunction`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import UnsupportedError

__all__ = ["INT", "REAL", "Arr", "CFunction", "Const", "Fn", "Scal", "c_type", "join",
           "real_literal", "specialisation_key"]

#: C types of runtime scalars.
REAL, INT = "real_t", "int"


@dataclass(frozen=True)
class Const:
    """A compile-time value, folded by the printer.

    Parameters
    ----------
    value : int, float or bool
    text : str, optional
        Its name in C (e.g. ``DT``); named constants are printed by name, not folded.
    """

    value: Any
    text: str | None = None


@dataclass(frozen=True)
class Arr:
    """A flat, row-major C array.

    Parameters
    ----------
    name : str
        Its C name.
    shape : tuple of int
        (size,) or (rows, cols).
    glob : bool
        A ``static const`` array at file scope (constant data, baked into a specialisation);
        else a runtime array, passed as a parameter.
    """

    name: str
    shape: tuple[int, ...]
    glob: bool = False

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if self.shape else 1


@dataclass(frozen=True)
class Scal:
    """A runtime scalar.

    Parameters
    ----------
    text : str
        A C expression.
    ctype : {"real_t", "int"}
        Its type (booleans are ``int``).
    """

    text: str
    ctype: str


@dataclass(frozen=True)
class Fn:
    """A function, by name.

    Parameters
    ----------
    name : str
        A formula, a hook, a scalar primitive or a model function.
    """

    name: str


def real_literal(value: float, real: str) -> str:
    """The C literal of ``value`` in ``real`` ("double" or "float").

    Parameters
    ----------
    value : float
    real : {"double", "float"}

    Returns
    -------
    str

    Examples
    --------
    >>> real_literal(0.5, "float"), real_literal(1e200, "double"), real_literal(3.0, "double")
    ('0.5F', '1e+200', '3.0')
    """
    v = float(value)
    if not math.isfinite(v):
        raise UnsupportedError(f"the C step needs finite constants; got {v!r}.")
    if real == "double":
        return repr(v)
    with np.errstate(over="ignore"):
        single = float(np.float32(v))
    if not math.isfinite(single):
        raise UnsupportedError(f"the constant {v!r} is beyond the range of float; generate "
                               "with real='double' (--real double).")
    return repr(single) + "F"


@dataclass
class CFunction:
    """A specialised function.

    Parameters
    ----------
    name : str
        Its C name.
    args : list of str
        The caller's C argument per kept parameter.
    result : Const, str or tuple of str
        A :class:`Const` when the call folds to a constant (nothing is emitted), a C type,
        ``"void"``, or a tuple of C types (returned through pointers).
    """

    name: str
    args: list[str]
    result: Any


def c_type(value: Any) -> str:
    """The C type of a scalar value (:data:`REAL` or :data:`INT`).

    Parameters
    ----------
    value : Const or Scal

    Returns
    -------
    str

    Examples
    --------
    >>> c_type(Const(1.0)), c_type(Scal("i", INT))
    ('real_t', 'int')
    """
    if isinstance(value, Scal):
        return value.ctype
    if isinstance(value, Const):
        return REAL if isinstance(value.value, float) else INT
    raise UnsupportedError(f"the C printer cannot store {value!r} in a scalar")


def join(a: str, b: str) -> str:
    """The type of an operation on types ``a`` and ``b`` (C's promotion of int to real).

    Parameters
    ----------
    a, b : str

    Returns
    -------
    str

    Examples
    --------
    >>> join(INT, REAL)
    'real_t'
    """
    return REAL if REAL in (a, b) else INT


def specialisation_key(value: Any) -> Any:
    """What a specialisation depends on: constants by value, arrays by shape (and name when
    they are globals), scalars by type.

    Parameters
    ----------
    value : Const, Arr, Scal, Fn, None or tuple of them

    Returns
    -------
    tuple
        Hashable.

    Examples
    --------
    >>> specialisation_key(Arr("w", (3,)))
    ('a', (3,))
    """
    if isinstance(value, Const):
        return ("c", type(value.value).__name__, value.value, value.text)
    if isinstance(value, Arr):
        return ("g", value.name, value.shape) if value.glob else ("a", value.shape)
    if isinstance(value, Scal):
        return ("s", value.ctype)
    if isinstance(value, Fn):
        return ("f", value.name)
    if isinstance(value, tuple):
        return ("t", type(value).__name__, tuple(specialisation_key(v) for v in value))
    if value is None:                   # a named tuple's field the binding leaves unset
        return ("n",)
    raise UnsupportedError(f"the C printer cannot pass {value!r}")
