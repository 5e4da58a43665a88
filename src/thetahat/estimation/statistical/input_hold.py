"""Stage 2's input samples for its hold: a smooth input's samples corrected for the linear hold.

Stage 2 propagates the model between samples with u as the hold reconstructs it
(:mod:`~thetahat.estimation.hold`, :mod:`~thetahat.estimation.statistical.plant_kernel`):
held (``"zoh"``), linear (``"foh"`` and ``"smooth"``) or band-limited (``"bandlimited"``). The
samples it reconstructs from are :func:`stage2_samples`: the raw samples for every hold but
``"smooth"``, and for ``"smooth"`` the samples ũ below, so that its line through them carries a
smooth input's mean over every interval. (``"foh"`` is the line through the raw samples: an
input that truly is linear between them.) The free run (:mod:`thetahat.studies.free_run`)
reconstructs from the same samples. When u is a smooth signal sampled at
spacing h, the linear interpolant of its samples has, over each interval, the mean
(u_{k−1} + u_k)/2 = ū − h² ü/12 + O(h⁴) instead of the true mean ū: for a 131 Hz input at
10 kHz a relative error of 6·10⁻⁴ per sample, a bias that long records resolve (the actuator
example's k_1 ended at 1.7× its Cramér–Rao bound). Replacing each sample by

    ũ_k = u_k − h² ü(t_k)/12

makes the linear interpolant of ũ carry the exact mean over every interval to O(h⁴). ü(t_k) is
estimated causally — from the samples up to k only, so that a stream (``step``) computes what
a record (``run``) computes — as the backward second difference D_k = u_k − 2u_{k−1} + u_{k−2}
(≈ h² ü(t_{k−1})) extrapolated by one sample: h² ü(t_k) ≈ 2D_k − D_{k−1}, i.e.

    ũ_k = u_k − (2u_k − 5u_{k−1} + 4u_{k−2} − u_{k−3})/12          (k ≥ 3; ũ_k = u_k before).

For a sinusoid of angular frequency ω this lowers the error of the interval mean from
(ωh)²/12 to O((ωh)⁴) and stays below the linear hold's up to ωh ≈ 1.2; above, at frequencies
the samples do not resolve, it is worse. Whether u is a sampled smooth signal is decided per
input channel from the samples so far: with ρ_k² = Σ_{j≤k} (Δ²u_j)² ÷ Σ_{j≤k} (Δu_j)²,
sample k is corrected only while ρ_k < 1. A sinusoid has ρ = 2 sin(ωh/2), so ρ < 1 ⇔
ωh < π/3, inside the range where the correction helps; a single step gives ρ = √2, white
noise or a PRBS switching every sample √3, a staircase held over several samples (a DAC's
zero-order hold) ρ near √2 unless the steps are small against a smooth trend: those keep
the linear hold. The formula assumes uniform sampling (differences of samples, not divided
differences).

What it may import: NumPy and the hold (:mod:`~thetahat.estimation.hold`); stage 2's
estimators import it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import OptionError
from ...model.perturbation import EVAL_BLOCK
from ..hold import check_hold

__all__ = ["HISTORY", "InputHistory", "smooth_input", "smooth_step", "stage2_samples",
           "streamable"]

FloatArray = NDArray[np.float64]

#: Samples of the past the correction of one sample needs (u_{k−3} … u_{k−1}).
HISTORY = 3


@dataclass(frozen=True, slots=True, eq=False)
class InputHistory:
    """What :func:`smooth_input` needs of the samples before a block.

    Attributes
    ----------
    u_last : ndarray, shape (j, m), j ≤ 3
        The last raw input samples, oldest first (fewer than 3 at a stream's start).
    d1, d2 : ndarray, shape (m,)
        Σ (Δu)² and Σ (Δ²u)² over all samples so far, per channel.
    """

    u_last: FloatArray
    d1: FloatArray = field(default_factory=lambda: np.zeros(0))
    d2: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __repr__(self) -> str:
        return f"InputHistory(samples={self.u_last.shape[0]}, d1={self.d1}, d2={self.d2})"


def smooth_input(U: FloatArray, history: InputHistory | None = None
                 ) -> tuple[FloatArray, InputHistory]:
    """Stage 2's input samples ũ for the linear hold: u corrected where it is smooth.

    Parameters
    ----------
    U : ndarray, shape (N, m)
        Raw input samples of a block of a record or stream.
    history : InputHistory, optional
        The previous block's (None: the record's first block).

    Returns
    -------
    U_tilde : ndarray, shape (N, m)
        ũ_k = u_k − (2u_k − 5u_{k−1} + 4u_{k−2} − u_{k−3})/12 where the channel is smooth so
        far (ρ_k < 1, see the module docstring) and k ≥ 3; u_k elsewhere.
    history : InputHistory
        For the next block: processing a record in blocks gives the samples of one call.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.estimation.statistical.input_hold import smooth_input
    >>> h, w = 1e-3, 2 * np.pi * 20.0
    >>> t = np.arange(200) * h
    >>> Ut, _ = smooth_input(np.sin(w * t)[:, None])
    >>> exact = (np.cos(w * t[:-1]) - np.cos(w * t[1:])) / (w * h)    # u's mean per interval
    >>> lin = np.abs((np.sin(w * t[:-1]) + np.sin(w * t[1:])) / 2 - exact)[10:].max()
    >>> new = np.abs((Ut[:-1, 0] + Ut[1:, 0]) / 2 - exact)[10:].max()
    >>> bool(new < lin / 20)       # (ωh)²/12 against O((ωh)⁴): ωh = 0.126 here
    True
    >>> step = np.repeat([0.0, 1.0], 10)[:, None]          # a step: ρ = √2, kept as sampled
    >>> bool(np.array_equal(smooth_input(step)[0], step))
    True
    """
    U = np.asarray(U, dtype=np.float64)
    N, m = U.shape
    if N == 1 and (history is None or (history.u_last.shape[0] <= HISTORY
                                       and history.u_last.shape[1:] == (m,)
                                       and history.d1.shape[0] in (0, m)
                                       and history.d2.shape[0] == history.d1.shape[0])):
        return _smooth_sample(U, history)
    past = np.zeros((0, m)) if history is None else history.u_last
    d1_0 = np.zeros(m) if history is None or history.d1.shape[0] == 0 else history.d1
    d2_0 = np.zeros(m) if history is None or history.d2.shape[0] == 0 else history.d2
    j = past.shape[0]
    V = np.concatenate([past, U])                   # stream sample j + i is U[i] (j ≤ 3)
    first = np.zeros((V.shape[0], m))               # Δu_i at row i (0 where undefined)
    second = np.zeros((V.shape[0], m))              # Δ²u_i = D_i at row i
    first[1:] = np.diff(V, axis=0)
    second[2:] = np.diff(V, n=2, axis=0)
    # running sums over the new rows, accumulated one sample at a time from the history's
    # (a stream of one-sample blocks adds the same terms in the same order)
    s1 = np.cumsum(np.concatenate([d1_0[None], first[j:] ** 2]), axis=0)[1:]
    s2 = np.cumsum(np.concatenate([d2_0[None], second[j:] ** 2]), axis=0)[1:]
    rows = np.arange(j, V.shape[0])
    extrap = np.zeros((N, m))
    late = rows >= HISTORY
    extrap[late] = 2.0 * second[rows[late]] - second[rows[late] - 1]
    smooth = (s2 < s1) & late[:, None]
    Ut = np.where(smooth, U - extrap / 12.0, U)
    keep = V[-HISTORY:].copy()
    return Ut, InputHistory(u_last=keep, d1=s1[-1].copy() if N else d1_0.copy(),
                            d2=s2[-1].copy() if N else d2_0.copy())


def smooth_step(u: Any, hist: Any, sums: Any, count: int, m: int, ut: Any) -> None:
    """ũ of one sample of a stream, its history advanced in place: :func:`smooth_input` one
    sample at a time, the same floating-point operations in the same order. The one
    definition of a stream's correction: a stream's step calls it on Python floats (NumPy's
    per-call cost is most of a stream step's otherwise: 65 µs against 5), and the generated C
    (``thetahat codegen --hold smooth``) prints it.

    Parameters
    ----------
    u : sequence of float, length m
        The new sample.
    hist : mutable sequence of float, length 3 m
        The last three samples, oldest first (row-major, m a row); rows before the stream's
        first sample are not read.
    sums : mutable sequence of float, length 2 m
        Σ (Δu)² of each channel, then Σ (Δ²u)², over the samples so far.
    count : int
        Samples before this one (what matters: whether it reaches 1, 2, 3).
    m : int
        Channels.
    ut : mutable sequence of float, length m
        Written: ũ.

    Examples
    --------
    >>> hist, sums, ut = [0.0] * 3, [0.0] * 2, [0.0]
    >>> for k, u in enumerate([0.0, 0.01, 0.04, 0.09]):     # u = t², ü = 2: corrected at k = 3
    ...     smooth_step([u], hist, sums, k, 1, ut)
    >>> round(ut[0], 9), hist                 # u_3 − h² ü / 12 with h = 0.1
    (0.088333333, [0.01, 0.04, 0.09])
    """
    for i in range(m):
        a = hist[2 * m + i]                 # u_{k-1}
        b = hist[m + i]                     # u_{k-2}
        e = hist[i]                         # u_{k-3}
        f = 0.0                             # Δu_k (0 at a stream's first sample)
        sec = 0.0                           # Δ²u_k (0 before its third)
        if count >= 1:
            f = u[i] - a
        if count >= 2:
            sec = f - (a - b)
        s1 = sums[i] + f * f
        s2 = sums[m + i] + sec * sec
        sums[i] = s1
        sums[m + i] = s2
        ut[i] = u[i]
        if count >= HISTORY and s2 < s1:
            ut[i] = u[i] - (2.0 * sec - ((a - b) - (b - e))) / 12.0
        hist[i] = b
        hist[m + i] = a
        hist[2 * m + i] = u[i]


def _smooth_sample(U: FloatArray, history: InputHistory | None
                   ) -> tuple[FloatArray, InputHistory]:
    """:func:`smooth_input` of one sample (a stream's step), by :func:`smooth_step`."""
    m = U.shape[1]
    j = 0 if history is None else history.u_last.shape[0]
    hist = [0.0] * ((HISTORY - j) * m) + ([] if history is None
                                          else history.u_last.ravel().tolist())
    sums = ([0.0] * (2 * m) if history is None or history.d1.shape[0] == 0
            else [*history.d1.tolist(), *history.d2.tolist()])
    ut = [0.0] * m
    smooth_step(U[0].tolist(), hist, sums, j, m, ut)
    keep = min(j + 1, HISTORY)
    return (np.array([ut]), InputHistory(u_last=np.array(hist[(HISTORY - keep) * m:]).reshape(
        keep, m), d1=np.array(sums[:m]), d2=np.array(sums[m:])))


def stage2_samples(U: FloatArray, hold: str, history: InputHistory | None = None
                   ) -> tuple[FloatArray, InputHistory | None]:
    """The input samples stage 2 reconstructs u from under ``hold`` (C-contiguous copies).

    Parameters
    ----------
    U : ndarray, shape (N, m)
        Raw input samples of a block of a record or stream.
    hold : {"zoh", "foh", "bandlimited", "smooth"}
    history : InputHistory, optional
        The previous block's (``"smooth"`` only; None: the first block).

    Returns
    -------
    samples : ndarray, shape (N, m)
        ũ of :func:`smooth_input` for ``"smooth"``; the raw samples otherwise.
    history : InputHistory or None
        For the next block (``"smooth"``), else None.

    Examples
    --------
    >>> import numpy as np
    >>> U = np.sin(np.arange(50) * 0.1)[:, None]
    >>> bool(np.array_equal(stage2_samples(U, "foh")[0], U))
    True
    >>> bool(np.array_equal(stage2_samples(U, "smooth")[0], smooth_input(U)[0]))
    True
    """
    if check_hold(hold) != "smooth":
        return np.array(U, dtype=np.float64, order="C"), None
    if U.shape[0] <= EVAL_BLOCK:
        Ut, hist = smooth_input(U, history)
        return np.ascontiguousarray(Ut), hist
    # a long record a block at a time, each carrying the history of the one before: the same
    # sums in the same order (the cumulative sums run one sample at a time), so the same ũ to
    # the bit, with the differences and sums a block long
    out = np.empty(U.shape)
    for a in range(0, U.shape[0], EVAL_BLOCK):
        out[a:a + EVAL_BLOCK], history = smooth_input(U[a:a + EVAL_BLOCK], history)
    return out, history


def streamable(hold: str, who: str) -> str:
    """``hold`` if a stream (``step``) can use it: the band-limited hold reads samples after
    the interval, which a stream has not yet.

    Parameters
    ----------
    hold : str
    who : str
        The estimator (named in the error).

    Returns
    -------
    str

    Raises
    ------
    OptionError
        ``hold="bandlimited"``.

    Examples
    --------
    >>> streamable("zoh", "JointEKF")
    'zoh'
    """
    if check_hold(hold) == "bandlimited":
        raise OptionError(f"{who}.step cannot use hold='bandlimited': the band-limited "
                          "reconstruction between two samples reads samples after them, which "
                          "a stream has not yet; use run on the record, or hold='smooth' "
                          "(or 'zoh' for a DAC's input) for a stream.")
    return hold
