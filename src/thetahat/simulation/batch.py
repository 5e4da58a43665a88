"""Monte-Carlo batches: one run per seed, optionally in parallel processes, results in order.

A batch calls a user function ``fn(seed)`` once per seed (typically: simulate the plant with
that noise seed, run the observer, return a small result) and collects the results in the
order of the seeds, whether the runs were sequential or spread over worker processes. A
progress bar is shown with ``tqdm`` when it is installed and the batch takes a while.
"""

from __future__ import annotations

import numbers
import os
import pickle
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ArgumentTypeError, DimensionError, ThetahatWarning

__all__ = ["BatchResult", "monte_carlo"]

#: A progress bar appears only when the batch has run this long (s): short batches, such as
#: those in tests, stay silent, and long studies show progress.
PROGRESS_DELAY_S = 2.0


@dataclass(frozen=True, slots=True, eq=False)
class BatchResult:
    """Results of a Monte-Carlo batch, in the order of the seeds.

    Attributes
    ----------
    seeds : tuple of int
        The seeds, as given.
    results : tuple
        ``fn(seed)`` for each seed, same order.
    n_jobs : int
        Number of worker processes used (1 = sequential, in this process).
    wall_time : float
        Seconds for the whole batch.
    """

    seeds: tuple[int, ...]
    results: tuple[Any, ...]
    n_jobs: int
    wall_time: float

    def __len__(self) -> int:
        return len(self.results)

    def __iter__(self) -> Iterator[Any]:
        return iter(self.results)

    def __getitem__(self, i: int) -> Any:
        return self.results[i]

    def stack(self, attribute: str | None = None) -> NDArray[Any]:
        """Stack the results (or one attribute of each) along a new first axis.

        Parameters
        ----------
        attribute : str, optional
            Name of an attribute of every result (e.g. ``"theta_hat"``); default: the
            results themselves (numbers or arrays).

        Returns
        -------
        ndarray, shape (len(seeds), ...)

        Raises
        ------
        DimensionError
            The results (or attributes) have different shapes.
        """
        items = self.results if attribute is None else [getattr(r, attribute)
                                                        for r in self.results]
        try:
            return np.stack([np.asarray(a) for a in items])
        except ValueError as exc:
            what = "results" if attribute is None else f"attribute {attribute!r} of the results"
            raise DimensionError(f"cannot stack the {what}: {exc}") from exc

    def __repr__(self) -> str:
        kinds = sorted({type(r).__name__ for r in self.results})
        return (f"BatchResult(n_runs={len(self.results)}, seeds={_short(self.seeds)}, "
                f"results={'/'.join(kinds) or '-'}, n_jobs={self.n_jobs}, "
                f"wall_time={self.wall_time:.3g} s)")


def _short(seeds: Sequence[int]) -> str:
    if len(seeds) <= 6:
        return str(list(seeds))
    return f"[{seeds[0]}, {seeds[1]}, {seeds[2]}, ..., {seeds[-1]}]"


def _check_seeds(seeds: Iterable[int]) -> tuple[int, ...]:
    out = []
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, numbers.Integral) or int(s) < 0:
            raise DimensionError(f"seeds must be non-negative integers; got {s!r}.")
        out.append(int(s))
    if not out:
        raise DimensionError("seeds must hold at least one seed; e.g. seeds=range(100).")
    if len(set(out)) != len(out):
        warnings.warn("seeds contain duplicates: those runs repeat the same noise and are not "
                      "independent Monte-Carlo samples.", ThetahatWarning, stacklevel=3)
    return tuple(out)


def _workers(n_jobs: int | None, n_runs: int) -> int:
    if n_jobs is None:
        return 1
    if isinstance(n_jobs, bool) or not isinstance(n_jobs, numbers.Integral) or n_jobs == 0 \
            or n_jobs < -1:
        raise DimensionError(f"n_jobs must be a positive integer, -1 (all cores) or None; got "
                             f"{n_jobs!r}.")
    wanted = (os.cpu_count() or 1) if n_jobs == -1 else int(n_jobs)
    return max(1, min(wanted, n_runs))


def _progress_bar(total: int, enabled: bool) -> Any:
    """A tqdm bar that appears after PROGRESS_DELAY_S, or None without tqdm / when disabled."""
    if not enabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc="monte_carlo", unit="run", delay=PROGRESS_DELAY_S,
                leave=False)


def monte_carlo(fn: Callable[[int], Any], seeds: Iterable[int], *, progress: bool = True,
                n_jobs: int | None = 1, scheduler: Any = None,
                chunk_size: int | None = None) -> BatchResult:
    """Run ``fn(seed)`` for every seed and collect the results in seed order.

    Parameters
    ----------
    fn : callable ``fn(seed) -> result``
        One Monte-Carlo run. With ``n_jobs > 1`` it must be picklable (a module-level
        function or a ``functools.partial`` of one), and so must its result.
    seeds : iterable of int
        Non-negative seeds, one per run; the results follow this order.
    progress : bool, optional
        Show a tqdm progress bar (if tqdm is installed) once the batch has run for
        :data:`PROGRESS_DELAY_S` seconds.
    n_jobs : int or None, optional
        Worker processes: 1 or None runs sequentially in this process; -1 uses all cores.
        Capped at the number of runs.
    scheduler : str or dask.distributed.Client, optional
        Run on a Dask cluster (``"tcp://HOST:PORT"`` or a Client) through
        :func:`thetahat.engine.run_keyed`, in chunks of seeds keyed by seed: a worker that
        dies loses and duplicates nothing. ``n_jobs`` is then ignored (``n_jobs`` of the
        result is 0). The results equal those of a run in this process.
    chunk_size : int, optional
        Seeds per task on a cluster (default: about 16 tasks).

    Returns
    -------
    BatchResult

    Raises
    ------
    DimensionError
        Empty or negative seeds, or a bad ``n_jobs``.
    Exception
        Whatever ``fn`` raises, for the first failing seed in seed order (remaining parallel
        runs are cancelled).

    Warns
    -----
    ThetahatWarning
        The seeds contain duplicates.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.simulation.batch import monte_carlo
    >>> res = monte_carlo(lambda s: np.random.default_rng(s).normal(), seeds=[3, 1, 2])
    >>> res.seeds, res.stack().shape
    ((3, 1, 2), (3,))
    """
    if not callable(fn):
        raise ArgumentTypeError(f"fn must be callable as fn(seed); got {type(fn).__name__}.")
    seeds_ = _check_seeds(seeds)
    if scheduler is not None:
        from ..engine import run_keyed, seed_task
        start = time.perf_counter()
        unique = tuple(dict.fromkeys(seeds_))
        done = run_keyed(seed_task(fn), unique, unique, scheduler=scheduler,
                         chunk_size=chunk_size, label="monte_carlo", progress=progress)
        return BatchResult(seeds=seeds_, results=tuple(done[s] for s in seeds_), n_jobs=0,
                           wall_time=time.perf_counter() - start)
    workers = _workers(n_jobs, len(seeds_))
    bar = _progress_bar(len(seeds_), progress)
    start = time.perf_counter()
    try:
        if workers == 1:
            results = []
            for s in seeds_:
                results.append(fn(s))
                if bar is not None:
                    bar.update(1)
        else:
            results = _parallel(fn, seeds_, workers, bar)
    finally:
        if bar is not None:
            bar.close()
    return BatchResult(seeds=seeds_, results=tuple(results), n_jobs=workers,
                       wall_time=time.perf_counter() - start)


def _parallel(fn: Callable[[int], Any], seeds: tuple[int, ...], workers: int,
              bar: Any) -> list[Any]:
    """Run in a process pool; return results in seed order, re-raising the first failure."""
    try:
        pickle.dumps(fn)
    except (pickle.PicklingError, AttributeError, TypeError) as exc:
        raise ArgumentTypeError(f"with n_jobs > 1, fn must be picklable (a module-level function or a "
                        f"functools.partial of one, not a lambda or a local function): {exc}"
                        ) from exc
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures: list[Future[Any]] = [pool.submit(fn, s) for s in seeds]
        if bar is not None:
            for f in futures:
                f.add_done_callback(lambda _f: bar.update(1))
        try:
            return [f.result() for f in futures]
        except BaseException:
            for f in futures:
                f.cancel()
            raise
