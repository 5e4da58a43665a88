"""The distributed engine: keyed, chunked tasks in this process or on a Dask cluster.

Every large job of thetahat (a fleet of logged records, a Monte-Carlo study) is a list of
independent *items*, each with a unique *key* (a file name, a seed). The engine cuts the list
into chunks whose size does not depend on where they run, runs one task per chunk, and
returns a ``{key: result}`` mapping:

* ``scheduler=None`` (the default) runs the chunks here, one after the other: no cluster,
  no setup, and no Dask needed;
* ``scheduler="tcp://HOST:PORT"`` or a :class:`dask.distributed.Client` submits them to a
  Dask cluster (the ``dist`` extra). Each task has a deterministic key built from its items'
  keys, so a resubmission is the same task, and ``retries`` lets the scheduler re-run the
  chunks of a worker that dies. Results are collected by key: a chunk that ran twice counts
  once, a key that never came back is an error, never a silent gap.

Because the chunks are the same whatever the scheduler and each chunk is computed by the same
function, a run on a cluster returns the same numbers as a run in this process.
"""

from __future__ import annotations

import hashlib
import math
import numbers
from collections.abc import Callable, Hashable, Sequence
from typing import Any

from .errors import DimensionError, MissingExtraError, ThetahatError

__all__ = ["CHUNK_TARGET", "DEFAULT_RETRIES", "EngineError", "chunks", "run_keyed", "seed_task"]

#: Default number of chunks a job is cut into when no chunk size is given (independent of the
#: cluster, so that chunks — and results — are the same in-process and distributed): enough
#: to keep a few workers busy and to lose little when one dies, few enough that a task of a
#: typical study (records of seconds at 1 kHz) runs for seconds, not milliseconds.
CHUNK_TARGET = 16
#: How long to wait for a scheduler address to answer (s).
CONNECT_TIMEOUT_S = 10.0
#: Times the scheduler re-runs a task whose worker died before giving up.
DEFAULT_RETRIES = 3


class EngineError(ThetahatError, RuntimeError):
    """A distributed job failed as a whole (scheduler unreachable, a key came back missing)."""


def chunks(items: Sequence[Any], chunk_size: int | None = None) -> list[list[Any]]:
    """Cut ``items`` into consecutive chunks of ``chunk_size`` (default: about
    :data:`CHUNK_TARGET` chunks).

    Parameters
    ----------
    items : sequence
        The work, in order.
    chunk_size : int, optional
        Items per chunk (a positive integer; the last chunk may be shorter). Default
        ⌈len(items) / :data:`CHUNK_TARGET`⌉, at least 1.

    Returns
    -------
    list of list
        The consecutive chunks; their concatenation is ``list(items)`` (no chunks when
        ``items`` is empty).

    Raises
    ------
    DimensionError
        ``chunk_size`` is not a positive integer or None.

    Examples
    --------
    >>> from thetahat.engine import chunks
    >>> chunks(list(range(5)), 2)
    [[0, 1], [2, 3], [4]]
    """
    n = len(items)
    if chunk_size is None:
        chunk_size = max(1, math.ceil(n / CHUNK_TARGET))
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, numbers.Integral) \
            or chunk_size < 1:
        raise DimensionError(f"chunk_size must be a positive integer or None; got "
                             f"{chunk_size!r}.")
    return [list(items[i:i + chunk_size]) for i in range(0, n, int(chunk_size))]


def _run_seeds(seeds: list[int], *, fn: Callable[[int], Any]) -> list[tuple[int, Any]]:
    return [(s, fn(s)) for s in seeds]


def seed_task(fn: Callable[[int], Any]) -> Callable[[list[int]], list[tuple[int, Any]]]:
    """The chunk task of a Monte-Carlo: ``fn(seed)`` for each seed of the chunk, keyed by seed.

    Parameters
    ----------
    fn : callable ``fn(seed) -> result``
        One run of the study for an integer seed. On a cluster it must be picklable (a
        module-level function or a ``functools.partial`` of one).

    Returns
    -------
    callable ``task(seeds) -> [(seed, result), ...]``
        A task for :func:`run_keyed` with the seeds as items and keys: a
        ``functools.partial``, hence picklable when ``fn`` is.

    Examples
    --------
    >>> from thetahat.engine import seed_task
    >>> seed_task(lambda s: 10 * s)([1, 2])
    [(1, 10), (2, 20)]
    """
    import functools

    return functools.partial(_run_seeds, fn=fn)


def _task_key(label: str, keys: Sequence[Hashable]) -> str:
    digest = hashlib.sha1(repr(list(keys)).encode()).hexdigest()[:16]
    return f"thetahat-{label}-{digest}"


def _client(scheduler: Any) -> tuple[Any, bool]:
    """(client, owned): a Client for an address (owned: close it after), or the given one."""
    try:
        from dask.distributed import Client
    except ImportError as exc:
        raise MissingExtraError("a scheduler needs Dask's distributed scheduler: pip install "
                          "'thetahat[dist]' (or leave scheduler=None to run here).") from exc
    if isinstance(scheduler, Client):
        return scheduler, False
    if not isinstance(scheduler, str) or "://" not in scheduler:
        raise EngineError(f"scheduler must be an address such as 'tcp://127.0.0.1:8786', a "
                          f"dask.distributed.Client, or None; got {scheduler!r}.")
    try:
        return Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s"), True
    except (OSError, TimeoutError) as exc:
        raise EngineError(f"cannot reach the Dask scheduler at {scheduler}: {exc}. Start one "
                          f"(dask scheduler / dask worker) or drop --scheduler.") from exc


def _progress(total: int, enabled: bool, desc: str) -> Any:
    if not enabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit="item", delay=2.0, leave=False)


def run_keyed(task: Callable[[list[Any]], Sequence[tuple[Hashable, Any]]], items: Sequence[Any],
              keys: Sequence[Hashable], *, scheduler: Any = None,
              chunk_size: int | None = None, label: str = "job", progress: bool = True,
              retries: int = DEFAULT_RETRIES) -> dict[Hashable, Any]:
    """Run ``task`` on chunks of ``items`` and return ``{key: result}`` for every key.

    Parameters
    ----------
    task : callable ``task(chunk) -> [(key, result), ...]``
        Computes a chunk (a list of items) and returns one ``(key, result)`` pair per item.
        On a cluster it must be picklable (a module-level function or a
        ``functools.partial`` of one).
    items : sequence
        The work, e.g. file paths or seeds.
    keys : sequence of hashable
        One unique key per item, in the same order (``task`` returns the same keys).
    scheduler : None, str or dask.distributed.Client
        None: run here. An address ``"tcp://HOST:PORT"`` or a Client: run on that cluster.
    chunk_size : int, optional
        Items per task; default about :data:`CHUNK_TARGET` chunks. It does not depend on the
        scheduler, so results do not either.
    label : str
        Name of the job in task keys and the progress bar.
    progress : bool
        A tqdm bar (if installed) once the job has run for 2 s.
    retries : int
        Re-runs of a task whose worker died (cluster only).

    Returns
    -------
    dict
        ``{key: result}`` with exactly the given keys.

    Raises
    ------
    DimensionError
        Keys are not unique or do not match the items; bad ``chunk_size``.
    MissingExtraError
        A scheduler is given but Dask's distributed scheduler is not installed.
    EngineError
        The scheduler cannot be reached, or a key is missing.
    Exception
        Whatever ``task`` raises (tasks should catch per-item failures themselves).

    Examples
    --------
    >>> from thetahat.engine import run_keyed
    >>> square = lambda chunk: [(x, x * x) for x in chunk]
    >>> run_keyed(square, [3, 1, 2], keys=[3, 1, 2], chunk_size=2)
    {3: 9, 1: 1, 2: 4}
    """
    keys = list(keys)
    if len(keys) != len(items):
        raise DimensionError(f"run_keyed: {len(items)} items but {len(keys)} keys.")
    if len(set(keys)) != len(keys):
        raise DimensionError("run_keyed: keys must be unique (they identify each result).")
    parts = chunks(list(items), chunk_size)
    kparts = chunks(keys, chunk_size)
    bar = _progress(len(items), progress, label)
    out: dict[Hashable, Any] = {}
    try:
        if scheduler is None:
            for part in parts:
                _collect(out, task(part), bar)
        else:
            _run_on_cluster(task, parts, kparts, scheduler, label, retries, out, bar)
    finally:
        if bar is not None:
            bar.close()
    missing = [k for k in keys if k not in out]
    extra = [k for k in out if k not in set(keys)]
    if missing or extra:
        raise EngineError(f"{label}: results for {len(missing)} key(s) missing "
                          f"({missing[:3]}...) and {len(extra)} unexpected; the task must return "
                          "one (key, result) per item.")
    return {k: out[k] for k in keys}


def _collect(out: dict[Hashable, Any], pairs: Sequence[tuple[Hashable, Any]], bar: Any) -> None:
    for key, value in pairs:
        if key not in out:               # a chunk re-run after a worker died counts once
            out[key] = value
            if bar is not None:
                bar.update(1)


def _run_on_cluster(task: Callable[..., Any], parts: list[list[Any]],
                    kparts: list[list[Hashable]], scheduler: Any, label: str, retries: int,
                    out: dict[Hashable, Any], bar: Any) -> None:
    from dask.distributed import as_completed

    client, owned = _client(scheduler)
    try:
        futures = [client.submit(task, part, key=_task_key(label, ks), retries=retries,
                                 pure=False)
                   for part, ks in zip(parts, kparts)]
        for fut in as_completed(futures):
            _collect(out, fut.result(), bar)
    finally:
        if owned:
            client.close()
