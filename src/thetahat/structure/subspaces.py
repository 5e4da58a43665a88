"""Geometric subspaces of a triple (C, A, B) with orthonormal bases (SVD).

V* — the largest output-nulling controlled-invariant subspace (computed as the orthogonal
complement of the dual S*); S_i — the nested input-containing conditioned-invariant
subspaces (S_1 = im B, S_{i+1} = A(S_i ∩ ker C) + im B) whose limit is S*. For a
left-invertible triple, dim V* = n_a (the zero dynamics), dim S* = n_q (the integrator
chains of the SCB), and dim S_i − dim S_{i−1} counts the chains of length ≥ i.

All functions take *normalised* data (‖A‖ = ‖B‖ = ‖C‖ = 1 or 0) and an absolute
singular-value tolerance ``tol`` on that data: rank decisions are relative to the data as a
whole, never to a sub-block's own norm.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def orth(M: FloatArray, tol: float) -> FloatArray:
    """Orthonormal basis of range(M): left singular vectors with σ > tol."""
    n = M.shape[0]
    if M.size == 0:
        return np.zeros((n, 0))
    U, s, _ = np.linalg.svd(M, full_matrices=False)
    return U[:, : int(np.sum(s > tol))]


def null(M: FloatArray, tol: float) -> FloatArray:
    """Orthonormal basis of ker(M): right singular vectors with σ <= tol."""
    n = M.shape[1]
    if M.shape[0] == 0 or n == 0:
        return np.eye(n)
    _, s, Vh = np.linalg.svd(M, full_matrices=True)
    rank = int(np.sum(s > tol))
    return Vh[rank:].T.copy()


def complement(Q: FloatArray, within: FloatArray | None = None, tol: float = 1e-10) -> FloatArray:
    """Orthonormal basis of the orthogonal complement of span(Q) (inside span(within)).

    Q must have orthonormal columns; then a complete QR factorisation gives the complement
    exactly and cheaply (no rank decision is needed). With ``within``, the complement of
    span(Q) inside span(within) is found by an SVD null space.
    """
    n = Q.shape[0]
    if within is not None:
        if Q.shape[1] == 0:
            return within.copy()
        return within @ null(Q.T @ within, tol)
    if Q.shape[1] == 0:
        return np.eye(n)
    Qf, _ = np.linalg.qr(Q, mode="complete")
    return Qf[:, Q.shape[1]:].copy()


def rank(M: FloatArray, tol: float) -> int:
    """Numerical rank: the number of singular values above tol."""
    if M.size == 0:
        return 0
    return int(np.sum(np.linalg.svd(M, compute_uv=False) > tol))


def largest_output_nulling(A: FloatArray, B: FloatArray, C: FloatArray,
                           tol: float) -> FloatArray:
    """Orthonormal basis of V*, the largest subspace V ⊂ ker C with A V ⊂ V + im B.

    Computed by duality, V*(C, A, B) = S*(Bᵀ, Aᵀ, Cᵀ)^⊥: the dual iteration grows from im Cᵀ
    and works on subspaces of dimension n − n_a, which is much cheaper than shrinking ker C
    when the zero dynamics are large. (The direct iteration V_0 = ker C,
    V_{i+1} = ker C ∩ A⁻¹(V_i + im B) gives the same subspace.)
    """
    S_dual = input_containing_sequence(A.T, C.T, B.T, tol)[-1]
    return complement(S_dual)


def input_containing_sequence(A: FloatArray, B: FloatArray, C: FloatArray,
                              tol: float) -> list[FloatArray]:
    """Orthonormal bases of S_1 ⊂ S_2 ⊂ … ⊂ S* (the list stops when the dimension is stable).

    S_1 = im B and S_{i+1} = A(S_i ∩ ker C) + im B. The returned list has one entry per
    distinct S_i, so ``len(result)`` is the length of the longest chain.
    """
    n = A.shape[0]
    S = orth(B, tol)
    seq = [S]
    for _ in range(n + 1):
        Z = S @ null(C @ S, tol)                                # S ∩ ker C
        S_next = orth(np.hstack([A @ Z, B]), tol)
        if S_next.shape[1] == S.shape[1]:
            return seq
        S = S_next
        seq.append(S)
    return seq  # pragma: no cover
