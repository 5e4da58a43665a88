"""The observer's plan: its matrices, gains and discretisation caches, built once per (design, dt).

A :class:`StepPlan` holds everything the step of :mod:`thetahat.estimation.observer.step` needs that does
not change from sample to sample, for B observers at once (a leading *batch axis* of length B,
or 1 when every row shares the same observer): the system matrices, the gains K_x, K_φ of (3),
the constant part L of the observer's Jacobian, the φ-matrices Φ₁ = h φ₁(hL), Φ₂ = h² φ₂(hL) of
the exponential step (:mod:`thetahat.estimation.observer.discretize`) for the step length h — for the
corrected step and for the prediction over a missing sample (K = 0) —, the same for the second
observer of Sec. VI, and the per-row parameters of the update law (Γ).

This is the stable public contract the back ends build on: the Python step, the batched
:func:`~thetahat.estimation.observer.batch_run.run_batch`, the compiled kernel and code generators read
these fields and nothing private. Fields are read-only arrays; the layout of the observer state
is ``col(x̂, z, θ̂[, x̂₂][, law state])`` with the offsets given by :attr:`StepPlan.offsets`.

What lives here: :class:`StepPlan`, :class:`SecondPlan`, :class:`StateLayout`, the observer's
cache of plans by step length (:class:`StepPlans`), :func:`stack_plans` for a batch and
:data:`DT_RTOL`. What it may import: :mod:`.discretize` and the package's helpers only (every
back end imports it).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validate import positive_scalar, readonly
from ...errors import DimensionError
from .discretize import DT_KEY_DIGITS, PLAN_CACHE_SIZE, PhiPlan, phi_plan

__all__ = ["DT_RTOL", "SecondPlan", "StateLayout", "StepPlan", "StepPlans", "dt_key",
           "linear_part", "stack_plans"]

FloatArray = NDArray[np.float64]

#: Relative spread of a record's steps around one step length that a back end compiled for a
#: fixed step (the generated C, :meth:`CompiledObserver.step
#: <thetahat.estimation.observer.compiled.CompiledObserver.step>`) accepts as that length.
DT_RTOL = 1e-9


def _frozen(a: ArrayLike) -> FloatArray:
    """A read-only, C-contiguous float64 copy of a plan field."""
    return readonly(np.ascontiguousarray(a, dtype=np.float64))


def _phi_or_nan(L: FloatArray, dt: float | None) -> PhiPlan:
    """φ-matrices of L for dt (its key), or NaN-filled ones for the continuous-time plan."""
    if dt is not None:
        return phi_plan(L, dt_key(dt))
    nan = np.full(L.shape, np.nan)
    return PhiPlan(dt=math.nan, Phi1=nan, Phi2=nan)


def dt_key(dt: float) -> float:
    """Step lengths equal to :data:`~thetahat.estimation.observer.discretize.DT_KEY_DIGITS` significant
    digits share one plan; this is the shared key (and the h the φ-matrices are computed for).

    Parameters
    ----------
    dt : float
        A step length > 0.

    Returns
    -------
    float

    Examples
    --------
    >>> dt_key(1e-3 * (1 + 1e-15)) == dt_key(1e-3)
    True
    """
    return float(f"{positive_scalar('dt', dt):.{DT_KEY_DIGITS}g}")


@dataclass(frozen=True, slots=True)
class StateLayout:
    """Offsets of the parts of the observer state ``col(x̂, z, θ̂[, x̂₂][, law state])``.

    Attributes
    ----------
    n, m, r, k, p : int
        Dimensions of x, u, y, φ and θ.
    second : bool
        Whether x̂₂ of a second observer is part of the state.
    law_size : int
        Length of the update law's own state (0 for a memoryless law).
    """

    n: int
    m: int
    r: int
    k: int
    p: int
    second: bool
    law_size: int

    @property
    def x(self) -> slice:
        """x̂."""
        return slice(0, self.n)

    @property
    def z(self) -> slice:
        """z of (3b)."""
        return slice(self.n, self.n + self.k)

    @property
    def theta(self) -> slice:
        """θ̂."""
        return slice(self.n + self.k, self.n + self.k + self.p)

    @property
    def x2(self) -> slice:
        """x̂₂ (empty without a second observer)."""
        a = self.n + self.k + self.p
        return slice(a, a + (self.n if self.second else 0))

    @property
    def law(self) -> slice:
        """The update law's state (empty for a memoryless law)."""
        a = self.x2.stop
        return slice(a, a + self.law_size)

    @property
    def size(self) -> int:
        """Length of the state vector (:attr:`law`'s stop)."""
        return self.n + self.k + self.p + (self.n if self.second else 0) + self.law_size

    def read(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """Copies of x̂, θ̂ and x̂₂ (None without a second observer) of a state vector.

        Parameters
        ----------
        s : ndarray, shape (size,)

        Returns
        -------
        x_hat : ndarray (n,)
        theta_hat : ndarray (p,)
        x_hat_refined : ndarray (n,) or None

        Examples
        --------
        >>> import numpy as np
        >>> lay = StateLayout(n=2, m=1, r=1, k=1, p=1, second=False, law_size=0)
        >>> x, th, x2 = lay.read(np.arange(4.0))
        >>> x.tolist(), th.tolist(), x2
        ([0.0, 1.0], [3.0], None)
        """
        a, b = self.n + self.k, self.n + self.k + self.p
        return (s[:self.n].copy(), s[a:b].copy(),
                s[b:b + self.n].copy() if self.second else None)


def linear_part(A: FloatArray, C: FloatArray, E: FloatArray, K_x: FloatArray,
                K_phi: FloatArray) -> FloatArray:
    """L = [[A − K_x C, E], [−K_φ C, 0]], the constant Jacobian part of (3a)–(3b) in (x̂, z).

    With K_x = 0 and K_φ = 0 it is the prediction over a missing sample. Leading batch axes of
    the gains carry over.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (r, n)
    E : ndarray, shape (n, k)
    K_x : ndarray, shape (..., n, r)
    K_phi : ndarray, shape (..., k, r)

    Returns
    -------
    ndarray, shape (..., n + k, n + k)

    Examples
    --------
    >>> import numpy as np
    >>> linear_part(np.zeros((1, 1)), np.ones((1, 1)), np.ones((1, 1)), np.array([[3.0]]),
    ...             np.array([[2.0]])).tolist()
    [[-3.0, 1.0], [-2.0, 0.0]]
    """
    n, k = E.shape
    batch = np.broadcast_shapes(K_x.shape[:-2], K_phi.shape[:-2])
    L = np.zeros(batch + (n + k, n + k))
    L[..., :n, :n] = A - K_x @ C
    L[..., :n, n:] = E
    L[..., n:, :n] = -(K_phi @ C)
    return L


@dataclass(frozen=True, slots=True, eq=False)
class SecondPlan:
    """Constant data of one step of the second observer of Sec. VI (batch axis B or 1).

    Attributes
    ----------
    dt : float
        Step length h.
    A, B, C, E : ndarray
        System matrices of (1).
    K_x : ndarray, shape (B|1, n, r)
        Its output-injection gain.
    g_on_estimates : bool
        g is evaluated at ``C x̂₂`` instead of the measured y (Sec. VIII).
    Phi1, Phi2 : ndarray, shape (B|1, n, n)
        h φ₁(hL₂), h² φ₂(hL₂) of L₂ = A − K_x C.
    Phi1_open, Phi2_open : ndarray, shape (1, n, n), or None
        The same for A (prediction over a missing sample); None without ``predict``.

    Examples
    --------
    >>> import numpy as np
    >>> plan = SecondPlan.build(A=[[0.0]], B=[[1.0]], C=[[1.0]], E=[[1.0]], K_x=[[2.0]],
    ...                         dt=0.5)
    >>> bool(np.isclose(plan.Phi1[0, 0, 0], (1 - np.exp(-1.0)) / 2))
    True
    """

    dt: float
    A: FloatArray
    B: FloatArray
    C: FloatArray
    E: FloatArray
    K_x: FloatArray
    g_on_estimates: bool
    Phi1: FloatArray
    Phi2: FloatArray
    Phi1_open: FloatArray | None
    Phi2_open: FloatArray | None

    @classmethod
    def build(cls, *, A: ArrayLike, B: ArrayLike, C: ArrayLike, E: ArrayLike, K_x: ArrayLike,
              dt: float | None, g_on_estimates: bool = False,
              predict: bool = True) -> SecondPlan:
        """Compute the plan of one second observer (batch axis of length 1).

        Parameters
        ----------
        A, B, C, E : array_like
            System matrices of (1).
        K_x : array_like, shape (n, r)
            Gain of the second observer.
        dt : float or None
            Step length; None builds the continuous-time plan (no φ-matrices: NaN-filled),
            which ``rhs`` reads.
        g_on_estimates : bool
            As for :class:`~thetahat.estimation.observer.redesign.SecondObserver`.
        predict : bool
            Also compute the φ-matrices of the prediction over a missing sample.

        Returns
        -------
        SecondPlan
        """
        A_, B_, C_, E_ = (np.asarray(M, dtype=np.float64) for M in (A, B, C, E))
        h = math.nan if dt is None else dt_key(dt)
        K = np.asarray(K_x, dtype=np.float64)[None]
        pl = _phi_or_nan(A_ - K[0] @ C_, dt)
        po = _phi_or_nan(A_, dt) if predict else None
        return cls(dt=h, A=_frozen(A_), B=_frozen(B_), C=_frozen(C_), E=_frozen(E_),
                   K_x=_frozen(K), g_on_estimates=bool(g_on_estimates),
                   Phi1=_frozen(pl.Phi1[None]), Phi2=_frozen(pl.Phi2[None]),
                   Phi1_open=None if po is None else _frozen(po.Phi1[None]),
                   Phi2_open=None if po is None else _frozen(po.Phi2[None]))

    @property
    def batch(self) -> int:
        """Length of the batch axis."""
        return int(self.K_x.shape[0])

    def __repr__(self) -> str:
        return (f"SecondPlan(dt={self.dt:.6g}, B={self.batch}, n={self.A.shape[0]}, "
                f"g_on_estimates={self.g_on_estimates})")


@dataclass(frozen=True, slots=True, eq=False)
class StepPlan:
    """Constant data of one observer step of length ``dt`` for a batch of B observers.

    Arrays with a leading axis have length B (one observer per row) or 1 (shared by every
    row); the step broadcasts them. Build it with
    :meth:`ModifiedHighGainObserver.plan <thetahat.estimation.observer.observer.ModifiedHighGainObserver.plan>`
    (cached per step length) and :func:`stack_plans` for a batch.

    Attributes
    ----------
    dt : float
        The step length h the φ-matrices are computed for.
    layout : StateLayout
        Dimensions and the offsets of the state's parts.
    A, B, C, E : ndarray
        The system matrices of (1), shapes (n, n), (n, m), (r, n), (n, k).
    K_x : ndarray, shape (B|1, n, r)
        Gain K_x(ε) of (3a).
    K_phi : ndarray, shape (B|1, k, r)
        Gain K_φ(ε) of (3b).
    KxC : ndarray, shape (B|1, n, n)
        K_x C.
    L : ndarray, shape (B|1, n + k, n + k)
        :func:`linear_part` of the gains.
    Bv : ndarray, shape (B|1, n + k, m + r)
        [[B, K_x], [0, K_φ]]: how v = col(u, y) enters (3a)–(3b).
    Phi1, Phi2 : ndarray, shape (B|1, n + k, n + k)
        h φ₁(hL), h² φ₂(hL).
    Phi1_open, Phi2_open : ndarray, shape (1, n + k, n + k), or None
        The same for L with K = 0 (prediction over a missing sample); None when the plan was
        built without ``predict`` (an observer whose ``nan_policy`` is "raise").
    second : SecondPlan or None
        The plan of the attached second observer (Sec. VI).
    Gamma : ndarray, shape (B|1, p, p), or None
        Γ of the update law per row (None for a law without Γ).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> plan = lugre.observer().plan(1e-3)
    >>> plan.Phi1.shape, plan.layout.size
    ((1, 3, 3), 6)
    """

    dt: float
    layout: StateLayout
    A: FloatArray
    B: FloatArray
    C: FloatArray
    E: FloatArray
    K_x: FloatArray
    K_phi: FloatArray
    KxC: FloatArray
    L: FloatArray
    Bv: FloatArray
    Phi1: FloatArray
    Phi2: FloatArray
    Phi1_open: FloatArray | None
    Phi2_open: FloatArray | None
    second: SecondPlan | None
    Gamma: FloatArray | None

    @classmethod
    def build(cls, *, A: ArrayLike, B: ArrayLike, C: ArrayLike, E: ArrayLike, K_x: ArrayLike,
              K_phi: ArrayLike, dt: float | None, p: int, second: SecondPlan | None = None,
              Gamma: ArrayLike | None = None, law_size: int = 0,
              predict: bool = True) -> StepPlan:
        """Compute the plan of one observer (batch axis of length 1).

        Parameters
        ----------
        A, B, C, E : array_like
            System matrices of (1).
        K_x, K_phi : array_like, shapes (n, r), (k, r)
            Gains of (3).
        dt : float or None
            Step length; None builds the continuous-time plan (φ-matrices NaN-filled), which
            ``rhs`` reads.
        p : int
            Number of parameters.
        second : SecondPlan, optional
            The plan of an attached second observer, for the same dt.
        Gamma : array_like, shape (p, p), optional
            Γ of the update law.
        law_size : int
            Length of the update law's state.
        predict : bool
            Also compute the φ-matrices of the prediction over a missing sample.

        Returns
        -------
        StepPlan
        """
        A_, B_, C_, E_ = (np.asarray(M, dtype=np.float64) for M in (A, B, C, E))
        n, m = B_.shape
        r, k = C_.shape[0], E_.shape[1]
        h = math.nan if dt is None else dt_key(dt)
        Kx = np.asarray(K_x, dtype=np.float64)[None]
        Kphi = np.asarray(K_phi, dtype=np.float64)[None]
        L = linear_part(A_, C_, E_, Kx, Kphi)
        L_open = linear_part(A_, C_, E_, np.zeros_like(Kx), np.zeros_like(Kphi))
        Bv = np.zeros((1, n + k, m + r))
        Bv[0, :n, :m] = B_
        Bv[0, :n, m:] = Kx[0]
        Bv[0, n:, m:] = Kphi[0]
        pl = _phi_or_nan(L[0], dt)
        po = _phi_or_nan(L_open[0], dt) if predict else None
        layout = StateLayout(n=n, m=m, r=r, k=k, p=int(p), second=second is not None,
                             law_size=int(law_size))
        return cls(dt=h, layout=layout, A=_frozen(A_), B=_frozen(B_), C=_frozen(C_),
                   E=_frozen(E_), K_x=_frozen(Kx), K_phi=_frozen(Kphi), KxC=_frozen(Kx @ C_),
                   L=_frozen(L), Bv=_frozen(Bv), Phi1=_frozen(pl.Phi1[None]),
                   Phi2=_frozen(pl.Phi2[None]),
                   Phi1_open=None if po is None else _frozen(po.Phi1[None]),
                   Phi2_open=None if po is None else _frozen(po.Phi2[None]), second=second,
                   Gamma=None if Gamma is None else _frozen(np.asarray(Gamma)[None]))

    @property
    def batch(self) -> int:
        """Length of the batch axis (1 when the rows share one observer)."""
        return int(self.K_x.shape[0])

    def rows(self, index: ArrayLike) -> StepPlan:
        """The plan of a subset of the rows (shared arrays stay shared).

        Parameters
        ----------
        index : array_like of int
            The rows to keep.

        Returns
        -------
        StepPlan
        """
        fields: dict[str, object] = dict(_pick(self, _ROW_FIELDS, index))
        if self.second is not None:
            fields["second"] = _replace(self.second, _pick(self.second, _SECOND_ROW_FIELDS,
                                                           index))
        return _replace(self, fields)

    def __repr__(self) -> str:
        lay = self.layout
        return (f"StepPlan(dt={self.dt:.6g}, B={self.batch}, n={lay.n}, m={lay.m}, r={lay.r}, "
                f"k={lay.k}, p={lay.p}, second={lay.second}, law_size={lay.law_size})")


#: Fields of a plan with a batch axis that may differ between rows.
_ROW_FIELDS = ("K_x", "K_phi", "KxC", "L", "Bv", "Phi1", "Phi2", "Gamma")
_SECOND_ROW_FIELDS = ("K_x", "Phi1", "Phi2")

Plan = TypeVar("Plan", StepPlan, SecondPlan)


def _pick(plan: StepPlan | SecondPlan, names: Sequence[str], index: ArrayLike
          ) -> dict[str, FloatArray | None]:
    out: dict[str, FloatArray | None] = {}
    for name in names:
        val = getattr(plan, name)
        out[name] = val if val is None or val.shape[0] == 1 else val[index]
    return out


def _replace(plan: Plan, fields: Mapping[str, object]) -> Plan:
    values = {name: getattr(plan, name) for name in type(plan).__dataclass_fields__}
    values.update(fields)
    return type(plan)(**values)


def _stack(plans: Sequence[StepPlan] | Sequence[SecondPlan], names: Sequence[str]
           ) -> dict[str, FloatArray | None]:
    fields: dict[str, FloatArray | None] = {}
    for name in names:
        vals = [getattr(pl, name) for pl in plans]
        if vals[0] is None:
            fields[name] = None
        elif all(v is vals[0] or np.array_equal(v, vals[0]) for v in vals[1:]):
            fields[name] = vals[0]
        else:
            fields[name] = readonly(np.concatenate(vals, axis=0))
    return fields


def stack_plans(plans: Sequence[StepPlan]) -> StepPlan:
    """One plan for a batch: row i is ``plans[i]`` (all with the same dt, layout and system).

    Fields equal in every plan stay shared (batch axis of length 1).

    Parameters
    ----------
    plans : sequence of StepPlan
        Plans of single observers, built for the same dt.

    Returns
    -------
    StepPlan

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> plan = stack_plans([lugre.observer(e).plan(1e-3) for e in (1.0, 0.5)])
    >>> plan.batch, plan.Phi1.shape, plan.second.Phi1.shape, plan.C.shape
    (2, (2, 3, 3), (1, 2, 2), (1, 2))
    """
    first = plans[0]
    if len(plans) == 1:
        return first
    fields: dict[str, object] = dict(_stack(plans, _ROW_FIELDS))
    if first.second is not None:
        seconds = [pl.second for pl in plans if pl.second is not None]
        if len(seconds) != len(plans):
            raise DimensionError("stack_plans: either every plan has a second observer or none "
                                 "has; stack the plans of observers built alike.")
        fields["second"] = _replace(first.second, _stack(seconds, _SECOND_ROW_FIELDS))
    return _replace(first, fields)


class StepPlans:
    """The plans of one observer, one per step length, built on first use and kept.

    Step lengths equal to :data:`~thetahat.estimation.observer.discretize.DT_KEY_DIGITS`
    significant digits share a plan (:func:`dt_key`); at most
    :data:`~thetahat.estimation.observer.discretize.PLAN_CACHE_SIZE` are kept, the oldest
    dropped first. :meth:`ModifiedHighGainObserver.plan
    <thetahat.estimation.observer.observer.ModifiedHighGainObserver.plan>` reads them.

    Parameters
    ----------
    A, B, C, E : ndarray
        System matrices of (1).
    K_x, K_phi : ndarray, shapes (n, r), (k, r)
        Gains of (3).
    p : int
        Number of parameters.
    Gamma : ndarray, shape (p, p), or None
        Γ of the update law.
    law_size : int
        Length of the update law's state.
    second : callable, optional
        ``second(dt, predict=...)`` → the :class:`SecondPlan` of an attached second observer
        (``dt`` None: its continuous-time plan).
    predict : bool
        Also compute the φ-matrices of the prediction over missing samples.

    Examples
    --------
    >>> import numpy as np
    >>> plans = StepPlans(A=np.zeros((1, 1)), B=np.zeros((1, 1)), C=np.eye(1), E=np.eye(1),
    ...                   K_x=np.eye(1), K_phi=np.eye(1), p=1, Gamma=None, law_size=0)
    >>> plans(1e-3) is plans(1e-3 * (1 + 1e-15)), plans.continuous().layout.size
    (True, 3)
    """

    def __init__(self, *, A: FloatArray, B: FloatArray, C: FloatArray, E: FloatArray,
                 K_x: FloatArray, K_phi: FloatArray, p: int, Gamma: FloatArray | None,
                 law_size: int, second: Callable[..., SecondPlan] | None = None,
                 predict: bool = False) -> None:
        self._parts: dict[str, Any] = {"A": A, "B": B, "C": C, "E": E, "K_x": K_x, "K_phi": K_phi, "p": p,
                       "Gamma": Gamma, "law_size": law_size}
        self._second = second
        self._predict = predict
        self._plans: OrderedDict[float | None, StepPlan] = OrderedDict()

    def _build(self, key: float | None) -> StepPlan:
        predict = self._predict and key is not None
        second = None if self._second is None else self._second(key, predict=predict)
        return StepPlan.build(**self._parts, dt=key, second=second, predict=predict)

    def __call__(self, dt: float) -> StepPlan:
        """The plan for step length ``dt`` > 0."""
        plans = self._plans
        if type(dt) is float:             # fast path: this very step length was seen
            plan = plans.get(dt)
            if plan is not None:
                return plan
        key = dt_key(dt)
        plan = plans.get(key)
        if plan is None:
            plan = plans[key] = self._build(key)
        if type(dt) is float:
            plans[dt] = plan
        while len(plans) > PLAN_CACHE_SIZE:
            plans.popitem(last=False)
        return plan

    def continuous(self) -> StepPlan:
        """The plan without φ-matrices (``dt=None``) that ``rhs`` reads."""
        plan = self._plans.get(None)
        if plan is None:
            plan = self._plans[None] = self._build(None)
        return plan
