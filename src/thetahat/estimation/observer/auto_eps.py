r"""``eps = "auto"``: the observer's ε from the record's one-step output prediction error.

K(ε) places the observer's chain poles at λ/ε (Remark 2), so ε sets how fast (x̂, φ̂) follow
the measurements. Too large, and the observer lags the perturbation; too small, and it
follows the measurement noise. Theorem 1 asks only that ε be small enough; the paper leaves the
number to the designer. Here the record chooses it, as a Kalman filter's gain would be chosen
by prediction-error identification: with θ̂ held at θ̂₀, the observer run with K(ε) gives
(x̂_k, φ̂_k), and the model predicts the next sample from them alone,

    ŷ_{k+1|k} = C x(t_{k+1}),   ẋ = A x + B u + E φ̂_k,   x(t_k) = x̂_k,

u held or linear between the samples as the run's hold says, φ̂ held (the observer's own
model of φ, the extended system (2), between two samples). The criterion is

    J(ε) = log det Ŝ(ε),   Ŝ = the sample covariance of y_{k+1} − ŷ_{k+1|k},

which is invariant to the outputs' units, and whose minimum over all gains of a linear model
with Gaussian noise is the steady-state Kalman predictor. The observer's estimate of φ does
not depend on θ̂ (φ̂ is an extended state), so holding θ̂ at θ̂₀ does not bias the choice.

:func:`eps_bounds` gives the search range from the model's poles and the record's time
scales: the fastest chain pole |λ|max/ε no faster than the Nyquist rate π/Δt (the samples
cannot show a faster observer), and the slowest |λ|min/ε no slower than
:data:`SETTLING_TIME_CONSTANTS` time constants in the record's duration T (else the observer
has not settled when the record ends), within the paper's 0 < ε ≤ 1. :func:`choose_eps`
scans the range on a log grid, refines around the best point, and returns the ε of the least
J (the largest of equal ones: a smaller ε amplifies the noise in x̂ and φ̂ for nothing).
Measured on thirteen shipped models against the true φ of their simulated records: the chosen
ε estimates φ with an RMS error 0.97–1.44× that of the best ε in hindsight
(benchmarks/bench_auto_eps.py; tests/test_modelfile_eps.py asserts ≤ 2× on five).

The criterion is the observer's, not the update law's: the law integrates φ̂ − g(v, x̂, θ̂),
and a faster observer feeds it more noise. The paper's final θ̂ was further from θ (in
Cramér–Rao sd) at this ε than at ε = 1 on four of five models measured
(docs/sec7-8-tuning-and-example.md), which is why model files default to ε = 1.

What lives here: :func:`eps_bounds`, :func:`prediction_cost`, :func:`choose_eps`, their
constants and :class:`EpsChoice`. What it may import: NumPy, SciPy and the package's errors.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ...errors import DimensionError, DesignError

__all__ = ["EPS_MAX", "EPS_STEPS_PER_DECADE", "REFINEMENTS", "SETTLING_TIME_CONSTANTS",
           "TRANSIENT_FRACTION", "EpsChoice",
           "choose_eps", "eps_bounds", "prediction_cost"]

FloatArray = NDArray[np.float64]

#: The slowest chain pole makes at least this many time constants within the record.
SETTLING_TIME_CONSTANTS = 50.0
#: The prediction errors are measured after this fraction of the record: five of the slowest
#: pole's time constants at ε_max (e⁻⁵ of x̂(0)'s error left).
TRANSIENT_FRACTION = 5.0 / SETTLING_TIME_CONSTANTS
#: The paper's designs take 0 < ε ≤ 1 (Sec. VII).
EPS_MAX = 1.0
#: Points per decade of the first scan of ε.
EPS_STEPS_PER_DECADE = 2
#: Times the log step is then halved around the best point (a factor 10^(1/8) ≈ 1.33 last).
REFINEMENTS = 2


def eps_bounds(chain_pole_magnitudes: ArrayLike, dt: float, duration: float
               ) -> tuple[float, float]:
    """The range of ε whose observer the record can show and settle.

    Parameters
    ----------
    chain_pole_magnitudes : array_like
        |λ| of the design's chain poles at ε = 1 (they sit at λ/ε).
    dt : float
        The record's typical (median) sample interval, s.
    duration : float
        The record's duration T, s.

    Returns
    -------
    (eps_min, eps_max) : tuple of float
        ε_min = |λ|max Δt / π (fastest pole at the Nyquist rate), ε_max = |λ|min T /
        :data:`SETTLING_TIME_CONSTANTS`; when the record is too short for both, ε_max = ε_min.
        Both at most :data:`EPS_MAX` = 1, the paper's range 0 < ε ≤ 1 (slower chain poles,
        ``chain_poles``, give a slower observer).

    Raises
    ------
    DesignError
        No chain pole, or a non-positive Δt or T.

    Examples
    --------
    >>> lo, hi = eps_bounds([1.0, 2.0, 3.0], dt=1e-3, duration=30.0)
    >>> round(lo, 6), round(hi, 3)
    (0.000955, 0.6)
    """
    mags = np.abs(np.asarray(chain_pole_magnitudes, dtype=np.float64)).ravel()
    if mags.size == 0 or not np.all(np.isfinite(mags)) or mags.min() <= 0:
        raise DesignError("eps = 'auto' needs the design's chain poles (finite, nonzero); "
                             "the model has none: give eps in [estimator].")
    if not (dt > 0 and duration > 0 and math.isfinite(dt) and math.isfinite(duration)):
        raise DesignError(f"eps = 'auto' needs a record with a positive sample interval and "
                             f"duration; got dt = {dt}, T = {duration}.")
    lo = float(mags.max()) * dt / math.pi
    hi = min(EPS_MAX, max(lo, float(mags.min()) * duration / SETTLING_TIME_CONSTANTS))
    return min(lo, hi), hi


def prediction_cost(A: ArrayLike, B: ArrayLike, E: ArrayLike, C: ArrayLike, t: ArrayLike,
                    u: ArrayLike | None, y: ArrayLike, x_hat: ArrayLike, phi_hat: ArrayLike,
                    *, hold: str = "zoh", skip: int = 0) -> float:
    """J = log det of the one-step output prediction errors' covariance (module docstring).

    Parameters
    ----------
    A, B, E, C : array_like
        The linear part (B may have 0 columns).
    t : array_like, shape (N,)
        Strictly increasing sample times.
    u : array_like, shape (N, m), or None
    y : array_like, shape (N, r)
        NaN rows (missing samples) are left out.
    x_hat, phi_hat : array_like, shapes (N, n) and (N, k)
        The observer's estimates at the samples.
    hold : {"zoh", "foh"}
        u held or linear between the samples ("bandlimited" is taken as "foh").
    skip : int
        Predictions of the first ``skip`` samples are left out (the observer's transient).

    Returns
    -------
    float
        ``inf`` when x̂ or φ̂ is not finite, or fewer than r + 2 predictions remain.

    Examples
    --------
    A perfect observer of ẋ = −x + u predicts each sample exactly but for the noise:

    >>> import numpy as np
    >>> t = np.arange(0.0, 10.0, 0.01)
    >>> x = np.exp(-t)
    >>> y = x[:, None] + 0.01 * np.random.default_rng(0).standard_normal((t.size, 1))
    >>> J = prediction_cost([[-1.0]], np.zeros((1, 0)), [[0.0]], [[1.0]], t, None, y,
    ...                     x[:, None], np.zeros((t.size, 1)))
    >>> bool(abs(J - np.log(1e-4)) < 0.2)
    True
    """
    A = np.atleast_2d(np.asarray(A, dtype=np.float64))
    C = np.atleast_2d(np.asarray(C, dtype=np.float64))
    n = A.shape[0]
    B = np.asarray(B, dtype=np.float64).reshape(n, -1)
    E = np.asarray(E, dtype=np.float64).reshape(n, -1)
    m, k, r = B.shape[1], E.shape[1], C.shape[0]
    t = np.asarray(t, dtype=np.float64).ravel()
    N = t.size
    Y = np.asarray(y, dtype=np.float64).reshape(N, r)
    X = np.asarray(x_hat, dtype=np.float64).reshape(N, n)
    F = np.asarray(phi_hat, dtype=np.float64).reshape(N, k)
    U = np.zeros((N, m)) if u is None else np.asarray(u, dtype=np.float64).reshape(N, m)
    if U.shape[1] != m:
        raise DimensionError(f"u has {U.shape[1]} columns; B has {m}.")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(F))):
        return math.inf
    h = np.diff(t)
    # z = (x, w, f, a): ẋ = Ax + Bw + Ef, ẇ = a (u's slope), ḟ = 0, ȧ = 0
    size = n + 2 * m + k
    M = np.zeros((size, size))
    M[:n, :n], M[:n, n:n + m], M[:n, n + m:n + m + k] = A, B, E
    M[n:n + m, n + m + k:] = np.eye(m)
    key = np.round(h, 12)
    steps, where = np.unique(key, return_inverse=True)
    Phi = scipy.linalg.expm(steps[:, None, None] * M[None])[:, :n, :]     # first n rows
    slope = (np.zeros((N - 1, m)) if hold == "zoh" or m == 0
             else (U[1:] - U[:-1]) / h[:, None])
    Z = np.concatenate([X[:-1], U[:-1], F[:-1], slope], axis=1)
    x_next = np.einsum("kij,kj->ki", Phi[where], Z)
    e = (Y[1:] - x_next @ C.T)[skip:]
    e = e[np.all(np.isfinite(e), axis=1)]
    if e.shape[0] < r + 2:
        return math.inf
    S = np.atleast_2d(np.cov(e.T))
    sign, logdet = np.linalg.slogdet(S)
    return float(logdet) if sign > 0 else -math.inf


@dataclass(frozen=True, slots=True)
class EpsChoice:
    """The ε ``"auto"`` chose and the scan behind it.

    Attributes
    ----------
    eps : float
        The chosen ε.
    bounds : tuple of float
        The scanned range (:func:`eps_bounds`).
    scanned : tuple of (float, float)
        (ε, J(ε)) for every ε tried, in increasing ε; J = inf where the observer stopped.
    at_edge : bool
        The chosen ε is an end of the range: the criterion asked for an observer faster than
        the samples show, or slower than the record lets settle.
    """

    eps: float
    bounds: tuple[float, float]
    scanned: tuple[tuple[float, float], ...]
    at_edge: bool

    def __repr__(self) -> str:
        edge = ", at the range's edge" if self.at_edge else ""
        return (f"EpsChoice(eps={self.eps:.3g}, bounds=({self.bounds[0]:.3g}, "
                f"{self.bounds[1]:.3g}), {len(self.scanned)} tried{edge})")


def choose_eps(cost: Callable[[float], float], bounds: tuple[float, float]) -> EpsChoice:
    """Scan ε over ``bounds`` on a log grid, refine around the best, and pick the least J.

    Parameters
    ----------
    cost : callable
        ε ↦ J(ε) (:func:`prediction_cost` of a run with K(ε)); ``inf`` where the run failed.
    bounds : (float, float)
        From :func:`eps_bounds`.

    Returns
    -------
    EpsChoice

    Raises
    ------
    DesignError
        J is not finite anywhere in the range (every run stopped).

    Examples
    --------
    >>> choice = choose_eps(lambda e: (np.log10(e) + 2.0) ** 2, (1e-4, 1.0))
    >>> round(choice.eps, 6), choice.at_edge
    (0.01, False)
    """
    lo, hi = bounds
    decades = math.log10(hi / lo)
    count = max(2, int(math.ceil(decades * EPS_STEPS_PER_DECADE)) + 1)
    grid = np.geomspace(lo, hi, count) if hi > lo else np.array([lo])
    seen: dict[float, float] = {}

    def J(e: float) -> float:
        if e not in seen:
            value = float(cost(e))
            seen[e] = math.inf if math.isnan(value) else value     # -inf: exact prediction
        return seen[e]

    values = [J(float(e)) for e in grid]
    if not np.any(np.asarray(values) < math.inf):
        raise DesignError(
            f"eps = 'auto': the observer stopped (or its estimates were not finite) at every "
            f"ε in [{lo:.3g}, {hi:.3g}]; check the model against the record, or give eps in "
            "[estimator].")
    if grid.size > 1:
        step = float(grid[1] / grid[0])
        for _ in range(REFINEMENTS):          # halve the log step around the best so far
            step **= 0.5
            at = min(seen, key=seen.__getitem__)
            for e in (at / step, at * step):
                if lo <= e <= hi:
                    J(float(e))
    eps_all = np.array(sorted(seen))
    J_all = np.array([seen[e] for e in eps_all])
    eps = float(eps_all[J_all == J_all.min()].max())
    return EpsChoice(eps=eps, bounds=(float(lo), float(hi)),
                     scanned=tuple((float(e), float(v)) for e, v in zip(eps_all, J_all)),
                     at_edge=grid.size > 1 and eps in (float(grid[0]), float(grid[-1])))
