"""Every exception and warning that thetahat raises.

Each exception also inherits the builtin it refines, so ``except ValueError`` keeps working for
callers that do not know this library. Messages name the object, what was expected, what was
found, and what to do.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "ThetahatError",
    "DimensionError",
    "StateError",
    "NonFiniteError",
    "NotLeftInvertibleError",
    "NotMinimumPhaseError",
    "ParameterSetError",
    "DesignError",
    "UpdateLawError",
    "ModelFileError",
    "SimulationError",
    "CCompilerError",
    "OptionError",
    "ArgumentTypeError",
    "UnsupportedError",
    "InputLimitError",
    "SymbolicTimeoutError",
    "ResourceLimitError",
    "IllConditionedError",
    "UnstableDesignError",
    "IndexOutOfRangeError",
    "FileAccessError",
    "MissingExtraError",
    "ThetahatWarning",
    "ConvergenceWarning",
    "IllConditionedWarning",
]


class ThetahatError(Exception):
    """Base class of every error raised by thetahat."""


class DimensionError(ThetahatError, ValueError):
    """An array has the wrong shape; the message names it and the expected shape."""


class StateError(DimensionError):
    """A state handed to an estimator's ``step`` or ``run`` that it cannot continue: not its
    state type, made for another model (other dimensions), or of a stream it did not start or
    not the stream's latest (the message says which, and to start from ``init()``)."""


class NonFiniteError(ThetahatError, ValueError):
    """NaN or inf found where finite numbers are required (data, matrices, parameters)."""


class NotLeftInvertibleError(ThetahatError, ValueError):
    """The triple (C, A, B) is not left-invertible (Assumption 1 fails).

    Attributes
    ----------
    rank_B : int
        Numerical rank of the input matrix.
    normal_rank : int
        Normal rank of the Rosenbrock system matrix (n + k is required).
    dim_intersection : int
        dim(V* ∩ im B); must be 0.
    """

    def __init__(self, message: str, *, rank_B: int = -1, normal_rank: int = -1,
                 dim_intersection: int = -1) -> None:
        super().__init__(message)
        self.rank_B = rank_B
        self.normal_rank = normal_rank
        self.dim_intersection = dim_intersection


class NotMinimumPhaseError(ThetahatError, ValueError):
    """An invariant zero lies in the closed right half-plane (Assumption 1 fails).

    Attributes
    ----------
    zeros : ndarray of complex
        The offending zeros (real part >= -tolerance).
    """

    def __init__(self, message: str, *, zeros: ArrayLike = ()) -> None:
        super().__init__(message)
        self.zeros = np.asarray(zeros, dtype=complex)


class ParameterSetError(ThetahatError, ValueError):
    """A parameter set Θ is malformed, or a parameter lies outside Θ where it must not."""


class DesignError(ThetahatError, ValueError):
    """Gain-design input is impossible: ε <= 0, poles not in the open left half-plane,
    wrong number of poles, or a structure the design cannot handle."""


class UpdateLawError(ThetahatError, ValueError):
    """An update law is misconfigured (Γ not symmetric positive definite, θ* returning
    non-finite values where the law needs it, ...)."""


class ModelFileError(ThetahatError, ValueError):
    """A model or data file given to the command line cannot be parsed or is inconsistent."""


class SimulationError(ThetahatError, RuntimeError):
    """A numerical integration failed (the solver's message is included) or produced NaN/inf."""


class CCompilerError(ThetahatError, RuntimeError):
    """The C compiler is missing or rejected generated code (the message holds its output)."""


class OptionError(ThetahatError, ValueError):
    """An option has a value outside its allowed set (the message lists the allowed values)."""


class ArgumentTypeError(ThetahatError, TypeError):
    """An argument has the wrong type (the message names the type that is expected)."""


class UnsupportedError(ThetahatError, NotImplementedError):
    """A valid input that this routine does not handle; the message names the alternative."""


class IndexOutOfRangeError(ThetahatError, IndexError):
    """An index is outside the valid range (the message gives the range)."""


class FileAccessError(ThetahatError, OSError):
    """A file or folder thetahat needs cannot be created or written."""


class InputLimitError(ThetahatError, ValueError):
    """An input exceeds a size, nesting or exponent limit of :mod:`thetahat.limits`.

    The limits keep hostile or accidental input (a 10-character exponent tower, a
    10 000-deep nesting) from hanging the program; the message names the limit.
    """


class SymbolicTimeoutError(ThetahatError, TimeoutError):
    """Symbolic work (SymPy ``solve``, ``simplify``, ...) exceeded its time budget.

    Attributes
    ----------
    seconds : float
        The budget that was exceeded (``thetahat.limits.SYMBOLIC_TIME_BUDGET`` by default).
    """

    def __init__(self, message: str, *, seconds: float = float("nan")) -> None:
        super().__init__(message)
        self.seconds = seconds


class ResourceLimitError(ThetahatError, MemoryError):
    """A computation would allocate more memory than is available (estimated before it starts).

    Attributes
    ----------
    required, available : int
        Bytes the allocation needs and bytes the limit allows.
    """

    def __init__(self, message: str, *, required: int = -1, available: int = -1) -> None:
        super().__init__(message)
        self.required = required
        self.available = available


class IllConditionedError(ThetahatError, ValueError):
    """A triple is left-invertible, but too ill-conditioned to bring into SCB form at the given
    rank tolerance (a numerical, not a structural, failure).

    Attributes
    ----------
    condition : float
        The estimate that decided it (for the SCB: 1 / sin of the smallest angle between V*
        and S*).
    tol : float
        The tolerance that was used.
    suggested_tol : float or None
        A tolerance at which the construction succeeds, when one was found.
    """

    def __init__(self, message: str, *, condition: float = float("nan"),
                 tol: float = float("nan"), suggested_tol: float | None = None) -> None:
        super().__init__(message)
        self.condition = condition
        self.tol = tol
        self.suggested_tol = suggested_tol


class UnstableDesignError(DesignError):
    """A gain designed on one system leaves the error dynamics of the true system unstable.

    Attributes
    ----------
    eigenvalues : ndarray of complex
        The eigenvalues of the true closed-loop error system with Re λ >= 0.
    """

    def __init__(self, message: str, *, eigenvalues: ArrayLike = ()) -> None:
        super().__init__(message)
        self.eigenvalues = np.asarray(eigenvalues, dtype=complex)


class MissingExtraError(ThetahatError, ImportError):
    """A call needs an optional extra (numba, matplotlib, python-control, …) that is not
    installed; the message names the ``pip install 'thetahat[extra]'`` that provides it."""


class ThetahatWarning(UserWarning):
    """Base class of thetahat warnings: legal but suspicious input."""


class ConvergenceWarning(ThetahatWarning):
    """An iteration or a simulation did not converge as expected."""


class IllConditionedWarning(ThetahatWarning):
    """A computed transform or design is ill-conditioned (for example a large cond Γs)."""
