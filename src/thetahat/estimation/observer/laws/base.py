"""The update-law contract of Sec. IV: the abstract :class:`UpdateLaw` (``rate``, ``step``,
``advance`` with a law state and per-row Γ), :class:`ConstantLaw`, and the helpers every law
shares (argument checks, finite candidates, the Γ⁻¹-weighted projection per row).

The laws of Propositions 1–4 live in :mod:`~thetahat.estimation.observer.laws.inversion` and
:mod:`~thetahat.estimation.observer.laws.gradient`; :mod:`~thetahat.estimation.observer.laws` gathers them all.
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...._validate import check_finite, positive_scalar
from ....errors import DimensionError, ParameterSetError, UpdateLawError
from ....model.paramset import Box, ParameterSet
from ....model.system import PerturbedLinearSystem
from .. import formulas
from . import formulas as law_formulas
from ...kernels.kernel_args import LawArrays
from ...kernels.modules import numpy_binding
from ...kernels.printer import Program
from ...kernels.subset import External, definition
from .projection import Projection, Saturation

__all__ = ["FAR", "INIT_RTOL", "ConstantLaw", "UpdateLaw", "apply_saturation", "as_batch",
           "broadcast_rows", "check_law_options", "finite_candidate", "is_diagonal",
           "law_binding", "law_program", "project_rows"]

FloatArray = NDArray[np.float64]

#: θ̂₀ may lie this far outside Θ, relative to max(1, ‖θ̂₀‖), and still be accepted (and snapped
#: onto Θ): a boundary point written with 15 significant digits is off by rounding only.
INIT_RTOL = 1e-12
#: Candidate points are clipped to ±FAR before the projection: far enough to be projected onto
#: the same face as an overflowing value, small enough that differences with points of Θ stay
#: finite.
FAR = 1e300



@functools.cache
def law_program() -> Program:
    """The law formulas (:data:`~thetahat.estimation.observer.laws.formulas.LAW_FORMULAS`) as
    one program, their hooks provided by the binding.

    Returns
    -------
    Program

    Examples
    --------
    >>> law_program().closure(["held_law"])
    ['held_law']
    """
    hooks = {name: External(params, frozenset(params) & formulas.VIEWED)
             for name, params in law_formulas.HOOKS.items()}
    return Program({name: definition(fn) for name, fn in law_formulas.LAW_FORMULAS.items()},
                   hooks)


def law_binding(owner: object, key: Any, roots: tuple[str, ...], row: bool,
                names: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """Law formulas ``roots`` printed for NumPy (one row or a batch), bound to ``names()``
    once per ``(owner, key, row)`` (:func:`~thetahat.estimation.kernels.modules.numpy_binding`).

    Parameters
    ----------
    owner : object
        The law (kept alive with the binding).
    key : hashable
    roots : tuple of str
        Names of :data:`~thetahat.estimation.observer.laws.formulas.LAW_FORMULAS`.
    row : bool
        One row (vectors of shape (p,)), else rows on a leading axis.
    names : callable
        The hooks and constants.

    Returns
    -------
    dict of str to function
    """
    prog = law_program()
    return numpy_binding(owner, (key, roots, row), prog, roots, "row" if row else "batch",
                         names)


def as_batch(v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
              p: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, tuple[int, ...]]:
    """(v, x̂, φ̂, θ̂) as finite float64 arrays, and their broadcast batch shape.

    Parameters
    ----------
    v, x_hat, phi_hat, theta_hat : array_like, shapes (..., m + r), (..., n), (..., k), (..., p)
    p : int
        Number of parameters.

    Returns
    -------
    v, x_hat, phi_hat, theta_hat : ndarray
    batch : tuple of int

    Raises
    ------
    DimensionError
        A scalar, a wrong θ̂ width, or batch shapes that do not broadcast.
    NonFiniteError
        NaN or inf in an argument.

    Examples
    --------
    >>> as_batch([0.0, 1.0], [[0.0]] * 4, [1.0], [0.5], 1)[4]
    (4,)
    """
    arrs = []
    for name, a in (("v", v), ("x_hat", x_hat), ("phi_hat", phi_hat), ("theta_hat", theta_hat)):
        arr = np.asarray(a, dtype=np.float64)
        if arr.ndim == 0:
            raise DimensionError(f"{name} must have shape (..., size); got a scalar. Wrap it, "
                                 f"e.g. np.atleast_1d({name}).")
        check_finite(name, arr)
        arrs.append(arr)
    if arrs[3].shape[-1] != p:
        raise DimensionError(f"theta_hat must have shape (..., {p}); got {arrs[3].shape}.")
    try:
        batch = np.broadcast_shapes(*(a.shape[:-1] for a in arrs))
    except ValueError as exc:
        raise DimensionError(f"leading (batch) shapes do not broadcast: v {arrs[0].shape}, "
                             f"x_hat {arrs[1].shape}, phi_hat {arrs[2].shape}, theta_hat "
                             f"{arrs[3].shape}.") from exc
    return arrs[0], arrs[1], arrs[2], arrs[3], batch


def broadcast_rows(batch: tuple[int, ...], *arrays: FloatArray) -> list[FloatArray]:
    """Each array with its leading (batch) shape broadcast to ``batch`` (views, no copies).

    Parameters
    ----------
    batch : tuple of int
    *arrays : ndarray, shapes (..., size)

    Returns
    -------
    list of ndarray, shapes batch + (size,)

    Examples
    --------
    >>> import numpy as np
    >>> [a.shape for a in broadcast_rows((3,), np.zeros(2), np.zeros((3, 1)))]
    [(3, 2), (3, 1)]
    """
    return [a if a.shape[:-1] == batch else np.broadcast_to(a, batch + a.shape[-1:])
            for a in arrays]


def finite_candidate(cand: FloatArray, fallback: FloatArray) -> FloatArray:
    """NaN -> fallback, ±inf and huge values -> ±FAR, so that the projection can handle them.

    Parameters
    ----------
    cand : ndarray, shape (..., p)
        A candidate θ before the projection.
    fallback : ndarray, shape (..., p)
        What NaN entries become (the current θ̂).

    Returns
    -------
    ndarray, shape (..., p)

    Examples
    --------
    >>> import numpy as np
    >>> finite_candidate(np.array([np.nan, np.inf]), np.array([1.0, 1.0])).tolist()
    [1.0, 1e+300]
    """
    out = np.array(cand, dtype=np.float64, copy=True)
    p = out.shape[-1]
    fn = law_binding(law_program(), p, ("finite_candidate",), False,
                     lambda: {"NP": p, "FAR": FAR})["finite_candidate"]
    fn(out, np.broadcast_to(fallback, out.shape))
    return out


def is_diagonal(G: FloatArray) -> bool:
    """Whether every matrix of ``G`` (shape (..., p, p)) is diagonal.

    Parameters
    ----------
    G : ndarray, shape (..., p, p)

    Returns
    -------
    bool

    Examples
    --------
    >>> import numpy as np
    >>> is_diagonal(np.diag([1.0, 2.0])), is_diagonal(np.ones((2, 2)))
    (True, False)
    """
    d = np.diagonal(G, axis1=-2, axis2=-1)
    return bool(np.array_equal(G, d[..., None] * np.eye(G.shape[-1])))


def project_rows(proj: Projection, cand: FloatArray, G: FloatArray | None) -> FloatArray:
    """The Γ⁻¹-weighted projection onto Θ with the law's Γ, or one Γ per row of ``G``.

    Parameters
    ----------
    proj : Projection
        The law's projection (Θ, its Γ and boundary layer).
    cand : ndarray, shape (..., p)
        Finite candidates (:func:`finite_candidate`).
    G : ndarray, shape (..., p, p), or None
        Γ per row; None: the projection's own.

    Returns
    -------
    ndarray, shape (..., p)
        Points of Θ.
    """
    if G is None:
        return proj.project(cand)
    ps = proj.parameter_set
    if isinstance(ps, Box) and is_diagonal(G):
        return ps.nearest(cand)          # a clip, whatever the diagonal metric
    p = cand.shape[-1]
    flat = cand.reshape(-1, p)
    Gs = np.broadcast_to(G, flat.shape[:1] + (p, p))
    out = np.empty_like(flat)
    distinct, which = np.unique(Gs.reshape(len(flat), -1), axis=0, return_inverse=True)
    for j, Gj in enumerate(distinct):
        rows = np.flatnonzero(which.reshape(-1) == j)
        out[rows] = Projection(ps, Gj.reshape(p, p), layer=proj.layer).project(flat[rows])
    return out.reshape(cand.shape)


def check_law_options(owner: str, parameter_set: ParameterSet, on_invalid: str,
                      saturation: Saturation | None) -> None:
    """Check the options every law shares: Θ, ``on_invalid`` and ``saturation``.

    Parameters
    ----------
    owner : str
        The law's name, for the message.
    parameter_set : ParameterSet
    on_invalid : str
        "raise" or "freeze".
    saturation : Saturation or None

    Raises
    ------
    DimensionError
        ``parameter_set`` is not a ParameterSet.
    UpdateLawError
        Unknown ``on_invalid``, or ``saturation`` of the wrong type.
    """
    if not isinstance(parameter_set, ParameterSet):
        raise DimensionError(f"{owner}: parameter_set must be a thetahat ParameterSet; got "
                             f"{type(parameter_set).__name__}.")
    if on_invalid not in ("raise", "freeze"):
        raise UpdateLawError(f"{owner}: on_invalid must be 'raise' or 'freeze'; got "
                             f"{on_invalid!r}.")
    if saturation is not None and not isinstance(saturation, Saturation):
        raise UpdateLawError(f"{owner}: saturation must be a Saturation or None.")


def apply_saturation(sat: Saturation | None, x: FloatArray,
                     phi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(x̂, φ̂) saturated by ``sat`` (Remark 3), unchanged without one.

    Parameters
    ----------
    sat : Saturation or None
    x, phi : ndarray, shapes (..., n), (..., k)

    Returns
    -------
    x, phi : ndarray
    """
    return (x, phi) if sat is None else sat.apply(x, phi)


class UpdateLaw(ABC):
    r"""Abstract update law (8): θ̂̇ = u_θ(v, x̂, φ̂, θ̂), projection included.

    $$
    \dot{\hat\theta} = u_\theta(v, \hat x, \hat\phi, \hat\theta),
    \qquad \hat\theta(t) \in \Theta \text{ for all } t. \tag{8}
    $$

    Concrete laws are final frozen dataclasses. Two entry points over one law:
    ``rate`` for continuous time (the observer's (3b) uses it as θ̂̇) and ``step`` for
    discrete time, which must return a point of Θ whatever the data.
    """

    @property
    @abstractmethod
    def parameter_set(self) -> ParameterSet:
        """Θ, where θ̂ stays."""

    @abstractmethod
    def rate(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
             theta_hat: FloatArray) -> FloatArray:
        """θ̂̇ = u_θ(v, x̂, φ̂, θ̂) (8); shape (..., p)."""

    def step(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
             theta_hat: FloatArray, dt: float, *, Gamma: ArrayLike | None = None
             ) -> FloatArray:
        """θ̂ after a step of length dt, guaranteed in Θ (default: Euler, then ``nearest``).

        ``Gamma`` (shape (..., p, p), one Γ per batch row) replaces the law's own Γ; laws
        without a Γ refuse it.
        """
        dt = positive_scalar("dt", dt)
        if Gamma is not None:
            raise UpdateLawError(f"{type(self).__name__} has no gain Γ; pass Gamma=None.")
        th = np.asarray(theta_hat, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            nxt = th + dt * self.rate(v, x_hat, phi_hat, theta_hat)
        return self.parameter_set.nearest(finite_candidate(nxt, th))

    # ------------------------------------------------------------------ batched contract
    @property
    def gain(self) -> FloatArray | None:
        """The per-row parameter of the law, Γ (p, p), or None for a law without one.

        A batch of observers passes one Γ per row to :meth:`advance` (``Gamma=``, shape
        (B, p, p)); everything else about the law is shared by the rows.
        """
        G = getattr(self, "Gamma", None)
        return None if G is None else np.asarray(G, dtype=np.float64)

    @property
    def state_size(self) -> int:
        """Length of the law's own state (a gain matrix, filtered regressors, ...); 0 here.

        The state lives in the observer state after θ̂ (and x̂₂) and is advanced by
        :meth:`advance` in the same step.
        """
        return 0

    def init_state(self, theta_hat0: FloatArray) -> FloatArray:
        """Initial law state for the validated θ̂₀ (shape (..., p)); shape (..., state_size).

        Parameters
        ----------
        theta_hat0 : ndarray, shape (..., p)

        Returns
        -------
        ndarray, shape (..., state_size)
        """
        th = np.asarray(theta_hat0, dtype=np.float64)
        return np.zeros(th.shape[:-1] + (self.state_size,))

    def advance(self, v: FloatArray, x_hat: FloatArray, phi_hat: FloatArray,
                theta_hat: FloatArray, state: FloatArray, dt: float, *,
                Gamma: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
        """One step of θ̂ and of the law's state: the entry point of the observer's step.

        Parameters
        ----------
        v : ndarray, shape (B, m + r)
        x_hat : ndarray, shape (B, n)
        phi_hat : ndarray, shape (B, k)
        theta_hat : ndarray, shape (B, p)
        state : ndarray, shape (B, state_size)
            The law's state at the start of the step.
        dt : float
            Step length > 0.
        Gamma : ndarray, shape (B|1, p, p), optional
            Γ per row (default: the law's own).

        Returns
        -------
        theta_hat : ndarray, shape (B, p)
            In Θ.
        state : ndarray, shape (B, state_size)

        Notes
        -----
        The default (memoryless laws) is ``step`` with the state passed through; a law with a
        state overrides it and propagates both in one go.
        """
        if Gamma is None:
            th = self.step(v, x_hat, phi_hat, theta_hat, dt)
        else:
            th = self.step(v, x_hat, phi_hat, theta_hat, dt, Gamma=Gamma)
        return np.asarray(th, dtype=np.float64), state

    def for_observer(self, system: PerturbedLinearSystem, K_x: FloatArray,
                     K_phi: FloatArray) -> UpdateLaw:
        """The law as the observer with gains (K_x, K_φ) runs it; this law itself here.

        A law that depends on the observer's gains (the filtered regressor of
        :class:`~thetahat.estimation.observer.laws.least_squares.FilteredLeastSquares`) returns a copy
        bound to them; :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver`
        calls it when it is built.

        Parameters
        ----------
        system : PerturbedLinearSystem
        K_x : ndarray, shape (n, r)
        K_phi : ndarray, shape (k, r)

        Returns
        -------
        UpdateLaw
        """
        del system, K_x, K_phi
        return self

    def init(self, theta_hat0: ArrayLike | None = None) -> FloatArray:
        """Validated initial estimate θ̂(t₀) ∈ Θ, shape (..., p).

        Parameters
        ----------
        theta_hat0 : array_like, shape (..., p), optional
            Defaults to the interior point (centre) of Θ.

        Raises
        ------
        ParameterSetError
            θ̂₀ lies outside Θ (Assumption 3 needs θ̂(t₀) ∈ Θ).
        NonFiniteError
            θ̂₀ holds NaN or inf.
        """
        ps = self.parameter_set
        th = np.array(ps.interior_point if theta_hat0 is None else theta_hat0, dtype=np.float64)
        if th.ndim == 0 or th.shape[-1] != ps.dim:
            raise DimensionError(f"theta_hat0 must have shape (..., {ps.dim}); got {th.shape}.")
        check_finite("theta_hat0", th)
        tol = INIT_RTOL * max(1.0, float(np.max(np.abs(th))))
        inside = np.asarray(ps.contains(th, tol=tol))
        if not np.all(inside):
            bad = th if th.ndim == 1 else th.reshape(-1, ps.dim)[~inside.reshape(-1)][0]
            raise ParameterSetError(f"theta_hat0 = {np.round(bad, 6).tolist()} lies outside "
                                    f"Θ = {ps!r}; start the estimator inside Θ, e.g. at "
                                    f"parameter_set.nearest(theta_hat0).")
        return ps.nearest(th)


@final
@dataclass(frozen=True, slots=True, eq=False)
class ConstantLaw(UpdateLaw):
    """θ̂̇ = 0: the parameter estimate is held at a known or assumed value.

    Parameters
    ----------
    theta : array_like, shape (p,)
        The value held; it is also what ``init()`` returns.
    parameter_set : ParameterSet
        Θ; ``theta`` must lie in it.

    Raises
    ------
    ParameterSetError
        ``theta`` is outside Θ.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.paramset import Box
    >>> from thetahat.estimation.observer.laws import ConstantLaw
    >>> law = ConstantLaw([0.3], Box([0.0], [1.0]))
    >>> law.init().tolist(), law.rate([0.0, 1.0], [0.0, 0.0], [2.0], [0.3]).tolist()
    ([0.3], [0.0])
    """

    theta: FloatArray
    parameter_set: ParameterSet

    def __init__(self, theta: ArrayLike, parameter_set: ParameterSet) -> None:
        if not isinstance(parameter_set, ParameterSet):
            raise DimensionError(f"parameter_set must be a thetahat ParameterSet; got "
                                 f"{type(parameter_set).__name__}.")
        object.__setattr__(self, "parameter_set", parameter_set)
        th = UpdateLaw.init(self, np.atleast_1d(np.asarray(theta, dtype=np.float64)))
        th.setflags(write=False)
        object.__setattr__(self, "theta", th)

    def rate(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
             theta_hat: ArrayLike) -> FloatArray:
        """Zero, shape (..., p)."""
        *_, batch = as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        return np.zeros(batch + (self.parameter_set.dim,))

    def step(self, v: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike, theta_hat: ArrayLike,
             dt: float, *, Gamma: ArrayLike | None = None) -> FloatArray:
        """θ̂ unchanged (projected onto Θ should it lie outside); shape (..., p).

        ``Gamma`` is accepted for the batched contract and has no effect (θ̂̇ = 0).
        """
        positive_scalar("dt", dt)
        v_, x, phi, th, batch = as_batch(v, x_hat, phi_hat, theta_hat, self.parameter_set.dim)
        thn = np.empty(batch + th.shape[-1:])
        env = law_binding(self, None, ("held_law",), False, lambda: _held_names(self))
        env["held_law"](LawArrays(), v_, x, phi, np.broadcast_to(th, thn.shape), dt, thn, None)
        return thn

    def init(self, theta_hat0: ArrayLike | None = None) -> FloatArray:
        """``theta`` when θ̂₀ is not given, else the validated θ̂₀."""
        return UpdateLaw.init(self, self.theta if theta_hat0 is None else theta_hat0)


def _held_names(law: ConstantLaw) -> dict[str, Any]:
    """The hooks of :func:`law_formulas.held_law` for one law."""
    def project(LP: LawArrays, thn: FloatArray) -> int:
        thn[...] = law.parameter_set.nearest(thn)
        return 0

    return {"project": project, "NP": law.parameter_set.dim}
