"""Random systems with a known special coordinate basis, for tests and benchmarks.

A system is built directly in the form (6) — zero dynamics with chosen zeros, an observable
(C_b, A_b) block, integrator chains of chosen lengths, random couplings where (6) allows
them — and then hidden behind random, well-conditioned state, output and input changes of
coordinates. Its structure is therefore known by construction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from .errors import DimensionError

FloatArray = NDArray[np.float64]

#: Structures the tests exercise (SISO, square MIMO uniform / non-uniform, non-square with χ_b):
#: name → (chain_lengths, n_a, n_b, r_b).
STRUCTURES = {
    "siso_rd1_zeros": ((1,), 2, 0, 0),
    "siso_rd3": ((3,), 0, 0, 0),
    "siso_rd2_zero": ((2,), 1, 0, 0),
    "mimo_uniform": ((2, 2), 1, 0, 0),
    "mimo_nonuniform_1_3": ((1, 3), 2, 0, 0),
    "nonsquare_b_block": ((2,), 1, 2, 1),
    "nonsquare_mixed": ((1, 3), 1, 3, 2),
}


@dataclass(frozen=True, slots=True)
class KnownStructure:
    """A random triple and the structure it was built with.

    Attributes
    ----------
    A, B, C : ndarray
        The triple (C, A, B) in original coordinates.
    n_a, n_b : int
    chain_lengths : tuple of int
        Sorted ascending (the order ``scb`` reports).
    zeros : ndarray of complex
        The invariant zeros (eig of the constructed A_a), sorted.
    condition : float
        cond of the state transform used in the construction.
    """

    A: FloatArray
    B: FloatArray
    C: FloatArray
    n_a: int
    n_b: int
    chain_lengths: tuple[int, ...]
    zeros: NDArray[np.complex128]
    condition: float


def well_conditioned(rng: np.random.Generator, n: int, cond: float = 10.0) -> FloatArray:
    """A random n×n matrix U diag(σ) Vᵀ with singular values spread in [1, cond]."""
    if n == 0:
        return np.zeros((0, 0))
    U, _ = np.linalg.qr(rng.standard_normal((n, n)))
    V, _ = np.linalg.qr(rng.standard_normal((n, n)))
    s = np.geomspace(1.0, cond, n) if n > 1 else np.ones(1)
    return (U * s) @ V.T


def _stable_block(rng: np.random.Generator, zeros: Sequence[complex]) -> FloatArray:
    """A real matrix with the given eigenvalues (complex ones in conjugate pairs)."""
    blocks, used = [], set()
    zs = list(zeros)
    for i, z in enumerate(zs):
        if i in used:
            continue
        if abs(complex(z).imag) > 0:
            j = next(j for j in range(i + 1, len(zs)) if j not in used
                     and abs(complex(zs[j]) - complex(z).conjugate()) < 1e-12)
            used.add(j)
            a, b = complex(z).real, complex(z).imag
            blocks.append(np.array([[a, b], [-b, a]]))
        else:
            blocks.append(np.array([[complex(z).real]]))
    if not blocks:
        return np.zeros((0, 0))
    D = np.zeros((len(zs), len(zs)))
    i = 0
    for blk in blocks:
        s = blk.shape[0]
        D[i:i + s, i:i + s] = blk
        i += s
    V = well_conditioned(rng, len(zs), 3.0)
    return V @ D @ np.linalg.inv(V)


def random_scb_system(rng: np.random.Generator, *, chain_lengths: Sequence[int],
                      n_a: int = 0, n_b: int = 0, r_b: int = 0,
                      zeros: Sequence[complex] | None = None,
                      cond: float = 10.0, coupling: float = 1.0) -> KnownStructure:
    """A random left-invertible triple with prescribed structure.

    Parameters
    ----------
    rng : numpy.random.Generator
    chain_lengths : sequence of int
        Lengths n_qj ≥ 1 of the k integrator chains.
    n_a : int
        Number of invariant zeros (random stable ones unless ``zeros`` is given).
    n_b, r_b : int
        Size of the χ_b block and number of extra outputs γ_b (r = k + r_b); needs
        0 < r_b <= n_b or r_b = n_b = 0.
    zeros : sequence of complex, optional
        The invariant zeros (length n_a; conjugate pairs for complex ones).
    cond : float
        Condition number of the random state transform (output and input transforms use 3).
    coupling : float
        Scale of the random couplings that (6) allows.

    Examples
    --------
    >>> import numpy as np
    >>> from thetahat.testing import random_scb_system
    >>> sys = random_scb_system(np.random.default_rng(0), chain_lengths=(1, 3), n_a=2)
    >>> sys.A.shape, sys.B.shape, sys.C.shape
    ((6, 6), (6, 2), (2, 6))
    """
    lengths = [int(L) for L in chain_lengths]
    if any(L < 1 for L in lengths) or not lengths:
        raise DimensionError("chain_lengths must be a non-empty sequence of positive integers")
    if r_b > n_b:
        raise DimensionError(f"r_b = {r_b} extra outputs need n_b >= r_b states (C must have "
                         "full row rank)")
    if n_b > 0 and r_b == 0:
        raise DimensionError("an n_b > 0 block needs r_b > 0 outputs to be observable")
    k, n_q = len(lengths), sum(lengths)
    n, r = n_a + n_b + n_q, k + r_b
    if zeros is None:
        zeros = -rng.uniform(0.5, 3.0, n_a)
    zeros = np.asarray(zeros, dtype=complex)
    if zeros.size != n_a:
        raise DimensionError(f"zeros must have length n_a = {n_a}")
    c = coupling
    At = np.zeros((n, n))
    ia, ib = slice(0, n_a), slice(n_a, n_a + n_b)
    starts = n_a + n_b + np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(int)
    tops, lasts = starts, starts + np.array(lengths) - 1
    At[ia, ia] = _stable_block(rng, zeros)
    A_b = rng.standard_normal((n_b, n_b))
    C_b = rng.standard_normal((r_b, n_b))
    At[ib, ib] = A_b
    At[ia, ib] = c * rng.standard_normal((n_a, r_b)) @ C_b
    At[np.ix_(range(n_a), tops)] = c * rng.standard_normal((n_a, k))
    At[np.ix_(range(n_a, n_a + n_b), tops)] = c * rng.standard_normal((n_b, k))
    for s, L in zip(starts, lengths):
        for i in range(L - 1):
            At[s + i, s + i + 1] = 1.0
            At[np.ix_([s + i], tops)] = c * rng.standard_normal((1, k))
    At[lasts, :] = c * rng.standard_normal((k, n))
    Bt = np.zeros((n, k))
    Bt[lasts, np.arange(k)] = 1.0
    Ct = np.zeros((r, n))
    Ct[np.arange(k), tops] = 1.0
    Ct[k:, ib] = C_b
    Gs = well_conditioned(rng, n, cond)
    Go = well_conditioned(rng, r, 3.0)
    Gi = well_conditioned(rng, k, 3.0)
    Gs_inv = np.linalg.inv(Gs)
    A = Gs @ At @ Gs_inv
    B = Gs @ Bt @ np.linalg.inv(Gi)
    C = Go @ Ct @ Gs_inv
    return KnownStructure(A=A, B=B, C=C, n_a=n_a, n_b=n_b,
                          chain_lengths=tuple(sorted(lengths)),
                          zeros=np.sort_complex(zeros), condition=float(np.linalg.cond(Gs)))
