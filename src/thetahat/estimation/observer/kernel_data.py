"""What the compiled step takes from an observer: its parts checked, its plan laid out as arrays.

The numba kernel (:mod:`~thetahat.estimation.observer.compiled`) and the generated C
(:mod:`thetahat.codegen`) run the same formulas on the same data: :func:`kernel_parts` checks
that an observer's parts have a compiled form and collects them (:class:`KernelParts`: g, Θ, θ*
and the law's options); :func:`kernel_arrays` lays its
:class:`~thetahat.estimation.observer.plan.StepPlan` out as the named tuples of
:mod:`~thetahat.estimation.kernels.kernel_args` for one row; :func:`phi_table` gives the
φ-matrices of a record's step lengths and :func:`kernel_work` the kernel's scratch.

What it may import: the observer, its plan and laws, the model's parts, the kernels' argument
tuples and projection data, and the package's errors. Never the observer's back ends
(compiled, codegen), which import it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import UnsupportedError
from ...model.paramset import Ball, Box, Ellipsoid
from ...model.perturbation import SymbolicPerturbation
from ..kernels.kernel_args import (LawArrays, PlanArrays, SecondArrays, WorkArrays, dimensions,
                                   work_arrays)
from ..kernels.set_projection import ellipsoid_data
from .laws import ConstantLaw, GradientInversion, IntermittentInversion, SmoothRamp
from .laws.inversion import gain_eigen
from .laws.least_squares import FilteredLeastSquares
from .laws.theta_star import ThetaStar, as_theta_star
from .observer import ModifiedHighGainObserver
from .plan import StateLayout, StepPlan

__all__ = ["KernelParts", "SUPPORTED", "kernel_arrays", "kernel_parts", "kernel_work",
           "phi_table", "unsupported"]

FloatArray = NDArray[np.float64]

#: What the compiled path supports, as its error messages say.
SUPPORTED = ("supported: a SymbolicPerturbation g, a Box Θ with diagonal Γ or a Ball or "
              "Ellipsoid Θ, ConstantLaw, "
              "IntermittentInversion (l ≡ 1, i.e. AlgebraicInversion, or a smooth_ramp weight) "
              "with a symbolic θ*, GradientInversion with the default M, FilteredLeastSquares on a "
              "Box Θ, no saturation, an optional SecondObserver")



def unsupported(what: str) -> UnsupportedError:
    """The error of a part the compiled path does not support (``what`` names it).

    Parameters
    ----------
    what : str

    Returns
    -------
    UnsupportedError

    Examples
    --------
    >>> "a Polytope Θ" in str(unsupported("a Polytope Θ"))
    True
    """
    return UnsupportedError(f"compile_observer: {what} is not supported by the compiled path "
                               f"({SUPPORTED}); use the Python observer (run/step) or "
                               "run_batch.")


def _diagonal_gain(law: Any) -> FloatArray:
    G = np.asarray(law.Gamma, dtype=np.float64)
    if not np.array_equal(G, np.diag(np.diag(G))):
        raise unsupported("a non-diagonal Γ (its Γ⁻¹-weighted projection onto a box is a "
                           "least-squares problem)")
    return G


@dataclass(frozen=True, slots=True)
class KernelParts:
    """What the kernel takes from an observer, checked (see :func:`kernel_parts`).

    Attributes
    ----------
    code : int
        0 ConstantLaw, 1 IntermittentInversion with l ≡ 1, 2 with a smooth ramp, 3 gradient,
        4 the filtered least squares.
    perturbation : SymbolicPerturbation
        g, printed into the kernel.
    theta_set : Box, Ball or Ellipsoid
        Θ.
    theta_star : ThetaStar or None
        θ* of the inversion laws.
    ramp : tuple of float or None
        (low, high) of the smooth ramp l (code 2).
    freeze : bool
        The inversion law's ``on_invalid == "freeze"``.
    M : sympy.Matrix or None
        A user's M of the gradient law (code 3), in g's symbols (its ``sympy_form``).
    least_squares : FilteredLeastSquares or None
        The least-squares law (code 4), bound to the observer: its filter and R₀.
    """

    code: int
    perturbation: SymbolicPerturbation
    theta_set: Box | Ball | Ellipsoid
    theta_star: ThetaStar | None = None
    ramp: tuple[float, float] | None = None
    freeze: bool = False
    M: Any = None
    least_squares: FilteredLeastSquares | None = None

    @property
    def law_size(self) -> int:
        """Length of the law's state (the least-squares law's; 0 for the others)."""
        return 0 if self.least_squares is None else self.least_squares.state_size

    @property
    def ellipsoid(self) -> bool:
        """Θ is a ball or an ellipsoid (``kernel_source(..., ellipsoid=True)``), not a box."""
        return not isinstance(self.theta_set, Box)


def kernel_parts(observer: ModifiedHighGainObserver) -> KernelParts:
    """Check that the kernel supports the observer's parts, and collect them.

    Parameters
    ----------
    observer : ModifiedHighGainObserver

    Returns
    -------
    KernelParts

    Raises
    ------
    UnsupportedError
        A part the kernel does not support (the message names it).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.observer.kernel_data import kernel_parts
    >>> kernel_parts(lugre.observer(1.0)).code      # the intermittent law with a smooth ramp
    2
    """
    pert = observer.system.perturbation
    if not isinstance(pert, SymbolicPerturbation):
        raise unsupported(f"a {type(pert).__name__} g (it must be a SymbolicPerturbation)")
    law = observer.update_law
    theta_set = law.parameter_set
    if isinstance(law, FilteredLeastSquares):
        return _least_squares_parts(law, pert, theta_set)
    if law.state_size:
        raise unsupported("an update law with a state")
    if not isinstance(theta_set, Box | Ball | Ellipsoid):
        raise unsupported(f"Θ = {type(theta_set).__name__} (it must be a Box, Ball or "
                           "Ellipsoid)")
    if getattr(law, "saturation", None) is not None:
        raise unsupported("an update law with saturation")
    if isinstance(law, ConstantLaw):
        return KernelParts(code=0, perturbation=pert, theta_set=theta_set)
    if isinstance(theta_set, Box):
        _diagonal_gain(law)
    if isinstance(law, GradientInversion):
        if not (law.perturbation is pert or law.perturbation == pert):
            raise unsupported("GradientInversion with a g other than the observer's")
        M = None
        if law.M is not None:
            form = getattr(law.M, "sympy_form", None)
            if form is None:
                raise unsupported(f"GradientInversion with a user M that is a Python callable "
                                   f"({type(law.M).__name__}) without sympy_form(g), its "
                                   "SymPy matrix in g's symbols")
            M = form(pert)
        return KernelParts(code=3, perturbation=pert, theta_set=theta_set, M=M)
    if not isinstance(law, IntermittentInversion):
        raise unsupported(f"the update law {type(law).__name__}")
    code, ramp = 1, None
    if isinstance(law.l, SmoothRamp):
        code, ramp = 2, (float(law.l.low), float(law.l.high))
    elif law.l is not None:
        raise unsupported("an excitation weight l other than smooth_ramp(low, high)")
    ts = as_theta_star(law.theta_star, pert)
    if ts is not None:
        return KernelParts(code=code, perturbation=pert, theta_set=theta_set, theta_star=ts,
                           ramp=ramp, freeze=law.on_invalid == "freeze")
    raise UnsupportedError(
        f"compile_observer: the θ* of {type(law).__name__} is a Python callable "
        f"({type(law.theta_star).__name__}), which cannot be compiled; build the law with a "
        "ThetaStar (thetahat.estimation.observer.laws.theta_star.ThetaStar.from_expr(expr, perturbation=g, "
        "phi=[...]) or from_perturbation), or give theta_star in the model file: both carry "
        "θ*'s SymPy form.")


def _least_squares_parts(law: FilteredLeastSquares, pert: SymbolicPerturbation,
                         theta_set: Any) -> KernelParts:
    """:class:`KernelParts` of the filtered least-squares law (code 4), or why not."""
    if not isinstance(theta_set, Box):
        raise unsupported(f"FilteredLeastSquares on a {type(theta_set).__name__} Θ (its "
                          "projection in the information's metric is compiled for a Box)")
    if not (law.perturbation is pert or law.perturbation == pert):
        raise unsupported("FilteredLeastSquares with a g other than the observer's")
    if law.filter is None:
        raise unsupported("FilteredLeastSquares not bound to the observer")
    return KernelParts(code=4, perturbation=pert, theta_set=theta_set, least_squares=law)


# --------------------------------------------------------------------------- public API

def phi_table(observer: ModifiedHighGainObserver, dts: FloatArray, present: NDArray[np.bool_]
              ) -> tuple[NDArray[np.int64], tuple[FloatArray, ...]]:
    """The φ-matrices of a record's steps: which table entry each step uses, and the table.

    One entry per distinct (step length, sample present): Φ₁, Φ₂ of the observer's
    :meth:`~ModifiedHighGainObserver.plan` for that length — the corrected ones, or the
    prediction's over a missing sample — and the second observer's (zeros without one).

    Parameters
    ----------
    observer : ModifiedHighGainObserver
    dts : ndarray, shape (N - 1,)
        Step lengths.
    present : ndarray of bool, shape (N - 1,)
        Whether the sample at the start of each step is present.

    Returns
    -------
    plan_of : ndarray of int64, shape (N - 1,)
    table : tuple of ndarray
        (Φ₁, Φ₂, Φ₁ of the second observer, Φ₂ of the second observer), shapes (J, ·, ·).

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> plan_of, table = phi_table(lugre.observer(), np.array([1e-3, 2e-3, 1e-3]),
    ...                            np.ones(3, dtype=bool))
    >>> plan_of.tolist(), table[0].shape
    ([0, 1, 0], (2, 3, 3))
    """
    lay = observer.layout
    keys = np.where(present, dts, -dts)          # a missing sample: its own entry
    uniq, inverse = np.unique(keys, return_inverse=True)
    q, n = lay.n + lay.k, lay.n
    table = tuple(np.zeros((uniq.size, d, d)) for d in (q, q, n, n))
    for j, key in enumerate(uniq.tolist()):
        plan = observer.plan(abs(key))
        sec = plan.second
        mats: tuple[FloatArray | None, ...]
        if key > 0:
            mats = (plan.Phi1, plan.Phi2, None if sec is None else sec.Phi1,
                    None if sec is None else sec.Phi2)
        else:
            mats = (plan.Phi1_open, plan.Phi2_open, None if sec is None else sec.Phi1_open,
                    None if sec is None else sec.Phi2_open)
        for dest, M in zip(table, mats):
            if M is not None:
                dest[j] = M[0]
    return np.ascontiguousarray(inverse.reshape(-1), dtype=np.int64), table


def kernel_arrays(parts: KernelParts, plan: StepPlan
                  ) -> tuple[PlanArrays, SecondArrays, LawArrays, tuple[bool, bool]]:
    """(P, P2, LP, flags): the plan's arrays for one row, the second observer's, the law's,
    and (a second observer is attached, its g sees C x̂₂): what the kernel takes.

    The named tuples of :mod:`~thetahat.estimation.kernels.kernel_args` (the fields every binding
    uses; see :mod:`~thetahat.estimation.observer.formulas` and
    :mod:`~thetahat.estimation.observer.laws.formulas`). Writable, C-contiguous copies: numba compiles
    one specialisation per array type.

    Parameters
    ----------
    parts : KernelParts
    plan : StepPlan
        For one row.

    Returns
    -------
    tuple
    """
    lay = plan.layout
    n, m, r, k, p = lay.n, lay.m, lay.r, lay.k, lay.p

    def own(a: Any) -> FloatArray:
        return np.array(a, dtype=np.float64, order="C", copy=True)

    P = PlanArrays(L=own(plan.L[0]), Bv=own(plan.Bv[0]), E=own(plan.E), C=own(plan.C),
                   A=own(plan.A), B=own(plan.B), K_x=own(plan.K_x[0]), KxC=own(plan.KxC[0]),
                   Phi1=own(plan.Phi1[0]), Phi2=own(plan.Phi2[0]))
    sec = plan.second
    if sec is None:                  # never read: flags[0] (a second observer) is False
        P2 = SecondArrays(*(np.zeros(shape) for shape in ((n, n), (n, m), (r, n), (n, k),
                                                          (n, r), (n, n), (n, n))))
    else:
        P2 = SecondArrays(A=own(sec.A), B=own(sec.B), C=own(sec.C), E=own(sec.E),
                          K_x=own(sec.K_x[0]), Phi1=own(sec.Phi1[0]), Phi2=own(sec.Phi2[0]))
    ps = parts.theta_set
    G = own(np.eye(p) if plan.Gamma is None else plan.Gamma[0])
    if isinstance(ps, Box):
        box: dict[str, Any] = {"lower": own(ps.lower), "upper": own(ps.upper)}
    else:                            # the metric Γ (ConstantLaw: Euclidean), Θ's c and Q
        box = {"lower": own(ps.center), "upper": own(ps.center), "ell": ellipsoid_data(ps),
               "pw": np.zeros((p + 2, p + 1)), "Gamma": np.eye(p) if parts.code == 0 else G}
    if parts.code == 0:
        LP = LawArrays(**box)
    elif parts.code == 4 and parts.least_squares is not None:
        LP = parts.least_squares.law_arrays(None)   # its Φ₁: the step's (compiled._call)
    elif parts.code == 3:
        LP = LawArrays(g=np.zeros(k), J=np.zeros((k, p)), Mt=np.zeros((p, k)),
                       GM=np.zeros((p, k)), f=np.zeros(p), K=np.zeros((p, p)),
                       Z=np.zeros((p + 1, p + 1)), Ex=np.zeros((p + 1, p + 1)),
                       T=np.zeros((p + 1, p + 1)), U=np.zeros((p + 1, p + 1)),
                       **{"Gamma": G, **box})
    else:                            # Γ = V diag(Λ) Vᵀ (a diagonal Γ: V = I exactly)
        low, high = parts.ramp if parts.ramp is not None else (0.0, 1.0)
        lam, V, VT = (own(a) for a in gain_eigen(G))
        LP = LawArrays(lam=lam, V=V, VT=VT, ts=np.zeros(p),
                       err=np.zeros(p), opts=np.array([low, high, parts.ramp is not None,
                                                       parts.freeze], dtype=np.float64), **box)
    return P, P2, LP, (sec is not None, sec is not None and sec.g_on_estimates)


def kernel_work(lay: StateLayout) -> tuple[WorkArrays, tuple[FloatArray, ...]]:
    """Scratch of the kernel: the formulas' work buffers and the rows (s, s⁺, u, y).

    Parameters
    ----------
    lay : StateLayout

    Returns
    -------
    W : WorkArrays
        The formulas' work buffers (:func:`~thetahat.estimation.kernels.kernel_args.work_arrays`).
    rows : tuple of ndarray
        (s, s⁺, u, y, u₁, y₁) of one sample (u₁, y₁: the end of a first-order-hold step).
    """
    W = work_arrays(dimensions(lay.n, lay.m, lay.r, lay.k, lay.p, lay.law_size))
    return W, (np.zeros(lay.size), np.zeros(lay.size), np.zeros(max(lay.m, 1)),
               np.zeros(lay.r), np.zeros(max(lay.m, 1)), np.zeros(lay.r))
