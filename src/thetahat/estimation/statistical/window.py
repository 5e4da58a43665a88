"""Bounded fits: MAP fits over a moving window of samples, the older data as an arrival cost.

A fit of all the data so far (:func:`~thetahat.estimation.statistical.map_fit.fit_record`)
costs O(k) at sample k, so its latency and memory grow with the record. A *window* W bounds
both: while k ≤ W the fits are those of all the data (the information schedule), and from
then on a fit every W samples covers only the samples since the previous fit, k₀ … k₁ − 1,
with the joint posterior of col(x(t_{k₀}), θ) at the window's start — the joint EKF's, which
:class:`~thetahat.estimation.statistical.mle.MapEstimator` restarts from each fit, or stage 2's
in :class:`~thetahat.estimation.statistical.guarded.GuardedEstimator` — as a Gaussian prior:

    J(q) = Σ_{k₀ < k < k₁} ‖y_k − C x_k(q)‖²_{R⁻¹} + (q − s̄)ᵀ P̄⁺ (q − s̄)      (:func:`fit_window`)

(y_{k₀} is summarised by the prior). Each fit then sweeps at most W + 1 samples whatever k is,
and a stream keeps only those: a buffer of W + 1 samples, emptied to its last sample at each
fit (the windows do not overlap, so the buffer never wraps).

How W is chosen (``window="auto"``, :func:`window_reached`): the first count of the doubling
grid k = k_f·2ⁱ (k_f = :func:`~thetahat.estimation.statistical.map_fit.first_fit_samples`) at
which the information about θ from samples 0 … k − 1 — the Fisher information at the start
values (x̂(0), θ̂(0)), x(0) unknown under its prior, i.e. the inverse Cramér–Rao bound the fits
would attain — is :data:`WINDOW_INFO_GAIN` times the prior's on every component of θ, then
held within [:data:`WINDOW_MIN`, ``window_max``]. The reason: an arrival cost is a Gaussian
summary of the older data, exact for a model linear in q and accurate when the posterior it
summarises is concentrated where the model is nearly linear, i.e. when the data dominate the
prior; a window that carries that much information on its own is long enough for each fit to
re-linearise on its own data. It is a count of samples, from the model, the input and σ —
never seconds. Records that never reach the gain get ``window_max``.

What it may import: :mod:`thetahat.model`, the package's errors and, in this room,
``common``, ``map_fit``, ``plant_kernel`` and ``sweep``.
"""

from __future__ import annotations

import math
from typing import Callable, Collection

import numpy as np
from numpy.typing import NDArray

from ...errors import OptionError
from ...model.system import PerturbedLinearSystem
from .common import resolve_noise_std
from .map_fit import FitResult, FitSchedule, first_fit_samples, fit_map, solve_scaled
from .plant_kernel import Propagation, model_kernel
from .sweep import sweep_kernel

__all__ = ["ARRIVAL_FLOOR", "Anchor", "WINDOW_INFO_GAIN", "WINDOW_MAX", "WINDOW_MIN",
           "arrival_information", "check_window", "fit_window", "resolve_window", "stream_window",
           "window_grid",
           "window_reached", "windowed", "windowed_counts"]

FloatArray = NDArray[np.float64]
#: A window's start: (k0, s, P, σ) — the sample, the posterior N(s, P) of col(x, θ) there and
#: the noise level the window's fit takes when σ is not given.
Anchor = tuple[int, FloatArray, FloatArray, FloatArray]

#: ``window="auto"``: the window's information about θ is this many times the prior's (its
#: standard deviation a tenth of the prior's |Θ|/4) on every component.
WINDOW_INFO_GAIN = 100.0
#: The shortest automatic window: a fit's fixed cost (the Python around its compiled sweeps)
#: is about one and a half sweeps of 256 samples (on LuGre, 10⁵ samples, the sweeps are 77 %
#: of the window fits' time at 256), so shorter windows would spend mostly that, costing
#: more in total without being more accurate.
WINDOW_MIN = 256
#: The arrival cost's information is the inverse of the posterior covariance with its scaled
#: eigenvalues floored at this fraction of the largest. The posterior of a fit of a model
#: without process noise is degenerate: x at the window's end is a function of θ (rank p, the
#: initial state forgotten), and a pseudo-inverse would leave x free in those directions,
#: losing θ's information through them (on LuGre the window fits' standard error grew from
#: 2e-4 to 0.99). Floored, x given θ is held to 1e-4 of its standard deviation.
ARRIVAL_FLOOR = 1e-8
#: The longest automatic window (default ``window_max``): a fit sweeps its window about six
#: times (≈ 5 µs per sample and sweep on LuGre), so a fit of 4096 samples takes ≈ 0.1 s.
WINDOW_MAX = 4096


def check_window(owner: str, window: int | str | None, window_max: int,
                 system: PerturbedLinearSystem) -> None:
    """Refuse a ``window`` other than None, ``"auto"`` or an integer ≥ the first fit's samples
    (:func:`~thetahat.estimation.statistical.map_fit.first_fit_samples`), or a ``window_max``
    that is not an integer ≥ 3.

    Parameters
    ----------
    owner : str
        The estimator's name, for the message.
    window : int, "auto" or None
    window_max : int
    system : PerturbedLinearSystem

    Raises
    ------
    OptionError
        With the allowed values.

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> check_window("MapEstimator", "auto", 4096, lugre.system())
    >>> check_window("MapEstimator", 2, 4096, lugre.system())
    Traceback (most recent call last):
    ...
    thetahat.errors.OptionError: MapEstimator: window must be None (fits of all the data), "auto" or an integer >= 12 samples (the first fit's); got 2.
    """
    least = first_fit_samples(system)
    ok = (window is None or window == "auto"
          or (isinstance(window, (int, np.integer)) and not isinstance(window, bool)
              and window >= least))
    if not ok:
        raise OptionError(f"{owner}: window must be None (fits of all the data), \"auto\" or "
                          f"an integer >= {least} samples (the first fit's); got {window!r}.")
    if not (isinstance(window_max, (int, np.integer)) and not isinstance(window_max, bool)
            and window_max >= 3):
        raise OptionError(f"{owner}: window_max must be an integer >= 3 samples; got "
                          f"{window_max!r}.")


def window_grid(system: PerturbedLinearSystem, window_max: int) -> list[int]:
    """The sample counts at which ``window="auto"`` is decided: k_f·2ⁱ below ``window_max``.

    Parameters
    ----------
    system : PerturbedLinearSystem
    window_max : int

    Returns
    -------
    list of int

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> window_grid(lugre.system(), 200)
    [12, 24, 48, 96, 192]
    """
    g, out = first_fit_samples(system), []
    while g < window_max:
        out.append(g)
        g *= 2
    return out


def window_reached(schedule: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray,
                   k1: int, prior0: tuple[FloatArray, FloatArray]) -> bool:
    """Whether samples 0 … k1 − 1 carry :data:`WINDOW_INFO_GAIN` times the prior's information
    about every component of θ, at the prior's mean (the module docstring).

    Parameters
    ----------
    schedule : FitSchedule
        The model, σ (estimated from Y[:k1] when not given), the hold and the sub-steps
        (1 when not set: the estimators pass their ``substeps`` option, not a record's
        choice, so that a stream, which has no record, decides as a run does; a trajectory
        that is not finite at one sub-step never reaches the gain, and W is ``window_max``).
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        N ≥ k1; U stage 2's input samples.
    k1 : int
    prior0 : tuple of ndarray
        (q̄, Π⁻¹) of :meth:`~thetahat.estimation.statistical.map_fit.FitSchedule.initial_prior`
        (diagonal Π⁻¹).

    Returns
    -------
    bool
        False also when the trajectory is not finite at the start values.
    """
    system = schedule.system
    n, p = system.n, system.p
    sw = sweep_kernel(model_kernel(system, compiled=schedule.compiled))
    sigma = resolve_noise_std(schedule.noise_std, Y[:k1])
    pc, WT = Propagation(hold=schedule.hold, substeps=schedule.substeps or 1,
                         h_rho=schedule.h_rho).arrays()
    A, b, T = np.empty((n + p, n + p)), np.empty(n + p), np.empty((n, n + p))
    q0, info0 = prior0
    with np.errstate(all="ignore"):
        J = sw(q0[:n].copy(), q0[n:].copy(), np.ascontiguousarray(U, dtype=np.float64), Y,
               np.ascontiguousarray(t, dtype=np.float64), 0, k1, False, 1.0 / sigma ** 2,
               pc, WT, True, A, b, T, np.empty((k1, n)))
    if not (math.isfinite(J) and np.all(np.isfinite(A))):
        return False
    _, cov = solve_scaled(A + info0, np.zeros(n + p))
    var, var0 = np.diag(cov)[n:], 1.0 / np.diag(info0)[n:]
    return bool(np.all(var > 0.0) and np.all(WINDOW_INFO_GAIN * var <= var0))


def resolve_window(window: int | str | None, window_max: int, schedule: FitSchedule,
                   t: FloatArray, U: FloatArray, Y: FloatArray,
                   prior0: tuple[FloatArray, FloatArray]) -> int | None:
    """The window W of a record: ``window`` if an integer; for ``"auto"`` the first count of
    :func:`window_grid` that :func:`window_reached`, within [:data:`WINDOW_MIN`,
    ``window_max``] (``window_max`` when none is and the record reaches it; None, i.e. every
    fit of all the data, when the record is shorter).

    Parameters
    ----------
    window : int, "auto" or None
    window_max : int
    schedule : FitSchedule
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
    prior0 : tuple of ndarray

    Returns
    -------
    int or None
    """
    if window is None or isinstance(window, (int, np.integer)):
        return None if window is None else int(window)
    N = t.shape[0]
    for g in window_grid(schedule.system, window_max):
        if g > N:
            return None
        if window_reached(schedule, t, U, Y, g, prior0):
            return min(max(g, WINDOW_MIN), window_max)
    return window_max if N >= window_max else None


def stream_window(schedule: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray, k: int,
                  prior0: tuple[FloatArray, FloatArray], window_max: int,
                  grid: Collection[int]) -> int | None:
    """The ``"auto"`` window W a stream decides at sample count k, or None (not yet): the rule
    of :func:`resolve_window` applied to the samples so far, so that a stream's W is the
    run's on the same samples.

    Parameters
    ----------
    schedule, prior0
        As for :func:`window_reached`.
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
        N ≥ k: the stream's samples so far.
    k : int
    window_max : int
    grid : collection of int
        :func:`window_grid` of the model and ``window_max``.

    Returns
    -------
    int or None
    """
    if k >= window_max:
        return window_max
    if k in grid and window_reached(schedule, t[:k], U[:k], Y[:k], k, prior0):
        return min(max(k, WINDOW_MIN), window_max)
    return None


def windowed(ks: list[int], W: int | None) -> list[int]:
    """The fit counts with a window W: those of ``ks`` below W, then every W samples, then
    the last of ``ks`` (the record's own fit).

    Parameters
    ----------
    ks : list of int
        The counts of the fits of all the data (increasing).
    W : int or None
        None: ``ks`` unchanged.

    Returns
    -------
    list of int

    Examples
    --------
    >>> windowed([12, 17, 25, 36, 51, 73, 100], 30)
    [12, 17, 25, 30, 60, 90, 100]
    """
    if W is None or not ks or ks[-1] <= W:
        return list(ks)
    return ([k for k in ks if k < W] + list(range(W, ks[-1], W)) + [ks[-1]])


def windowed_counts(at: Callable[[int], int], W: int) -> Callable[[int], int]:
    """j ↦ k_j of a stream with a window W: ``at``'s counts below W, then W, 2W, ….

    Parameters
    ----------
    at : callable
        The information schedule (j ↦ k_j).
    W : int

    Returns
    -------
    callable

    Examples
    --------
    >>> from thetahat.estimation.statistical.map_fit import information_schedule
    >>> f = windowed_counts(information_schedule(12), 30)
    >>> [f(j) for j in range(6)]
    [12, 17, 25, 30, 60, 90]
    """
    below = 0
    while at(below) < W:
        below += 1

    def counts(j: int) -> int:
        return at(j) if j < below else W * (j - below + 1)
    return counts


def arrival_information(P: FloatArray) -> FloatArray:
    """The information of the arrival cost N(s̄, P): P⁻¹ after Jacobi scaling, the scaled
    eigenvalues floored at :data:`ARRIVAL_FLOOR` of the largest.

    Parameters
    ----------
    P : ndarray (q, q)
        Symmetric positive semidefinite.

    Returns
    -------
    ndarray (q, q)

    Examples
    --------
    >>> import numpy as np
    >>> P = np.array([[1.0, 1.0], [1.0, 1.0]])        # x = θ exactly: rank 1
    >>> info = arrival_information(P)
    >>> bool(info[0, 0] > 1e7 and abs(info[0, 0] + info[0, 1]) / info[0, 0] < 1e-6)
    True
    """
    P = np.asarray(P, dtype=np.float64)
    d = np.sqrt(np.maximum(np.diag(P), 1e-300))
    lam, V = np.linalg.eigh(0.5 * (P + P.T) / np.outer(d, d))
    lam = np.maximum(lam, ARRIVAL_FLOOR * max(float(lam[-1]), 1e-300))
    return ((V / lam) @ V.T) / np.outer(d, d)


def fit_window(schedule: FitSchedule, t: FloatArray, U: FloatArray, Y: FloatArray, *,
               k0: int, k1: int, s0: FloatArray, P0: FloatArray, noise_std: FloatArray,
               final: bool = False) -> FitResult:
    """The MAP fit of samples k0 + 1 … k1 − 1 with the arrival cost N(s0, P0) on
    col(x(t_{k0}), θ) (the module docstring), warm-started at s0.

    Parameters
    ----------
    schedule : FitSchedule
        The model, σ if given, the iterations, the hold and the sub-steps.
    t, U, Y : ndarray, shapes (N,), (N, m), (N, r)
    k0, k1 : int
        The window's anchor (its sample is summarised by the prior) and its end (exclusive).
    s0, P0 : ndarray (n + p,), (n + p, n + p)
        The posterior at sample k0: the EKF's, or the previous fit's at its end.
    noise_std : ndarray (r,)
        σ when the schedule has none (the fits of all the data estimated it).
    final : bool
        The record's last fit (iterates to convergence: ``first_max_iter``).

    Returns
    -------
    FitResult
        On k0 … k1 − 1; ``cov`` is that of col(x(t_{k0}), θ).
    """
    info = arrival_information(P0)
    sigma = (np.asarray(noise_std, dtype=np.float64) if schedule.noise_std is None
             else resolve_noise_std(schedule.noise_std, Y[k0:k1]))
    s = np.asarray(s0, dtype=np.float64)
    return fit_map(schedule.system, t, U, Y, k0=k0, k1=k1, q_start=s.copy(), q_prior=s,
                   prior_info=info, noise_std=sigma, skip_first=True,
                   max_iter=schedule.first_max_iter if final else schedule.max_iter,
                   hold=schedule.hold, substeps=schedule.substeps, h_rho=schedule.h_rho,
                   compiled=schedule.compiled)
