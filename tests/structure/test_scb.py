"""The numeric SCB: the paper's DC motor, the form (6), random systems of known structure."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from thetahat import (DimensionError, IllConditionedWarning, NonFiniteError,
                      NotLeftInvertibleError, invariant_zeros, scb)
from thetahat.testing import random_scb_system

#: Relative accuracy of transforms on well-conditioned systems (construction cond ≤ 10, n ≤ 30):
#: round-off times cond Γs (≤ 1e5) stays far below this.
REPRO_RTOL = 1e-6
#: Zeros of random systems: simple zeros of a cond-10 construction are accurate to ~1e-10.
ZERO_ATOL = 1e-6


def reproduce(res, A, B, C):
    """Largest relative error of Γs Ã Γs⁻¹, Γs B̃ Γi⁻¹, Γo C̃ Γs⁻¹ against (A, B, C)."""
    Gs, Go, Gi = res.state_transform, res.output_transform, res.input_transform
    Gs_inv = np.linalg.inv(Gs)
    errs = [np.abs(Gs @ res.A_tilde @ Gs_inv - A).max() / np.abs(A).max(),
            np.abs(Gs @ res.B_tilde @ np.linalg.inv(Gi) - B).max() / np.abs(B).max(),
            np.abs(Go @ res.C_tilde @ Gs_inv - C).max() / np.abs(C).max()]
    return max(errs)


def check_pattern(res):
    """The transformed triple has exactly the form (6): assert it entry by entry."""
    n_a, n_b, k = res.n_a, res.n_b, res.k
    At, Bt, Ct = res.A_tilde, res.B_tilde, res.C_tilde
    tops = [s.start for s in res.chain_slices()]
    lasts = [s.stop - 1 for s in res.chain_slices()]
    # B̃: a single 1 at the last state of each chain
    expected_B = np.zeros_like(Bt)
    expected_B[lasts, range(k)] = 1.0
    assert np.array_equal(Bt, expected_B)
    # C̃: γ_qj is the top of chain j; γ_b = C_b χ_b only
    assert np.array_equal(Ct[:k][:, tops], np.eye(k))
    mask = np.ones(Ct.shape, bool)
    mask[:k, tops] = False
    mask[k:, n_a:n_a + n_b] = False
    assert np.all(Ct[mask] == 0)
    # a-rows: χ_b only through L_ab C_b; χ_q only through chain tops
    q_nontop = [i for i in range(n_a + n_b, At.shape[0]) if i not in tops]
    assert np.all(At[:n_a][:, q_nontop] == 0)
    np.testing.assert_allclose(At[:n_a, n_a:n_a + n_b], res.L_ab @ res.C_b, atol=1e-12)
    # b-rows: no χ_a, χ_q only through tops
    assert np.all(At[n_a:n_a + n_b, :n_a] == 0)
    assert np.all(At[n_a:n_a + n_b][:, q_nontop] == 0)
    # non-last chain rows: shift + chain tops only
    for sl in res.chain_slices():
        for i in range(sl.start, sl.stop - 1):
            row = At[i].copy()
            assert row[i + 1] == 1.0
            row[i + 1] = 0.0
            row[tops] = 0.0
            assert np.all(row == 0)


def test_dc_motor_sigma1_positive(dc_motor):
    """Sec. VIII: one zero at −σ0/σ1, one chain of length 2, the printed SCB."""
    A, E, C = dc_motor.extended()
    J, s0, s1, a2 = dc_motor.J, dc_motor.sigma0, dc_motor.sigma1, dc_motor.alpha2
    res = scb(A, E, C)
    assert (res.n_a, res.n_b, res.chain_lengths) == (1, 0, (2,))
    np.testing.assert_allclose(res.invariant_zeros, [-s0 / s1], rtol=1e-10)
    np.testing.assert_allclose(res.A_a, [[-s0 / s1]], rtol=1e-10)
    # last row of the chain, as printed in the paper (Γo = 1 normalisation)
    d_q = [-s0 * (-s1 * a2 + J * s0) / (J * s1 ** 2), (J * s0 - s1 * a2 - s1 ** 2) / (s1 * J)]
    np.testing.assert_allclose(res.D_q.ravel(), d_q, rtol=1e-8)
    # χ_a's scale is free; L_aq·D_a is invariant
    prod = s0 * (-s1 * a2 + J * s0) / s1 ** 3 * s0 / J
    np.testing.assert_allclose((res.L_aq @ res.D_a).item(), prod, rtol=1e-8)
    assert res.minimum_phase
    check_pattern(res)
    assert reproduce(res, A, E, C) < REPRO_RTOL


def test_dc_motor_design_system(dc_motor):
    """σ1 = 0: no zeros, a chain of length 3, χ̇_q3 = −σ0/J χ_q2 − α2/J χ_q3 + δ."""
    A, E, C = dc_motor.extended(sigma1=0.0)
    res = scb(A, E, C)
    assert (res.n_a, res.n_b, res.chain_lengths) == (0, 0, (3,))
    np.testing.assert_allclose(res.D_q.ravel(),
                               [0.0, -dc_motor.sigma0 / dc_motor.J, -dc_motor.alpha2 / dc_motor.J],
                               atol=1e-6)
    check_pattern(res)


def test_condition_of_dc_motor_transforms(dc_motor):
    """Derivative coordinates: cond Γs ≈ 1e5 (σ1 = 0.6) and ≈ 1e7 (σ1 = 0), see the SCB note."""
    c06 = scb(*dc_motor.extended()).condition
    c00 = scb(*dc_motor.extended(sigma1=0.0)).condition
    assert 1e4 < c06 < 1e6
    assert 1e6 < c00 < 1e8


def test_form_and_reproduction(known_system):
    ks = known_system
    res = scb(ks.A, ks.B, ks.C)
    assert (res.n_a, res.n_b, res.chain_lengths) == (ks.n_a, ks.n_b, ks.chain_lengths)
    check_pattern(res)
    assert reproduce(res, ks.A, ks.B, ks.C) < REPRO_RTOL
    np.testing.assert_allclose(np.sort_complex(res.invariant_zeros), ks.zeros, atol=ZERO_ATOL)
    if res.n_b:   # (C_b, A_b) observable
        O = np.vstack([res.C_b @ np.linalg.matrix_power(res.A_b, i) for i in range(res.n_b)])
        assert np.linalg.matrix_rank(O) == res.n_b


def test_siso_form_5_has_pure_shift_chains(rng):
    """SISO: the non-last chain rows carry no output injection (form (5))."""
    ks = random_scb_system(rng, chain_lengths=(4,), n_a=2)
    res = scb(ks.A, ks.B, ks.C)
    assert np.all(res.L_qq == 0)


def test_random_systems_recover_structure():
    """≥ 200 seeded random systems, n up to 30: structure, form (6), zeros, conditioning."""
    rng = np.random.default_rng(7)
    ratios = []
    for trial in range(220):
        k = int(rng.integers(1, 4))
        lengths = tuple(int(v) for v in rng.integers(1, 5, size=k))
        r_b = int(rng.integers(0, 3))
        n_b = r_b + int(rng.integers(0, 3)) if r_b else 0
        n_a = int(rng.integers(0, 6)) if trial % 10 else 10
        if trial % 25 == 0:                    # the largest case: n = 11 + 5 + 14 = 30
            lengths, n_b, r_b, n_a = (3, 4, 4), 5, 2, 14
        ks = random_scb_system(rng, chain_lengths=lengths, n_a=n_a, n_b=n_b, r_b=r_b)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IllConditionedWarning)
            res = scb(ks.A, ks.B, ks.C)
        assert (res.n_a, res.n_b, res.chain_lengths) == (ks.n_a, ks.n_b, ks.chain_lengths), trial
        assert res.residual < REPRO_RTOL
        assert reproduce(res, ks.A, ks.B, ks.C) < REPRO_RTOL, trial
        if n_a:
            np.testing.assert_allclose(np.sort_complex(res.invariant_zeros), ks.zeros,
                                       atol=ZERO_ATOL)
            # an independent computation: the staircase reduction of the Rosenbrock pencil
            np.testing.assert_allclose(invariant_zeros(ks.A, ks.B, ks.C), ks.zeros,
                                       atol=ZERO_ATOL)
        ratios.append(res.condition / ks.condition)
    ratios = np.array(ratios)
    # cond Γs stays near the construction's (cond 10): measured median ≈ 1.5, worst ≈ 35
    assert np.median(ratios) < 5
    assert ratios.max() < 200


def test_zeros_invariant_under_similarity(known_system, rng):
    ks = known_system
    T = np.linalg.qr(rng.standard_normal((ks.A.shape[0],) * 2))[0] @ np.diag(
        rng.uniform(0.5, 2.0, ks.A.shape[0]))
    Ti = np.linalg.inv(T)
    res = scb(Ti @ ks.A @ T, Ti @ ks.B, ks.C @ T)
    np.testing.assert_allclose(np.sort_complex(res.invariant_zeros), ks.zeros, atol=ZERO_ATOL)


def test_zero_at_origin_is_not_minimum_phase():
    # y'' = u + ... with a zero at s = 0: G(s) = s/(s^2 + 3s + 2), controllable canonical form
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    B = np.array([[0.0], [1.0]])
    C = np.array([[0.0, 1.0]])
    res = scb(A, B, C)
    assert res.n_a == 1
    assert abs(res.invariant_zeros[0]) < 1e-12
    assert not res.minimum_phase


def test_non_minimum_phase_zero_reported():
    # G(s) = (s − 2)/(s^2 + 3s + 2)
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    res = scb(A, [[0.0], [1.0]], [[-2.0, 1.0]])
    np.testing.assert_allclose(res.invariant_zeros, [2.0], atol=1e-10)
    assert not res.minimum_phase


def test_unobservable_mode_is_a_zero():
    """A decoupling zero: an unobservable mode at −5 appears in A_a."""
    A = np.diag([-1.0, -5.0])
    res = scb(A, [[1.0], [1.0]], [[1.0, 0.0]])
    np.testing.assert_allclose(res.invariant_zeros, [-5.0], atol=1e-10)


def test_tolerance_decides_relative_degree(dc_motor):
    """A tiny σ1: the default tolerance sees relative degree 2, a loose one sees 3 (Sec. VII)."""
    A, E, C = dc_motor.extended(sigma1=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedWarning)
        assert scb(A, E, C).chain_lengths == (2,)
    assert scb(A, E, C, tol=1e-6).chain_lengths == (3,)


def test_ill_conditioned_warning(dc_motor):
    with pytest.warns(IllConditionedWarning, match="cond"):
        scb(*dc_motor.extended(sigma1=1e-4))


def test_not_left_invertible_rank_B():
    A = np.diag([-1.0, -2.0, -3.0])
    B = np.array([[1.0, 2.0], [0.0, 0.0], [1.0, 2.0]])
    with pytest.raises(NotLeftInvertibleError, match="B has rank 1") as info:
        scb(A, B, np.eye(3))
    assert info.value.rank_B == 1
    assert info.value.normal_rank == 4          # n + rank B = 3 + 1 < n + k = 5


def test_not_left_invertible_intersection():
    # the second input drives x3, which no output ever sees: V* ∩ im B ≠ 0
    A = np.diag([-1.0, -2.0, -3.0])
    B = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(NotLeftInvertibleError, match=r"V\* ∩ im B\) = 1") as info:
        scb(A, B, C)
    assert info.value.dim_intersection == 1
    assert info.value.normal_rank == 4          # n + k − 1: one input is invisible


def test_more_inputs_than_outputs_is_not_left_invertible():
    A = np.diag([-1.0, -2.0])
    with pytest.raises(NotLeftInvertibleError, match="not left-invertible"):
        scb(A, np.eye(2), [[1.0, 1.0]])


@pytest.mark.parametrize("args, err, match", [
    (([[0, 1], [0, 0]], [0, 1], [[1, 0]]), DimensionError, "B must be 2-D"),
    (([[0, 1], [0, 0]], [[0], [1]], [[1, 0, 0]]), DimensionError, r"C must have shape"),
    (([[0, 1]], [[0], [1]], [[1, 0]]), DimensionError, "A must"),
    (([[0, np.nan], [0, 0]], [[0], [1]], [[1, 0]]), NonFiniteError, "A contains NaN"),
    (([[0, 1], [0, 0]], [[0], [1]], [[1, 0], [2, 0]]), DimensionError, "redundant"),
])
def test_bad_input(args, err, match):
    with pytest.raises(err, match=match):
        scb(*args)
