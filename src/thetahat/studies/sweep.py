"""ε sweeps: how the observer behaves as ε is decreased from 1 (Sec. VII).

Sec. VII: "the observer is typically tuned by starting with ε = 1 and decreasing ε in small
decrements until satisfactory performance is achieved". Theorem 1 guarantees stability only
below some unknown ε*, while a smaller ε means a higher gain K(ε) ~ ε^(-n_q) and more noise
in the estimates; with sampled, noisy data a too small ε eventually destabilises the
discretised observer. :func:`eps_sweep` runs that tuning procedure over a Monte-Carlo batch:
for every ε (1 first, then decreasing) and every noise seed it simulates the data, builds the
observer for that ε, runs it and records accuracy and divergence.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import DesignError, DimensionError
from ..estimation.observer.observer import ModifiedHighGainObserver
from ..estimation.protocol import Estimator
from ..spec import EstimatorSpec
from .batch import check_seeds, monte_carlo
from .runs import DIVERGENCE_ERRORS, RunMetrics, failed_run, format_number, run_metrics

__all__ = ["EstimatorSource", "SweepResult", "SweepRow", "check_eps_values", "eps_sweep",
           "observer_for", "run_observer"]

FloatArray = NDArray[np.float64]

#: What a study builds its estimators from: an :class:`~thetahat.spec.EstimatorSpec` (its
#: ``build(eps=…, Gamma=…)``, one SCB for every ε) or a callable ``make(eps)`` /
#: ``make(eps, Gamma=…)`` returning any :class:`~thetahat.estimation.protocol.Estimator`.
EstimatorSource = Union[EstimatorSpec, Callable[..., Estimator]]


def observer_for(estimator: EstimatorSource, eps: float, Gamma: float | None = None) -> Any:
    """The observer a study runs at (ε, Γ).

    Parameters
    ----------
    estimator : EstimatorSpec or callable
        A spec (``estimator.build(eps=eps, Gamma=Gamma)``, no new SCB) or a callable
        ``estimator(eps)`` (``estimator(eps, Gamma=Gamma)`` when Γ is given).
    eps : float
        ε of the high-gain design.
    Gamma : float, optional
        Adaptation gain Γ; default: the estimator's own.

    Returns
    -------
    Estimator
        The spec's observer, or what the callable returns (any
        :class:`~thetahat.estimation.protocol.Estimator`).

    Examples
    --------
    >>> from thetahat.models import lugre
    >>> from thetahat.studies.sweep import observer_for
    >>> observer_for(lugre.estimator_spec(), 0.5, Gamma=3.0).update_law.Gamma.tolist()
    [[3.0]]
    """
    if isinstance(estimator, EstimatorSpec):
        return estimator.build(eps=eps, Gamma=Gamma)
    if Gamma is None:
        return estimator(eps)
    return estimator(eps, Gamma=Gamma)


def run_observer(estimator: EstimatorSource, obs: Estimator, data: Any,
                 theta_hat0: FloatArray) -> RunMetrics:
    """Run ``obs`` on one record from θ̂(0) and measure it; a divergence error is recorded.

    A paper observer runs on the fastest back end for the record
    (:func:`~thetahat.estimation.drive.runner`: the C printed from its formulas or
    numba's kernel for a record of at least ``COMPILE_MIN_SAMPLES`` samples, else Python).

    Parameters
    ----------
    estimator : EstimatorSpec or callable
        What built ``obs``; a spec supplies its sample hold.
    obs : Estimator
        From :func:`observer_for` (run through the estimator protocol; a paper observer
        with the spec's sample hold, on its fastest back end).
    data : PlantTrajectory or alike
        ``t``, ``u``, ``y`` and the true ``x``, ``theta`` (and optionally ``phi``).
    theta_hat0 : ndarray, shape (p,)
        Initial parameter estimate.

    Returns
    -------
    RunMetrics
        Diverged with NaN values when ``run`` raised one of
        :data:`~thetahat.studies.runs.DIVERGENCE_ERRORS`.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.studies.sweep import observer_for, run_observer
    >>> spec, data = lugre.estimator_spec(), lugre.simulate(seed=0, t_end=0.2, fs=500.0)
    >>> run_observer(spec, observer_for(spec, 1.0), data, np.array([0.5])).diverged
    False
    """
    from ..estimation.drive import runner
    try:
        with np.errstate(all="ignore"):            # an exploding state is the expected failure
            if isinstance(obs, ModifiedHighGainObserver):
                res = runner(obs, data.t).run(data.t, data.u, data.y,
                                              state0=obs.init(theta_hat0=theta_hat0))
            else:
                res = obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=theta_hat0))
    except DIVERGENCE_ERRORS as exc:
        return failed_run(np.asarray(data.x).shape[1], exc)
    return run_metrics(data, res)


@dataclass(frozen=True, slots=True, eq=False)
class SweepRow:
    """One ε of a sweep, aggregated over the seeds (statistics over the stable runs only).

    Attributes
    ----------
    eps : float
    n_runs, n_stable : int
        Number of seeds, and of runs that did not diverge.
    t_1pct_median, t_1pct_max : float
        Time after which |θ̂ − θ| <= 1 % |θ| for good (s); ``inf`` when θ̂ was outside the
        band at the end of the record.
    theta_max_error_median, theta_max_error_max : float
        max |θ̂ − θ| over the second half of the record.
    theta_rmse_median, theta_rmse_max : float
        RMS of ‖θ̂ − θ‖ over the second half.
    x_rmse_median, x_rmse_max : ndarray, shape (n,)
        RMSE of each component of x̂ (first observer) over the second half.
    x_rmse_refined_median, x_rmse_refined_max : ndarray, shape (n,), or None
        The same for the second observer's x̂₂ (None without a second observer).

    All statistics are NaN when no run of this ε was stable.
    """

    eps: float
    n_runs: int
    n_stable: int
    t_1pct_median: float
    t_1pct_max: float
    theta_max_error_median: float
    theta_max_error_max: float
    theta_rmse_median: float
    theta_rmse_max: float
    x_rmse_median: FloatArray
    x_rmse_max: FloatArray
    x_rmse_refined_median: FloatArray | None
    x_rmse_refined_max: FloatArray | None

    @property
    def fraction_stable(self) -> float:
        """n_stable / n_runs."""
        return self.n_stable / self.n_runs

    def __repr__(self) -> str:
        return (f"SweepRow(eps={self.eps:g}, stable={self.n_stable}/{self.n_runs}, "
                f"t_1pct_median={self.t_1pct_median:.4g}, "
                f"theta_rmse_median={self.theta_rmse_median:.3g})")


def _stats(values: FloatArray, keep: NDArray[np.bool_]) -> tuple[Any, Any]:
    """(median, max) over the kept runs (axis 0), NaN when none is kept."""
    sel = values[keep]
    if sel.shape[0] == 0:
        nan = np.full(values.shape[1:], np.nan)
        return (nan, nan) if nan.ndim else (math.nan, math.nan)
    med, mx = np.median(sel, axis=0), np.max(sel, axis=0)
    return (med, mx) if np.ndim(med) else (float(med), float(mx))


@dataclass(frozen=True, slots=True, eq=False)
class SweepResult:
    """Outcome of :func:`eps_sweep`: raw per-run metrics and their per-ε summary.

    Attributes
    ----------
    eps : tuple of float
        The ε values, starting at 1 and decreasing.
    seeds : tuple of int
        The noise seeds (the same for every ε).
    diverged : ndarray of bool, shape (n_eps, n_seeds)
        The run raised a divergence error (non-finite state, ...) or some estimate exceeded
        ``DIVERGENCE_FACTOR`` times the range of the truth (:func:`~thetahat.studies.
        metrics.diverged`).
    t_1pct : ndarray, shape (n_eps, n_seeds)
        Settling time of θ̂ to within 1 % of θ (``inf``: not settled at the end).
    theta_max_error : ndarray, shape (n_eps, n_seeds)
        max over the second half of the record of max_i |θ̂_i − θ_i|.
    theta_rmse : ndarray, shape (n_eps, n_seeds)
        RMS of ‖θ̂ − θ‖ over the second half.
    x_rmse : ndarray, shape (n_eps, n_seeds, n)
        RMSE of x̂ (first observer) per component over the second half.
    x_rmse_refined : ndarray, shape (n_eps, n_seeds, n), or None
        The same for the second observer's x̂₂; None when the observers have none.
    errors : tuple of tuple of (str or None)
        For each run, how it diverged (the error that stopped it, or the estimate that became
        non-finite or left its scale), None for a run that did not.
    wall_time : float
        Seconds for the whole sweep.

    Metrics of runs that raised are NaN; metrics of runs that diverged without raising are
    kept here but left out of :attr:`rows`.
    """

    eps: tuple[float, ...]
    seeds: tuple[int, ...]
    diverged: NDArray[np.bool_]
    t_1pct: FloatArray
    theta_max_error: FloatArray
    theta_rmse: FloatArray
    x_rmse: FloatArray
    x_rmse_refined: FloatArray | None
    errors: tuple[tuple[str | None, ...], ...]
    wall_time: float

    @property
    def rows(self) -> tuple[SweepRow, ...]:
        """The per-ε summary: fraction stable, median and max of each metric."""
        out = []
        for i, eps in enumerate(self.eps):
            keep = ~self.diverged[i]
            t_med, t_max = _stats(self.t_1pct[i], keep)
            e_med, e_max = _stats(self.theta_max_error[i], keep)
            r_med, r_max = _stats(self.theta_rmse[i], keep)
            x_med, x_max = _stats(self.x_rmse[i], keep)
            x2_med = x2_max = None
            if self.x_rmse_refined is not None:
                x2_med, x2_max = _stats(self.x_rmse_refined[i], keep)
            out.append(SweepRow(eps=eps, n_runs=len(self.seeds), n_stable=int(keep.sum()),
                                t_1pct_median=t_med, t_1pct_max=t_max,
                                theta_max_error_median=e_med, theta_max_error_max=e_max,
                                theta_rmse_median=r_med, theta_rmse_max=r_max,
                                x_rmse_median=x_med, x_rmse_max=x_max,
                                x_rmse_refined_median=x2_med, x_rmse_refined_max=x2_max))
        return tuple(out)

    @property
    def fraction_stable(self) -> FloatArray:
        """Fraction of the seeds that did not diverge, per ε; shape (n_eps,)."""
        return 1.0 - self.diverged.mean(axis=1)

    @property
    def stable_down_to(self) -> float | None:
        """The smallest ε at which every seed was stable (None if there is none)."""
        ok = [e for e, d in zip(self.eps, self.diverged) if not d.any()]
        return min(ok) if ok else None

    @property
    def first_unstable(self) -> float | None:
        """The largest ε at which some run diverged (None if none did)."""
        bad = [e for e, d in zip(self.eps, self.diverged) if d.any()]
        return max(bad) if bad else None

    def verdict(self) -> str:
        """One sentence: down to which ε every run was stable, and where divergence began."""
        down, bad = self.stable_down_to, self.first_unstable
        if bad is None:
            return (f"stable for every seed at every ε tried (down to ε = {down:g}); "
                    f"no divergence.")
        if down is None:
            return f"no ε was stable for every seed; divergence already at ε = {bad:g}."
        if down > bad:
            return (f"stable for every seed down to ε = {down:g}; runs diverge from "
                    f"ε = {bad:g} on.")
        return (f"not monotone: some runs diverge at ε = {bad:g}, yet every seed is stable "
                f"at ε = {down:g}.")

    def table(self, state_labels: Sequence[str] | None = None) -> str:
        """The per-ε summary as a text table, followed by :meth:`verdict`.

        Parameters
        ----------
        state_labels : sequence of str, optional
            Names of the state components (default x1, x2, ...).

        Returns
        -------
        str
            One line per ε: stable runs, then median / max over the stable runs of t_1 %,
            max |θ̂ − θ| (second half), θ RMSE (second half) and, per state component, the
            median RMSE of the first observer (and of the second, after a slash); then the
            verdict and the distinct errors that stopped runs (a set-up error that only
            shows while running, e.g. a bad θ*, would appear here for every ε).
        """
        n = self.x_rmse.shape[-1]
        labels = list(state_labels) if state_labels is not None else [f"x{i + 1}"
                                                                       for i in range(n)]
        if len(labels) != n:
            raise DimensionError(f"state_labels must hold {n} names; got {len(labels)}.")
        second = self.x_rmse_refined is not None
        x_head = [f"{lab} RMSE" + (" 1st/2nd" if second else "") for lab in labels]
        head = (f"{'eps':>6} {'stable':>7} {'t_1% med/max [s]':>17} "
                f"{'max|th err| med/max':>20} {'th RMSE med':>12} "
                + " ".join(f"{h:>19}" for h in x_head))
        title = (f"eps sweep: {len(self.seeds)} seed(s) per eps; median/max over the stable "
                 f"runs; th = theta; errors over the second half of the record")
        lines = [title, head, "-" * len(head)]
        fmt = format_number
        for row in self.rows:
            cells = [f"{row.eps:6.3g}", f"{row.n_stable:>3d}/{row.n_runs:<3d}",
                     f"{fmt(row.t_1pct_median, '.2f'):>8}/{fmt(row.t_1pct_max, '.2f'):<8}",
                     (f"{fmt(row.theta_max_error_median, '.2e'):>9}/"
                      f"{fmt(row.theta_max_error_max, '.2e'):<10}"),
                     f"{fmt(row.theta_rmse_median, '.2e'):>12}"]
            for i in range(n):
                cell = fmt(row.x_rmse_median[i], ".2e")
                if row.x_rmse_refined_median is not None:
                    cell += "/" + fmt(row.x_rmse_refined_median[i], ".2e")
                cells.append(f"{cell:>19}")
            lines.append(" ".join(cells))
        lines.append(self.verdict())
        raised: dict[str, list[str]] = {}
        for eps, errs in zip(self.eps, self.errors):
            for err in errs:
                if err is not None:
                    raised.setdefault(err if len(err) <= 100 else err[:97] + "...",
                                      []).append(f"{eps:g}")
        for err, where in raised.items():
            lines.append(f"  {len(where)} run(s) stopped (eps = {', '.join(dict.fromkeys(where))})"
                         f": {err}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready summary: settings, per-ε rows and raw per-run values.

        Non-finite numbers (failed runs, ``t_1pct = inf``) become None.
        """
        def clean(a: Any) -> Any:
            arr = np.asarray(a, dtype=float)
            if arr.ndim == 0:
                v = float(arr)
                return v if math.isfinite(v) else None
            return [clean(b) for b in arr]

        rows = []
        for row in self.rows:
            d: dict[str, Any] = {"eps": row.eps, "n_runs": row.n_runs,
                                 "n_stable": row.n_stable,
                                 "fraction_stable": row.fraction_stable}
            for name in ("t_1pct", "theta_max_error", "theta_rmse", "x_rmse", "x_rmse_refined"):
                med = getattr(row, f"{name}_median")
                if med is not None:
                    d[f"{name}_median"] = clean(med)
                    d[f"{name}_max"] = clean(getattr(row, f"{name}_max"))
            rows.append(d)
        raw: dict[str, Any] = {"diverged": self.diverged.tolist(), "t_1pct": clean(self.t_1pct),
                               "theta_max_error": clean(self.theta_max_error),
                               "theta_rmse": clean(self.theta_rmse),
                               "x_rmse": clean(self.x_rmse),
                               "errors": [list(e) for e in self.errors]}
        if self.x_rmse_refined is not None:
            raw["x_rmse_refined"] = clean(self.x_rmse_refined)
        return {"eps": list(self.eps), "seeds": list(self.seeds),
                "stable_down_to": self.stable_down_to, "first_unstable": self.first_unstable,
                "verdict": self.verdict(), "rows": rows, "runs": raw,
                "wall_time_s": self.wall_time}

    def __repr__(self) -> str:
        stable = ", ".join(f"{e:g}: {r.n_stable}/{r.n_runs}" for e, r in zip(self.eps,
                                                                            self.rows))
        return (f"SweepResult(stable={{{stable}}}, stable_down_to={self.stable_down_to}, "
                f"first_unstable={self.first_unstable}, wall_time={self.wall_time:.3g} s)")


def check_eps_values(eps_values: Iterable[float]) -> tuple[float, ...]:
    """The ε values of a study, checked: starting at 1, strictly decreasing, in (0, 1].

    Parameters
    ----------
    eps_values : iterable of float
        The ε values in the order of Sec. VII.

    Returns
    -------
    tuple of float

    Raises
    ------
    DesignError
        Not numbers, empty, not starting at 1 or not strictly decreasing.

    Examples
    --------
    >>> from thetahat.studies.sweep import check_eps_values
    >>> check_eps_values([1, 0.5, 0.2])
    (1.0, 0.5, 0.2)
    """
    try:
        eps = tuple(float(e) for e in eps_values)
    except (TypeError, ValueError) as exc:
        raise DesignError(f"eps_values must be numbers; got {eps_values!r}.") from exc
    rule = ("eps_values must start at 1 and decrease strictly, each in (0, 1] (Sec. VII: the "
            "observer is tuned by starting with ε = 1 and decreasing ε until the performance "
            "is satisfactory)")
    if not eps:
        raise DesignError(f"{rule}; got no value.")
    if not all(math.isfinite(e) and 0 < e <= 1 for e in eps) or eps[0] != 1.0 \
            or any(b >= a for a, b in itertools.pairwise(eps)):
        raise DesignError(f"{rule}; got {list(eps)}. E.g. eps_values=[1, 0.7, 0.5, 0.3].")
    return eps


def _one_run(estimator: EstimatorSource, simulate: Callable[[int], Any],
             eps_values: tuple[float, ...], seeds: tuple[int, ...], theta_hat0: FloatArray,
             index: int) -> RunMetrics:
    """Run number ``index`` (ε-major): simulate, build, run, measure."""
    data = simulate(seeds[index % len(seeds)])
    obs = observer_for(estimator, eps_values[index // len(seeds)])
    return run_observer(estimator, obs, data, theta_hat0)


def eps_sweep(estimator: EstimatorSource, simulate: Callable[[int], Any],
              eps_values: Iterable[float], seeds: Iterable[int], *, theta_hat0: ArrayLike,
              progress: bool = True, n_jobs: int | None = 1,
              scheduler: Any = None) -> SweepResult:
    """Run the tuning procedure of Sec. VII: ε = 1 first, then smaller ε, over noise seeds.

    For each ε and each seed: ``data = simulate(seed)``, the observer for ε
    (:func:`observer_for`), ``obs.run(data.t, data.u, data.y, state0=obs.init(theta_hat0=
    theta_hat0))``, then record divergence and accuracy against the truth in ``data``.

    Parameters
    ----------
    estimator : EstimatorSpec or callable ``make_observer(eps)``
        An :class:`~thetahat.spec.EstimatorSpec` (e.g. :func:`thetahat.models.lugre.
        estimator_spec` or :func:`thetahat.modelfile.estimator_spec`): its observers for every
        ε come from one SCB and run with its hold. Or a callable building the observer for
        one ε, e.g. :func:`thetahat.models.lugre.observer`: anything with
        ``init(theta_hat0=...)`` and ``run(t, u, y, state0=...)`` returning an
        :class:`~thetahat.estimation.protocol.EstimateResult` (any
        :class:`~thetahat.estimation.protocol.Estimator`).
    simulate : callable ``simulate(seed)``
        Simulates the plant with that noise seed; returns an object with ``t (N,)``,
        ``u (N, m)``, ``y (N, r)``, the true ``x (N, n)`` and ``theta (p,)`` (and optionally
        ``phi (N, k)``), such as a :class:`~thetahat.simulation.simulate.PlantTrajectory`
        (:func:`thetahat.models.lugre.simulate`, :func:`thetahat.modelfile.simulate_model`).
    eps_values : iterable of float
        Must start at 1 and decrease strictly, each in (0, 1] (Sec. VII).
    seeds : iterable of int
        Non-negative noise seeds; the same seeds are used for every ε.
    theta_hat0 : array_like, shape (p,)
        Initial parameter estimate (in Θ).
    progress : bool, optional
        Progress bar over the ε × seeds runs (tqdm, when installed; it appears after a few
        seconds).
    n_jobs : int or None, optional
        Worker processes (1: sequential; -1: all cores). With n_jobs > 1, ``estimator``
        and ``simulate`` must be picklable (specs, module-level functions and
        ``functools.partial`` of them are).
    scheduler : str or dask.distributed.Client, optional
        Run the ε × seeds runs on a Dask cluster (see
        :func:`~thetahat.studies.batch.monte_carlo`); same picklability as ``n_jobs``.

    Returns
    -------
    SweepResult

    Raises
    ------
    DesignError
        ``eps_values`` does not start at 1 or does not decrease.
    DimensionError
        Empty or negative seeds.
    Exception
        Whatever ``simulate`` or building the observer raise: only failures of ``run`` that signal
        divergence (:class:`~thetahat.errors.NonFiniteError`, ...) are recorded as diverged.

    Notes
    -----
    A run counts as diverged when ``run`` fails that way, or when θ̂, a component of x̂ (or
    x̂₂) or φ̂ exceeds ``DIVERGENCE_FACTOR`` (10³) times the largest magnitude of the
    corresponding truth anywhere in the record, or is non-finite. Errors are measured over
    the second half of the record (after the transient); ``t_1pct`` over the whole record.
    Each run simulates its own data, so a run is the same whether it is executed alone,
    sequentially or in a worker process.

    Examples
    --------
    >>> import functools
    >>> from thetahat.models import lugre
    >>> from thetahat.studies.sweep import eps_sweep
    >>> sim = functools.partial(lugre.simulate, t_end=2.0, fs=500.0)
    >>> res = eps_sweep(lugre.estimator_spec(), sim, [1.0, 0.5], seeds=[0], theta_hat0=[0.5],
    ...                 progress=False)
    >>> res.stable_down_to, res.first_unstable
    (0.5, None)
    >>> res.x_rmse.shape                        # (eps, seeds, states)
    (2, 1, 2)
    """
    eps = check_eps_values(eps_values)
    seeds_ = check_seeds(seeds)
    th0 = np.atleast_1d(np.asarray(theta_hat0, dtype=np.float64))
    fn = functools.partial(_one_run, estimator, simulate, eps, seeds_, th0)
    batch = monte_carlo(fn, range(len(eps) * len(seeds_)), progress=progress, n_jobs=n_jobs,
                        scheduler=scheduler)
    runs: list[RunMetrics] = list(batch.results)
    shape = (len(eps), len(seeds_))
    n = max(r.x_rmse.shape[0] for r in runs)
    has_second = any(r.x_rmse_refined is not None for r in runs)

    def grid(attr: str) -> FloatArray:
        return np.array([getattr(r, attr) for r in runs], dtype=float).reshape(shape)

    x2 = None
    if has_second:
        x2 = np.array([np.full(n, np.nan) if r.x_rmse_refined is None else r.x_rmse_refined
                       for r in runs]).reshape(shape + (n,))
    errors = tuple(tuple(runs[i * shape[1] + j].error for j in range(shape[1]))
                   for i in range(shape[0]))
    return SweepResult(eps=eps, seeds=seeds_,
                       diverged=np.array([r.diverged for r in runs]).reshape(shape),
                       t_1pct=grid("t_1pct"), theta_max_error=grid("theta_max_error"),
                       theta_rmse=grid("theta_rmse"),
                       x_rmse=np.array([r.x_rmse for r in runs]).reshape(shape + (n,)),
                       x_rmse_refined=x2, errors=errors, wall_time=batch.wall_time)
