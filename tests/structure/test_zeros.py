"""Tests of thetahat.structure.zeros: invariant zeros, normal rank, left-invertibility, phase.

Every expected answer comes from an independent route: numerator roots of a transfer function
realised by hand, a determinant computed exactly with SymPy, eig(A - B D^-1 C) for an invertible
D, ranks of P(s) at random points, or SLICOT's AB08ND through slycot.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import sympy
from scipy.optimize import linear_sum_assignment

from thetahat.errors import DimensionError, NonFiniteError
from thetahat.structure.zeros import (
    MINIMUM_PHASE_RTOL,
    invariant_zeros,
    is_left_invertible,
    is_minimum_phase,
    normal_rank,
    unstable_zeros,
)

#: Simple, well-conditioned zeros of small systems are accurate to a few hundred eps relative to
#: max(1, |z|, ||A||); 1e-9 leaves margin for the companion matrices below (||A|| up to ~200).
SIMPLE_ZERO_RTOL = 1e-9
#: A double zero is only determined to about sqrt(eps) ~ 1.5e-8 times the data scale; the
#: companion matrix of the double-zero example has norm ~ 1e2, so allow 1e-6.
DOUBLE_ZERO_ATOL = 1e-6
#: The mean of a cluster of zeros is well-conditioned even when each member is not.
CLUSTER_MEAN_ATOL = 1e-9
#: Random systems (and random transforms of known ones) can have moderately ill-conditioned
#: zeros: relative agreement to 1e-6 still rules out any wrong zero or a missing one.
RANDOM_ZERO_RTOL = 1e-6


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------

def ccf(num_roots, den_roots, gain=1.0):
    """Controllable canonical form of gain * prod(s - z) / prod(s - p), deg num < deg den.

    With x = [1, s, ..., s^(n-1)]^T u / a(s) we get x_n' = -a_0 x_1 - ... + u and
    y = b_0 x_1 + ... + b_(n-1) x_n = b(s) u / a(s): A is the companion matrix, B = e_n, and
    C holds the numerator coefficients in ascending order.
    """
    a = np.real(np.poly(den_roots))  # monic, descending
    b = gain * np.real(np.poly(num_roots)) if len(num_roots) else np.array([gain])
    n = len(a) - 1
    A = np.zeros((n, n))
    A[:-1, 1:] = np.eye(n - 1)
    A[-1, :] = -a[::-1][:-1]
    B = np.zeros((n, 1))
    B[-1, 0] = 1.0
    C = np.zeros((1, n))
    C[0, : len(b)] = b[::-1]
    return A, B, C


def match_error(z, expected, scale=1.0):
    """Max matched distance between two zero sets relative to max(scale, |expected|)."""
    z, expected = np.asarray(z, complex), np.asarray(expected, complex)
    assert z.shape == expected.shape, f"got {z.size} zeros {z}, expected {expected}"
    if z.size == 0:
        return 0.0
    cost = np.abs(z[:, None] - expected[None, :])
    rows, cols = linear_sum_assignment(cost)
    return float(np.max(cost[rows, cols] / np.maximum(scale, np.abs(expected[cols]))))


def rosenbrock(A, B, C, D, s):
    n = A.shape[0]
    return np.block([[s * np.eye(n) - A, -B], [C, D]])


def rank_at_random_points(A, B, C, D, rng, count=3):
    """Normal rank, independently: max rank of P(s) over random complex s with |s| ~ ||A||."""
    radius = max(1.0, np.linalg.norm(A, 2))
    ranks = []
    for _ in range(count):
        s = radius * (rng.standard_normal() + 1j * rng.standard_normal())
        ranks.append(np.linalg.matrix_rank(rosenbrock(A, B, C, D, s)))
    return max(ranks)


def well_conditioned(rng, n):
    """A random invertible matrix with condition number <= 10 (singular values in [1, 10])."""
    U, _ = np.linalg.qr(rng.standard_normal((n, n)))
    V, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return U @ np.diag(np.linspace(1.0, 10.0, n)) @ V.T


def slycot_zeros(slycot, A, B, C, D):
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    out = slycot.ab08nd(n, m, p, A, B, C, D, ldwork=max(1, 8 * (n + m + p) ** 2))
    nu, rank, Af, Bf = out[0], out[1], out[-2], out[-1]
    z = scipy.linalg.eigvals(Af[:nu, :nu], Bf[:nu, :nu]) if nu else np.zeros(0, complex)
    return z, n + rank


# ------------------------------------------------------------------------------------------
# SISO systems with known numerators
# ------------------------------------------------------------------------------------------

SISO_CASES = [
    # (numerator roots, denominator roots); relative degree = len(den) - len(num)
    ([], [-1.0, -2.0, -3.0]),                       # relative degree 3, no zeros
    ([-5.0], [-1.0, -2.0, -3.0]),                   # relative degree 2
    ([-1 + 2j, -1 - 2j], [-1.0, -2.0, -3.0]),       # relative degree 1, complex pair
    ([-0.5, -7.0], [-1.0, -2.0, -3.0, -4.0]),       # relative degree 2
    ([-4.0], [-1.0, -2.0]),                         # relative degree 1
    ([], [-1.0, -1 + 1j, -1 - 1j, -2.0]),           # relative degree 4, no zeros
]


@pytest.mark.parametrize("num, den", SISO_CASES)
def test_siso_zeros_are_numerator_roots(num, den):
    A, B, C = ccf(num, den)
    z = invariant_zeros(A, B, C)
    assert match_error(z, num, scale=np.linalg.norm(A, 2)) < SIMPLE_ZERO_RTOL
    assert is_left_invertible(A, B, C)
    assert is_minimum_phase(A, B, C)


def test_non_minimum_phase_zero():
    A, B, C = ccf([2.0, -3.0], [-1.0, -2.0, -4.0])
    z = invariant_zeros(A, B, C)
    assert match_error(z, [-3.0, 2.0]) < SIMPLE_ZERO_RTOL
    assert not is_minimum_phase(A, B, C)
    bad = unstable_zeros(z, scale=max(1.0, np.linalg.norm(A, 2)))
    assert match_error(bad, [2.0]) < SIMPLE_ZERO_RTOL


def test_zero_at_origin_is_not_minimum_phase():
    # G = s (s + 3) / ((s + 1)(s + 2)(s + 5)): the zero at 0 computes as +-O(eps), either sign.
    A, B, C = ccf([0.0, -3.0], [-1.0, -2.0, -5.0])
    z = invariant_zeros(A, B, C)
    assert match_error(z, [-3.0, 0.0], scale=10.0) < SIMPLE_ZERO_RTOL
    assert not is_minimum_phase(A, B, C)


def test_zeros_are_sorted_by_real_then_imaginary_part():
    A, B, C = ccf([-1 + 2j, -1 - 2j, -3.0, 0.5], [-1.0, -2.0, -4.0, -5.0, -6.0])
    z = invariant_zeros(A, B, C)
    keys = list(zip(z.real, z.imag))
    assert keys == sorted(keys)
    assert z.dtype == np.complex128 and z.ndim == 1


def test_double_zero_to_sqrt_eps():
    # (s + 2)^2 / ((s + 1)(s + 3)(s + 4)(s + 5)): a double zero at -2 splits by ~ sqrt(eps).
    A, B, C = ccf([-2.0, -2.0], [-1.0, -3.0, -4.0, -5.0])
    z = invariant_zeros(A, B, C)
    assert z.size == 2
    assert np.max(np.abs(z + 2.0)) < DOUBLE_ZERO_ATOL
    assert abs(np.mean(z) + 2.0) < CLUSTER_MEAN_ATOL


# ------------------------------------------------------------------------------------------
# decoupling zeros (Rosenbrock definition)
# ------------------------------------------------------------------------------------------

def test_unobservable_mode_is_a_zero():
    # Modes -1, -2 observable, 3 unobservable: G = 1/(s+1) + 1/(s+2) = (2s + 3)/((s+1)(s+2)),
    # so the transmission zero is -1.5 and the output decoupling zero is 3.
    A = np.diag([-1.0, -2.0, 3.0])
    B = np.ones((3, 1))
    C = np.array([[1.0, 1.0, 0.0]])
    assert match_error(invariant_zeros(A, B, C), [-1.5, 3.0]) < SIMPLE_ZERO_RTOL
    assert not is_minimum_phase(A, B, C)


def test_uncontrollable_mode_is_a_zero():
    # The dual of the previous system: the input decoupling zero 3 and the zero -1.5.
    A = np.diag([-1.0, -2.0, 3.0])
    B = np.array([[1.0], [1.0], [0.0]])
    C = np.ones((1, 3))
    assert match_error(invariant_zeros(A, B, C), [-1.5, 3.0]) < SIMPLE_ZERO_RTOL


def test_input_output_decoupling_zero_counts_once():
    # P(s) = blockdiag(P_12(s), s - 5) for the mode 5 that is neither driven nor seen.
    A = np.diag([-1.0, -2.0, 5.0])
    B = np.array([[1.0], [1.0], [0.0]])
    C = np.array([[1.0, 1.0, 0.0]])
    assert match_error(invariant_zeros(A, B, C), [-1.5, 5.0]) < SIMPLE_ZERO_RTOL


def test_decoupling_zero_hidden_by_similarity(rng):
    A = np.diag([-1.0, -2.0, 3.0])
    B = np.ones((3, 1))
    C = np.array([[1.0, 1.0, 0.0]])
    T = well_conditioned(rng, 3)
    At, Bt, Ct = np.linalg.solve(T, A @ T), np.linalg.solve(T, B), C @ T
    assert match_error(invariant_zeros(At, Bt, Ct), [-1.5, 3.0], scale=10.0) < RANDOM_ZERO_RTOL


def test_no_inputs_zeros_are_unobservable_modes():
    A = np.diag([-1.0, 2.0])
    C = np.array([[1.0, 0.0]])
    z = invariant_zeros(A, np.zeros((2, 0)), C)
    assert match_error(z, [2.0]) < SIMPLE_ZERO_RTOL
    assert normal_rank(A, np.zeros((2, 0)), C) == 2


# ------------------------------------------------------------------------------------------
# MIMO: square, tall, wide, D != 0
# ------------------------------------------------------------------------------------------

def exact_square_zeros(A, B, C, D):
    """Roots of det P(s), computed exactly with SymPy from integer data."""
    s = sympy.symbols("s")
    n = A.shape[0]
    to_sym = lambda M: sympy.Matrix(M.astype(int).tolist())  # noqa: E731
    P = sympy.Matrix(sympy.BlockMatrix([[s * sympy.eye(n) - to_sym(A), -to_sym(B)],
                                        [to_sym(C), to_sym(D)]]))
    det = sympy.Poly(sympy.expand(P.det()), s)
    assert not det.is_zero
    return np.roots(np.array(det.all_coeffs(), dtype=float)).astype(complex)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_square_mimo_matches_exact_determinant(seed):
    gen = np.random.default_rng(seed)
    n, m = 4, 2
    A = gen.integers(-3, 4, (n, n)).astype(float)
    B = gen.integers(-2, 3, (n, m)).astype(float)
    C = gen.integers(-2, 3, (m, n)).astype(float)
    D = np.zeros((m, m))
    expected = exact_square_zeros(A, B, C, D)
    z = invariant_zeros(A, B, C)
    assert match_error(z, expected, scale=np.linalg.norm(A, 2)) < RANDOM_ZERO_RTOL
    assert is_left_invertible(A, B, C)


def test_square_mimo_invertible_d_equals_closed_loop_eigenvalues(rng):
    # With D invertible, P(s) loses rank exactly at eig(A - B D^-1 C) (Schur complement on D).
    n, m = 5, 3
    A, B, C = rng.standard_normal((n, n)), rng.standard_normal((n, m)), rng.standard_normal((m, n))
    D = well_conditioned(rng, m)
    expected = np.linalg.eigvals(A - B @ np.linalg.solve(D, C))
    assert match_error(invariant_zeros(A, B, C, D), expected, scale=10.0) < RANDOM_ZERO_RTOL


def test_siso_feedthrough_zero():
    # G = 1/(s + 1) + 1/2 = (s + 3) / (2 (s + 1)): zero at -3.
    z = invariant_zeros([[-1.0]], [[1.0]], [[1.0]], [[0.5]])
    assert match_error(z, [-3.0]) < SIMPLE_ZERO_RTOL


def test_block_diagonal_mimo_zeros_are_the_union():
    A1, B1, C1 = ccf([-5.0], [-1.0, -2.0, -3.0])
    A2, B2, C2 = ccf([1.0, -0.5], [-1.0, -4.0, -6.0])
    Z = np.zeros
    A = np.block([[A1, Z((3, 3))], [Z((3, 3)), A2]])
    B = np.block([[B1, Z((3, 1))], [Z((3, 1)), B2]])
    C = np.block([[C1, Z((1, 3))], [Z((1, 3)), C2]])
    assert match_error(invariant_zeros(A, B, C), [-5.0, 1.0, -0.5]) < SIMPLE_ZERO_RTOL
    assert is_left_invertible(A, B, C)
    assert not is_minimum_phase(A, B, C)


def common_factor_tall():
    # x = [1, s, s^2]^T u / a(s), a = (s+1)(s+2)(s+3); y1 = (s-1)(s+3) u/a, y2 = (s-1)(s+1) u/a.
    # A null vector [x; u] of P(s) needs C x = 0, i.e. both numerators zero: only s = 1.
    A, B, _ = ccf([], [-1.0, -2.0, -3.0])
    C = np.array([[-3.0, 2.0, 1.0], [-1.0, 0.0, 1.0]])
    return A, B, C


def test_tall_system_with_common_zero():
    A, B, C = common_factor_tall()
    assert match_error(invariant_zeros(A, B, C), [1.0]) < SIMPLE_ZERO_RTOL
    assert is_left_invertible(A, B, C)
    assert normal_rank(A, B, C) == 4
    assert not is_minimum_phase(A, B, C)


def test_wide_system_is_dual_of_tall():
    # P_dual(s) is P(s)^T up to signs: same zeros, but normal rank n + 1 < n + m = 5.
    A, B, C = common_factor_tall()
    assert match_error(invariant_zeros(A.T, C.T, B.T), [1.0]) < SIMPLE_ZERO_RTOL
    assert normal_rank(A.T, C.T, B.T) == 4
    assert not is_left_invertible(A.T, C.T, B.T)


def test_random_tall_and_wide_have_no_zeros(rng):
    # A generic non-square system has no invariant zeros.
    for n, m, r in [(4, 1, 2), (5, 2, 3), (4, 3, 1), (6, 2, 1)]:
        A, B = rng.standard_normal((n, n)), rng.standard_normal((n, m))
        C = rng.standard_normal((r, n))
        assert invariant_zeros(A, B, C).size == 0
        assert normal_rank(A, B, C) == n + min(m, r)


# ------------------------------------------------------------------------------------------
# left-invertibility and the normal rank
# ------------------------------------------------------------------------------------------

def test_rank_deficient_b_is_not_left_invertible(rng):
    A = rng.standard_normal((3, 3))
    b = rng.standard_normal((3, 1))
    B = np.hstack([b, 2.0 * b])
    C = rng.standard_normal((2, 3))
    assert not is_left_invertible(A, B, C)
    assert normal_rank(A, B, C) == 4 == rank_at_random_points(A, B, C, np.zeros((2, 2)), rng)


def test_inputs_acting_identically_on_outputs_is_not_left_invertible(rng):
    # b1 and b2 differ only in the unobservable state 3, so G(s) has two equal columns
    # [1/(s+1), 1/(s+2)]^T although B has full column rank.
    A = np.diag([-1.0, -2.0, -3.0])
    B = np.array([[1.0, 1.0], [1.0, 1.0], [0.0, 1.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.linalg.matrix_rank(B) == 2
    assert not is_left_invertible(A, B, C)
    assert normal_rank(A, B, C) == 4 == rank_at_random_points(A, B, C, np.zeros((2, 2)), rng)


@pytest.mark.parametrize("n, m, r, b_rank, d_rank", [
    (4, 2, 2, 2, 0), (4, 2, 2, 1, 0), (5, 3, 2, 3, 1), (3, 1, 3, 1, 1), (6, 3, 3, 2, 2),
    (2, 2, 2, 2, 2), (5, 2, 4, 1, 1),
])
def test_normal_rank_matches_rank_at_random_points(n, m, r, b_rank, d_rank):
    gen = np.random.default_rng(1000 * n + 100 * m + 10 * r + b_rank)
    A, C = gen.standard_normal((n, n)), gen.standard_normal((r, n))
    B = gen.standard_normal((n, b_rank)) @ gen.standard_normal((b_rank, m))
    D = gen.standard_normal((r, d_rank)) @ gen.standard_normal((d_rank, m))
    rank = normal_rank(A, B, C, D)
    assert rank == rank_at_random_points(A, B, C, D, gen)
    assert is_left_invertible(A, B, C, D) == (rank == n + m)


# ------------------------------------------------------------------------------------------
# invariance and scaling
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(4))
def test_zeros_invariant_under_state_input_output_transforms(seed):
    gen = np.random.default_rng(100 + seed)
    A1, B1, C1 = ccf([-0.7, 2.0], [-1.0, -2.0, -3.0, -4.0])
    A2, B2, C2 = ccf([-1 + 1j, -1 - 1j], [-0.5, -2.5, -3.5, -6.0])
    Z = np.zeros
    A = np.block([[A1, Z((4, 4))], [Z((4, 4)), A2]])
    B = np.block([[B1, Z((4, 1))], [Z((4, 1)), B2]])
    C = np.block([[C1, Z((1, 4))], [Z((1, 4)), C2]])
    T, Q, R = well_conditioned(gen, 8), well_conditioned(gen, 2), well_conditioned(gen, 2)
    At, Bt, Ct = np.linalg.solve(T, A @ T), np.linalg.solve(T, B @ Q), R @ C @ T
    z0 = invariant_zeros(A, B, C)
    assert match_error(z0, [-0.7, 2.0, -1 + 1j, -1 - 1j]) < SIMPLE_ZERO_RTOL
    assert match_error(invariant_zeros(At, Bt, Ct), z0, scale=10.0) < RANDOM_ZERO_RTOL


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("b_scale", [1.0, 1e3])
def test_structurally_zero_markov_parameters_after_rotation(seed, b_scale):
    # Relative degree 3: C B = C A B = 0 exactly, but only to ~1e-13 after an orthogonal
    # similarity (||A|| ~ 3e3). The rank decisions must not see them as nonzero: exactly the
    # 3 numerator roots, no spurious zero near 1e13. (SLICOT AB08ND with its default tolerance
    # reports such a spurious zero for some of these rotations when B is scaled by 1e3.)
    num = [-1.0, -2.5, -0.3]
    A, B, C = ccf(num, [-1.5, -2.0, -3.0, -4.0, -5.0, -6.0])
    Q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((6, 6)))
    At, Bt, Ct = Q.T @ A @ Q, b_scale * (Q.T @ B), C @ Q
    z = invariant_zeros(At, Bt, Ct)
    assert match_error(z, num, scale=np.linalg.norm(A, 2)) < RANDOM_ZERO_RTOL


@pytest.mark.parametrize("seed", range(3))
def test_rotated_dc_motor_design_system_keeps_relative_degree_three(seed):
    # sigma1 = 0, ||A_e|| ~ 1.1e5: C E = C A E = 0 hold only to rounding after the rotation.
    A_e, E_e, C_e = dc_motor_error_system(0.0)
    Q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    assert invariant_zeros(Q.T @ A_e @ Q, Q.T @ E_e, C_e @ Q).size == 0
    A_e, E_e, C_e = dc_motor_error_system(0.6)
    z = invariant_zeros(Q.T @ A_e @ Q, Q.T @ E_e, C_e @ Q)
    assert match_error(z, [-260.0 / 0.6]) < RANDOM_ZERO_RTOL


def test_badly_scaled_input_and_output_do_not_change_zeros():
    A, B, C = ccf([-5.0, 1.0], [-1.0, -2.0, -3.0, -4.0])
    for b_scale, c_scale in [(1e-8, 1.0), (1.0, 1e8), (1e7, 1e-9)]:
        z = invariant_zeros(A, b_scale * B, c_scale * C)
        assert match_error(z, [-5.0, 1.0]) < SIMPLE_ZERO_RTOL


@pytest.mark.parametrize("c", [1e-4, 1e4])
def test_frequency_scaling_scales_zeros(c):
    # [c s I - c A, -c B; C, 0] has the rank of P(s): zeros of (cA, cB, C) are c times those of
    # (A, B, C).
    A, B, C = ccf([-5.0, 1.0], [-1.0, -2.0, -3.0, -4.0])
    z = invariant_zeros(c * A, c * B, C)
    assert match_error(z / c, [-5.0, 1.0]) < SIMPLE_ZERO_RTOL


# ------------------------------------------------------------------------------------------
# Lemma 1 of the paper
# ------------------------------------------------------------------------------------------

def augment_with_integrators(A, E, C):
    """The error system (4) with K = 0: an integrator at each input point of (C, A, E)."""
    n, k = E.shape
    A_e = np.block([[A, E], [np.zeros((k, n)), np.zeros((k, k))]])
    E_e = np.vstack([np.zeros((n, k)), np.eye(k)])
    C_e = np.hstack([C, np.zeros((C.shape[0], k))])
    return A_e, E_e, C_e


@pytest.mark.parametrize("n, k, r", [(3, 1, 1), (5, 2, 2), (4, 2, 3), (6, 3, 3)])
def test_lemma1_integrators_keep_zeros_and_left_invertibility(n, k, r):
    gen = np.random.default_rng(n * 100 + k * 10 + r)
    A, E, C = gen.standard_normal((n, n)), gen.standard_normal((n, k)), gen.standard_normal((r, n))
    # give the triple a decoupling zero too: a mode at -0.75 that the perturbation cannot reach
    A = np.block([[A, gen.standard_normal((n, 1))], [np.zeros((1, n)), -0.75 * np.ones((1, 1))]])
    E = np.vstack([E, np.zeros((1, k))])
    C = np.hstack([C, gen.standard_normal((r, 1))])
    A_e, E_e, C_e = augment_with_integrators(A, E, C)
    z, z_e = invariant_zeros(A, E, C), invariant_zeros(A_e, E_e, C_e)
    assert is_left_invertible(A, E, C) and is_left_invertible(A_e, E_e, C_e)
    assert match_error(z_e, z, scale=10.0) < RANDOM_ZERO_RTOL
    assert is_minimum_phase(A, E, C) == is_minimum_phase(A_e, E_e, C_e)


def test_lemma1_on_known_siso_zeros():
    num = [-0.5, -7.0]
    A, E, C = ccf(num, [-1.0, -2.0, -3.0, -4.0])
    A_e, E_e, C_e = augment_with_integrators(A, E, C)
    assert match_error(invariant_zeros(A_e, E_e, C_e), num, scale=100.0) < SIMPLE_ZERO_RTOL
    assert is_minimum_phase(A_e, E_e, C_e)


# ------------------------------------------------------------------------------------------
# the paper's DC motor (Sec. VIII)
# ------------------------------------------------------------------------------------------

def dc_motor_error_system(sigma1, J=0.0023, sigma0=260.0, alpha2=0.176):
    A_e = np.array([[-(alpha2 + sigma1) / J, -sigma0 / J, sigma1 / J],
                    [1.0, 0.0, -1.0],
                    [0.0, 0.0, 0.0]])
    E_e = np.array([[0.0], [0.0], [1.0]])
    C_e = np.array([[1.0, 0.0, 0.0]])
    return A_e, E_e, C_e


def test_dc_motor_zero_is_minus_sigma0_over_sigma1():
    # Sec. VIII: the SCB gives chi_a' = -(sigma0 / sigma1) chi_a + ..., so one zero at -433.33.
    A_e, E_e, C_e = dc_motor_error_system(0.6)
    z = invariant_zeros(A_e, E_e, C_e)
    assert match_error(z, [-260.0 / 0.6]) < SIMPLE_ZERO_RTOL
    assert is_left_invertible(A_e, E_e, C_e)
    assert is_minimum_phase(A_e, E_e, C_e)


def test_dc_motor_design_system_has_no_zeros():
    # sigma1 = 0: a single chain of three integrators (relative degree 3), no zero dynamics.
    A_e, E_e, C_e = dc_motor_error_system(0.0)
    assert invariant_zeros(A_e, E_e, C_e).size == 0
    assert is_left_invertible(A_e, E_e, C_e)


# ------------------------------------------------------------------------------------------
# cross-check against SLICOT AB08ND
# ------------------------------------------------------------------------------------------

def random_structured_system(seed):
    """Random systems of varied shapes; some with decoupling modes, rank-deficient B or D."""
    gen = np.random.default_rng(seed)
    n, m, r = int(gen.integers(1, 7)), int(gen.integers(1, 4)), int(gen.integers(1, 4))
    if seed % 3:  # two in three square: generic square systems have zeros, non-square do not
        r = m
    A, B, C = gen.standard_normal((n, n)), gen.standard_normal((n, m)), gen.standard_normal((r, n))
    kind = seed % 5
    D = np.zeros((r, m))
    if kind == 1:
        D = gen.standard_normal((r, m))
    elif kind == 2:
        D = np.outer(gen.standard_normal(r), gen.standard_normal(m))
    elif kind == 3:  # an uncontrollable and an unobservable mode, hidden by a similarity
        A = np.block([[A, gen.standard_normal((n, 1)), np.zeros((n, 1))],
                      [np.zeros((1, n)), np.array([[-0.6, 0.0]])],
                      [gen.standard_normal((1, n + 1)), np.array([[1.3]])]])
        B = np.vstack([B, np.zeros((1, m)), gen.standard_normal((1, m))])
        C = np.hstack([C, gen.standard_normal((r, 1)), np.zeros((r, 1))])
        T = well_conditioned(gen, n + 2)
        A, B, C = np.linalg.solve(T, A @ T), np.linalg.solve(T, B), C @ T
    elif kind == 4 and m > 1:  # rank-deficient B
        B[:, -1] = B[:, 0]
    return A, B, C, D


@pytest.mark.parametrize("seed", range(50))
def test_agrees_with_slycot_ab08nd(seed):
    slycot = pytest.importorskip("slycot")
    A, B, C, D = random_structured_system(seed)
    expected, expected_rank = slycot_zeros(slycot, A, B, C, D)
    assert match_error(invariant_zeros(A, B, C, D), expected, scale=1.0) < RANDOM_ZERO_RTOL
    assert normal_rank(A, B, C, D) == expected_rank


#: At a computed simple zero z, P(z) is within rounding of a matrix of lower rank.
RANK_DROP_RTOL = 1e-9


@pytest.mark.parametrize("seed", [3, 8, 13, 258, 678])
def test_rank_drops_at_every_computed_zero(seed):
    # Independent of any zero solver: at each computed zero the (normal rank)-th singular value
    # of P(z) vanishes, while at a random point it does not. Seeds 258 and 678 are a tall and a
    # wide system with a decoupling zero (1.3 and -0.6) that AB08ND (slycot 0.7) misses.
    A, B, C, D = random_structured_system(seed)
    rank = normal_rank(A, B, C, D)
    z = invariant_zeros(A, B, C, D)
    assert z.size > 0
    for zk in z:
        sv = np.linalg.svd(rosenbrock(A, B, C, D, zk), compute_uv=False)
        assert sv[rank - 1] < RANK_DROP_RTOL * sv[0]
    sv = np.linalg.svd(rosenbrock(A, B, C, D, 0.123 + 0.456j), compute_uv=False)
    assert sv[rank - 1] > 1e3 * RANK_DROP_RTOL * sv[0]


# ------------------------------------------------------------------------------------------
# unstable_zeros and tolerances
# ------------------------------------------------------------------------------------------

def test_unstable_zeros_closed_half_plane_with_margin():
    z = np.array([-1e-17, -2.0, 1 + 1j, 0.0, -1e-3, -5e-7])
    got = unstable_zeros(z, scale=1.0)
    np.testing.assert_array_equal(got, np.array([-1e-17, 1 + 1j, 0.0, -5e-7], dtype=complex))
    # a larger system scale widens the margin: -1e-3 >= -1e-6 * 1e4
    assert -1e-3 in unstable_zeros(z, scale=1e4)
    assert unstable_zeros(np.zeros(0), scale=1.0).size == 0
    assert unstable_zeros([-1.0], scale=1.0, rtol=2.0).size == 1


def test_minimum_phase_margin_is_relative_to_norm_of_a():
    # G = 1/(s + c) + beta/(s + 2c) has its zero at -c (2 + beta)/(1 + beta); beta is chosen to
    # put it at -1e-7 c, and ||A|| = 2c. With the default margin 1e-6 * max(1, 2c) the zero
    # counts as not minimum-phase, with a margin 100 times smaller it does not.
    beta = (1e-7 - 2.0) / (1.0 - 1e-7)
    for c in [1.0, 1e3]:
        A = np.diag([-c, -2.0 * c])
        B = np.ones((2, 1))
        C = np.array([[1.0, beta]])
        z = invariant_zeros(A, B, C)
        assert match_error(z, [-1e-7 * c], scale=c) < SIMPLE_ZERO_RTOL
        assert not is_minimum_phase(A, B, C)
        assert is_minimum_phase(A, B, C, rtol=MINIMUM_PHASE_RTOL / 100)


def test_user_tolerance_changes_rank_decisions():
    # D = 1e-9 is a genuine feedthrough at the default tolerance (zero near -1e9) but is
    # treated as zero with tol = 1e-6 (no finite zero: relative degree one).
    A, B, C, D = [[-1.0]], [[1.0]], [[1.0]], [[1e-9]]
    z = invariant_zeros(A, B, C, D)
    assert match_error(z, [-1.0 - 1e9]) < SIMPLE_ZERO_RTOL
    assert invariant_zeros(A, B, C, D, tol=1e-6).size == 0


# ------------------------------------------------------------------------------------------
# input validation
# ------------------------------------------------------------------------------------------

def test_nan_or_inf_raises():
    A, B, C = ccf([-1.0], [-2.0, -3.0])
    A_bad = A.copy()
    A_bad[0, 1] = np.nan
    with pytest.raises(NonFiniteError, match="A contains NaN or inf"):
        invariant_zeros(A_bad, B, C)
    with pytest.raises(NonFiniteError, match="D contains NaN or inf"):
        is_left_invertible(A, B, C, [[np.inf]])
    with pytest.raises(NonFiniteError, match="zeros contains NaN"):
        unstable_zeros([np.nan], scale=1.0)


def test_wrong_shapes_raise_dimension_error():
    A, B, C = ccf([-1.0], [-2.0, -3.0])
    with pytest.raises(DimensionError, match=r"D must have shape \(1, 1\)"):
        invariant_zeros(A, B, C, np.zeros((2, 1)))
    with pytest.raises(DimensionError, match=r"B must have shape \(2, \?\)"):
        normal_rank(A, np.ones((3, 1)), C)
    with pytest.raises(DimensionError, match="C must have shape"):
        is_minimum_phase(A, B, np.ones((1, 3)))
    with pytest.raises(DimensionError, match="A must be square"):
        invariant_zeros(np.ones((2, 3)), B, C)
    with pytest.raises(DimensionError, match="zeros must be a 1-D array"):
        unstable_zeros(np.zeros((2, 2)), scale=1.0)


def test_bad_tolerances_raise():
    A, B, C = ccf([-1.0], [-2.0, -3.0])
    with pytest.raises(DimensionError, match="tol must be > 0"):
        invariant_zeros(A, B, C, tol=-1.0)
    with pytest.raises(DimensionError, match="scale must be > 0"):
        unstable_zeros([1.0], scale=0.0)
    with pytest.raises(NonFiniteError, match="rtol must be finite"):
        unstable_zeros([1.0], scale=1.0, rtol=np.inf)
