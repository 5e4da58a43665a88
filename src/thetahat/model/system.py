"""The model of the paper, (1): ẋ = A x + B u + E φ, y = C x, φ = g(v, x, θ), θ ∈ Θ."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import as_matrix, as_triple, readonly
from ..errors import DimensionError
from .paramset import ParameterSet
from .perturbation import Perturbation

FloatArray = NDArray[np.float64]




@dataclass(frozen=True, slots=True)
class PerturbedLinearSystem:
    """A linear system with a nonlinearly parameterized perturbation, eq. (1).

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, m)
        Input matrix (``m = 0`` allowed: pass ``np.zeros((n, 0))``).
    C : array_like, shape (r, n)
    E : array_like, shape (n, k)
        Where the perturbation φ enters.
    perturbation : Perturbation, optional
        φ = g(v, x, θ) with v = col(u, y). Its dims must agree with (n, m, r, k).
    parameter_set : ParameterSet, optional
        Θ, the compact convex set known to contain θ; its dimension must equal p.

    Raises
    ------
    DimensionError
        A matrix has the wrong shape, or the perturbation / Θ disagree with the matrices.
    NonFiniteError
        A matrix holds NaN or inf.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat import PerturbedLinearSystem
    >>> sys = PerturbedLinearSystem(A=[[0, 1], [0, 0]], B=[[0], [1]], C=[[1, 0]], E=[[0], [1]])
    >>> sys.n, sys.m, sys.r, sys.k
    (2, 1, 1, 1)
    """

    A: FloatArray
    B: FloatArray
    C: FloatArray
    E: FloatArray
    perturbation: Perturbation | None = None
    parameter_set: ParameterSet | None = None

    def __init__(self, *, A: ArrayLike, B: ArrayLike, C: ArrayLike, E: ArrayLike,
                 perturbation: Perturbation | None = None,
                 parameter_set: ParameterSet | None = None) -> None:
        A_, B_, C_ = as_triple(A, B, C)
        n = A_.shape[0]
        E_ = as_matrix("E", E, (n, None))
        if E_.shape[1] == 0:
            raise DimensionError("E must have at least one column (k >= 1); got shape "
                                 f"{E_.shape}. Without a perturbation use an ordinary observer.")
        k = E_.shape[1]
        m, r = B_.shape[1], C_.shape[0]
        if parameter_set is not None and not isinstance(parameter_set, ParameterSet):
            raise DimensionError("parameter_set must be a thetahat ParameterSet (Box, Ball, "
                                 f"Ellipsoid, ...); got {type(parameter_set).__name__}.")
        if perturbation is not None:
            if not isinstance(perturbation, Perturbation):
                raise DimensionError("perturbation must be a thetahat Perturbation (e.g. "
                                     "SymbolicPerturbation or CallablePerturbation); got "
                                     f"{type(perturbation).__name__}.")
            pn, pm, pr, pp, pk = perturbation.dims
            if (pn, pm, pr, pk) != (n, m, r, k):
                raise DimensionError(
                    f"perturbation dims (n={pn}, m={pm}, r={pr}, k={pk}) disagree with the "
                    f"matrices (n={n}, m={m}, r={r}, k={k}); g must map v = col(u, y) of "
                    f"length m + r = {m + r} and x of length {n} to φ of length {k}.")
            if parameter_set is not None and parameter_set.dim != pp:
                raise DimensionError(f"parameter_set has dimension {parameter_set.dim} but the "
                                     f"perturbation has p = {pp} parameters.")
        object.__setattr__(self, "A", readonly(A_))
        object.__setattr__(self, "B", readonly(B_))
        object.__setattr__(self, "C", readonly(C_))
        object.__setattr__(self, "E", readonly(E_))
        object.__setattr__(self, "perturbation", perturbation)
        object.__setattr__(self, "parameter_set", parameter_set)

    @property
    def n(self) -> int:
        """Number of states."""
        return self.A.shape[0]

    @property
    def m(self) -> int:
        """Number of inputs u."""
        return self.B.shape[1]

    @property
    def r(self) -> int:
        """Number of outputs y."""
        return self.C.shape[0]

    @property
    def k(self) -> int:
        """Size of the perturbation φ."""
        return self.E.shape[1]

    @property
    def p(self) -> int:
        """Number of unknown parameters θ (0 without a perturbation)."""
        return 0 if self.perturbation is None else self.perturbation.dims[3]

    def require_perturbation(self, owner: str) -> Perturbation:
        """The perturbation g, for an ``owner`` that cannot work without one.

        Parameters
        ----------
        owner : str
            Who needs g (named in the error message), e.g. ``"ModifiedHighGainObserver"``.

        Returns
        -------
        Perturbation

        Raises
        ------
        DimensionError
            The system was built without a perturbation.

        Examples
        --------
        >>> from thetahat import PerturbedLinearSystem
        >>> sys = PerturbedLinearSystem(A=[[0.0]], B=[[1.0]], C=[[1.0]], E=[[1.0]])
        >>> sys.require_perturbation("my observer")
        Traceback (most recent call last):
        ...
        thetahat.errors.DimensionError: my observer needs system.perturbation ...
        """
        if self.perturbation is None:
            raise DimensionError(f"{owner} needs system.perturbation (g of (1)); build the "
                                 "system with perturbation=... .")
        return self.perturbation

    def require_parameter_set(self, owner: str) -> ParameterSet:
        """Θ, for an ``owner`` that cannot work without one.

        Parameters
        ----------
        owner : str
            Who needs Θ (named in the error message), e.g. ``"JointEKF"``.

        Returns
        -------
        ParameterSet

        Raises
        ------
        DimensionError
            The system was built without a parameter set.

        Examples
        --------
        >>> from thetahat import PerturbedLinearSystem
        >>> sys = PerturbedLinearSystem(A=[[0.0]], B=[[1.0]], C=[[1.0]], E=[[1.0]])
        >>> sys.require_parameter_set("stage 2")
        Traceback (most recent call last):
        ...
        thetahat.errors.DimensionError: stage 2 needs system.parameter_set ...
        """
        if self.parameter_set is None:
            raise DimensionError(f"{owner} needs system.parameter_set (Θ of Sec. II); build the "
                                 "system with parameter_set=... .")
        return self.parameter_set

    def __repr__(self) -> str:
        g = type(self.perturbation).__name__ if self.perturbation is not None else "None"
        th = repr(self.parameter_set) if self.parameter_set is not None else "None"
        return (f"PerturbedLinearSystem(n={self.n}, m={self.m}, r={self.r}, k={self.k}, "
                f"p={self.p}, perturbation={g}, parameter_set={th})")
