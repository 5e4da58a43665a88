"""X, the box the state stays in, and g redefined outside it (Remark 1).

Assumption 2 asks a Lipschitz-like condition on d, hence on g, that is global in the
estimates: no bound is presumed on x̂. An Arrhenius rate exp(−E/(R(T_f + ϑ))) or a hardening
spring k₃x³ is Lipschitz only on bounded sets, and a high-gain observer started away from the
state, or driven by a wrong θ̂, then meets a g that grows faster than its gains can dominate:
x̂ leaves every bound within a few samples. Remark 1 removes the difficulty: "we are free to
redefine g(v, x, θ) outside V × X × Θ without altering the accuracy of the system description
(1)", for example by a smooth saturation of x outside X.

:class:`StateSet` is X, a box with finite faces; :func:`saturate_states` returns
g(v, σ(x), θ) with, componentwise,

    σ(x) = c + w·tanh((x − c)/w),   c = min(max(x, lower), upper),   w = SATURATION_WIDTH·(upper − lower),

the identity on X, twice continuously differentiable across its faces (σ' = 1 and σ'' = 0
there), and within w of X everywhere. On X the saturated g is g itself, so every method (the
paper's observer and the statistical ones, which share the model's g) describes the plant as
before; outside X it is bounded with bounded derivatives, as Assumption 2 needs. The
saturation is written with Min, Max and tanh, which every printer of the library (NumPy,
numba, C) already prints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import sympy as sp
from numpy.typing import ArrayLike, NDArray

from ..errors import DimensionError, ThetahatError
from .perturbation import Perturbation, SymbolicPerturbation

__all__ = ["ASSUMPTION_2_REMEDY", "GROWTH_DECADES", "GROWTH_LIMIT", "OUTSIDE_FRACTION", "SATURATION_WIDTH", "StateSet",
           "StateSetError",
           "lipschitz_growth", "measured_states", "saturate_states", "saturation",
           "state_scale"]

FloatArray = NDArray[np.float64]

#: The width w of σ's tanh beyond each face, as a fraction of X's width along that
#: coordinate: g outside X then varies over at most a tenth of what it varies over X.
SATURATION_WIDTH = 0.1


#: :func:`lipschitz_growth` compares ‖∂g/∂x‖ at 10**GROWTH_DECADES times the data's scale
#: from the data with its largest value nearer (at 1, 10, … times the scale).
GROWTH_DECADES = 2
#: A growth of ‖∂g/∂x‖ above this factor is g not Lipschitz in x globally: a g with bounded
#: ∂g/∂x (tanh friction, a g saturated outside X) does not grow at all, while a quadratic term
#: grows 10-fold per decade, a cube 100-fold and an exponential without bound.
GROWTH_LIMIT = 3.0


#: What to do when Assumption 2 fails (the one wording of the analyze report, the paper's
#: method's warning and the divergence diagnosis).
ASSUMPTION_2_REMEDY = ("declare X, the box the states stay in, in [state_set] (g is then "
                       "saturated outside it, Remark 1)")

#: An estimate whose state leaves X on more than this fraction of the samples is reported
#: (:meth:`StateSet.leaving`): a few samples just past a face are noise on a state that runs
#: along it.
OUTSIDE_FRACTION = 0.01


class StateSetError(ThetahatError, ValueError):
    """X is not a box with finite faces, lower < upper, one pair per state."""


@dataclass(frozen=True, slots=True)
class StateSet:
    """X = {x : lower ≤ x ≤ upper}, componentwise, with finite faces (Assumption 2's X).

    Parameters
    ----------
    lower, upper : array_like, shape (n,)
        Finite, lower < upper in every coordinate.

    Raises
    ------
    StateSetError
        Shapes differ, an entry is not finite, or lower ≥ upper somewhere.

    Examples
    --------
    >>> from thetahat.model.state_set import StateSet
    >>> X = StateSet([0.0, -1.0], [2.0, 1.0])
    >>> X
    StateSet(lower=[0.0, -1.0], upper=[2.0, 1.0])
    >>> X.contains([1.0, 0.5]), X.contains([3.0, 0.0])
    (True, False)
    """

    lower: FloatArray
    upper: FloatArray

    def __init__(self, lower: ArrayLike, upper: ArrayLike) -> None:
        lo = np.array(lower, dtype=np.float64).reshape(-1)
        hi = np.array(upper, dtype=np.float64).reshape(-1)
        if lo.shape != hi.shape or lo.size == 0:
            raise StateSetError(f"X needs one lower and one upper bound per state; got "
                                f"{lo.size} and {hi.size}.")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise StateSetError("X's bounds must be finite (X is the bounded set the states "
                                "stay in; give a generous range rather than inf).")
        bad = np.flatnonzero(~(lo < hi))
        if bad.size:
            i = int(bad[0])
            raise StateSetError(f"X needs lower < upper in every coordinate; state {i + 1} has "
                                f"[{lo[i]:g}, {hi[i]:g}].")
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @property
    def n(self) -> int:
        """The number of states."""
        return int(self.lower.size)

    @property
    def width(self) -> FloatArray:
        """w of each coordinate's saturation (:data:`SATURATION_WIDTH` of X's width)."""
        return SATURATION_WIDTH * (self.upper - self.lower)

    def contains(self, x: ArrayLike) -> bool:
        """Whether every row of ``x`` (shape (n,) or (N, n)) lies in X (NaN rows are ignored).

        Parameters
        ----------
        x : array_like

        Returns
        -------
        bool
        """
        a = np.atleast_2d(np.asarray(x, dtype=np.float64))
        a = a[np.all(np.isfinite(a), axis=1)]
        return bool(np.all((a >= self.lower) & (a <= self.upper)))

    def leaving(self, x: ArrayLike, names: tuple[str, ...] | None = None) -> str | None:
        """A sentence when states of ``x`` (shape (N, n): where the plant was, e.g. measured
        states; NaN where not known) leave X on more than :data:`OUTSIDE_FRACTION` of their
        known samples, else None: there g is saturated, and the model is not the g the file
        writes.

        Parameters
        ----------
        x : array_like (N, n)
            NaN entries are not known (a state not measured) and are left out.
        names : tuple of str, optional
            The states' names.

        Returns
        -------
        str or None

        Examples
        --------
        >>> import numpy as np
        >>> from thetahat.model.state_set import StateSet
        >>> X = StateSet([0.0], [1.0])
        >>> X.leaving(np.linspace(0.0, 1.0, 50)[:, None]) is None
        True
        >>> X.leaving(np.linspace(0.0, 2.0, 50)[:, None], ("q",))[:45]
        'the plant leaves X ([state_set]): q on 50 % o'
        """
        a = np.atleast_2d(np.asarray(x, dtype=np.float64))
        label = names if names is not None else tuple(f"x{i + 1}" for i in range(self.n))
        found = []
        for i in range(self.n):
            col = a[:, i][np.isfinite(a[:, i])]
            if col.size == 0:
                continue
            below, above = col < self.lower[i], col > self.upper[i]
            share = float(np.mean(below | above))
            if not share > OUTSIDE_FRACTION:
                continue
            reach = [f"down to {col.min():.4g} (face {self.lower[i]:.4g})"] if below.any() else []
            if above.any():
                reach.append(f"up to {col.max():.4g} (face {self.upper[i]:.4g})")
            found.append(f"{label[i]} on {100 * share:.0f} % of its samples, "
                         f"{' and '.join(reach)}")
        if not found:
            return None
        return (f"the plant leaves X ([state_set]): {'; '.join(found)}; g is saturated outside "
                "X (Remark 1), so there the model is not the g written in the file: widen X to "
                "where the states can be")

    def __repr__(self) -> str:
        return (f"StateSet(lower={[float(v) for v in self.lower]}, "
                f"upper={[float(v) for v in self.upper]})")


def saturation(x: sp.Expr, lower: float, upper: float) -> sp.Expr:
    """σ(x) = c + w·tanh((x − c)/w), c = min(max(x, lower), upper), w = SATURATION_WIDTH·width.

    The identity on [lower, upper], continuously differentiable, within w of the interval.

    Parameters
    ----------
    x : sympy.Expr
    lower, upper : float
        Finite, lower < upper.

    Returns
    -------
    sympy.Expr

    Examples
    --------
    >>> import sympy as sp
    >>> from thetahat.model.state_set import saturation
    >>> x = sp.Symbol("x", real=True)
    >>> s = saturation(x, 0.0, 10.0)
    >>> [float(s.subs(x, v)) for v in (5.0, 10.0)]
    [5.0, 10.0]
    >>> 10.0 < float(s.subs(x, 1e6)) <= 11.0
    True
    """
    w = sp.Float(SATURATION_WIDTH * (float(upper) - float(lower)))
    c = sp.Min(sp.Max(x, sp.Float(float(lower))), sp.Float(float(upper)))
    return c + w * sp.tanh((x - c) / w)


def saturate_states(perturbation: SymbolicPerturbation, X: StateSet) -> SymbolicPerturbation:
    """g(v, σ(x), θ): g with each state saturated outside X (Remark 1).

    Parameters
    ----------
    perturbation : SymbolicPerturbation
    X : StateSet
        One pair of bounds per state of g.

    Returns
    -------
    SymbolicPerturbation
        The same symbols; equal to ``perturbation`` on X, bounded with bounded derivatives in x
        outside it when g is continuous.

    Raises
    ------
    DimensionError
        X's size is not g's n.

    Examples
    --------
    >>> import numpy as np, sympy as sp
    >>> from thetahat.model.perturbation import SymbolicPerturbation
    >>> from thetahat.model.state_set import StateSet, saturate_states
    >>> y, x1, th = sp.symbols("y x1 theta")
    >>> g = SymbolicPerturbation.from_sympy(th * x1**3, u=[], y=[y], x=[x1], theta=[th])
    >>> gs = saturate_states(g, StateSet([-2.0], [2.0]))
    >>> v, th0 = np.array([0.0]), np.array([1.0])
    >>> float(gs.g(v, np.array([1.5]), th0)[0]) == float(g.g(v, np.array([1.5]), th0)[0])
    True
    >>> float(gs.g(v, np.array([1e3]), th0)[0]) <= 2.4 ** 3
    True
    """
    n = perturbation.dims[0]
    if X.n != n:
        raise DimensionError(f"X has {X.n} pair(s) of bounds; g has n = {n} states.")
    swap = {s: saturation(s, float(lo), float(hi))
            for s, lo, hi in zip(perturbation.x, X.lower, X.upper)}
    expr = perturbation.expr.xreplace(swap)
    return SymbolicPerturbation.from_sympy(expr, u=perturbation.u, y=perturbation.y,
                                           x=perturbation.x, theta=perturbation.theta)


def lipschitz_growth(perturbation: Perturbation, v: ArrayLike, x: ArrayLike,
                     theta: ArrayLike, scale: ArrayLike) -> float:
    """How much ‖∂g/∂x‖ grows away from the data: a probe of Assumption 2's global condition.

    The largest ‖∂g/∂x‖ (Frobenius) at x ± s·e_i and at eight fixed pseudo-random directions,
    at distances s = 10**j · ``scale``, j = 0 … :data:`GROWTH_DECADES`, with v and θ fixed;
    the ratio of the farthest maximum to the largest nearer one (inf when g or its Jacobian is
    not finite far away). Above :data:`GROWTH_LIMIT`, g is not Lipschitz in x outside a bounded
    set, and a high-gain observer may be driven off by it (declare X: :func:`saturate_states`).
    A probe, not a proof: it samples.

    Parameters
    ----------
    perturbation : Perturbation
        Any g with ∂g/∂x (:meth:`~thetahat.model.perturbation.Perturbation.dg_dx`).
    v : array_like, shape (m + r,)
    x : array_like, shape (n,)
        A state where the data are (e.g. x̂(0)).
    theta : array_like, shape (p,)
    scale : array_like, shape (n,)
        Each state's scale in the data (> 0).

    Returns
    -------
    float
        ≥ 0, or inf.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.parse import parse_perturbation
    >>> from thetahat.model.state_set import lipschitz_growth
    >>> cubic = parse_perturbation("theta*x**3", u=[], y=["y"], x=["x"], theta=["theta"])
    >>> friction = parse_perturbation("theta*tanh(x/0.1)", u=[], y=["y"], x=["x"],
    ...                               theta=["theta"])
    >>> args = (np.zeros(1), np.ones(1), np.ones(1), np.ones(1))
    >>> lipschitz_growth(cubic, *args) > 10, lipschitz_growth(friction, *args) < 3
    (True, True)
    """
    n = perturbation.dims[0]
    x0 = np.asarray(x, dtype=np.float64).reshape(n)
    sc = np.broadcast_to(np.asarray(scale, dtype=np.float64).reshape(-1), (n,))
    rng = np.random.default_rng(20260501)
    dirs = np.vstack([np.eye(n), -np.eye(n), rng.standard_normal((8, n))])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    vv = np.asarray(v, dtype=np.float64).reshape(-1)
    th = np.asarray(theta, dtype=np.float64).reshape(-1)

    def largest(distance: float) -> float:
        pts = x0 + distance * dirs * sc
        N = pts.shape[0]
        with np.errstate(all="ignore"):
            J = np.asarray(perturbation.dg_dx(np.broadcast_to(vv, (N, vv.size)), pts,
                                              np.broadcast_to(th, (N, th.size))))
            norms = np.sqrt(np.sum(J.reshape(N, -1) ** 2, axis=1))
        return float(np.max(norms)) if np.all(np.isfinite(norms)) else math.inf

    near = max(largest(10.0 ** j) for j in range(GROWTH_DECADES))
    far = largest(10.0 ** GROWTH_DECADES)
    if not math.isfinite(far):
        return math.inf
    return far / near if near > 0.0 else (0.0 if far == 0.0 else math.inf)


def state_scale(x: ArrayLike) -> FloatArray:
    """Each state's scale in ``x`` (shape (n,) or (N, n); NaN entries ignored), for
    :func:`lipschitz_growth`: its largest magnitude, or the largest of every state's where it
    is below a thousandth of that (an unmeasured state started at 0), or 1 where all are 0.

    Parameters
    ----------
    x : array_like

    Returns
    -------
    ndarray (n,)
        > 0.

    Examples
    --------
    >>> from thetahat.model.state_set import state_scale
    >>> state_scale([[1.0, 0.0], [-3.0, 0.0]]).tolist()
    [3.0, 3.0]
    """
    a = np.abs(np.atleast_2d(np.asarray(x, dtype=np.float64)))
    reach = np.max(np.where(np.isfinite(a), a, 0.0), axis=0, initial=0.0)
    top = float(reach.max(initial=0.0))
    if not top > 0.0:
        return np.ones(a.shape[1])
    return np.where(reach > 1e-3 * top, reach, top)


def measured_states(C: ArrayLike, y: ArrayLike) -> FloatArray:
    """The states the outputs measure one by one: x_i = y_j / c for each row of C that is c·e_iᵀ
    (c ≠ 0), NaN for the other states (where the plant went is known only for those).

    Parameters
    ----------
    C : array_like (r, n)
    y : array_like (N, r)

    Returns
    -------
    ndarray (N, n)

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.model.state_set import measured_states
    >>> measured_states([[2.0, 0.0]], [[4.0], [6.0]]).tolist()
    [[2.0, nan], [3.0, nan]]
    """
    C_ = np.atleast_2d(np.asarray(C, dtype=np.float64))
    Y = np.asarray(y, dtype=np.float64).reshape(-1, C_.shape[0])
    out = np.full((Y.shape[0], C_.shape[1]), np.nan)
    for j, row in enumerate(C_):
        nz = np.flatnonzero(row != 0.0)
        if nz.size == 1 and np.all(np.isnan(out[:, nz[0]])):
            out[:, nz[0]] = Y[:, j] / row[nz[0]]
    return out
