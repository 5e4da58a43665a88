"""The MAP fit's pass over a window: the data cost, its Gauss–Newton terms and the trajectory.

:func:`sweep` runs the model from x(t_{k0}) over a window of samples with the sampled-data map
of :mod:`~thetahat.estimation.statistical.plant_kernel` (RK4 sub-steps, u between the samples
as the hold reconstructs it), chains the output sensitivities ψ_k = C ∂x_k/∂q (q = col(x(t_{k0}),
θ)) through the map's exact Jacobians and sums the data cost and its Gauss–Newton terms;
:func:`sweep_kernel` prints it over one model's plant kernels (its free names ``propagate_into``,
``plant_work`` and ``C_OUT`` bound;
:func:`~thetahat.estimation.statistical.plant_kernel.printed_kernels`).
The MAP fits (:mod:`~thetahat.estimation.statistical.map_fit`) and the MAP estimator's
predictions before its first fit (:mod:`~thetahat.estimation.statistical.mle`) run it.

What it may import: NumPy and, in this room, :mod:`~thetahat.estimation.statistical.plant_kernel`.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from .plant_kernel import ModelKernel, printed_kernels

__all__ = ["sweep", "sweep_kernel"]

FloatArray = NDArray[np.float64]


# Names of the printed sweep module (declared for the type checker; bound when printed).
propagate_into: Callable[..., Any]
plant_work: Callable[..., Any]
C_OUT: FloatArray


def sweep(x0: Any, th: Any, U: Any, Y: Any, tt: Any, k0: int, k1: int, skip0: bool,
          Rinv: Any, pc: Any, WT: Any, want: bool, A: Any, b: Any, T: Any, X: Any) -> float:
    """The fit's pass over a window: the data cost, its Gauss–Newton terms and the trajectory.

    Data cost Σ ‖y_k − C x_k‖²_{R⁻¹} over samples k0 … k1−1 (k0 left out when ``skip0``)
    from x(t_{k0}) = x0 at θ = th, x propagated by the model's ``propagate_into`` (u held as
    ``pc, WT`` say); with ``want`` also A = Σ ψᵀ R⁻¹ ψ, b = Σ ψᵀ R⁻¹ r and T = ∂x_{k1−1}/∂q
    (ψ_k = C ∂x_k/∂q, q = col(x0, θ), chained through the map's exact Jacobians); X
    (k1 − k0, n) receives the trajectory.
        Parameters
    ----------
    x0 : ndarray, shape (n,)
    th : ndarray, shape (p,)
    U, Y : ndarray, shapes (N, m), (N, r)
    tt : ndarray, shape (N,)
    k0, k1 : int
    skip0 : bool
    Rinv : ndarray, shape (r,)
        1/σ² per output.
    pc, WT : ndarray
        :meth:`~thetahat.estimation.statistical.plant_kernel.Propagation.arrays`.
    want : bool
    A, b, T, X : ndarray, shapes (n + p, n + p), (n + p,), (n, n + p), (k1 − k0, n)
        Output.

    Returns
    -------
    float
        The data cost.
    """
    n = x0.shape[0]
    p = th.shape[0]
    r = C_OUT.shape[0]
    nq = n + p
    x = x0.copy()
    S = np.zeros((n, nq))
    for i in range(n):
        S[i, i] = 1.0
    Phi = np.empty((n, n))
    Gam = np.empty((n, p))
    Sn = np.empty((n, nq))
    psi = np.empty((r, nq))
    res = np.empty(r)
    work = plant_work(n, p, p, U.shape[1], WT.shape[1])
    if want:
        A[:, :] = 0.0
        b[:] = 0.0
    J = 0.0
    for k in range(k0, k1):
        if k > k0:
            propagate_into(x, x, th, U, k - 1, tt[k] - tt[k - 1], pc, WT, want, Phi, Gam,
                           *work)
            if want:
                for i in range(n):
                    for j in range(nq):
                        acc = Gam[i, j - n] if j >= n else 0.0
                        for a in range(n):
                            acc += Phi[i, a] * S[a, j]
                        Sn[i, j] = acc
                for i in range(n):      # element by element: numba's array-into-slice
                    for j in range(nq):  # assignment compiles a string-formatting path
                        S[i, j] = Sn[i, j]
        for i in range(n):
            X[k - k0, i] = x[i]
        ok = True
        for i in range(r):
            acc = Y[k, i]
            for a in range(n):
                acc -= C_OUT[i, a] * x[a]
            res[i] = acc
            if not math.isfinite(acc):
                ok = False
        if not ok or (skip0 and k == k0):
            continue
        for i in range(r):
            J += res[i] * res[i] * Rinv[i]
        if want:
            for i in range(r):
                for j in range(nq):
                    acc = 0.0
                    for a in range(n):
                        acc += C_OUT[i, a] * S[a, j]
                    psi[i, j] = acc
            for j in range(nq):
                for i in range(r):
                    b[j] += psi[i, j] * Rinv[i] * res[i]
                for c in range(j, nq):
                    acc = 0.0
                    for i in range(r):
                        acc += psi[i, j] * Rinv[i] * psi[i, c]
                    A[j, c] += acc
    if want:
        for j in range(nq):
            for c in range(j):
                A[j, c] = A[c, j]
        for i in range(n):
            for j in range(nq):
                T[i, j] = S[i, j]
    return J


@functools.lru_cache(maxsize=16)
def sweep_kernel(model: ModelKernel) -> Callable[..., float]:
    """:func:`sweep` printed over a model's plant kernels (compiled with them; built once per
    model kernel).

    Parameters
    ----------
    model : ModelKernel

    Returns
    -------
    callable
        ``sweep(x0, th, U, Y, t, k0, k1, skip0, Rinv, pc, WT, want, A, b, T, X) -> J``.
    """
    mod, (name,) = printed_kernels(
        "thetahat_sweep", "Printed by thetahat.estimation.statistical.map_fit: the MAP fit's "
        "sweep of one model; do not edit (content-addressed).", [sweep],
        {"propagate_into": model.propagate_into, "plant_work": model.plant_work,
         "C_OUT": model.C}, model.compiled)
    fn: Callable[..., float] = getattr(mod, name)
    return fn
