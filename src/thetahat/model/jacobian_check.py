"""Checks of a perturbation's Jacobians: against central finite differences of g
(:func:`check_jacobians`), and that g depends on θ at all (:func:`require_theta_dependence`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validate import check_finite, positive_scalar
from ..errors import DimensionError, UpdateLawError
from .perturbation import (ARG_NAMES, CallablePerturbation, Perturbation, SymbolicPerturbation,
                           batch_args, central_difference)

__all__ = ["CHECK_ATOL", "CHECK_RTOL", "DEPENDENCE_SAMPLES", "JacobianCheck",
           "JacobianComparison", "check_jacobians", "require_theta_dependence"]

FloatArray = NDArray[np.float64]

#: Default relative tolerance of :func:`check_jacobians`. The finite-difference reference is
#: accurate to about eps**(2/3) for well-scaled g, but to only ~1e-6 for the LuGre g, whose
#: ω0 = 0.01 makes it vary on a scale far below the step floor of 1; 1e-4 leaves a margin of
#: 100 over that, while any wrong formula (a missing factor or sign) is off by O(1).
CHECK_RTOL: float = 1e-4

#: Default absolute tolerance of :func:`check_jacobians`: the floor for entries that vanish
#: analytically, where central differences return rounding noise of order eps * |g| / h
#: ≈ 4e-11 |g|; 1e-8 covers |g| up to a few hundred.
CHECK_ATOL: float = 1e-8

@final
@dataclass(frozen=True, slots=True)
class JacobianComparison:
    """One Jacobian compared with central finite differences of g.

    Attributes
    ----------
    name : str
        ``"dg_dv"``, ``"dg_dx"`` or ``"dg_dtheta"``.
    max_abs_error : float
        max |J - J_fd| over the batch and the entries.
    max_abs_index : tuple of int
        Where it occurs: batch index followed by (row, column).
    max_rel_error : float
        max |J - J_fd| / (|J_fd| + atol / rtol): the relative error, with magnitudes below
        atol / rtol counted as atol / rtol so that vanishing entries are judged absolutely.
        The comparison passes when this is <= rtol, i.e. |J - J_fd| <= atol + rtol |J_fd|
        everywhere.
    max_rel_index : tuple of int
        Where the largest relative error occurs.
    value, reference : float
        J and J_fd at ``max_rel_index``.
    ok : bool
    """

    name: str
    max_abs_error: float
    max_abs_index: tuple[int, ...]
    max_rel_error: float
    max_rel_index: tuple[int, ...]
    value: float
    reference: float
    ok: bool

    def __repr__(self) -> str:
        def where(index: tuple[int, ...]) -> str:
            if not index:
                return ""
            batch = f"batch {index[:-2]}, " if len(index) > 2 else ""
            return f" at {batch}entry {list(index[-2:])}"
        verdict = "ok" if self.ok else "MISMATCH"
        return (f"{self.name}: {verdict}; max abs error {self.max_abs_error:.3g}"
                f"{where(self.max_abs_index)}; max rel error {self.max_rel_error:.3g}"
                f"{where(self.max_rel_index)} (J = {self.value:.6g}, "
                f"finite differences = {self.reference:.6g})")


@final
@dataclass(frozen=True, slots=True)
class JacobianCheck:
    """Result of :func:`check_jacobians`: one comparison per checked Jacobian.

    Attributes
    ----------
    dg_dv, dg_dx, dg_dtheta : JacobianComparison or None
        None when that Jacobian was not checked (a :class:`CallablePerturbation` whose
        Jacobian already comes from finite differences).
    rtol, atol : float
        The tolerances used.
    n_points : int
        Number of batch points compared.
    """

    dg_dv: JacobianComparison | None
    dg_dx: JacobianComparison | None
    dg_dtheta: JacobianComparison | None
    rtol: float
    atol: float
    n_points: int

    @property
    def ok(self) -> bool:
        """True when every checked Jacobian agrees with finite differences."""
        return all(c.ok for c in (self.dg_dv, self.dg_dx, self.dg_dtheta) if c is not None)

    def __repr__(self) -> str:
        lines = [f"JacobianCheck(ok={self.ok}, rtol={self.rtol:g}, atol={self.atol:g}, "
                 f"n_points={self.n_points})"]
        for name in ("dg_dv", "dg_dx", "dg_dtheta"):
            c = getattr(self, name)
            lines.append(f"  {c!r}" if c is not None
                         else f"  {name}: not checked (already finite differences)")
        return "\n".join(lines)


def _compare(name: str, J: FloatArray, J_fd: FloatArray, rtol: float, atol: float
             ) -> JacobianComparison:
    if J.size == 0:
        return JacobianComparison(name, 0.0, (), 0.0, (), 0.0, 0.0, True)
    err = np.abs(J - J_fd)
    err = np.where(np.isnan(err), np.inf, err)
    rel = err / (np.abs(J_fd) + atol / rtol)
    rel = np.where(np.isnan(rel), np.inf, rel)
    i_abs = np.unravel_index(int(np.argmax(err)), err.shape)
    i_rel = np.unravel_index(int(np.argmax(rel)), rel.shape)
    return JacobianComparison(
        name=name, max_abs_error=float(err[i_abs]),
        max_abs_index=tuple(int(i) for i in i_abs), max_rel_error=float(rel[i_rel]),
        max_rel_index=tuple(int(i) for i in i_rel), value=float(J[i_rel]),
        reference=float(J_fd[i_rel]), ok=bool(np.all(err <= atol + rtol * np.abs(J_fd))))


def check_jacobians(perturbation: Perturbation, v: ArrayLike, x: ArrayLike, theta: ArrayLike, *,
                    rtol: float = CHECK_RTOL, atol: float = CHECK_ATOL) -> JacobianCheck:
    """Compare the Jacobians of ``perturbation`` with central finite differences of its g.

    Parameters
    ----------
    perturbation : Perturbation
    v : array_like, shape (..., m + r)
    x : array_like, shape (..., n)
    theta : array_like, shape (..., p)
        The points, a batch with broadcastable leading shapes; they must be finite.
    rtol, atol : float, optional
        Entry (i, j) passes when |J - J_fd| <= atol + rtol |J_fd| (defaults CHECK_RTOL
        = 1e-4 and CHECK_ATOL = 1e-8; see their comments for the reasons).

    Returns
    -------
    JacobianCheck
        The largest absolute and relative mismatch of each Jacobian, where it occurs,
        and ``ok``.

    Raises
    ------
    DimensionError
        Wrong shapes, or tolerances that are not positive.
    NonFiniteError
        A point holds NaN or inf.

    Notes
    -----
    The finite differences use the step rule of :class:`CallablePerturbation`. For a
    :class:`CallablePerturbation` only the user-supplied Jacobians are checked. Near a
    kink of g (|y| at y = 0) the two can legitimately disagree; check away from kinks.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.perturbation import CallablePerturbation
    >>> pert = CallablePerturbation(g=lambda v, x, th: th * x ** 2, n=1, m=0, r=1, p=1, k=1,
    ...                             dg_dx=lambda v, x, th: (th * x)[..., None])  # wrong: 2θx
    >>> check_jacobians(pert, np.zeros(1), np.array([1.5]), np.array([2.0])).ok
    False
    """
    if not isinstance(perturbation, Perturbation):
        raise DimensionError(f"perturbation must be a thetahat Perturbation; got "
                             f"{type(perturbation).__name__}.")
    rtol = positive_scalar("rtol", rtol)
    atol = positive_scalar("atol", atol)
    v_, x_, t_, batch = batch_args(perturbation.dims, v, x, theta)
    for name, arr in (("v", v_), ("x", x_), ("theta", t_)):
        check_finite(name, arr)
    k = perturbation.dims[4]
    if isinstance(perturbation, CallablePerturbation):
        checked = perturbation.supplied_jacobians
    else:
        checked = ARG_NAMES
    methods = (perturbation.dg_dv, perturbation.dg_dx, perturbation.dg_dtheta)
    results: dict[str, JacobianComparison | None] = {}
    for i, (name, method) in enumerate(zip(ARG_NAMES, methods)):
        label = "dg_d" + name
        if name not in checked:
            results[label] = None
            continue
        expected = batch + (k, (v_, x_, t_)[i].shape[-1])
        J = np.asarray(method(v_, x_, t_), dtype=np.float64)
        if J.shape != expected:
            raise DimensionError(f"{label} of {type(perturbation).__name__} returned shape "
                                 f"{J.shape}; expected {expected}.")
        J_fd = central_difference(perturbation.g, i, [v_, x_, t_], batch, k)
        results[label] = _compare(label, J, J_fd, rtol, atol)
    return JacobianCheck(**results, rtol=rtol, atol=atol, n_points=int(np.prod(batch)))


#: Sample points of :func:`require_theta_dependence` for perturbations without a symbolic form.
DEPENDENCE_SAMPLES = 64


def require_theta_dependence(perturbation: Perturbation, parameter_set: Any, *,
                             owner: str, seed: int = 0) -> None:
    """Refuse a perturbation whose g does not depend on θ (∂g/∂θ ≡ 0): θ cannot be estimated.

    A :class:`SymbolicPerturbation` is checked structurally (no θ symbol in g, or ∂g/∂θ
    built as zero; a dependence that only cancels after simplification is not detected); any other
    perturbation at ``DEPENDENCE_SAMPLES`` points with θ sampled from Θ and v, x standard
    normal (a sampled check can miss a dependence confined to a small region, never invent one).

    Parameters
    ----------
    perturbation : Perturbation
    parameter_set : ParameterSet
        Θ, sampled with ``parameter_set.sample(rng, count)``.
    owner : str
        Names the caller in the message (e.g. "GradientInversion").
    seed : int
        Seed of the sampled check.

    Raises
    ------
    UpdateLawError
        ∂g/∂θ vanishes identically (or at every sample).

    Examples
    --------
    >>> import sympy as sp
    >>> from thetahat.model.perturbation import SymbolicPerturbation
    >>> from thetahat.model.paramset import Box
    >>> y, x, th = sp.symbols("y x theta")
    >>> g = SymbolicPerturbation.from_sympy(y**2, u=[], y=[y], x=[x], theta=[th])
    >>> require_theta_dependence(g, Box([0.0], [1.0]), owner="GradientInversion")
    Traceback (most recent call last):
    ...
    thetahat.errors.UpdateLawError: GradientInversion: g does not depend on θ ...
    """
    n, m, r, p, k = perturbation.dims
    if isinstance(perturbation, SymbolicPerturbation):
        J = perturbation.jacobian("theta")
        # structural test (cheap for any size of g): no θ symbol left, or ∂g/∂θ == 0 as built
        independent = not (perturbation.expr.free_symbols & set(perturbation.theta)) or all(
            e == 0 for e in J)
        how = "∂g/∂θ is identically zero"
    else:
        rng = np.random.default_rng(seed)
        th = np.asarray(parameter_set.sample(rng, DEPENDENCE_SAMPLES), dtype=np.float64)
        v = rng.standard_normal((DEPENDENCE_SAMPLES, m + r))
        x = rng.standard_normal((DEPENDENCE_SAMPLES, n))
        with np.errstate(all="ignore"):
            J = np.asarray(perturbation.dg_dtheta(v, x, th), dtype=np.float64)
        independent = bool(np.all(J == 0))
        how = f"∂g/∂θ is zero at all {DEPENDENCE_SAMPLES} sampled points of Θ"
    if independent:
        raise UpdateLawError(
            f"{owner}: g does not depend on θ ({how}), so the output carries no information "
            f"about θ and no update law can estimate it. Check that the parameter symbols in "
            f"g are the ones declared as theta.")
