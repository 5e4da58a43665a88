"""Automatic choice of (ε, Γ): a grid search in the order of Sec. VII.

Sec. VII tunes the observer "by starting with ε = 1 and decreasing ε in small decrements until
satisfactory performance is achieved". :func:`tune_eps_gamma` automates that procedure for the
pair (ε, Γ): for every ε (1 first, then decreasing) and every adaptation gain Γ it runs the
observer on a few tuning seeds, rejects the pairs for which some run diverged or whose θ̂ did
not settle within 1 % of θ on every seed, and picks among the others the pair with the
smallest score (by default the worst θ RMSE over the seeds, second half of the record). When
no pair converges it says so and picks none: a pick it cannot stand behind would be taken for
a tuning.

Γ is the gain of the update law of Proposition 2, u_θ = Proj(l Γ (θ* − θ̂)): a larger Γ pulls
θ̂ faster towards the algebraic inverse θ* while the excitation indicator l is on, at the
price of passing more of the noise of θ* (through x̂ and φ̂) into θ̂. Every Γ > 0 keeps
Assumption 3 — the proofs of Propositions 1–2 use V_u = θ̃ᵀΓ⁻¹θ̃/2 (Prop. 2 with the extra
term −μ ∫ e^(t−τ) l dτ, μ < λ_min(Γ⁻¹)), which is a valid Lyapunov function for any symmetric
positive-definite Γ — so the choice of Γ is a matter of performance only. ε, in contrast, is
only guaranteed to work below an unknown ε* (Theorem 1), and a too small ε makes the
discretised observer diverge on sampled, noisy data.
"""

from __future__ import annotations

import functools
import itertools
import math
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import DesignError, DimensionError, ThetahatWarning
from .batch import check_seeds, monte_carlo
from .runs import DIVERGENCE_ERRORS, RunMetrics, format_number, run_metrics
from .sweep import EstimatorSource, check_eps_values, observer_for, run_observer

__all__ = ["CRITERIA", "TuneResult", "tune_eps_gamma"]

FloatArray = NDArray[np.float64]

#: Scores :func:`tune_eps_gamma` can minimise (each the worst value over the tuning seeds).
CRITERIA = ("theta_rmse", "t_1pct")


@dataclass(frozen=True, slots=True, eq=False)
class TuneResult:
    """Outcome of :func:`tune_eps_gamma`: the chosen (ε, Γ) and the metrics of every pair.

    Attributes
    ----------
    eps : tuple of float
        The ε values tried, starting at 1 and decreasing (Sec. VII).
    Gamma : tuple of float
        The Γ values tried, increasing.
    seeds : tuple of int
        The tuning seeds (the same for every pair).
    criterion : str
        The minimised score, one of :data:`CRITERIA`.
    diverged : ndarray of bool, shape (n_eps, n_Gamma, n_seeds)
        The run raised a divergence error or some estimate left ``DIVERGENCE_FACTOR`` times
        the range of its truth (as in :func:`~thetahat.studies.sweep.eps_sweep`).
    theta_rmse : ndarray, shape (n_eps, n_Gamma, n_seeds)
        RMS of ‖θ̂ − θ‖ over the second half of the record (NaN when the run raised).
    t_1pct : ndarray, shape (n_eps, n_Gamma, n_seeds)
        Time after which |θ̂ − θ| <= 1 % |θ| for good (``inf``: not settled).
    x_rmse : ndarray, shape (n_eps, n_Gamma, n_seeds, n)
        RMSE of each component of x̂ over the second half.
    score : ndarray, shape (n_eps, n_Gamma)
        The worst ``criterion`` over the seeds; ``inf`` for a rejected (diverged) pair.
    best_eps, best_Gamma : float or None
        The chosen pair: among the pairs that converged (:attr:`converged`: θ̂ settled within
        1 % of θ on every seed), the scores within ``rel_tol`` of the smallest, the larger
        ε, then the smaller Γ; None when no pair converged (a ThetahatWarning says so, and
        :meth:`verdict` why) — a pair that did not converge is never chosen.
    errors : tuple of str
        Every diverged run, with its ε, Γ and seed, and how it diverged: the error that
        stopped it, or the estimate that became non-finite or left ``DIVERGENCE_FACTOR``
        times the truth's scale.
    wall_time : float
        Seconds for the whole search.
    """

    eps: tuple[float, ...]
    Gamma: tuple[float, ...]
    seeds: tuple[int, ...]
    criterion: str
    diverged: NDArray[np.bool_]
    theta_rmse: FloatArray
    t_1pct: FloatArray
    x_rmse: FloatArray
    score: FloatArray
    best_eps: float | None
    best_Gamma: float | None
    errors: tuple[str, ...]
    wall_time: float

    @property
    def rejected(self) -> NDArray[np.bool_]:
        """Pairs with at least one diverged seed; shape (n_eps, n_Gamma)."""
        return np.asarray(self.diverged.any(axis=2), dtype=np.bool_)

    @property
    def converged(self) -> NDArray[np.bool_]:
        """Pairs whose θ̂ settled within 1 % of θ (t_1 % finite) on every seed and never
        diverged: the pairs that meet the criterion a choice needs; shape (n_eps, n_Gamma)."""
        with np.errstate(invalid="ignore"):
            settled = np.all(np.isfinite(self.t_1pct), axis=2)
        return np.asarray(settled & ~self.rejected, dtype=np.bool_)

    def verdict(self) -> str:
        """One sentence: the chosen pair and its score, or why none was chosen."""
        if self.best_eps is None:
            if self.rejected.all():
                return ("no (eps, Gamma) pair was stable on every seed; try larger eps "
                        "(eps = 1 first, Sec. VII) or other Gamma.")
            return (f"no (eps, Gamma) pair converged: on none of the {self.score.size} "
                    f"pairs did θ̂ settle within 1 % of θ on every seed (t_1% = inf), so "
                    "none is chosen. The law may not converge on this model and scenario: "
                    "check its conditions (thetahat estimate --method paper reports them), "
                    "try a longer record, other Gamma, or method guarded or mle.")
        i, j = self.eps.index(self.best_eps), self.Gamma.index(self.best_Gamma)
        return (f"chosen: eps = {self.best_eps:g}, Gamma = {self.best_Gamma:g} "
                f"({self.criterion} = {self.score[i, j]:.3g}, worst over "
                f"{len(self.seeds)} seed(s)); {int(self.rejected.sum())} of "
                f"{self.score.size} pair(s) rejected as diverged, "
                f"{int((~self.converged & ~self.rejected).sum())} as not settled within 1 %.")

    def table(self, state_labels: Sequence[str] | None = None) -> str:
        """One line per (ε, Γ): stable seeds, worst θ RMSE, t_1 %, state RMSE; then the choice.

        Parameters
        ----------
        state_labels : sequence of str, optional
            Names of the state components (default x1, x2, ...).

        Returns
        -------
        str
        """
        n = self.x_rmse.shape[-1]
        labels = list(state_labels) if state_labels is not None else [f"x{i + 1}"
                                                                       for i in range(n)]
        if len(labels) != n:
            raise DimensionError(f"state_labels must hold {n} names; got {len(labels)}.")
        head = (f"{'eps':>6} {'Gamma':>7} {'stable':>7} {'th RMSE max':>12} "
                f"{'t_1% max [s]':>13} " + " ".join(f"{lab + ' RMSE max':>14}"
                                                    for lab in labels))
        lines = [(f"(eps, Gamma) search: {len(self.seeds)} seed(s) per pair; worst over the "
                 f"seeds; errors over the second half; score = {self.criterion}"),
                 head, "-" * len(head)]
        fmt = format_number
        for (i, e), (j, g) in itertools.product(enumerate(self.eps), enumerate(self.Gamma)):
            n_ok = int((~self.diverged[i, j]).sum())
            bad = self.rejected[i, j]
            cells = [f"{e:6.3g}", f"{g:7.3g}", f"{n_ok:>3d}/{len(self.seeds):<3d}",
                     f"{'-' if bad else fmt(float(np.max(self.theta_rmse[i, j])), '.3e'):>12}",
                     f"{'-' if bad else fmt(float(np.max(self.t_1pct[i, j])), '.2f'):>13}"]
            cells += [f"{'-' if bad else fmt(float(np.max(self.x_rmse[i, j, :, c])), '.2e'):>14}"
                      for c in range(n)]
            mark = " <- chosen" if (e == self.best_eps and g == self.best_Gamma) else (
                " diverged" if bad else ("" if self.converged[i, j] else " not settled"))
            lines.append(" ".join(cells) + mark)
        lines.append(self.verdict())
        lines += [f"  run stopped: {err if len(err) <= 100 else err[:97] + '...'}"
                  for err in self.errors]
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready summary (non-finite numbers become None)."""
        def clean(a: Any) -> Any:
            arr = np.asarray(a, dtype=float)
            if arr.ndim == 0:
                v = float(arr)
                return v if math.isfinite(v) else None
            return [clean(b) for b in arr]

        return {"eps": list(self.eps), "Gamma": list(self.Gamma), "seeds": list(self.seeds),
                "criterion": self.criterion, "best_eps": self.best_eps,
                "best_Gamma": self.best_Gamma, "verdict": self.verdict(),
                "score": clean(self.score), "rejected": self.rejected.tolist(),
                "runs": {"diverged": self.diverged.tolist(),
                         "theta_rmse": clean(self.theta_rmse), "t_1pct": clean(self.t_1pct),
                         "x_rmse": clean(self.x_rmse)},
                "errors": list(self.errors), "wall_time_s": self.wall_time}

    def __repr__(self) -> str:
        return (f"TuneResult(best_eps={self.best_eps}, best_Gamma={self.best_Gamma}, "
                f"criterion={self.criterion!r}, pairs={self.score.size}, "
                f"rejected={int(self.rejected.sum())}, wall_time={self.wall_time:.3g} s)")


def _check_gammas(gammas: Iterable[float]) -> tuple[float, ...]:
    try:
        out = tuple(float(g) for g in gammas)
    except (TypeError, ValueError) as exc:
        raise DesignError(f"gammas must be numbers; got {gammas!r}.") from exc
    if not out or not all(math.isfinite(g) and g > 0 for g in out) \
            or any(b <= a for a, b in itertools.pairwise(out)):
        raise DesignError("gammas must be finite, > 0 (Γ positive definite, Propositions 1–4) "
                          f"and strictly increasing; got {list(out)}. E.g. "
                          "gammas=[1, 3, 10, 30].")
    return out


def _run_eps(estimator: EstimatorSource, observers: list[Any], records: list[Any],
             th0: FloatArray) -> list[RunMetrics]:
    """Runs of one ε: every Γ on every seed (Γ-major), vectorised when possible.

    The observers of one ε differ only in Γ, so :func:`~thetahat.estimation.observer.batch_run.
    run_batch` runs all of them on all seeds at once. When that batch diverges (one exploding
    run stops it), or the observers are not :class:`ModifiedHighGainObserver` or the records
    do not share one time grid, the runs are repeated one by one — as they are for records of
    at least ``COMPILE_MIN_SAMPLES`` samples, each on its compiled form
    (:func:`~thetahat.studies.sweep.run_observer`), which beats the NumPy batch there.
    """
    from ..estimation.observer.batch_run import run_batch
    from ..estimation.drive import COMPILE_MIN_SAMPLES
    from ..estimation.observer.observer import ModifiedHighGainObserver

    pairs = [(o, d) for o in observers for d in records]
    t0 = np.asarray(records[0].t)
    if t0.size < COMPILE_MIN_SAMPLES and all(
            isinstance(o, ModifiedHighGainObserver) for o in observers) and all(
            np.array_equal(np.asarray(d.t), t0) for d in records[1:]):
        state0 = np.stack([o.init(theta_hat0=th0) for o, _ in pairs])
        try:
            with np.errstate(all="ignore"):
                res = run_batch([o for o, _ in pairs], t0, np.stack([d.u for _, d in pairs]),
                                np.stack([d.y for _, d in pairs]), state0=state0)
        except DIVERGENCE_ERRORS:
            pass
        else:
            return [run_metrics(d, res[b]) for b, (_, d) in enumerate(pairs)]
    return [run_observer(estimator, o, d, th0) for o, d in pairs]


def _tune_eps(estimator: EstimatorSource, eps: tuple[float, ...], gammas: tuple[float, ...],
              records: list[Any], th0: FloatArray, index: int) -> list[RunMetrics]:
    """The task of ε number ``index``: every Γ on every record (one engine task)."""
    return _run_eps(estimator, [observer_for(estimator, eps[index], g) for g in gammas],
                    records, th0)


def tune_eps_gamma(estimator: EstimatorSource, simulate: Callable[[int], Any], *,
                   eps_values: Iterable[float] = (1.0, 0.7, 0.5, 0.3),
                   gammas: Iterable[float] = (1.0, 3.0, 10.0, 30.0),
                   seeds: Iterable[int] = (1000, 1001), theta_hat0: ArrayLike,
                   criterion: str = "theta_rmse", rel_tol: float = 0.05,
                   n_jobs: int | None = 1, scheduler: Any = None,
                   progress: bool = False) -> TuneResult:
    """Pick ε and Γ by a grid search over tuning seeds, ε decreasing from 1 (Sec. VII).

    For every ε (1 first, then decreasing) and every Γ: the observer for (ε, Γ)
    (:func:`~thetahat.studies.sweep.observer_for`), run on ``simulate(seed)`` for each seed
    from ``obs.init(theta_hat0=...)``,
    and record divergence, θ RMSE and t_1 % of θ̂ and the RMSE of x̂ against the truth. A pair
    with a diverged run is rejected; among the others the smallest ``criterion`` (its worst
    value over the seeds) wins.

    Parameters
    ----------
    estimator : EstimatorSpec or callable ``make_observer(eps, Gamma=...)``
        An :class:`~thetahat.spec.EstimatorSpec` (its ``build(eps=…, Gamma=…)``: one SCB
        for the whole grid, its hold for every run), or a callable building the observer,
        e.g. :func:`thetahat.models.lugre.observer`: anything with
        ``init(theta_hat0=...)`` and ``run(t, u, y, state0=...)``. When it returns
        :class:`~thetahat.estimation.observer.observer.ModifiedHighGainObserver` objects, the runs of
        one ε (all Γ, all seeds) are vectorised with
        :func:`~thetahat.estimation.observer.batch_run.run_batch`.
    simulate : callable ``simulate(seed)``
        Simulates the plant with that noise seed, returning ``t``, ``u``, ``y`` and the true
        ``x`` and ``theta`` (e.g. a ``functools.partial`` of :func:`thetahat.models.lugre.
        simulate`). Called once per seed.
    eps_values : iterable of float, optional
        Must start at 1 and decrease strictly, each in (0, 1] (Sec. VII).
    gammas : iterable of float, optional
        Scalar adaptation gains Γ (Γ·I for p > 1), finite, > 0 and strictly increasing.
    seeds : iterable of int, optional
        Non-negative tuning seeds (keep them apart from the seeds used to evaluate the
        result, so the choice is not fitted to the test noise).
    theta_hat0 : array_like, shape (p,)
        Initial parameter estimate (in Θ).
    criterion : {"theta_rmse", "t_1pct"}, optional
        The score: θ RMSE over the second half, or the settling time to 1 %; the worst over
        the seeds in both cases.
    rel_tol : float, optional
        Scores within this relative margin of the best count as ties (default 0.05: two
        seeds cannot resolve smaller differences); ties go to the larger ε, then the
        smaller Γ.
    n_jobs : int or None, optional
        Worker processes for the ε values (1: in this process; -1: all cores); each ε
        (all Γ, all seeds) is one task, run by :func:`~thetahat.studies.batch.monte_carlo`.
        ``estimator`` must then be picklable (specs and module-level functions are).
    scheduler : str or dask.distributed.Client, optional
        Run the ε tasks on a Dask cluster (see :func:`~thetahat.studies.batch.monte_carlo`);
        the result equals the one computed in this process.
    progress : bool, optional
        Progress bar over the ε values (tqdm, when installed).

    Returns
    -------
    TuneResult

    Raises
    ------
    DesignError
        Bad ``eps_values`` (not starting at 1, not decreasing), bad ``gammas`` or an unknown
        ``criterion``.
    DimensionError
        Empty or negative seeds.

    Warns
    -----
    ThetahatWarning
        No pair converged: none is chosen (the message is :meth:`TuneResult.verdict`).

    Notes
    -----
    Γ scales the update law of Proposition 2, u_θ = Proj(l Γ (θ* − θ̂)); any Γ > 0 keeps
    Assumption 3 (the proof uses V_u = θ̃ᵀΓ⁻¹θ̃/2, positive definite for every Γ > 0), so Γ is
    tuned for performance only. ε is stable only below an unknown ε* (Theorem 1) and a too
    small ε diverges on sampled, noisy data; hence the search starts at ε = 1. Scores within
    ``rel_tol`` of the best are ties, and ties go to the larger ε (less noise amplification,
    K(ε) ~ ε^(−n_q)) and then to the smaller Γ.
    The choice holds for the scenario ``simulate`` describes; a different input, noise level
    or sampling rate calls for a new search.

    Examples
    --------
    >>> import functools
    >>> from thetahat.models import lugre
    >>> from thetahat.studies.tune import tune_eps_gamma
    >>> sim = functools.partial(lugre.simulate, t_end=2.0, fs=500.0)
    >>> res = tune_eps_gamma(lugre.estimator_spec(), sim, eps_values=[1.0, 0.5],
    ...                      gammas=[1.0, 10.0], seeds=[1000], theta_hat0=[0.5])
    >>> res.score.shape
    (2, 2)
    >>> bool(res.score[res.eps.index(res.best_eps), res.Gamma.index(res.best_Gamma)]
    ...      <= 1.05 * res.score.min())
    True
    """
    if criterion not in CRITERIA:
        raise DesignError(f"criterion must be one of {CRITERIA}; got {criterion!r}.")
    eps = check_eps_values(eps_values)
    gam = _check_gammas(gammas)
    seeds_ = check_seeds(seeds)
    th0 = np.atleast_1d(np.asarray(theta_hat0, dtype=np.float64))
    start = time.perf_counter()
    records = [simulate(s) for s in seeds_]             # once, shipped to every ε task
    task = functools.partial(_tune_eps, estimator, eps, gam, records, th0)
    batch = monte_carlo(task, range(len(eps)), progress=progress, n_jobs=n_jobs,
                        scheduler=scheduler, chunk_size=1)
    runs: list[RunMetrics] = [r for per_eps in batch.results for r in per_eps]
    shape = (len(eps), len(gam), len(seeds_))
    n = max(r.x_rmse.shape[0] for r in runs)

    def grid(attr: str) -> FloatArray:
        return np.array([getattr(r, attr) for r in runs], dtype=float).reshape(shape)

    div = np.array([r.diverged for r in runs]).reshape(shape)
    metrics = {"theta_rmse": grid("theta_rmse"), "t_1pct": grid("t_1pct")}
    rejected = div.any(axis=2)
    with np.errstate(invalid="ignore"):
        score = np.where(rejected, np.inf, np.max(metrics[criterion], axis=2))
    score = np.where(np.isnan(score), np.inf, score)
    converged = ~rejected & np.all(np.isfinite(metrics["t_1pct"]), axis=2)
    best_eps = best_gam = None
    if converged.any():
        # only pairs that met the criterion (settled on every seed) are candidates; near-ties
        # (within rel_tol of the best) go to the larger ε, then the smaller Γ: decrease ε
        # only while it clearly helps (Sec. VII)
        cand = np.where(converged, score, np.inf)
        near = cand <= np.min(cand) * (1.0 + rel_tol)
        i, j = np.unravel_index(int(np.flatnonzero(near.ravel())[0]), score.shape)
        best_eps, best_gam = eps[i], gam[j]
    labels = itertools.product(eps, gam, seeds_)
    errors = tuple(f"eps={e:g}, Gamma={g:g}, seed={s}: {r.error}"
                   for (e, g, s), r in zip(labels, runs) if r.error is not None)
    result = TuneResult(eps=eps, Gamma=gam, seeds=seeds_, criterion=criterion, diverged=div,
                        theta_rmse=metrics["theta_rmse"], t_1pct=metrics["t_1pct"],
                        x_rmse=np.array([r.x_rmse for r in runs]).reshape(shape + (n,)),
                        score=score, best_eps=best_eps, best_Gamma=best_gam, errors=errors,
                        wall_time=time.perf_counter() - start)
    if best_eps is None:
        warnings.warn(result.verdict(), ThetahatWarning, stacklevel=2)
    return result
