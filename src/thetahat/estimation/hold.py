"""The hold: how a sampled signal is reconstructed between its sampling instants, for every method.

Every estimator integrates the model between two samples, so every one needs u (and the
observer v = col(u, y)) *between* them. The hold says what it is; one reconstruction serves the
joint EKF, the MAP fits, the likelihood with process noise, the Cramér–Rao bound, the trust
report and the free-run simulation
(:func:`thetahat.studies.free_run.simulate_output`):

* ``"zoh"`` — zero-order hold: u(t_k + a h) = u_k for a ∈ [0, 1) (a DAC holding its output);
* ``"foh"`` — first-order hold: u linear between u_k and u_{k+1};
* ``"smooth"`` — the first-order hold through the samples corrected for a smooth signal's
  interval mean (below);
* ``"bandlimited"`` — the band-limited signal through the samples: the Whittaker–Shannon
  interpolation Σ_j u_{k+j} sinc(a − j) with the sinc windowed by a Kaiser window over
  ±:data:`BANDLIMITED_HALF_WIDTH` samples (β = :data:`KAISER_BETA`) and the weights scaled to
  sum to 1 (a constant passes exactly, and every sample is reproduced at its own instant).
  A sinusoid of frequency up to :data:`BANDLIMITED_BAND` of the Nyquist frequency is
  reproduced at every fraction a of the interval within a relative
  :data:`BANDLIMITED_ERROR` (the largest |Σ_j w_j(a) e^{iω(j − a)} − 1| over a ∈ [0, 1] and
  ω ≤ 0.8π, computed on a grid of 65 × 400 points; tests/estimation/test_hold.py). For
  comparison the linear hold's error there is 1 − cos(ωh/2) ≈ (ωh)²/8 at mid-interval: 6 % at
  ω h = 0.7 (the Silverbox's resonance, 9 samples per period), 69 % at 0.8π.

The holds are one formula: at the fraction a of the interval from sample k to k + 1,

    u(t_k + a h) = Σ_{j = −L+1}^{L} w_j(a) u_{k+j},

with the taps table w(a) of :func:`hold_weights` (L = 1 for the zero- and first-order holds:
w = (1, 0) and (1 − a, a), ``"smooth"`` the latter; L = :data:`BANDLIMITED_HALF_WIDTH` for the
band-limited one).
Samples beyond the record's ends are taken equal to its first and last sample. The fraction is
of the sample index: with irregular instants the band-limited reconstruction interpolates in
the index (exact for uniform sampling, an approximation for jittered instants), the zero- and
first-order holds are exact on any grid. The band-limited hold reads L samples *after* the
interval: it is for records (``run``), not streams (``step`` refuses it).

``"smooth"`` is the first-order hold through corrected samples, for a *smooth signal sampled at
points* (a measured input, not a DAC's): the line through the raw samples has, over each
interval, the mean ū − h² ü/12 instead of ū, so every channel that its samples show to be
smooth is reconstructed through ũ_k = u_k − h² ü(t_k)/12 with ü from past samples only
(:func:`~thetahat.estimation.statistical.input_hold.stage2_samples`); a channel that is not
smooth keeps its samples. It is causal (a stream's ``step`` takes it) and stage 2's default. It
is not ``"foh"``: for an input that truly is linear between its samples (a first-order-hold
DAC, a simulation driven by the interpolant) it is wrong by h² ü/12 — on a 3 s record of the
Silverbox model driven by such an input at 610 Hz (σ = 0.3 mV) the MAP fit under ``"foh"``
landed within 1.1 of its Cramér–Rao sd of the true θ, under ``"smooth"`` 60–370 sd away (a
one-off measurement). Every path takes the hold it is given the same way: the free run and the
output-error fit (:mod:`thetahat.studies.free_run`) reconstruct ``"smooth"`` through ũ too.
Near the Nyquist frequency neither line is close to a smooth input; ``"bandlimited"`` is
(records only).

An integrator exact for a forcing linear in time over each step (the paper's observer's
exponential integrator is one) needs one straight line per step: :func:`step_lines` gives the
line closest to the hold's reconstruction over the step in the mean-square sense — for the
zero- and first-order holds the reconstruction itself; for the band-limited one the line with
the band-limited signal's mean and first moment over the step. (The paper's observer takes
``"zoh"`` and ``"foh"`` through its own ``run(hold=…)``, and a run's ``"smooth"`` or
``"bandlimited"`` as ``"foh"`` through the raw samples
(:func:`thetahat.modelfile.holds.split_hold`): the band-limited lines and the corrected samples
are not yet wired into it.)

What it may import: NumPy and :mod:`math`; nothing of the estimation wing (every room uses it).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import DimensionError, OptionError

__all__ = ["BANDLIMITED_BAND", "BANDLIMITED_ERROR", "BANDLIMITED_HALF_WIDTH", "CODES",
           "DEFAULT_HOLD", "HOLDS", "Hold", "KAISER_BETA", "bessel_i0", "check_hold", "half_width",
           "hold_code", "hold_weights", "reconstruct", "step_lines", "weight_table"]

FloatArray = NDArray[np.float64]

#: The holds.
HOLDS = ("zoh", "foh", "bandlimited", "smooth")
Hold = Literal["zoh", "foh", "bandlimited", "smooth"]
#: Each hold's code in the compiled kernels (its taps table): ``"smooth"`` is the first-order
#: hold's line, through the samples :func:`~thetahat.estimation.statistical.input_hold.
#: stage2_samples` corrects.
CODES = {"zoh": 0, "foh": 1, "bandlimited": 2, "smooth": 1}
#: The hold of stage 2, its trust report and the free run unless told: a measured input is a
#: smooth signal sampled at points.
DEFAULT_HOLD = "smooth"
#: L: the band-limited reconstruction reads the samples k − L + 1 … k + L (2L taps).
BANDLIMITED_HALF_WIDTH = 16
#: β of the Kaiser window (with L = 16 the β of the smallest in-band error, searched over
#: [6, 14] in steps of 0.25: 2.3e-5).
KAISER_BETA = 10.0
#: The band (fraction of the Nyquist frequency) within which :data:`BANDLIMITED_ERROR` holds.
BANDLIMITED_BAND = 0.8
#: The band-limited reconstruction's largest relative error on a sinusoid within the band.
BANDLIMITED_ERROR = 3e-5


def check_hold(hold: object) -> str:
    """``hold`` if it is one of :data:`HOLDS`.

    Parameters
    ----------
    hold : str

    Returns
    -------
    str

    Raises
    ------
    OptionError
        Another value.

    Examples
    --------
    >>> check_hold("bandlimited")
    'bandlimited'
    """
    if not isinstance(hold, str) or hold not in HOLDS:
        raise OptionError(f"hold must be one of {HOLDS}; got {hold!r}.")
    return hold


def hold_code(hold: str) -> int:
    """The hold's code in the compiled kernels: 0 zoh, 1 foh and smooth, 2 bandlimited.

    Parameters
    ----------
    hold : str

    Returns
    -------
    int

    Examples
    --------
    >>> hold_code("foh")
    1
    """
    return CODES[check_hold(hold)]


def half_width(hold: str) -> int:
    """L of the hold's taps table (the table has 2L columns, taps j = −L + 1 … L).

    Parameters
    ----------
    hold : str

    Returns
    -------
    int

    Examples
    --------
    >>> half_width("zoh"), half_width("bandlimited")
    (1, 16)
    """
    return BANDLIMITED_HALF_WIDTH if check_hold(hold) == "bandlimited" else 1


def bessel_i0(x: float) -> float:
    """I₀(x), the modified Bessel function of order 0, by its power series (|x| ≤ 20).

    Parameters
    ----------
    x : float

    Returns
    -------
    float
        Σ_k ((x/2)²)ᵏ / (k!)², summed until a term falls below 1e-17 of the sum.

    Examples
    --------
    >>> import numpy as np
    >>> bool(abs(bessel_i0(10.0) / np.i0(10.0) - 1.0) < 1e-14)
    True
    """
    q = 0.25 * x * x
    term = 1.0
    total = 1.0
    k = 1
    while term > 1e-17 * total and k < 200:
        term *= q / (k * k)
        total += term
        k += 1
    return total


def hold_weights(code: int, a: float, beta: float, w: FloatArray) -> None:
    """The taps table at the fraction ``a`` of an interval, written into ``w`` (2L,).

    ``w[j + L − 1]`` weighs sample k + j (j = −L + 1 … L), L = len(w) / 2: the zero-order hold
    (code 0) puts 1 on j = 0; the first-order hold (code 1) 1 − a on j = 0 and a on j = 1; the
    band-limited one (code 2) sinc(a − j) times the Kaiser window I₀(β√(1 − ((a − j)/L)²))/I₀(β),
    scaled so that the taps sum to 1 (module docstring). Written in numba's subset of Python
    (stage 2's printed kernels include it).

    Parameters
    ----------
    code : int
        :func:`hold_code`.
    a : float
        The fraction of the interval, 0 ≤ a ≤ 1.
    beta : float
        The Kaiser window's β (read for code 2).
    w : ndarray, shape (2L,)
        Output.

    Examples
    --------
    >>> import numpy as np
    >>> w = np.empty(2)
    >>> hold_weights(1, 0.25, 0.0, w); w.tolist()
    [0.75, 0.25]
    """
    n = w.shape[0]
    L = n // 2
    for i in range(n):
        w[i] = 0.0
    if code == 0:
        w[L - 1] = 1.0
        return
    if code == 1:
        w[L - 1] = 1.0 - a
        w[L] = a
        return
    i0b = bessel_i0(beta)
    total = 0.0
    for i in range(n):
        x = a - (i - L + 1)
        if abs(x) >= L:
            continue
        s = 1.0 if x == 0.0 else math.sin(math.pi * x) / (math.pi * x)
        r = x / L
        v = s * bessel_i0(beta * math.sqrt(max(1.0 - r * r, 0.0))) / i0b
        w[i] = v
        total += v
    for i in range(n):
        w[i] /= total


def weight_table(hold: str, fractions: ArrayLike) -> FloatArray:
    """The taps tables at several fractions: row i is :func:`hold_weights` at ``fractions[i]``.

    Parameters
    ----------
    hold : str
        One of :data:`HOLDS`.
    fractions : array_like, shape (F,)
        Fractions of the interval, in [0, 1].

    Returns
    -------
    ndarray, shape (F, 2L)

    Examples
    --------
    >>> weight_table("zoh", [0.0, 0.5]).tolist()
    [[1.0, 0.0], [1.0, 0.0]]
    """
    a = np.asarray(fractions, dtype=np.float64).reshape(-1)
    code, L = hold_code(hold), half_width(hold)
    out = np.empty((a.shape[0], 2 * L))
    for i, ai in enumerate(a.tolist()):
        hold_weights(code, ai, KAISER_BETA, out[i])
    return out


def _samples(U: FloatArray, L: int) -> FloatArray:
    """U padded with L − 1 copies of its first row before and L of its last after."""
    return np.concatenate([np.repeat(U[:1], L - 1, axis=0), U, np.repeat(U[-1:], L, axis=0)])


def reconstruct(U: ArrayLike, hold: str, k: ArrayLike, a: ArrayLike) -> FloatArray:
    """The held signal at the instants t_k + a (t_{k+1} − t_k): Σ_j w_j(a) u_{k+j}.

    Parameters
    ----------
    U : array_like, shape (N, m)
        The samples.
    hold : str
        One of :data:`HOLDS`.
    k : array_like of int, shape (M,)
        The interval of each instant (0 ≤ k ≤ N − 2; N − 1: the last sample itself).
    a : array_like, shape (M,)
        The fraction of the interval, in [0, 1].

    Returns
    -------
    ndarray, shape (M, m)

    Raises
    ------
    DimensionError
        ``k`` outside the record, or ``a`` outside [0, 1].

    Examples
    --------
    >>> import numpy as np
    >>> U = np.array([[0.0], [2.0], [4.0]])
    >>> reconstruct(U, "foh", [0, 1], [0.5, 0.25]).ravel().tolist()
    [1.0, 2.5]
    """
    U_ = np.asarray(U, dtype=np.float64)
    U_ = U_.reshape(U_.shape[0], -1)
    k_ = np.asarray(k, dtype=np.int64).reshape(-1)
    a_ = np.asarray(a, dtype=np.float64).reshape(-1)
    if k_.size and (k_.min() < 0 or k_.max() >= U_.shape[0]):
        raise DimensionError(f"reconstruct: interval indices must lie in 0 … {U_.shape[0] - 1}.")
    if a_.size and not (a_.min() >= 0.0 and a_.max() <= 1.0):
        raise DimensionError("reconstruct: fractions must lie in [0, 1].")
    L = half_width(hold)
    Up = _samples(U_, L)
    W = weight_table(hold, a_)
    rows = k_[:, None] + np.arange(2 * L)[None, :]          # padded row of sample k + j
    return np.einsum("ij,ijm->im", W, Up[rows])


#: Gauss–Legendre nodes of the line fit of :func:`step_lines` (exact for the polynomial taps
#: of the zero- and first-order holds, and to 1e-12 for the band-limited ones' smooth taps).
LINE_NODES = 24


def step_lines(V: ArrayLike, hold: str) -> tuple[FloatArray, FloatArray]:
    """Per step k → k + 1, the straight line nearest the held signal: its values at both ends.

    The line ℓ(a) = α + β a minimising ∫₀¹ (v(t_k + a h) − ℓ(a))² da has the reconstruction's
    mean m and first moment μ = ∫₀¹ a v da over the step: ℓ(0) = 4m − 6μ, ℓ(1) = 6μ − 2m. For
    the zero- and first-order holds it is the reconstruction itself (ℓ = v_k; ℓ from v_k to
    v_{k+1}). A band-limited step whose taps reach a non-finite sample takes the first-order
    hold's ends (v_k, v_{k+1}; v_k when v_{k+1} is not finite).

    Parameters
    ----------
    V : array_like, shape (N, c)
        The samples (the observer's v = col(u, y); NaN marks a missing y).
    hold : str
        One of :data:`HOLDS`.

    Returns
    -------
    V0, V1 : ndarray, shape (N − 1, c)
        The line's values at the start and the end of each step.

    Examples
    --------
    >>> import numpy as np
    >>> V = np.arange(5.0)[:, None] ** 2
    >>> V0, V1 = step_lines(V, "foh")
    >>> V0[:, 0].tolist(), V1[:, 0].tolist()
    ([0.0, 1.0, 4.0, 9.0], [1.0, 4.0, 9.0, 16.0])
    """
    V_ = np.asarray(V, dtype=np.float64)
    V_ = V_.reshape(V_.shape[0], -1)
    N = V_.shape[0]
    if N < 2:
        return np.zeros((0, V_.shape[1])), np.zeros((0, V_.shape[1]))
    if check_hold(hold) != "bandlimited":          # the reconstruction is the line itself
        return V_[:-1].copy(), (V_[:-1] if hold == "zoh" else V_[1:]).copy()
    x, wq = np.polynomial.legendre.leggauss(LINE_NODES)
    a, wq = 0.5 * (x + 1.0), 0.5 * wq
    W = weight_table(hold, a)                      # (nodes, 2L)
    mean = wq @ W
    moment = (wq * a) @ W
    c0, c1 = 4.0 * mean - 6.0 * moment, 6.0 * moment - 2.0 * mean
    L = half_width(hold)
    Vp = _samples(V_, L)
    rows = np.arange(N - 1)[:, None] + np.arange(2 * L)[None, :]
    taps = Vp[rows]                                # (N − 1, 2L, c)
    V0 = np.einsum("j,kjc->kc", c0, taps)
    V1 = np.einsum("j,kjc->kc", c1, taps)
    bad = ~np.isfinite(V0) | ~np.isfinite(V1)
    if bad.any():
        end = np.where(np.isfinite(V_[1:]), V_[1:], V_[:-1])
        V0 = np.where(bad, V_[:-1], V0)
        V1 = np.where(bad, end, V1)
    return V0, V1
