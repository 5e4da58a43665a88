"""Threads of the numerical libraries: one BLAS thread for thetahat's small matrices.

thetahat's matrices are small (n, p ≲ 10): a BLAS or LAPACK call on them costs microseconds,
and OpenBLAS's default of one thread per core turns each call into a hand-off between threads
that spin on busy cores — a 2×2 ``scipy.linalg.expm`` took 895 µs instead of 8 µs on a loaded
machine, and the NumPy gradient law calls it once per sample. :func:`one_blas_thread` holds the
BLAS libraries loaded in this process to one thread for the duration of a block, with
threadpoolctl when it is installed (the ``speed`` extra, with numba); without it the block
runs with the libraries' own setting (the command line sets ``OPENBLAS_NUM_THREADS=1`` before
NumPy loads; a program can do the same).
"""

from __future__ import annotations

import contextlib
from contextlib import AbstractContextManager

__all__ = ["one_blas_thread"]


def one_blas_thread() -> AbstractContextManager[object]:
    """A context in which the loaded BLAS libraries use one thread (threadpoolctl's
    ``threadpool_limits(1, "blas")`` when installed, else a context that changes nothing).

    On leaving the block each library is given back its previous number of threads; blocks
    nest.

    Returns
    -------
    context manager

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.threads import one_blas_thread
    >>> with one_blas_thread():
    ...     float(np.linalg.det(np.eye(2)))
    1.0
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")
