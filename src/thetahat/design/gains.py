"""High-gain design K(ε) in the special coordinate basis (Sec. III-A.2, III-B.2, corrigendum).

For the error system ż = A z + E δ − K C z, with the SCB (6) of (C, A, E):

    K(ε) = Γs [[K_aa, K_ab], [K_bq, K_bb], [K_qq, K_qb]] Γo⁻¹                       (7)

with K_aa = L_aq, K_ab = L_ab, K_bq = L_bq, K_bb placed once (independent of ε), K_qb = 0,
and K_qjq = K'_qjq + L_qjq where, by the corrigendum,

    K'_qjq = [0 … col(K̄_qj1/ε, …, K̄_qjn_qj/ε^n_qj) … 0]   (column j),

K̄_qj being the coefficients of the desired characteristic polynomial of H_j = A_qj − K̄_qj C_qj.
Convention (it reproduces the paper's numbers): L_qjq injects only into the non-last rows of a
chain; output terms in a chain's last row belong to D_qj and are *not* cancelled. Cancelling
them would turn the DC motor's second-observer gain ≈ [3, 0]ᵀ into ≈ [3, 1]ᵀ.

Remark 2: eig(A − K(ε)C) = eig(A_a) ∪ eig(A_b − K_bb C_b) ∪ {n_q poles with ελ → eig(H_j)}.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import warnings
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.linalg as sla
from numpy.typing import ArrayLike, NDArray

from .._validate import as_triple
from ..errors import DesignError, NonFiniteError, NotMinimumPhaseError, ThetahatWarning
from ..structure.scb import SCBResult, scb
from ..structure.zeros import unstable_zeros

FloatArray = NDArray[np.float64]
PoleSpec = None | Sequence[Sequence[complex]] | Callable[[int], Sequence[complex]]

#: Tolerance for conjugate pairing of requested poles (relative to their magnitude).
CONJ_RTOL = 1e-9
#: Smallest ε^(longest chain) accepted: the gains scale like 1/ε^L and products of gains
#: with the states must stay far from float64 overflow (1e308).
EPS_POWER_MIN = 1e-100
#: Attempts (different seeded right-hand sides) of the Sylvester pole placement.
PLACE_TRIES = 8
#: ε-scalings of the chain gains: the corrigendum's K̄_qji/ε^i (the default), or the original
#: paper's K̄_qji/ε^(n̄_q − n_qj + i), kept to show what the corrigendum fixes.
SCALINGS = ("corrigendum", "original")


@dataclass(frozen=True, slots=True, repr=False)
class GainDesign:
    """A high-gain design K(ε) and what it was built from.

    Attributes
    ----------
    K : ndarray, shape (n, r)
        Gain for ż = A z + E δ − K C z, eq. (7).
    eps : float
        ε of the design.
    chain_poles : tuple of tuple of complex
        Poles of each H_j, in chain order.
    b_poles : tuple of complex
        Poles of A_b − K_bb C_b.
    K_bar : tuple of ndarray
        K̄_qj for each chain.
    K_bb : ndarray, shape (n_b, r_b)
    K_tilde : ndarray, shape (n, r)
        The gain in SCB coordinates (χ, γ).
    scb : SCBResult
        The SCB the design used.
    eigenvalues : ndarray of complex
        eig(A − K C) of the system it was designed on, sorted.
    K_x, K_phi : ndarray or None
        For a design on the extended system (4) (``modified_high_gain``): the split
        K = [K_x; K_φ] with K_x (n_x, r) and K_φ (k, r). For a plain ``high_gain`` design,
        K_x = K and K_phi is None.
    A, C : ndarray, shapes (n, n) and (r, n)
        The system the gain was designed on (for ``modified_high_gain``: A_e and C_e of (4)).
    scaling : {"corrigendum", "original"}
        The ε-exponents of the chain gains (see :func:`high_gain`).

    Notes
    -----
    Only the chain injection K'_qj = col(K̄_qj1/ε, …, K̄_qjn/ε^n) of (7) depends on ε (by
    the corrigendum); the SCB, K̄_qj and K_bb do not. :meth:`at` therefore gives K(ε) for
    another ε from this design without a new SCB (ε sweeps, tuning).
    """

    K: FloatArray
    eps: float
    chain_poles: tuple[tuple[complex, ...], ...]
    b_poles: tuple[complex, ...]
    K_bar: tuple[FloatArray, ...]
    K_bb: FloatArray
    K_tilde: FloatArray
    scb: SCBResult
    eigenvalues: NDArray[np.complex128]
    K_x: FloatArray | None
    K_phi: FloatArray | None
    A: FloatArray
    C: FloatArray
    scaling: str = "corrigendum"

    def at(self, eps: float) -> GainDesign:
        """The same design at another ε, reusing the SCB, K̄_qj and K_bb (corrigendum).

        Parameters
        ----------
        eps : float
            0 < ε ≤ 1; larger ε warns, ε ≤ 0 raises (as in :func:`high_gain`).

        Returns
        -------
        GainDesign
            Equal to a fresh :func:`high_gain` (or :func:`modified_high_gain`) design at
            ``eps`` with the same poles; ``self`` when ``eps`` is this design's ε.

        Raises
        ------
        DesignError
            ε ≤ 0 or not a number.
        NonFiniteError
            ε is NaN or inf.

        Examples
        --------
        >>> import numpy as np
        >>> from thetahat import modified_high_gain
        >>> J, s0, a2 = 0.0023, 260.0, 0.176
        >>> A, E, C = [[-a2 / J, -s0 / J], [1, 0]], [[0], [-1]], [[1, 0]]
        >>> d05 = modified_high_gain(A, E, C, eps=1.0).at(0.5)
        >>> [round(float(v), 4) for v in d05.K.ravel()]
        [12.0, -0.0085, 12.0302]
        >>> bool(np.allclose(d05.K, modified_high_gain(A, E, C, eps=0.5).K, rtol=1e-12))
        True
        """
        e = check_eps(eps)
        if e == self.eps:
            return self
        _check_eps_power(e, self.scb.chain_lengths)
        Kt = scb_gain(self.scb, self.K_bar, self.K_bb, e,
                      corrected=self.scaling == "corrigendum")
        n_x = None if self.K_phi is None else self.K_phi.shape[0]
        return _assemble(self.scb, Kt, e, self.chain_poles, self.b_poles, self.K_bar,
                         self.K_bb, self.A, self.C, n_phi=n_x, scaling=self.scaling)

    def __repr__(self) -> str:
        K = np.array2string(self.K.ravel() if self.K.shape[1] == 1 else self.K, precision=6)
        return (f"GainDesign(eps={self.eps:g}, chains={self.scb.chain_lengths}, n_a={self.scb.n_a},"
                f" n_b={self.scb.n_b}, K={K}, max Re eig={np.max(self.eigenvalues.real):.4g})")


def extended_system(A: ArrayLike, E: ArrayLike, C: ArrayLike
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The error system (4) with K = 0: state col(x̃, φ̃), input d̃, output ỹ.

    Parameters
    ----------
    A : array_like, shape (n, n)
    E : array_like, shape (n, k)
    C : array_like, shape (r, n)
        The linear part of (1).

    Returns
    -------
    A_e : ndarray, shape (n + k, n + k)
        [[A, E], [0, 0]].
    E_e : ndarray, shape (n + k, k)
        [0; I_k].
    C_e : ndarray, shape (r, n + k)
        [C, 0].

    Examples
    --------
    >>> from thetahat import extended_system
    >>> A_e, E_e, C_e = extended_system([[0.0]], [[1.0]], [[1.0]])
    >>> A_e.tolist(), E_e.ravel().tolist(), C_e.tolist()
    ([[0.0, 1.0], [0.0, 0.0]], [0.0, 1.0], [[1.0, 0.0]])
    """
    A, E, C = as_triple(A, E, C, names=("A", "E", "C"))
    n, k = E.shape
    A_e = np.block([[A, E], [np.zeros((k, n + k))]])
    E_e = np.vstack([np.zeros((n, k)), np.eye(k)])
    C_e = np.hstack([C, np.zeros((C.shape[0], k))])
    return A_e, E_e, C_e


def check_eps(eps: object) -> float:
    """ε as a float, checked: a finite number > 0; ε > 1 warns (Sec. VII starts at ε = 1).

    Parameters
    ----------
    eps : float
        The high-gain parameter ε.

    Returns
    -------
    float

    Raises
    ------
    DesignError
        ε ≤ 0 or not a number.
    NonFiniteError
        ε is NaN or inf.

    Warns
    -----
    ThetahatWarning
        ε > 1.

    Examples
    --------
    >>> from thetahat.design.gains import check_eps
    >>> check_eps("0.5")
    0.5
    """
    try:
        e = float(eps)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise DesignError(f"eps must be a number in (0, 1]; got {eps!r}.") from exc
    if not np.isfinite(e):
        raise NonFiniteError(f"eps must be finite; got {e}.")
    if e <= 0:
        raise DesignError(f"eps must be > 0 (the gains scale like 1/eps^i); got {e}. "
                          "Start at eps = 1 and decrease (Sec. VII).")
    if e > 1:
        warnings.warn(f"eps = {e:g} > 1: the paper's design takes 0 < eps <= 1; larger eps "
                      "lowers the gain below the starting point of Sec. VII.", ThetahatWarning,
                      stacklevel=3)
    return e


def _check_poles(name: str, poles, count: int) -> tuple[complex, ...]:
    p = np.atleast_1d(np.asarray(poles, dtype=complex)).ravel()
    if p.size != count:
        raise DesignError(f"{name} needs {count} poles; got {p.size}.")
    if not np.all(np.isfinite(p)):
        raise NonFiniteError(f"{name} contains NaN or inf: {p}.")
    if np.any(p.real >= 0):
        raise DesignError(f"{name} must lie in the open left half-plane; got "
                          f"{[complex(z) for z in p[p.real >= 0]]}.")
    pos = sorted(p[p.imag > 0], key=lambda z: (z.real, z.imag))
    neg = sorted(np.conj(p[p.imag < 0]), key=lambda z: (z.real, z.imag))
    if len(pos) != len(neg) or any(abs(a - b) > CONJ_RTOL * max(1.0, abs(a))
                                   for a, b in zip(pos, neg)):
        raise DesignError(f"{name}: complex poles must come in conjugate pairs; got {p}.")
    return tuple(complex(z) for z in p)


def _resolve_chain_poles(spec: PoleSpec, lengths: tuple[int, ...]) -> tuple[tuple[complex, ...], ...]:
    if spec is None:
        return tuple(tuple(complex(-(i + 1)) for i in range(L)) for L in lengths)
    if callable(spec):
        return tuple(_check_poles(f"chain_poles({L})", spec(L), L) for L in lengths)
    spec = list(spec)
    if len(spec) != len(lengths):
        raise DesignError(f"chain_poles must give one pole list per chain; the SCB has "
                          f"{len(lengths)} chains of lengths {lengths}, got {len(spec)} lists.")
    return tuple(_check_poles(f"chain_poles[{j}]", p, L) for j, (p, L) in enumerate(zip(spec, lengths)))


def chain_coefficients(poles: Sequence[complex]) -> FloatArray:
    """K̄ = (K̄_1, …, K̄_n) with det(sI − H) = sⁿ + K̄_1 sⁿ⁻¹ + … + K̄_n for H = A_q − K̄ C_q."""
    return np.real(np.poly(np.asarray(poles, dtype=complex)))[1:]


def chain_injection(K_bar: FloatArray, eps: float) -> FloatArray:
    """col(K̄_1/ε, …, K̄_n/ε^n): the corrigendum's K'_qj for one chain."""
    return K_bar / eps ** np.arange(1, K_bar.size + 1)


def _real_block(poles: Sequence[complex]) -> FloatArray:
    """A real non-derogatory matrix with the given (conjugate-closed) eigenvalues.

    Repeated eigenvalues are chained into one Jordan-like block so that a single output can
    place them (scipy's place_poles cannot place a pole more often than rank(C)).
    """
    p = sorted(poles, key=lambda z: (round(z.real, 12), round(abs(z.imag), 12), z.imag))
    blocks = []
    for z in p:
        if z.imag > 0:
            blocks.append(np.array([[z.real, z.imag], [-z.imag, z.real]]))
        elif z.imag == 0:
            blocks.append(np.array([[z.real]]))
    n = sum(b.shape[0] for b in blocks)
    L = np.zeros((n, n))
    i = 0
    for b in blocks:
        s = b.shape[0]
        L[i:i + s, i:i + s] = b
        if i + s < n:
            L[i + s - 1, i + s] = 1.0       # couple consecutive blocks: non-derogatory
        i += s
    return L


def place_observer(A: FloatArray, C: FloatArray, poles: Sequence[complex], *,
                   seed: int = 0) -> FloatArray:
    """K with eig(A − K C) = poles, for an observable pair (C, A); repeated poles allowed.

    Sylvester method: with Λ real non-derogatory with the desired spectrum and Y random,
    solve Aᵀ X − X Λ = Cᵀ Y; then Kᵀ = Y X⁻¹ gives (Aᵀ − Cᵀ Kᵀ) X = X Λ. If eig(A) meets the
    target, a preliminary distinct placement first moves it away. The best-conditioned X of a
    few seeded tries is kept.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.design.gains import place_observer
    >>> K = place_observer(np.array([[0., 1.], [0., 0.]]), np.array([[1., 0.]]), [-2, -2])
    >>> np.round(np.linalg.eigvals(np.array([[0., 1.], [0., 0.]]) - K @ [[1., 0.]]), 6).real
    array([-2., -2.])
    """
    n = A.shape[0]
    if n == 0:
        return np.zeros((0, C.shape[0]))
    Lam = _real_block(poles)
    F, G = A.T, C.T
    H0 = np.zeros((C.shape[0], n))
    target = np.asarray(poles, complex)
    scale = max(1.0, float(np.max(np.abs(target))), float(np.linalg.norm(A, 2)))
    if np.min(np.abs(np.linalg.eigvals(A)[:, None] - target[None, :])) < 1e-6 * scale:
        from scipy.signal import place_poles
        shift = -2.0 * scale * (1.0 + np.arange(n) / max(n, 1))
        if G.shape[1] >= 1:
            H0 = place_poles(F, G, shift).gain_matrix
    F0 = F - G @ H0
    rng = np.random.default_rng(seed)
    best, best_cond = None, np.inf
    for _ in range(PLACE_TRIES):
        Y = rng.standard_normal((G.shape[1], n))
        X = sla.solve_sylvester(F0, -Lam, G @ Y)
        c = np.linalg.cond(X)
        if c < best_cond:
            best, best_cond = (X, Y), c
        if c < 1e6:
            break
    if best is None:
        raise DesignError("pole placement failed: the Sylvester equation has no solution; "
                          "try other b_poles.")
    X, Y = best
    if not np.isfinite(best_cond) or best_cond > 1e12:
        raise DesignError("pole placement failed: (C_b, A_b) looks unobservable, or the "
                          "requested b_poles cannot be reached; try other b_poles.")
    H = H0 + np.linalg.solve(X.T, Y.T).T
    return H.T


def require_minimum_phase(sc: SCBResult, A: FloatArray, what: str) -> None:
    """Raise :class:`NotMinimumPhaseError` naming the zeros when eig A_a is not Hurwitz.

    Parameters
    ----------
    sc : SCBResult
        The SCB of the triple the design is made on.
    A : ndarray, shape (n, n)
        Its A (sets the scale of the minimum-phase margin, as in ``unstable_zeros``).
    what : str
        Names the design in the message.

    Raises
    ------
    NotMinimumPhaseError
        An invariant zero in the closed right half-plane (Assumption 1 fails).
    """
    if sc.minimum_phase:
        return
    bad = unstable_zeros(sc.invariant_zeros, scale=max(1.0, float(np.linalg.norm(A, 2))))
    zs = ", ".join(f"{complex(z):.6g}" for z in bad)
    raise NotMinimumPhaseError(
        f"{what}: (C, A, E) is not minimum-phase: invariant zero(s) {zs} in the closed right "
        "half-plane, so A_a of the SCB (5)/(6) is not Hurwitz and the estimation error would "
        "grow whatever the gain (Assumption 1). Change the measured outputs or where φ "
        "enters; pass allow_nonminimum_phase=True only to study the failure.", zeros=bad)


def _check_eps_power(eps: float, lengths: Sequence[int]) -> None:
    L = max(lengths, default=1)
    if math.log(eps) * L > math.log(sys.float_info.max):       # ε^L overflows float64
        raise DesignError(f"eps = {eps:g} is too large: the gains shrink like 1/eps^{L} and "
                          f"eps^{L} overflows float64. ε is a small parameter (start at 1 and "
                          f"decrease it, Sec. VII).")
    if eps ** L < EPS_POWER_MIN:
        raise DesignError(f"eps = {eps:g} is too small: the gains grow like 1/eps^{L} (the "
                          f"longest chain) and overflow float64. Use eps >= "
                          f"{EPS_POWER_MIN ** (1 / L):.3g}; in practice ε stops helping long "
                          "before (Sec. VII).")


def high_gain(A: ArrayLike, E: ArrayLike, C: ArrayLike, eps: float, chain_poles: PoleSpec = None,
              b_poles: Sequence[complex] | None = None, *, tol: float | None = None,
              scaling: str = "corrigendum", allow_nonminimum_phase: bool = False) -> GainDesign:
    """Gain family K(ε) for ż = A z + E δ − K C z (Sec. III-A.2 / III-B.2 with the corrigendum).

    Parameters
    ----------
    A : array_like, shape (n, n)
    E : array_like, shape (n, k)
    C : array_like, shape (r, n)
        (C, A, E) must be left-invertible (Assumption 1).
    eps : float
        0 < ε ≤ 1; larger ε warns, ε ≤ 0 raises.
    chain_poles : None, list of pole lists, or callable
        Poles of each H_j = A_qj − K̄_qj C_qj. None: the paper's −1, −2, …, −n_qj for each
        chain; a list: one list per chain in the SCB's chain order (ascending length); a
        callable: n_qj → poles.
    b_poles : sequence of complex, optional
        The n_b poles of A_b − K_bb C_b (repeated poles allowed). Default −1, −2, …, −n_b.
    tol : float, optional
        Rank tolerance of the SCB.
    scaling : {"corrigendum", "original"}
        The ε-exponents of the chain gains: the corrigendum's K̄_qji/ε^i (default), or the
        original paper's K̄_qji/ε^(n̄_q − n_qj + i). They differ only for chains shorter than
        the longest (MIMO systems of non-uniform rank), where "original" breaks Remark 2;
        it is kept to show that in tests and examples, not for use.
    allow_nonminimum_phase : bool, default False
        Design even when (C, A, E) has zeros in the closed right half-plane (the error
        dynamics are then unstable; only for studying the failure).

    Returns
    -------
    GainDesign

    Raises
    ------
    DesignError
        ε ≤ 0, ε so small that the gains overflow, poles not in the open left half-plane,
        wrong number of poles, unknown scaling.
    NotLeftInvertibleError
        (C, A, E) not left-invertible.
    NotMinimumPhaseError
        (C, A, E) not minimum-phase (unless ``allow_nonminimum_phase``); ``.zeros`` holds the
        offending zeros.

    Examples
    --------
    The second observer of Sec. VIII (DC motor design system, σ1 = 0), poles −1, −2:

    >>> import numpy as np
    >>> from thetahat import high_gain
    >>> J, s0, a2 = 0.0023, 260.0, 0.176
    >>> A = [[-a2 / J, -s0 / J], [1, 0]]; E = [[0], [-1]]; C = [[1, 0]]
    >>> [round(float(v), 5) for v in high_gain(A, E, C, eps=1.0).K.ravel()]
    [3.0, -0.00205]
    """
    A, E, C = as_triple(A, E, C, names=("A", "E", "C"))
    eps = check_eps(eps)
    if scaling not in SCALINGS:
        raise DesignError(f"scaling must be one of {SCALINGS}; got {scaling!r}.")
    sc = scb(A, E, C, tol=tol)
    if not allow_nonminimum_phase:
        require_minimum_phase(sc, A, "high-gain design")
    lengths = sc.chain_lengths
    _check_eps_power(eps, lengths)
    cpoles = _resolve_chain_poles(chain_poles, lengths)
    if b_poles is None:
        bp = tuple(complex(-(i + 1)) for i in range(sc.n_b))
    else:
        bp = _check_poles("b_poles", b_poles, sc.n_b)
    K_bb = place_observer(sc.A_b, sc.C_b, bp) if sc.n_b else np.zeros((0, sc.r_b))
    K_bars = tuple(chain_coefficients(p) for p in cpoles)
    Kt = scb_gain(sc, K_bars, K_bb, eps, corrected=scaling == "corrigendum")
    return _assemble(sc, Kt, eps, cpoles, bp, K_bars, K_bb, A, C, n_phi=None, scaling=scaling)


def _assemble(sc: SCBResult, Kt: FloatArray, eps: float,
              cpoles: tuple[tuple[complex, ...], ...], bp: tuple[complex, ...],
              K_bars: tuple[FloatArray, ...], K_bb: FloatArray, A: FloatArray, C: FloatArray,
              *, n_phi: int | None, scaling: str) -> GainDesign:
    """K = Γs K̃ Γo⁻¹ (7), the closed-loop spectrum, and the [K_x; K_φ] split when n_phi."""
    K = sc.state_transform @ Kt @ np.linalg.solve(sc.output_transform, np.eye(C.shape[0]))
    eig = np.sort_complex(np.linalg.eigvals(A - K @ C)).astype(np.complex128)
    if n_phi is None:
        K_x, K_phi = K, None
    else:
        n = K.shape[0] - n_phi
        K_x, K_phi = K[:n].copy(), K[n:].copy()
    return GainDesign(K=K, eps=eps, chain_poles=cpoles, b_poles=bp, K_bar=K_bars, K_bb=K_bb,
                      K_tilde=Kt, scb=sc, eigenvalues=eig, K_x=K_x, K_phi=K_phi, A=A, C=C,
                      scaling=scaling)


def scb_gain(sc: SCBResult, K_bars: Sequence[FloatArray], K_bb: FloatArray, eps: float, *,
             corrected: bool = True) -> FloatArray:
    """The gain K̃ of (7) in SCB coordinates, rows (χ_a, χ_b, χ_q), columns (γ_q, γ_b).

    Only the chain injection K'_qj = col(K̄_qj1/ε, …, K̄_qjn/ε^n) depends on ε.

    Parameters
    ----------
    sc : SCBResult
        The SCB (6) of the triple the gain is designed for.
    K_bars : sequence of ndarray
        K̄_qj for each chain (:func:`chain_coefficients`), in the SCB's chain order.
    K_bb : ndarray, shape (n_b, r_b)
        Gain placing eig(A_b − K_bb C_b).
    eps : float
        ε > 0.
    corrected : bool, optional
        True (default): the corrigendum's exponents ε^i. False: the uncorrected exponents of
        the original paper (ε^(n̄_q − n_qj + i)), to show in tests why the corrigendum matters.

    Returns
    -------
    ndarray, shape (n, r)
        K̃ with K = Γs K̃ Γo⁻¹.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.design.gains import chain_coefficients, scb_gain
    >>> from thetahat.structure.scb import scb
    >>> sc = scb(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]),
    ...          np.array([[1.0, 0.0]]))
    >>> K_bar = chain_coefficients([-1.0, -2.0])
    >>> scb_gain(sc, [K_bar], np.zeros((0, 0)), 0.5).ravel().tolist()
    [6.0, 8.0]
    """
    n_a, n_b, k = sc.n_a, sc.n_b, sc.k
    n, r = sc.A_tilde.shape[0], sc.C_tilde.shape[0]
    Kt = np.zeros((n, r))
    Kt[:n_a, :k] = sc.L_aq
    Kt[:n_a, k:] = sc.L_ab
    Kt[n_a:n_a + n_b, :k] = sc.L_bq
    Kt[n_a:n_a + n_b, k:] = K_bb
    Kt[n_a + n_b:, :k] = sc.L_qq
    nbar = max(sc.chain_lengths)
    for j, (sl, Kb) in enumerate(zip(sc.chain_slices(), K_bars)):
        if corrected:
            Kt[sl, j] += chain_injection(Kb, eps)
        else:
            L = Kb.size
            Kt[sl, j] += Kb / eps ** (nbar - L + np.arange(1, L + 1))
    return Kt


def modified_high_gain(A: ArrayLike, E: ArrayLike, C: ArrayLike, eps: float, chain_poles: PoleSpec = None,
                       b_poles: Sequence[complex] | None = None, *,
                       tol: float | None = None, scaling: str = "corrigendum",
                       allow_nonminimum_phase: bool = False) -> GainDesign:
    """Gains K(ε) = [K_x; K_φ] of the modified high-gain observer (3), designed on (4).

    The error system (4) with K = 0 is (C_e, A_e, E_e) = ``extended_system(A, E, C)``; by
    Lemma 1 it is left-invertible and minimum-phase when (C, A, E) is.

    Parameters
    ----------
    A, E, C : array_like
        The linear part of (1), or of a simplified design system (Sec. VII–VIII).
    eps, chain_poles, b_poles, tol, scaling, allow_nonminimum_phase
        As in :func:`high_gain`.

    Returns
    -------
    GainDesign
        With ``K_x`` (n, r) and ``K_phi`` (k, r) set.

    Examples
    --------
    The first observer of Sec. VIII (σ1 = 0 design system, poles −1, −2, −3, ε = 1):

    >>> import numpy as np
    >>> from thetahat import modified_high_gain
    >>> J, s0, a2 = 0.0023, 260.0, 0.176
    >>> d = modified_high_gain([[-a2 / J, -s0 / J], [1, 0]], [[0], [-1]], [[1, 0]], eps=1.0)
    >>> [round(float(v), 4) for v in d.K.ravel()]
    [6.0, -0.0042, 6.0075]
    """
    A_, E_, C_ = as_triple(A, E, C, names=("A", "E", "C"))
    n = A_.shape[0]
    d = high_gain(*extended_system(A_, E_, C_), eps, chain_poles, b_poles, tol=tol,
                  scaling=scaling, allow_nonminimum_phase=allow_nonminimum_phase)
    return dataclasses.replace(d, K_x=d.K[:n].copy(), K_phi=d.K[n:].copy())
