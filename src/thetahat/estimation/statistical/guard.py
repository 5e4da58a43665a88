"""The guard between the two stages: evidence-based, so it never biases a correct stage 2.

The output θ̂ follows stage 2 (θ̂₂, EKF + MAP re-anchoring) only inside a band around stage 1
(θ̂_G, the paper's observer and update law, Theorem 1):

    θ̂ = Π_Θ( θ̂_G + clip(θ̂₂ − θ̂_G, −δ, δ) ),    δ(t) = max(δ_G(t), κ σ₂(t), δ_F(t)),

so that, whatever stage 2 does, θ̂ ∈ Θ and ‖θ̂ − θ‖ ≤ ‖θ̂_G − θ‖ + ‖δ(t)‖ for the true θ ∈ Θ
(Π_Θ is the Euclidean projection, non-expansive towards any point of the convex Θ; for a box
it is a clip and the bound holds per component, |θ̂_i − θ_i| ≤ |θ̂_G,i − θ_i| + δ_i). Θ may be
any convex set of :mod:`~thetahat.model.paramset`; |Θ| below is the width of its bounding box
(:func:`~thetahat.estimation.statistical.stage2_set.theta_bounds`). The band's width is built on evidence only:

* δ_G(t), stage 1's measured progress. With the samples split dyadically, *late* is the range
  of θ̂_G over [2^{J−1}, k] (k ∈ [2^J, 2^{J+1})) and *early* its range before 2^{J−1}; their
  ratio ρ = late/early measures stage 1's contraction. If stage 1 converges geometrically,
  late/(1 − ρ) bounds the movement still to come from 2^{J−1} on, hence its error; δ_G =
  c·late/(1 − ρ). Without evidence of contraction (ρ ≥ ρ_max, or stage 1 has not moved, as
  under weak excitation where Theorem 1 gives no rate) δ_G = |Θ|: stage 2 is not held back.
  No rate is assumed: a slow stage 1 keeps a wide band until its own data show it settling,
  which is the failure of a band shrinking at a fixed rate (design note, "the guard's pitfall").
* σ₂(t), stage 2's own standard deviation √P_θθ (capped at the prior's |Θ|/4), so that its
  noise is never clipped.

* δ_F(t), a consistent MAP fit's evidence on stage 1's error: when a fit of the data so far
  passed its consistency check with estimate θ_F and standard error s_F, θ lies within κ s_F
  of θ_F, so stage 1's error is at least |θ̂_G − θ_F| − κ s_F; δ_G, which stands for that
  error, is then at least |θ̂_G − θ_F| + κ s_F. (A slow stage 1 can look settled — its late
  range small against the early one — while still far from θ; the fit is the evidence that
  it is not.)

Stage 2 is reset from stage 1 (x̂, θ̂_G and the prior covariance) when it is non-finite, or
after it has been clipped for ``dwell``·k consecutive samples (k the samples so far; with
:data:`GUARD_DWELL` = 1 − 1/√2 the span since k/√2, over which the information of the data
grew by the fit schedule's factor √2: a fraction of the run, never seconds) while stage 1
shows evidence (δ_G < |Θ|): then stage 2 disagrees with a settled stage 1 beyond both stages'
uncertainty.
The windowed normalised innovation squared (NIS ≈ 1 for a consistent filter) is reported as
a consistency diagnostic.

What lives here: the progress measure of stage 1 (:func:`progress_init`,
:func:`progress_reset`, :func:`progress_step`),
the guard at one sample (:func:`band`), the reset (:func:`reset_stage2`), a fit applied
(:func:`apply_fit`) and the per-sample
loop over the EKF kernels (:func:`guarded_loop`), all module-level functions in numba's
subset of Python. What it may import: NumPy and :mod:`math` only; the EKF kernels the loop
calls (``predict``, ``update``, ``project``) are bound when
:mod:`~thetahat.estimation.statistical.guarded` prints it over them.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

__all__ = ["progress_init", "progress_reset", "progress_step", "band", "reset_stage2",
           "apply_fit", "guarded_loop",
           "GUARD_C", "GUARD_RHO_MAX", "GUARD_KAPPA", "GUARD_DWELL", "NIS_WINDOW"]

#: Safety factor of δ_G on the extrapolated remaining movement of stage 1.
GUARD_C = 2.0
#: Largest contraction ratio late/early taken as evidence that stage 1 converges.
GUARD_RHO_MAX = 0.5
#: Stage 2's standard deviations kept inside the band.
GUARD_KAPPA = 4.0
#: Fraction of the samples so far that stage 2 must stay clipped before it is reset: the
#: span since k/√2, over which the information grew by the fit schedule's factor √2.
GUARD_DWELL = 1.0 - 1.0 / math.sqrt(2.0)
#: Samples of the exponentially weighted NIS average.
NIS_WINDOW = 200.0


def progress_init(theta0: np.ndarray) -> np.ndarray:
    """State of :func:`progress_step` after sample 0: per component (prefix min, max, block
    min, max, current min, max); shape (p, 6).

    Parameters
    ----------
    theta0 : ndarray, shape (p,)
        Stage 1's θ̂_G at sample 0 (the observer's initial estimate).

    Returns
    -------
    ndarray, shape (p, 6)
        Per component of θ: the running min and max of θ̂_G before the previous dyadic block
        (initialised to ``theta0``), of the previous block and of the current block (both
        empty: +inf, −inf).
    """
    st = np.empty((theta0.shape[0], 6))
    progress_reset(st, theta0)
    return st


def progress_reset(st: np.ndarray, theta0: np.ndarray) -> None:
    """Write :func:`progress_init`'s state for ``theta0`` into ``st`` (p, 6), in place (the
    generated C's form: its state has no allocation).

    Parameters
    ----------
    st : ndarray, shape (p, 6)
    theta0 : ndarray, shape (p,)
    """
    for i in range(theta0.shape[0]):
        st[i, 0] = theta0[i]
        st[i, 1] = theta0[i]
        st[i, 2] = np.inf
        st[i, 3] = -np.inf
        st[i, 4] = np.inf
        st[i, 5] = -np.inf


def progress_step(st: np.ndarray, k: int, theta: np.ndarray, width: np.ndarray, c: float,
                  rho_max: float, delta: np.ndarray) -> None:
    """Add stage 1's θ̂_G at sample k ≥ 1 to ``st`` and write δ_G into ``delta`` (p,).

    At k = 2^J the dyadic blocks shift; then, per component, *late* is the range of θ̂_G
    over the previous and current blocks and *early* its range before them, and
    δ_G = min(|Θ|, c·late/(1 − late/early)) if late < ρ_max·early, else |Θ| (no evidence
    that stage 1 contracts).

    Parameters
    ----------
    st : ndarray, shape (p, 6)
        The progress state from :func:`progress_init` (or an earlier call), updated in place.
    k : int
        The absolute sample index, k ≥ 1 (called once per sample, in order).
    theta : ndarray, shape (p,)
        Stage 1's θ̂_G at sample k.
    width : ndarray, shape (p,)
        |Θ| per component (upper − lower): δ_G's value without evidence, and its cap.
    c : float
        Safety factor on the extrapolated remaining movement (default in use
        :data:`GUARD_C`).
    rho_max : float
        Largest ratio late/early taken as evidence of contraction (:data:`GUARD_RHO_MAX`).
    delta : ndarray, shape (p,)
        Output: receives δ_G(k) per component.
    """
    p = theta.shape[0]
    if k & (k - 1) == 0:                           # k = 2^J: shift the dyadic blocks
        for i in range(p):
            st[i, 0] = min(st[i, 0], st[i, 2])
            st[i, 1] = max(st[i, 1], st[i, 3])
            st[i, 2] = st[i, 4]
            st[i, 3] = st[i, 5]
            st[i, 4] = np.inf
            st[i, 5] = -np.inf
    for i in range(p):
        st[i, 4] = min(st[i, 4], theta[i])
        st[i, 5] = max(st[i, 5], theta[i])
        early = st[i, 1] - st[i, 0]
        late = max(st[i, 3], st[i, 5]) - min(st[i, 2], st[i, 4])
        if not (early > 0.0) or not math.isfinite(late) or late >= rho_max * early:
            delta[i] = width[i]
        else:
            delta[i] = min(width[i], c * late / (1.0 - late / early))


# Names of the printed guard module (declared for the type checker; bound when printed:
# the EKF's time and measurement updates and Π_Θ of ekf_kernels.EKFKernels).
predict: Callable[..., None]
update: Callable[..., float]
project: Callable[..., None]


def band(s: Any, P: Any, k: int, thG: Any, dG: Any, cfg: Any, lo: Any, hi: Any, ell: Any,
         bad: bool, eye: Any, z: Any, BAND: Any) -> bool:
    """The guard at one sample: the band δ, stage 2's θ̂₂ clipped to it around θ̂_G, Π_Θ.

    Per component δ = max(δ_G, κ min(σ₂, σ₂ cap), |θ̂_G − θ_F| + κ s_F of the latest
    consistent fit when ``cfg`` holds one), written into ``BAND[k]``; the guarded
    θ̂ = Π_Θ(θ̂_G + clip(θ̂₂ − θ̂_G, −δ, δ)) into ``z`` (θ̂₂ − θ̂_G taken as 0 when stage 2 is
    ``bad``, not finite; Π_Θ the printed module's ``project`` with M = I); returns whether a
    component was clipped.
        Parameters
    ----------
    s : ndarray, shape (n + p,)
    P : ndarray, shape (n + p, n + p)
        Stage 2's state and covariance.
    k : int
    thG, dG : ndarray, shapes (N, p), (p,)
        Stage 1's θ̂_G and its band δ_G.
    cfg : ndarray
        The guard's configuration (:func:`guarded_loop`).
    lo, hi, ell : ndarray
        Θ.
    bad : bool
        Stage 2 is not finite.
    eye, z : ndarray, shapes (p, p), (p,)
        Work arrays (``z`` receives the guarded θ̂).
    BAND : ndarray, shape (N, p)
        Output.

    Returns
    -------
    bool
    """
    p = thG.shape[1]
    n = s.shape[0] - p
    with_fit = cfg.shape[0] >= 4 + 3 * p
    clipped = False
    for i in range(p):
        d = s[n + i] - thG[k, i]
        sd = math.sqrt(max(P[n + i, n + i], 0.0)) if not bad else 0.0
        width = max(dG[i], cfg[0] * min(sd, cfg[4 + i]))
        if with_fit and cfg[4 + 2 * p + i] >= 0.0:
            width = max(width, abs(thG[k, i] - cfg[4 + p + i]) + cfg[4 + 2 * p + i])
        if bad:
            d = 0.0
        if d > width:
            d = width
            clipped = True
        elif d < -width:
            d = -width
            clipped = True
        z[i] = thG[k, i] + d
        BAND[k, i] = width
    project(z, eye, lo, hi, ell)
    return clipped


def reset_stage2(s: np.ndarray, P: np.ndarray, P0: np.ndarray, k: int, xG: np.ndarray,
                 thG: np.ndarray) -> None:
    """Stage 2 reset from stage 1 at sample k: s = col(x̂_G, θ̂_G) and P = P0, in place.

    Parameters
    ----------
    s : ndarray (n + p,)
    P : ndarray (n + p, n + p)
    P0 : ndarray (n + p, n + p)
        The prior covariance.
    k : int
    xG, thG : ndarray (N, n), (N, p)
        Stage 1's x̂ and θ̂_G.
    """
    n = xG.shape[1]
    p = thG.shape[1]
    for i in range(n):
        s[i] = xG[k, i]
    for i in range(p):
        s[n + i] = thG[k, i]
    for i in range(n + p):      # element by element: numba's slice assignment
        for j in range(n + p):  # compiles its string-formatting error path
            P[i, j] = P0[i, j]


def apply_fit(s: Any, P: Any, R: Any, cfg: Any, theta: Any, cov: Any, sigma: Any) -> None:
    """A re-anchoring fit applied to a running stage 2 (the stream's form: θ only, since x
    has moved on since the fit's window), in place.

    θ̂₂ ← θ_F; the θ rows and columns of P zeroed, P_θθ ← the fit's covariance of θ; R ←
    diag(σ_F²); the guard's configuration ``cfg`` (:func:`guarded_loop`) takes θ_F and κ s_F,
    s_F = √diag of that covariance, as the latest consistent fit. The Python stream
    (:meth:`~thetahat.estimation.statistical.guarded_stream.GuardedStream.poll_fit`) and the
    generated C's ``<name>_apply_fit`` both call it.

    Parameters
    ----------
    s, P : ndarray, shapes (n + p,), (n + p, n + p)
        Stage 2's state and covariance.
    R : ndarray, shape (r, r)
        The measurement noise covariance.
    cfg : ndarray, shape (4 + 3p,)
        The guard's configuration.
    theta, cov, sigma : ndarray, shapes (p,), (p, p), (r,)
        The fit's θ, covariance of θ and noise σ.
    """
    p = theta.shape[0]
    n = s.shape[0] - p
    for i in range(p):
        s[n + i] = theta[i]
    for i in range(n + p):
        for j in range(n, n + p):
            P[i, j] = 0.0
            P[j, i] = 0.0
    for i in range(p):
        for j in range(p):
            P[n + i, n + j] = cov[i, j]
    for i in range(sigma.shape[0]):
        for j in range(sigma.shape[0]):
            R[i, j] = 0.0
        R[i, i] = sigma[i] * sigma[i]
    for i in range(p):
        cfg[4 + p + i] = theta[i]
        cfg[4 + 2 * p + i] = cfg[0] * math.sqrt(max(cov[i, i], 0.0))


def guarded_loop(s: Any, P: Any, P0: Any, U: Any, Y: Any, tt: Any, k0: int, k1: int,
                 off: int, R: Any, lo: Any, hi: Any, ell: Any, pc: Any, WT: Any, Q_x: Any,
                 thG: Any, xG: Any, pst: Any, gst: Any, cfg: Any, TH: Any, TH2: Any, X2: Any,
                 SD2: Any, BAND: Any, CLIP: Any, RESET: Any, NIS: Any) -> int:
    """The per-sample loop of the guarded estimator over the EKF's kernels.

    Runs stage 2 over samples k0 … k1−1 (absolute index k + ``off``; the EKF's ``predict``
    over the interval from sample k − 1 of ``U`` with u held as ``pc, WT`` say, then its
    ``update``) against stage 1's θ̂_G ``thG`` and x̂ ``xG``, writes the guarded θ̂
    (``TH``), stage 2's θ̂₂, x̂₂ and σ₂ (``TH2``, ``X2``, ``SD2``), the band δ (``BAND``), the
    clip and reset flags and the windowed NIS, updates the progress state ``pst``, ``gst`` =
    (dwell count, NIS average, first update index) and returns the number of resets of stage
    2 to stage 1. ``cfg`` = (κ, c, ρ_max, dwell as a fraction of the samples so far, σ₂ cap
    per component…, and optionally θ_F per component…, κ s_F per component… of the latest
    consistent fit; κ s_F < 0: none).
        Parameters
    ----------
    s, P, P0 : ndarray
        Stage 2's state, covariance and the covariance a reset restarts from.
    U, Y, tt : ndarray
        The record.
    k0, k1, off : int
        The samples run and the offset of their absolute index.
    R, lo, hi, ell, pc, WT, Q_x : ndarray
        As for :func:`~thetahat.estimation.statistical.ekf_kernels.ekf_loop`.
    thG, xG : ndarray
        Stage 1's θ̂_G and x̂.
    pst, gst, cfg : ndarray
        The progress state, the guard's state and configuration (above).
    TH, TH2, X2, SD2, BAND, CLIP, RESET, NIS : ndarray
        Output rows (above).

    Returns
    -------
    int
    """
    n = X2.shape[1]
    p = TH.shape[1]
    width = np.empty(p)                          # |Θ| per component
    for i in range(p):
        width[i] = hi[i] - lo[i]
    Phi = np.empty((n, n))
    Gam = np.empty((n, p))
    dG = np.empty(p)
    eye = np.eye(p)
    z = np.empty(p)
    thk = np.empty(p)                            # rows k of thG and Y, copied (the C
    yk = np.empty(Y.shape[1])                    # printer passes whole arrays)
    resets = 0
    for k in range(k0, k1):
        for i in range(p):
            thk[i] = thG[k, i]
        finite_y = True
        for j in range(Y.shape[1]):
            yk[j] = Y[k, j]
            if not math.isfinite(yk[j]):
                finite_y = False
        if k + off > 0:
            predict(s, P, U, k - 1, tt[k] - tt[k - 1], pc, WT, Q_x, Phi, Gam)
            progress_step(pst, k + off, thk, width, cfg[1], cfg[2], dG)
        else:
            for i in range(p):
                dG[i] = width[i]
        nis = np.nan
        if finite_y and k + off >= gst[2]:
            nis = update(s, P, yk, R, lo, hi, ell)
        # False, as a run-time bool: a literal False compiled band a second time (0.4 s)
        bad = k < k0
        for i in range(s.shape[0]):
            if not math.isfinite(s[i]) or not math.isfinite(P[i, i]):
                bad = True
        clipped = band(s, P, k, thG, dG, cfg, lo, hi, ell, bad, eye, z, BAND)
        for i in range(p):
            TH[k, i] = z[i]
        gst[0] = gst[0] + 1.0 if clipped else 0.0
        settled = True
        for i in range(p):
            if dG[i] >= width[i]:
                settled = False
        reset = bad or (gst[0] > cfg[3] * (k + off + 1) and settled)
        if reset:
            reset_stage2(s, P, P0, k, xG, thG)
            gst[0] = 0.0
            resets += 1
        if math.isfinite(nis):
            gst[1] += (nis - gst[1]) / NIS_WINDOW
        for i in range(n):
            X2[k, i] = s[i]
        for i in range(p):
            TH2[k, i] = s[n + i]
            SD2[k, i] = math.sqrt(max(P[n + i, n + i], 0.0))
        CLIP[k] = clipped
        RESET[k] = reset
        NIS[k] = gst[1]
    return resets
