"""V* computed through duality equals the direct iteration V_{i+1} = ker C ∩ A⁻¹(V_i + im B)."""

import numpy as np
import pytest

from thetahat.structure import subspaces as sub
from thetahat.testing import STRUCTURES, random_scb_system

TOL = 1e-10


def direct_v_star(A, B, C):
    """The textbook iteration, written independently of the library's dual route."""
    V = sub.null(C, TOL)
    while True:
        W = sub.orth(np.hstack([V, B]), TOL)
        N = sub.null(W.T, TOL)                       # (V + im B)^⊥
        V_next = sub.null(np.vstack([C, N.T @ A]), TOL)
        if V_next.shape[1] == V.shape[1]:
            return V_next
        V = V_next


@pytest.mark.parametrize("name", sorted(STRUCTURES))
def test_dual_v_star_equals_direct_iteration(name):
    lengths, n_a, n_b, r_b = STRUCTURES[name]
    ks = random_scb_system(np.random.default_rng(9), chain_lengths=lengths, n_a=n_a, n_b=n_b,
                           r_b=r_b)
    A, B, C = (M / np.linalg.norm(M, 2) for M in (ks.A, ks.B, ks.C))
    V1 = sub.largest_output_nulling(A, B, C, TOL)
    V2 = direct_v_star(A, B, C)
    assert V1.shape[1] == V2.shape[1] == ks.n_a
    # same subspace: the projector onto one annihilates the complement of the other
    assert np.linalg.norm(V1 - V2 @ (V2.T @ V1)) < 1e-8
