"""Many observer runs at once: observer (3) with update law (8), vectorised over a batch axis.

:func:`run_batch` advances B independent copies of a
:class:`~thetahat.estimation.observer.ModifiedHighGainObserver` over B records that share one
time grid — B noise seeds of a Monte-Carlo study, or B observers that differ only in their
gains (an ε sweep) or their adaptation gain Γ. Each step is the step of
:meth:`ModifiedHighGainObserver.run <thetahat.estimation.observer.ModifiedHighGainObserver.run>`
(the exponential, linearly implicit step of :mod:`thetahat.estimation.discretize`, the update
law's ``step``, z corrected by −∂g/∂θ Δθ̂, ZOH or FOH), written once for arrays with a leading
batch axis: g, its Jacobians and the update laws already evaluate whole batches, the matrix
products become batched ``matmul`` and the small linear solves one batched ``solve``. The
Python overhead of a step is paid once for all B runs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._validate import as_time_grid, check_finite, readonly
from ..errors import DimensionError, IndexOutOfRangeError, NonFiniteError, OptionError
from ..model.paramset import Box
from .discretize import DT_KEY_DIGITS, IMPLICITNESS
from .observer import HOLDS, ModifiedHighGainObserver, ObserverResult
from .update_laws import (AlgebraicInversion, ConstantLaw, IntermittentInversion, UpdateLaw,
                          _apply_saturation, _as_batch, _finite_candidate, _inversion_target)

__all__ = ["BatchObserverResult", "run_batch"]

FloatArray = NDArray[np.float64]

#: Fields of the update laws that may differ between the observers of one batch.
_GAIN_FIELDS = frozenset({"Gamma", "_proj"})




@dataclass(frozen=True, slots=True, eq=False)
class BatchObserverResult:
    """Estimates of B observer runs over one time grid, returned by :func:`run_batch`.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sampling instants (shared).
    x_hat : ndarray, shape (B, N, n)
        State estimates x̂ of (3a).
    phi_hat : ndarray, shape (B, N, k)
        Perturbation estimates φ̂ = g(v, x̂, θ̂) + z of (3c).
    theta_hat : ndarray, shape (B, N, p)
        Parameter estimates θ̂ of (8).
    x_hat_refined : ndarray, shape (B, N, n), or None
        x̂₂ of the second observer of Sec. VI (None when none is attached).
    skipped : ndarray of bool, shape (B, N)
        Samples whose y held NaN (``nan_policy="skip"``).

    Notes
    -----
    ``result[i]`` is the :class:`~thetahat.estimation.observer.ObserverResult` of run i, the
    same object ``observers[i].run`` returns (up to rounding); ``len(result)`` is B.
    """

    t: FloatArray
    x_hat: FloatArray
    phi_hat: FloatArray
    theta_hat: FloatArray
    x_hat_refined: FloatArray | None
    skipped: NDArray[np.bool_]

    def __len__(self) -> int:
        return int(self.x_hat.shape[0])

    def __getitem__(self, i: int) -> ObserverResult:
        """The result of run ``i`` as an :class:`ObserverResult`."""
        B = len(self)
        if not isinstance(i, (int, np.integer)) or not -B <= i < B:
            raise IndexOutOfRangeError(f"run index must be an integer in [-{B}, {B}); got {i!r}.")
        return ObserverResult(
            t=self.t, x_hat=self.x_hat[i], phi_hat=self.phi_hat[i], theta_hat=self.theta_hat[i],
            x_hat_refined=None if self.x_hat_refined is None else self.x_hat_refined[i],
            skipped=self.skipped[i])

    def __repr__(self) -> str:
        B, N = self.x_hat.shape[:2]
        span = f"[{self.t[0]:.6g}, {self.t[-1]:.6g}]" if N else "[]"
        refined = "None" if self.x_hat_refined is None else f"{self.x_hat_refined.shape}"
        return (f"BatchObserverResult(B={B}, N={N}, t={span}, x_hat={self.x_hat.shape}, "
                f"phi_hat={self.phi_hat.shape}, theta_hat={self.theta_hat.shape}, "
                f"x_hat_refined={refined}, skipped={int(self.skipped.sum())})")


# --------------------------------------------------------------------------- compatibility
def _equivalent(a: Any, b: Any) -> bool:
    """Structural equality of model parts (arrays by value, eq=False dataclasses by field)."""
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
                and a.shape == b.shape and bool(np.array_equal(a, b)))
    if type(a) is not type(b):
        return False
    if dataclasses.is_dataclass(a) and type(a).__eq__ is object.__eq__:
        return all(_equivalent(getattr(a, f.name), getattr(b, f.name))
                   for f in dataclasses.fields(a))
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 - anything that cannot compare is not equivalent
        return False


def _law_fields_equal(a: UpdateLaw, b: UpdateLaw) -> bool:
    """Same law up to Γ (and, for a ConstantLaw, the held value, which only sets ``init``)."""
    if type(a) is not type(b):
        return False
    ignore = _GAIN_FIELDS | ({"theta"} if isinstance(a, ConstantLaw) else set())
    return all(_equivalent(getattr(a, f.name), getattr(b, f.name))
               for f in dataclasses.fields(a) if f.name not in ignore)


def _check_compatible(observers: list[ModifiedHighGainObserver]) -> None:
    ref = observers[0]
    for i, obs in enumerate(observers[1:], start=1):
        what = None
        s0, s1 = ref.system, obs.system
        if not all(_equivalent(getattr(s0, a), getattr(s1, a)) for a in "ABCE"):
            what = "the system matrices (A, B, C, E)"
        elif not _equivalent(s0.perturbation, s1.perturbation):
            what = "the perturbation g"
        elif not _law_fields_equal(ref.update_law, obs.update_law):
            what = (f"the update law ({type(ref.update_law).__name__} vs "
                    f"{type(obs.update_law).__name__}; only Γ may differ)")
        elif (ref.second is None) != (obs.second is None):
            what = "whether a second observer is attached"
        elif ref.second is not None and ref.second.g_on_estimates != obs.second.g_on_estimates:
            what = "the second observer's g_on_estimates"
        elif ref.nan_policy != obs.nan_policy:
            what = "nan_policy"
        if what is not None:
            raise DimensionError(f"run_batch: observers[{i}] differs from observers[0] in "
                                 f"{what}; a batch may differ only in the gains K_x, K_φ (ε), "
                                 f"Γ and the second observer's K_x. Run the others separately.")


# --------------------------------------------------------------------------- batched algebra
def _mv(M: FloatArray, x: FloatArray) -> FloatArray:
    """Batched matrix-vector product: M (B|1, a, b), x (B, b) -> (B, a)."""
    return np.matmul(M, x[..., None])[..., 0]


def _exp_step(s: FloatArray, F: FloatArray, N: FloatArray, Phi1: FloatArray,
              Phi2: FloatArray | None, F_dot: FloatArray | None) -> FloatArray:
    """``linearly_implicit_exponential_step`` over the batch axis (Phi1, Phi2: (B|1, q, q))."""
    rhs = _mv(Phi1, F)
    if F_dot is not None:
        rhs = rhs + _mv(Phi2, F_dot)
    M = np.matmul(Phi1, N)
    M *= -IMPLICITNESS
    q = M.shape[-1]
    M[..., np.arange(q), np.arange(q)] += 1.0
    return s + np.linalg.solve(M, rhs[..., None])[..., 0]


class _Batch:
    """Stacked gains, plans and laws of B observers, or of one observer shared by all rows.

    Stacked arrays have a leading axis of length B, or 1 when one observer serves every
    record (``matmul`` broadcasts it); :meth:`pick` selects the rows of a subset.
    """

    def __init__(self, observers: list[ModifiedHighGainObserver], B: int) -> None:
        ref = observers[0]
        self.obs = observers
        self.ref = ref
        self.B = B
        self.n, self.m, self.r, self.k, self.p, self.size = ref._sizes
        self.sys = ref.system
        self.pert = ref.system.perturbation

        def stack(get: Any) -> FloatArray:
            return np.stack([np.asarray(get(o), dtype=np.float64) for o in observers])

        self.Kx = stack(lambda o: o.K_x)
        self.L = stack(lambda o: o._L)
        self.Bv = stack(lambda o: o._Bv)
        self.KxC = stack(lambda o: o._KxC)
        self.K2 = None if ref.second is None else stack(lambda o: o.second.K_x)
        self._plans: dict[tuple[float, bool], tuple[FloatArray, ...]] = {}
        self._groups = self._group_laws()
        self._gam = self._diagonal_gammas() if len(self._groups) > 1 else None

    @staticmethod
    def pick(a: FloatArray, rows: Any) -> FloatArray:
        """Rows ``rows`` of a stacked array (a shared (1, ...) array is returned as is)."""
        return a if a.shape[0] == 1 else a[rows]

    def plans(self, dt: float, correct: bool) -> tuple[FloatArray, ...]:
        """(Φ₁, Φ₂[, Φ₁, Φ₂ of the second observer]) stacked, for one step length."""
        key = (float(f"{dt:.{DT_KEY_DIGITS}g}"), correct)
        hit = self._plans.get(key)
        if hit is None:
            first = [(o._cache if correct else o._cache_open).get(dt) for o in self.obs]
            out = [np.stack([pl.Phi1 for pl in first]), np.stack([pl.Phi2 for pl in first])]
            if self.ref.second is not None:
                sec = [(o.second._cache if correct else o.second._cache_open).get(dt)
                       for o in self.obs]
                out += [np.stack([pl.Phi1 for pl in sec]), np.stack([pl.Phi2 for pl in sec])]
            hit = tuple(out)
            self._plans[key] = hit
        return hit

    # ------------------------------------------------------------------ update law
    def _group_laws(self) -> list[tuple[UpdateLaw, NDArray[np.intp]]]:
        """Rows whose laws have the same Γ share one call of ``law.step``."""
        groups: list[tuple[UpdateLaw, list[int]]] = []
        for i, o in enumerate(self.obs):
            law = o.update_law
            for rep, rows in groups:
                if _equivalent(getattr(rep, "Gamma", None), getattr(law, "Gamma", None)):
                    rows.append(i)
                    break
            else:
                groups.append((law, [i]))
        return [(rep, np.asarray(rows, dtype=np.intp)) for rep, rows in groups]

    def _diagonal_gammas(self) -> FloatArray | None:
        """Per-row diag(Γ) when every Γ is diagonal, Θ is a box and the law inverts g."""
        law = self.ref.update_law
        if not (isinstance(law, (IntermittentInversion, AlgebraicInversion))
                and isinstance(law.parameter_set, Box)):
            return None
        G = np.stack([o.update_law.Gamma for o in self.obs])
        D = np.diagonal(G, axis1=-2, axis2=-1)
        if not np.array_equal(G, D[..., None] * np.eye(self.p)):
            return None
        return D

    def law_step(self, v: FloatArray, x: FloatArray, phi: FloatArray, th: FloatArray,
                 dt: float, rows: Any) -> FloatArray:
        """θ̂ after the step for the rows ``rows`` (each with its own Γ)."""
        if len(self._groups) == 1:
            return np.asarray(self._groups[0][0].step(v, x, phi, th, dt), dtype=np.float64)
        if self._gam is not None:
            return self._inversion_step(self._gam[rows], v, x, phi, th, dt)
        index = np.arange(len(self.obs))[rows]
        out = np.empty_like(th)
        for law, members in self._groups:
            sel = np.flatnonzero(np.isin(index, members))
            if sel.size:
                out[sel] = law.step(v[sel], x[sel], phi[sel], th[sel], dt)
        return out

    def _inversion_step(self, gam: FloatArray, v: FloatArray, x: FloatArray, phi: FloatArray,
                        th: FloatArray, dt: float) -> FloatArray:
        """The exact step of Propositions 1–2 with a diagonal Γ per row, all rows at once.

        Same formula as ``_inversion_step`` of :mod:`~thetahat.estimation.update_laws`
        (θ* + e^(−lΓ dt)(θ̂ − θ*), then the Γ⁻¹-weighted projection, a clip for a box and a
        diagonal Γ), with Γ varying over the batch.
        """
        law = self.ref.update_law
        v, x, phi, th, batch = _as_batch(v, x, phi, th, self.p)
        x, phi = _apply_saturation(law.saturation, x, phi)
        weight = law.l if isinstance(law, IntermittentInversion) else None
        target, lw = _inversion_target(law.theta_star, weight, law.on_invalid,
                                       type(law).__name__, v, x, phi, th, batch)
        with np.errstate(over="ignore", invalid="ignore"):
            decay = np.exp(-lw[..., None] * dt * gam)
            cand = target - decay * (target - th)
        return law.parameter_set.nearest(_finite_candidate(cand, th))


# --------------------------------------------------------------------------- one step
def _forcing(bt: _Batch, s_xz: FloatArray, th: FloatArray, u: FloatArray, y: FloatArray,
             rows: Any, correct: bool, z_theta: FloatArray | None
             ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Batched ``ModifiedHighGainObserver._forcing``: (F, φ̂, ∂g/∂x, v)."""
    n = bt.n
    sysm, pert = bt.sys, bt.pert
    x, z = s_xz[:, :n], s_xz[:, n:]
    if correct:
        v = np.concatenate((u, y), axis=1)
        g = np.asarray(pert.g(v, x, th), dtype=np.float64)
        Gx = np.asarray(pert.dg_dx(v, x, th), dtype=np.float64)
        F = _mv(bt.pick(bt.L, rows), s_xz) + _mv(bt.pick(bt.Bv, rows), v)
        F[:, :n] += g @ sysm.E.T
        F[:, n:] -= _mv(Gx, _mv(bt.pick(bt.Kx, rows), y - x @ sysm.C.T))
        if z_theta is not None:
            F[:, n:] += z_theta
    else:
        v = np.concatenate((u, x @ sysm.C.T), axis=1)
        g = np.asarray(pert.g(v, x, th), dtype=np.float64)
        Gx = np.asarray(pert.dg_dx(v, x, th), dtype=np.float64)
        F = np.zeros(s_xz.shape)
        F[:, :n] = x @ sysm.A.T + u @ sysm.B.T + (g + z) @ sysm.E.T
    return F, g + z, Gx, v


def _advance(bt: _Batch, s: FloatArray, u0: FloatArray, y0: FloatArray, dt: float,
             correct: bool, rows: Any, u1: FloatArray | None,
             y1: FloatArray | None) -> FloatArray:
    """Batched ``ModifiedHighGainObserver._advance`` of the rows ``rows`` (shape (b, size))."""
    n, m, k, p = bt.n, bt.m, bt.k, bt.p
    sysm, pert = bt.sys, bt.pert
    s_xz = s[:, :n + k]
    x, th = s[:, :n], s[:, n + k:n + k + p]
    F, phi, Gx, v = _forcing(bt, s_xz, th, u0, y0, rows, correct, None)
    z_theta = None
    th_next = th
    if correct:
        th_next = bt.law_step(v, x, phi, th, dt, rows)
        d_th = th_next - th
        moving = np.flatnonzero(np.any(d_th != 0, axis=1))
        if moving.size:          # skip ∂g/∂θ for the rows whose θ̂ rests
            z_theta = np.zeros((s.shape[0], k))
            Gth = np.asarray(pert.dg_dtheta(v[moving], x[moving], th[moving]),
                             dtype=np.float64)
            z_theta[moving] = -_mv(Gth, d_th[moving]) / dt
            F[:, n:] += z_theta
    N = np.zeros((s.shape[0], n + k, n + k))
    if correct:
        N[:, :n, :n] = sysm.E @ Gx
        N[:, n:, :n] = Gx @ bt.pick(bt.KxC, rows)
    else:
        N[:, :n, :n] = sysm.E @ (Gx + np.asarray(pert.dg_dv(v, x, th))[:, :, m:] @ sysm.C)
    F_dot = None
    if u1 is not None:
        F1 = _forcing(bt, s_xz, th, u1, y1, rows, correct, z_theta)[0]
        F_dot = (F1 - F) / dt
    plans = bt.plans(dt, correct)
    xz = _exp_step(s_xz, F, N, bt.pick(plans[0], rows), bt.pick(plans[1], rows), F_dot)
    if bt.K2 is None:
        return np.concatenate((xz, th_next), axis=1)
    x2 = s[:, n + k + p:]
    F2, N2 = _second_terms(bt, x2, u0, y0, th, correct, rows, want_N=True)
    F2_dot = None
    if u1 is not None:
        F21 = _second_terms(bt, x2, u1, y1, th, correct, rows, want_N=False)[0]
        F2_dot = (F21 - F2) / dt
    x2_next = _exp_step(x2, F2, N2, bt.pick(plans[2], rows), bt.pick(plans[3], rows), F2_dot)
    return np.concatenate((xz, th_next, x2_next), axis=1)


def _second_terms(bt: _Batch, x2: FloatArray, u: FloatArray, y: FloatArray, th: FloatArray,
                  correct: bool, rows: Any, want_N: bool
                  ) -> tuple[FloatArray, FloatArray | None]:
    """Batched ``SecondObserver._g_terms``: F and (optionally) N."""
    sysm, pert = bt.sys, bt.pert
    y_hat = x2 @ sysm.C.T
    on_est = bt.ref.second.g_on_estimates or not correct
    v = np.concatenate((u, y_hat if on_est else y), axis=1)
    g = np.asarray(pert.g(v, x2, th), dtype=np.float64)
    F = x2 @ sysm.A.T + u @ sysm.B.T + g @ sysm.E.T
    if correct:
        F = F + _mv(bt.pick(bt.K2, rows), y - y_hat)
    if not want_N:
        return F, None
    Jg = np.asarray(pert.dg_dx(v, x2, th), dtype=np.float64)
    if on_est:
        Jg = Jg + np.asarray(pert.dg_dv(v, x2, th))[:, :, bt.m:] @ sysm.C
    return F, sysm.E @ Jg


# --------------------------------------------------------------------------- public API
def _as_observers(observers: Any) -> list[ModifiedHighGainObserver]:
    if isinstance(observers, ModifiedHighGainObserver):
        return [observers]
    if isinstance(observers, Sequence) and not isinstance(observers, (str, bytes)):
        obs = list(observers)
        if obs and all(isinstance(o, ModifiedHighGainObserver) for o in obs):
            return obs
    raise DimensionError("run_batch: observers must be a ModifiedHighGainObserver or a "
                         f"non-empty sequence of them; got {type(observers).__name__}.")


def _records(name: str, a: Any, B: int | None, N: int, width: int) -> FloatArray:
    if np.iscomplexobj(a):
        raise DimensionError(f"run_batch: {name} must be real; got complex samples.")
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 2 and width == 1:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[1:] != (N, width) or (B is not None and arr.shape[0] != B):
        b = "B" if B is None else str(B)
        raise DimensionError(f"run_batch: {name} must have shape ({b}, {N}, {width})"
                             f"{f' or ({b}, {N})' if width == 1 else ''}: one record per run "
                             f"on the shared time grid t; got {arr.shape}.")
    return np.ascontiguousarray(arr)


def _initial(observers: list[ModifiedHighGainObserver], state0: Any, B: int,
             size: int) -> FloatArray:
    if state0 is None:
        if len(observers) == 1:
            return np.tile(observers[0].init(), (B, 1))
        return np.stack([o.init() for o in observers])
    s0 = np.asarray(state0, dtype=np.float64)
    if s0.ndim == 1:
        s0 = np.tile(s0, (B, 1))
    if s0.shape != (B, size):
        raise DimensionError(f"run_batch: state0 must have shape ({size},) or ({B}, {size}); "
                             f"got {np.shape(state0)}.")
    check_finite("state0", s0)
    return s0.copy()


def run_batch(observers: ModifiedHighGainObserver | Sequence[ModifiedHighGainObserver],
              t: Any, U: Any, Y: Any, *, hold: str = "zoh",
              state0: Any = None) -> BatchObserverResult:
    """Run B observers over B sampled records at once (vectorised over a batch axis).

    Parameters
    ----------
    observers : ModifiedHighGainObserver or sequence of B of them
        One observer (used for every record) or B observers that differ only in their gains
        K_x, K_φ (e.g. different ε), in Γ of the update law and in the second observer's
        gain; everything else (system, g, θ*, l, Θ, ``nan_policy``) must agree.
    t : array_like, shape (N,)
        Shared sampling instants, strictly increasing.
    U : array_like, shape (B, N, m), or (B, N) when m = 1
        Input records (``None`` when m = 0).
    Y : array_like, shape (B, N, r), or (B, N) when r = 1
        Output records; NaN handled per the observers' ``nan_policy``.
    hold : {"zoh", "foh"}, default "zoh"
        As for :meth:`ModifiedHighGainObserver.run`.
    state0 : array_like, shape (state_size,) or (B, state_size), optional
        Initial states; default each observer's ``init()``.

    Returns
    -------
    BatchObserverResult
        ``result[i]`` agrees with ``observers[i].run(t, U[i], Y[i], ...)`` to rounding
        (the products are summed in another order; measured 5e-16 relative on the DC motor
        of Sec. VIII over 20 s, two observers with different ε and Γ).

    Raises
    ------
    DimensionError
        Shapes disagree, ``t`` is not strictly increasing, or the observers differ in more
        than their gains.
    NonFiniteError
        NaN or inf in t or U; inf in Y; NaN in Y under ``nan_policy="raise"``; a run
        diverged.
    ValueError
        Unknown ``hold``.

    Notes
    -----
    The step is that of :class:`ModifiedHighGainObserver` (see its Notes), eqs. (3a)–(3c)
    and (8). Different Γ in one batch cost one call of the update law per distinct Γ, except
    for Propositions 1–2 (:class:`AlgebraicInversion`, :class:`IntermittentInversion`) on a
    box with diagonal Γ, whose exact step is evaluated for all rows at once. Runs whose
    sample is missing (``nan_policy="skip"``) are advanced separately for that step.

    **Throughput** (DC motor of Sec. VIII with the second observer, 1 kHz, shared 2-core
    machine): about 4·10³ observer steps per second for B = 1 (a loop of ``run``: 5.5·10³),
    7·10⁴ for B = 20 and 3·10⁵ for B = 100, i.e. 50× a loop of ``run`` and 3700× a loop of
    ``scipy.integrate.solve_ivp(observer.rhs, method="LSODA")`` with a piecewise-constant
    input (80 steps per second). The compiled kernel of
    :mod:`thetahat.estimation.compiled` runs one observer at about 3·10⁶ steps per second.

    Examples
    --------
    Three noise seeds of the paper's DC motor, one observer:

    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.batch_run import run_batch
    >>> runs = [lugre.simulate(seed=s, t_end=0.5) for s in range(3)]
    >>> U = np.stack([r.u for r in runs]); Y = np.stack([r.y for r in runs])
    >>> obs = lugre.observer()
    >>> res = run_batch(obs, runs[0].t, U, Y)
    >>> res.theta_hat.shape
    (3, 501, 1)
    >>> one = obs.run(runs[1].t, runs[1].u, runs[1].y)
    >>> bool(np.allclose(res[1].x_hat, one.x_hat, rtol=1e-10, atol=1e-12))
    True
    """
    if hold not in HOLDS:
        raise OptionError(f"hold must be one of {HOLDS}; got {hold!r}.")
    obs = _as_observers(observers)
    _check_compatible(obs)
    ref = obs[0]
    n, m, r, k, p, size = ref._sizes
    t_, dts = as_time_grid(t)
    N = t_.shape[0]
    B0 = len(obs) if len(obs) > 1 else None
    Yb = _records("Y", Y, B0, N, r)
    B = Yb.shape[0]
    Ub = _records("U", np.zeros((B, N, 0)) if U is None else U, B, N, m)
    check_finite("U", Ub)
    if np.isinf(Yb).any():
        raise NonFiniteError("Y contains inf; only NaN marks a missing sample.")
    ok = np.isfinite(Yb).all(axis=2)
    if not ok.all() and ref.nan_policy == "raise":
        b, i = (int(a[0]) for a in np.nonzero(~ok))
        raise NonFiniteError(f"Y contains NaN ({int((~ok).sum())} samples, first in run {b} at "
                             f"index {i}) and nan_policy='raise'; pass nan_policy='skip' to "
                             "the observer to predict over missing samples, or clean the data.")
    bt = _Batch(obs, B)
    s = _initial(obs, state0, B, size)
    S = np.empty((B, N, size))
    S[:, 0] = s
    foh = hold == "foh"
    all_rows = slice(None)
    for i in range(N - 1):
        dt = float(dts[i])
        u1 = Ub[:, i + 1] if foh else None
        y1 = np.where(ok[:, i + 1, None], Yb[:, i + 1], Yb[:, i]) if foh else None
        if ok[:, i].all():
            s = _advance(bt, s, Ub[:, i], Yb[:, i], dt, True, all_rows, u1, y1)
        else:
            nxt = np.empty_like(s)
            for flag in (True, False):
                rows = np.flatnonzero(ok[:, i] == flag)
                if rows.size:
                    nxt[rows] = _advance(
                        bt, s[rows], Ub[rows, i], Yb[rows, i], dt, flag, rows,
                        None if u1 is None else u1[rows],
                        None if y1 is None else (y1[rows] if flag else Yb[rows, i]))
            s = nxt
        S[:, i + 1] = s
    if not np.isfinite(S).all():
        b, i = (int(a[0]) for a in np.nonzero(~np.isfinite(S).all(axis=2)))
        raise NonFiniteError(f"the state of run {b} became non-finite at t[{i}] = {t_[i]!r}; "
                             "check the gains, the update law and the data scaling.")
    X, Z, TH = S[..., :n], S[..., n:n + k], S[..., n + k:n + k + p]
    Yv = np.where(ok[..., None], Yb, X @ ref.system.C.T)
    V = np.concatenate((Ub, Yv), axis=2)
    PHI = np.asarray(ref.system.perturbation.g(V, X, TH), dtype=np.float64) + Z
    X2 = readonly(S[..., n + k + p:]) if ref.second is not None else None
    return BatchObserverResult(t=readonly(t_), x_hat=readonly(X), phi_hat=readonly(PHI),
                               theta_hat=readonly(TH), x_hat_refined=X2,
                               skipped=readonly(~ok, dtype=None))
