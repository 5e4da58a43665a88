"""The joint EKF's per-sample kernels on s = col(x, θ): predict, update, the loop, one sample.

The augmented state s = col(x, θ) with θ constant (no random walk) follows the sampled-data
map of :mod:`~thetahat.estimation.statistical.plant_kernel` (RK4 sub-steps, u between the
samples as the hold reconstructs it), so the transition matrix is T = [[Φ, Γ], [0, I]] with
the exact Jacobians Φ = ∂F/∂x, Γ = ∂F/∂θ. Each sample is

* the **prediction** (:func:`ekf_predict`): s ← (F(x, θ), θ), P ← T P Tᵀ + Q with
  Q = diag(Q_x, 0);
* the **gain** (:func:`ekf_gain`): H = [C 0], S = H P Hᵀ + R factored by Cholesky,
  K = P Hᵀ S⁻¹, the innovation ν and νᵀ S⁻¹ ν;
* the **update** (:func:`ekf_update`): s ← s + K ν, P in Joseph form
  P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ (:func:`ekf_joseph`, which keeps P symmetric positive
  semi-definite in floating point), then θ projected onto Θ in the P_θθ⁻¹-weighted norm (a
  box: a clip; any convex Θ, see :mod:`~thetahat.estimation.statistical.stage2_set`);
* and the **loop** over a record's samples (:func:`ekf_loop`), which stops at the first
  sample whose s or P's diagonal is not finite (its index, reported by :func:`divergence_message`).

They are module-level functions in numba's subset of Python whose free names — the model's
``propagate``, its output matrix ``C_OUT`` and the projection ``project`` — are bound when
:func:`ekf_kernels` prints them into a module of their own over the model's printed plant
module (:func:`~thetahat.estimation.statistical.plant_kernel.printed_kernels`), numba-compiled
when numba is installed. They are shared by the joint EKF
(:mod:`~thetahat.estimation.statistical.ekf`), the MAP estimator between its fits
(:mod:`~thetahat.estimation.statistical.mle`) and the guarded estimator's stage 2
(:mod:`~thetahat.estimation.statistical.guarded`).

What it may import: :mod:`thetahat.model`, the package's errors, the bottom of the
estimation wing (:mod:`~thetahat.estimation.status`), and, in this room,
:mod:`~thetahat.estimation.statistical.plant_kernel` and
:mod:`~thetahat.estimation.statistical.stage2_set`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from ...errors import UnsupportedError
from ...model.paramset import Box
from ...model.system import PerturbedLinearSystem
from ..status import Status, status_error
from .plant_kernel import ModelKernel, Propagation, model_kernel, printed_kernels
from .stage2_set import clip_kernel, has_compiled_projection, project_kernel, stage2_set

__all__ = ["EKFKernels", "NIS_MODEL_ERROR", "divergence_message", "ekf_gain", "ekf_joseph",
           "ekf_kernels", "ekf_loop", "ekf_predict", "ekf_sample", "ekf_update"]

FloatArray = NDArray[np.float64]

#: A median normalised innovation squared (NIS ÷ r, 1 for a model that fits) above this before
#: a divergence is a model error, not bad luck: χ²_r/r has its median below 1 and a 99.9 %
#: quantile below 11 for every r ≥ 1 (r = 1: 10.8).
NIS_MODEL_ERROR = 11.0


@dataclass(frozen=True, slots=True, eq=False)
class EKFKernels:
    """The EKF's per-sample operations on (s, P) in place (printed over one model's kernels).

    ``predict(s, P, U, k, h, pc, WT, Q_x, Phi, Gam)`` and
    ``update(s, P, y, R, lo, hi, ell) -> NIS`` (normalised innovation squared ÷ r, after which
    θ is projected onto Θ = (lo, hi, ell), see
    :func:`~thetahat.estimation.statistical.stage2_set.project_kernel`); ``loop(s, P, U, Y, t,
    k0, k1, R, lo, hi, ell, pc, WT, Q_x, X, TH, SD, NIS) -> status`` runs samples k0 … k1−1 and
    returns −1, or the index where s or P's diagonal became non-finite.

    Parameters
    ----------
    model : ModelKernel
        The plant kernels (f, Φ, Γ and the RK4 sampled-data map) the EKF is built on; its
        ``compiled`` flag says whether the operations below are numba-compiled.
    predict : callable
        ``predict(s, P, U, k, h, pc, WT, Q_x, Phi, Gam) -> None``: the time update over the
        interval of length ``h`` from sample k of ``U`` (u held as
        :class:`~thetahat.estimation.statistical.plant_kernel.Propagation` ``pc, WT`` say;
        :func:`ekf_predict`).
    update : callable
        ``update(s, P, y, R, lo, hi, ell) -> float``: the measurement update with y (r,) and
        R (r, r), then θ projected onto Θ (:func:`ekf_update`); returns the normalised
        innovation squared νᵀ S⁻¹ ν ÷ r (≈ 1 for a consistent filter).
    loop : callable
        ``loop(s, P, U, Y, t, k0, k1, R, lo, hi, ell, pc, WT, Q_x, X, TH, SD, NIS) -> int``:
        the filter over samples k0 … k1−1 (:func:`ekf_loop`); returns −1, or the first sample
        index at which s became non-finite.
    project : callable
        ``project(theta, M, lo, hi, ell) -> None``: Π_Θ in place in the norm ‖·‖_{M⁻¹}
        (:func:`~thetahat.estimation.statistical.stage2_set.project_kernel` or its clip for a
        box, or a ConvexSet's Python projection); the guard uses it with M = I.
    printed : bool
        The projection is printed with the operations (compiled with them when the model's
        kernels are); False for a ConvexSet's Python projection (the operations then run as
        plain Python, calling it).
    """

    model: ModelKernel
    predict: Callable[..., None]
    update: Callable[..., float]
    loop: Callable[..., int]
    project: Callable[..., None]
    printed: bool = True


# Names of the printed EKF module (declared for the type checker; bound when printed).
propagate: Callable[..., Any]
project: Callable[..., None]
C_OUT: FloatArray


def ekf_predict(s: Any, P: Any, U: Any, k: int, h: float, pc: Any, WT: Any, Q_x: Any,
                Phi: Any, Gam: Any) -> None:
    """The time update over the interval from sample k: s ← (F(x, θ), θ), P ← T P Tᵀ + Q.

    Overwrites s = col(x, θ) (shape (n + p,)) with (F(x, θ), θ), F the model's map over the
    interval of length ``h`` from sample k of ``U`` (``propagate`` of the printed plant
    module, u held as ``pc, WT`` say), and P (shape (n + p, n + p)) with T P Tᵀ + diag(Q_x,
    0), T = [[Φ, Γ], [0, I]], Q_x (n, n); ``Phi`` (n, n) and ``Gam`` (n, p) are work arrays
    that receive Φ and Γ.
        Parameters
    ----------
    s : ndarray, shape (n + p,)
    P : ndarray, shape (n + p, n + p)
        Updated in place.
    U : ndarray, shape (N, m)
        Stage 2's input samples.
    k : int
        The interval's first sample.
    h : float
        The interval's length.
    pc, WT : ndarray
        :meth:`~thetahat.estimation.statistical.plant_kernel.Propagation.arrays`.
    Q_x : ndarray, shape (n, n)
    Phi : ndarray, shape (n, n)
    Gam : ndarray, shape (n, p)
        Work arrays (receive Φ and Γ).
    """
    n = Phi.shape[0]
    p = Gam.shape[1]
    N = n + p
    x = s[:n].copy()
    th = s[n:].copy()
    # a runtime True (n ≥ 1), not the literal: numba would compile a second specialisation
    # of propagate for Literal[bool] (≈ 0.9 s of a first run) besides the one the MAP sweep
    # and the likelihood use
    xn = propagate(x, th, U, k, h, pc, WT, n > 0, Phi, Gam)
    # T = [[Φ, Γ], [0, I]], element by element: numba's slice assignment compiles its
    # string-formatting error path (≈ 3 s of a guarded run's first compilation)
    T = np.zeros((N, N))
    for i in range(n):
        for j in range(n):
            T[i, j] = Phi[i, j]
        for j in range(p):
            T[i, n + j] = Gam[i, j]
    for i in range(n, N):
        T[i, i] = 1.0
    TP = np.zeros((N, N))
    for i in range(N):
        for j in range(N):
            acc = 0.0
            for a in range(N):
                acc += T[i, a] * P[a, j]
            TP[i, j] = acc
    for i in range(N):
        for j in range(i, N):
            acc = 0.0
            for a in range(N):
                acc += TP[i, a] * T[j, a]
            P[i, j] = acc
            P[j, i] = acc
    for i in range(n):
        for j in range(n):
            P[i, j] += Q_x[i, j]
        s[i] = xn[i]


def ekf_gain(s: Any, P: Any, y: Any, R: Any) -> tuple[Any, Any, float]:
    """The Kalman gain of the output map H = [C 0], with the innovation and its test value.

    ν = y − C x, S = H P Hᵀ + R = L Lᵀ (Cholesky; S is positive definite for R > 0),
    K = P Hᵀ S⁻¹ (n + p, r) and νᵀ S⁻¹ ν (not ÷ r), returned as (K, ν, νᵀS⁻¹ν); reads s
    and P only. C is the printed module's ``C_OUT``.
        Parameters
    ----------
    s : ndarray, shape (n + p,)
    P : ndarray, shape (n + p, n + p)
    y : ndarray, shape (r,)
    R : ndarray, shape (r, r)

    Returns
    -------
    K : ndarray, shape (n + p, r)
    nu : ndarray, shape (r,)
    nis : float
        νᵀ S⁻¹ ν.
    """
    N = P.shape[0]
    r = C_OUT.shape[0]
    n = C_OUT.shape[1]
    PHt = np.zeros((N, r))
    for i in range(N):
        for j in range(r):
            acc = 0.0
            for a in range(n):
                acc += P[i, a] * C_OUT[j, a]
            PHt[i, j] = acc
    S = R.copy()
    nu = y.copy()
    for i in range(r):
        for a in range(n):
            nu[i] -= C_OUT[i, a] * s[a]
        for j in range(r):
            acc = 0.0
            for a in range(n):
                acc += C_OUT[i, a] * PHt[a, j]
            S[i, j] += acc
    # Cholesky S = L Lᵀ (S is SPD: R > 0)
    L = np.zeros((r, r))
    for i in range(r):
        for j in range(i + 1):
            acc = S[i, j]
            for a in range(j):
                acc -= L[i, a] * L[j, a]
            if i == j:
                L[i, i] = math.sqrt(max(acc, 1e-300))
            else:
                L[i, j] = acc / L[j, j]
    # K = PHt S⁻¹ (row-wise solves), w = S⁻¹ ν
    K = np.zeros((N, r))
    for row in range(N):
        z = PHt[row].copy()
        for i in range(r):
            for a in range(i):
                z[i] -= L[i, a] * z[a]
            z[i] /= L[i, i]
        for i in range(r - 1, -1, -1):
            for a in range(i + 1, r):
                z[i] -= L[a, i] * z[a]
            z[i] /= L[i, i]
        for i in range(r):          # element by element: see ekf_predict
            K[row, i] = z[i]
    w = nu.copy()
    for i in range(r):
        for a in range(i):
            w[i] -= L[i, a] * w[a]
        w[i] /= L[i, i]
    nis = 0.0
    for i in range(r):
        nis += w[i] * w[i]
    return K, nu, nis


def ekf_joseph(P: Any, K: Any, R: Any) -> None:
    """The covariance update in Joseph form for H = [C 0]: P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ
    in place (symmetric by construction).

    Parameters
    ----------
    P : ndarray, shape (n + p, n + p)
        Updated in place.
    K : ndarray, shape (n + p, r)
    R : ndarray, shape (r, r)
    """
    N = P.shape[0]
    r = C_OUT.shape[0]
    n = C_OUT.shape[1]
    IKH = np.eye(N)
    for i in range(N):
        for j in range(n):
            acc = 0.0
            for a in range(r):
                acc += K[i, a] * C_OUT[a, j]
            IKH[i, j] -= acc
    A = np.zeros((N, N))
    for i in range(N):
        for j in range(N):
            acc = 0.0
            for a in range(N):
                acc += IKH[i, a] * P[a, j]
            A[i, j] = acc
    for i in range(N):
        for j in range(i, N):
            acc = 0.0
            for a in range(N):
                acc += A[i, a] * IKH[j, a]
            for a in range(r):
                for b in range(r):
                    acc += K[i, a] * R[a, b] * K[j, b]
            P[i, j] = acc
            P[j, i] = acc


def ekf_update(s: Any, P: Any, y: Any, R: Any, lo: Any, hi: Any, ell: Any) -> float:
    """The measurement update: gain, state, Joseph-form covariance, then θ projected onto Θ
    (``project`` of the printed module, in the norm of P_θθ); returns νᵀ S⁻¹ ν ÷ r.

    Parameters
    ----------
    s : ndarray, shape (n + p,)
    P : ndarray, shape (n + p, n + p)
        Updated in place.
    y : ndarray, shape (r,)
    R : ndarray, shape (r, r)
    lo, hi : ndarray, shape (p,)
        Θ's bounding box.
    ell : ndarray
        Θ's ellipsoid data (:mod:`~thetahat.estimation.kernels.set_projection`).

    Returns
    -------
    float
        νᵀ S⁻¹ ν ÷ r.
    """
    K, nu, nis = ekf_gain(s, P, y, R)
    N = P.shape[0]
    r = nu.shape[0]
    n = C_OUT.shape[1]
    for i in range(N):
        for j in range(r):
            s[i] += K[i, j] * nu[j]
    ekf_joseph(P, K, R)
    p = lo.shape[0]
    th = s[n:].copy()
    project(th, P[n:, n:].copy(), lo, hi, ell)
    for i in range(p):
        s[n + i] = th[i]
    return nis / r


def ekf_loop(s: Any, P: Any, U: Any, Y: Any, tt: Any, k0: int, k1: int, R: Any, lo: Any,
             hi: Any, ell: Any, pc: Any, WT: Any, Q_x: Any, X: Any, TH: Any, SD: Any,
             NIS: Any) -> int:
    """The filter over samples k0 … k1−1 of a record.

    Predicts from sample k−1 when k > 0 (:func:`ekf_predict`), then updates unless y_k has a
    non-finite entry (:func:`ekf_update`), writing x̂ into ``X`` (N, n), θ̂ into ``TH``
    (N, p), √diag P_θθ into ``SD`` (N, p) and the NIS into ``NIS`` (N,; NaN where not
    updated); returns −1, or the first sample index at which s or P's diagonal became
    non-finite (its row is not written).
        Parameters
    ----------
    s : ndarray, shape (n + p,)
    P : ndarray, shape (n + p, n + p)
        The state and covariance at sample k0, updated in place.
    U, Y : ndarray, shapes (N, m), (N, r)
    tt : ndarray, shape (N,)
    k0, k1 : int
    R : ndarray, shape (r, r)
    lo, hi, ell : ndarray
        Θ (as :func:`ekf_update`).
    pc, WT : ndarray
        :meth:`~thetahat.estimation.statistical.plant_kernel.Propagation.arrays`.
    Q_x : ndarray, shape (n, n)
    X, TH, SD, NIS : ndarray
        Output rows (above).

    Returns
    -------
    int
    """
    n = X.shape[1]
    p = TH.shape[1]
    Phi = np.empty((n, n))
    Gam = np.empty((n, p))
    for k in range(k0, k1):
        if k > 0:
            ekf_predict(s, P, U, k - 1, tt[k] - tt[k - 1], pc, WT, Q_x, Phi, Gam)
        finite_y = True
        for j in range(Y.shape[1]):
            if not math.isfinite(Y[k, j]):
                finite_y = False
        NIS[k] = ekf_update(s, P, Y[k], R, lo, hi, ell) if finite_y else np.nan
        for i in range(n + p):
            if not math.isfinite(s[i]) or not math.isfinite(P[i, i]):
                return k
        for i in range(n):              # element by element: see ekf_predict
            X[k, i] = s[i]
        for i in range(p):
            TH[k, i] = s[n + i]
            SD[k, i] = math.sqrt(max(P[n + i, n + i], 0.0))
    return -1


_DOC = ("Printed by thetahat.estimation.statistical.ekf_kernels: the joint EKF of one model; "
        "do not edit (content-addressed).")


def _make(model: ModelKernel, projection: Callable[..., None]) -> EKFKernels:
    """The kernels of ``model`` over ``projection``: a kernel of
    :mod:`~thetahat.estimation.kernels.set_projection` printed with them, or a ConvexSet's
    Python projection (uncompiled: a module instance of its own whose ``project`` it is)."""
    printed = projection in (clip_kernel, project_kernel)
    provided: dict[str, Any] = {"propagate": model.propagate, "C_OUT": model.C,
                                "project": projection if printed else "project"}
    roots: list[Callable[..., Any]] = [ekf_predict, ekf_update, ekf_loop]
    mod, names = printed_kernels("thetahat_ekf", _DOC, roots + ([projection] if printed else []),
                                 provided, model.compiled and printed,
                                 constants=None if printed else {"project": "None"},
                                 fresh=not printed)
    if printed:
        projection = getattr(mod, names[3])
    else:
        setattr(mod, "project", projection)
    return EKFKernels(model=model, predict=getattr(mod, names[0]),
                      update=getattr(mod, names[1]), loop=getattr(mod, names[2]),
                      project=projection, printed=printed)


@functools.lru_cache(maxsize=16)
def _cached(model: ModelKernel, box: bool) -> EKFKernels:
    return _make(model, clip_kernel if box else project_kernel)


@functools.lru_cache(maxsize=16)
def _cached_python_projection(model: ModelKernel, theta_set: Any) -> EKFKernels:
    st = stage2_set(theta_set)

    def project(theta: Any, M: Any, lo: Any, hi: Any, ell: Any) -> None:
        st.project(theta, M)

    return _make(model, project)


def ekf_kernels(system: PerturbedLinearSystem, *, compiled: bool | None = None) -> EKFKernels:
    """The EKF kernels of a model (built once per model kernel).

    Parameters
    ----------
    system : PerturbedLinearSystem
        The model of stage 2, with a
        :class:`~thetahat.model.perturbation.SymbolicPerturbation` (see
        :func:`~thetahat.estimation.statistical.plant_kernel.model_kernel`).
    compiled : bool, optional
        Compile the kernels with numba; default (None): when numba is installed and Θ has a
        compiled projection (a Box, Ball or Ellipsoid). A
        :class:`~thetahat.model.paramset.ConvexSet` Θ is projected in Python
        (:mod:`~thetahat.estimation.statistical.stage2_set`), so its kernels run uncompiled.

    Returns
    -------
    EKFKernels
        ``predict``, ``update``, ``loop`` and ``project`` on col(x, θ) for this model; the
        same object for the same model kernel (an LRU cache of 16). Θ itself is data
        (``lo, hi, ell`` of :class:`~thetahat.estimation.statistical.stage2_set.StageTwoSet`).

    Raises
    ------
    DimensionError
        The perturbation is not symbolic.
    MissingExtraError
        ``compiled=True`` without numba.
    UnsupportedError
        ``compiled=True`` with a ConvexSet Θ.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.models import lugre
    >>> from thetahat.estimation.statistical.ekf_kernels import ekf_kernels
    >>> k = ekf_kernels(lugre.system(), compiled=False)
    >>> s, P = np.array([0.0, 0.0, 0.5]), np.diag([1.0, 1e-6, 0.05])
    >>> nis = k.update(s, P, np.array([0.1]), np.array([[4e-4]]), np.array([0.05]),
    ...                np.array([1.0]), np.zeros((2, 1)))
    >>> bool(P[0, 0] < 4e-4)           # the measurement of ω shrank its variance below R
    True
    """
    theta_set = system.require_parameter_set("stage 2")
    if has_compiled_projection(theta_set):
        return _cached(model_kernel(system, compiled=compiled), isinstance(theta_set, Box))
    if compiled:
        raise UnsupportedError(f"Θ = {theta_set!r} has no compiled projection (its P is a "
                               "Python callable); pass compiled=None or False, or give Θ as a "
                               "Box, Ball or Ellipsoid.")
    return _cached_python_projection(model_kernel(system, compiled=False), theta_set)


def ekf_sample(kernels: EKFKernels, system: PerturbedLinearSystem, s: FloatArray, P: FloatArray,
               u0: FloatArray | None, u1: FloatArray, y: FloatArray, dt: float,
               propagation: Propagation, Q_x: FloatArray, R: FloatArray | None,
               k: int) -> float:
    """One sample of the joint EKF, in place: the ``step`` of every estimator that runs it.

    Predicts s = col(x̂, θ̂) and P from the previous sample (input u0 → u1 over ``dt``; none when
    ``u0`` is None: the first sample), then updates with ``y`` (none when y holds NaN or ``R``
    is None: σ not known yet), θ̂ projected onto Θ. What :attr:`EKFKernels.loop` does for one
    sample of a record.

    Parameters
    ----------
    kernels : EKFKernels
        :func:`ekf_kernels` of ``system``.
    system : PerturbedLinearSystem
    s : ndarray (n + p,)
    P : ndarray (n + p, n + p)
        C order; both overwritten.
    u0 : ndarray (m,) or None
    u1 : ndarray (m,)
    y : ndarray (r,)
    dt : float
    propagation : Propagation
        The hold (not band-limited: a stream has no later samples) and the sub-steps.
    Q_x : ndarray (n, n)
    R : ndarray (r, r) or None
    k : int
        The sample's index (named in the error).

    Returns
    -------
    float
        The update's normalised innovation squared ÷ r (NaN: no update).

    Raises
    ------
    NonFiniteError
        The filter diverged (s or P's diagonal not finite): the error of
        :attr:`~thetahat.estimation.status.Status.DIVERGED`.
    """
    n, p = Q_x.shape[0], s.shape[0] - Q_x.shape[0]
    if u0 is not None:
        pc, WT = propagation.arrays()
        kernels.predict(s, P, np.ascontiguousarray(np.stack([u0, u1]), dtype=np.float64), 0,
                        dt, pc, WT, Q_x, np.empty((n, n)), np.empty((n, p)))
    nis = math.nan
    if R is not None and all(map(math.isfinite, y.tolist())):
        ts = stage2_set(system.require_parameter_set("stage 2"))
        nis = float(kernels.update(s, P, y, R, ts.lo, ts.hi, ts.ell))
    # (finiteness of a few values on Python floats: NumPy's per-call cost is most of a step's)
    if not (all(map(math.isfinite, s.tolist()))
            and all(map(math.isfinite, np.diagonal(P).tolist()))):
        raise status_error(Status.DIVERGED, f"the EKF diverged at sample {k}; check the model "
                           "and noise_std.")
    return nis


def divergence_message(t: FloatArray, bad: int, nis: FloatArray, r: int) -> str:
    """What to say of a joint EKF whose state became non-finite at sample ``bad``.

    The message of the :attr:`~thetahat.estimation.status.Status.DIVERGED` status of
    :meth:`~thetahat.estimation.statistical.ekf.JointEKF.run` and of the MAP estimator's
    filter between its fits.

    Parameters
    ----------
    t : ndarray (N,)
    bad : int
        The first sample with a non-finite state.
    nis : ndarray (N,)
        The normalised innovations squared of the samples before (NaN where none).
    r : int
        Outputs per sample (NIS's expectation).

    Returns
    -------
    str
        Says where, and — when the median NIS ÷ r before the divergence exceeds
        :data:`NIS_MODEL_ERROR` — that the model taken as exact does not fit the record and
        what to do about it.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.ekf_kernels import divergence_message
    >>> msg = divergence_message(np.arange(5.0), 4, np.array([3e4, 2e4, 5e4, 4e4, np.nan]), 1)
    >>> "does not fit" in msg
    True
    """
    seen = np.asarray(nis[:bad], dtype=np.float64)
    seen = seen[np.isfinite(seen)]
    ratio = float(np.median(seen)) / max(r, 1) if seen.size else 0.0
    where = f"the EKF diverged at t[{bad}] = {float(t[bad]):.6g}"
    if ratio > NIS_MODEL_ERROR:
        return (f"{where}: its innovations before were {math.sqrt(ratio):.3g}"
                " times their predicted size, so the model taken as exact (no process noise)"
                " does not fit this record; give a process noise q_x > 0, or use method"
                " 'guarded' or 'mle', which estimate it from the data.")
    return f"{where}; check the model and noise_std."
