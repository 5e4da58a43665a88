"""Tests of thetahat.structure.scb_symbolic: the exact SCB of symbolic triples.

Every example is checked three ways: exactly (the transforms reproduce the system and the
transformed triple has the pattern (5)/(6), decided by cancellation to zero), against the
paper (Sec. VIII, the DC motor with LuGre friction), and numerically (after substituting random
positive numbers, eig(A_a) equals the finite generalised eigenvalues of the Rosenbrock pencil,
computed independently with scipy).
"""

from __future__ import annotations

import doctest
from functools import lru_cache

import numpy as np
import pytest
import scipy.linalg
import sympy as sp

import thetahat.structure.scb_symbolic as scb_symbolic_module
from thetahat.errors import DimensionError, NotLeftInvertibleError
from thetahat.structure.scb_symbolic import SymbolicSCBResult, scb_symbolic

#: Zeros of the small, well-separated examples after substituting O(1) numbers are simple and
#: well conditioned; the pencil's QZ and eig(A_a) agree to ~1e-12 relative, 1e-8 leaves margin.
ZERO_RTOL = 1e-8
#: |β| below this fraction of |α| marks an infinite eigenvalue of the (singular) pencil.
INFINITE_BETA_RTOL = 1e-10
#: Smallest singular value of P(z) at a true zero of a non-square system, relative to ‖P(z)‖:
#: exactly zero in exact arithmetic, round-off (~1e-15) in floating point.
RANK_DROP_RTOL = 1e-9

J, s0, s1, a2 = sp.symbols("J sigma0 sigma1 alpha2", positive=True)
a, b, c, d, h, p, q1 = sp.symbols("a b c d h p q1", positive=True)
b0, b1, e = sp.symbols("b0 b1 e", positive=True)

#: Integer similarity with det 2, to hide the structure of hand-built examples.
P5 = sp.Matrix([[1, 1, 0, 0, 0], [0, 1, 0, 0, 1], [0, 0, 1, 1, 0], [1, 0, 0, 1, 0],
                [0, 0, 1, 0, 1]])
P3 = sp.Matrix([[1, 1, 0], [0, 1, 1], [1, 0, 2]])
P4 = sp.Matrix([[1, 0, 1, 0], [0, 1, 0, 1], [1, 1, 0, 0], [0, 0, 1, 2]])


def _scramble(A, B, C, P):
    return P.inv() * A * P, P.inv() * B, C * P


def _dc_motor(sigma1=s1):
    """The extended error system (4) of Sec. VIII-A with K = 0."""
    A = sp.Matrix([[-(a2 + sigma1) / J, -s0 / J, sigma1 / J], [1, 0, -1], [0, 0, 0]])
    return A, sp.Matrix([0, 0, 1]), sp.Matrix([[1, 0, 0]])


def _siso_rd1():
    A = sp.Matrix([[-a, 1, 0], [0, -b, 1], [1, 0, -c]])
    return _scramble(A, sp.Matrix([1, p, 0]), sp.Matrix([[1, 0, 0]]), P3)


def _siso_rd3():
    """Controllable canonical form of (s + a)/(s⁴ + d s³ + c s² + b s + 1): zero at −a."""
    A = sp.Matrix([[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [-1, -b, -c, -d]])
    return _scramble(A, sp.Matrix([0, 0, 0, 1]), sp.Matrix([[a, 1, 0, 0]]), P4)


def _mimo_square():
    """2 × 2, chains of lengths 1 and 3, one zero at −c; u2 enters the long chain's 2nd row."""
    A = sp.Matrix([[0, 1, 0, 0, q1], [0, 0, 1, 0, 0], [a, 0, 0, 0, b],
                   [0, b1, 0, 0, b0], [1, 0, 0, d, -c]])
    B = sp.Matrix([[0, 0], [0, h], [1, 0], [0, 1], [0, 0]])
    C = sp.Matrix([[1, 0, 0, 0, 0], [0, 0, 0, 1, 0]])
    return _scramble(A, B, C, P5)


def _mimo_nonsquare():
    """k = 1, r = 2: a chain of length 2, n_b = 2, and an a-row that sees χ_b outside C_b."""
    A = sp.Matrix([[0, 1, 0, 0, 0], [0, 0, p, 0, q1], [1, 0, 0, 1, 0],
                   [1, 0, -b0, -b1, 0], [1, 0, 0, e, -c]])
    B = sp.Matrix([0, 1, 0, 0, 0])
    C = sp.Matrix([[1, 0, 0, 0, 0], [0, 0, 1, 0, 0]])
    return _scramble(A, B, C, P5)


EXAMPLES = {
    "dc_motor": _dc_motor,
    "dc_motor_sigma1_0": lambda: _dc_motor(sp.Integer(0)),
    "siso_rd1": _siso_rd1,
    "siso_rd3": _siso_rd3,
    "mimo_square": _mimo_square,
    "mimo_nonsquare": _mimo_nonsquare,
}


@lru_cache(maxsize=None)
def _computed(name: str) -> tuple[sp.Matrix, sp.Matrix, sp.Matrix, SymbolicSCBResult]:
    A, B, C = EXAMPLES[name]()
    return A, B, C, scb_symbolic(A, B, C)


def _is_zero_matrix(M) -> bool:
    return all(sp.cancel(x) == 0 for x in sp.Matrix(M))


def _expected_pattern(res: SymbolicSCBResult, r: int):
    """Ã, B̃, C̃ assembled from the blocks alone, in the exact form (6)."""
    n_a, n_b, k = res.n_a, res.n_b, len(res.chain_lengths)
    n = n_a + n_b + res.n_q
    starts = [n_a + n_b + sum(res.chain_lengths[:j]) for j in range(k)]
    lasts = [st + L - 1 for st, L in zip(starts, res.chain_lengths)]
    At = sp.zeros(n, n)
    At[:n_a, :n_a] = res.A_a
    At[:n_a, n_a:n_a + n_b] = res.L_ab * res.C_b
    At[n_a:n_a + n_b, n_a:n_a + n_b] = res.A_b
    for j, st in enumerate(starts):
        At[:n_a, st] = res.L_aq[:, j]
        At[n_a:n_a + n_b, st] = res.L_bq[:, j]
        for i in range(n_a + n_b, n):
            At[i, st] = res.L_qq[i - n_a - n_b, j]
    for i in range(n_a + n_b, n):
        if i not in lasts:
            At[i, i + 1] = 1
    Bt, Ct = sp.zeros(n, k), sp.zeros(r, n)
    for j, (st, last) in enumerate(zip(starts, lasts)):
        At[last, :] = sp.Matrix.hstack(res.D_a[j, :], res.D_b[j, :], res.D_q[j, :])
        Bt[last, j] = 1
        Ct[j, st] = 1
    Ct[k:, n_a:n_a + n_b] = res.C_b
    return At, Bt, Ct, lasts


def _numbers(rng, *mats):
    syms = sorted(set().union(*(M.free_symbols for M in mats)), key=str)
    vals = dict(zip(syms, rng.uniform(0.5, 2.0, size=len(syms))))
    return [np.array(M.subs(vals).evalf(), dtype=float) for M in mats], vals


def _pencil_zeros(A, B, C):
    """Finite generalised eigenvalues of [[A, B], [C, 0]] − s [[I, 0], [0, 0]] (square only)."""
    n, k = B.shape
    M = np.block([[A, B], [C, np.zeros((C.shape[0], k))]])
    N = np.zeros_like(M)
    N[:n, :n] = np.eye(n)
    w = scipy.linalg.eig(M, N, right=False, homogeneous_eigvals=True)
    alpha, beta = w
    finite = np.abs(beta) > INFINITE_BETA_RTOL * np.maximum(np.abs(alpha), 1.0)
    return np.sort_complex(alpha[finite] / beta[finite])


# ------------------------------------------------------------------------------------------
# the paper's DC motor, Sec. VIII
# ------------------------------------------------------------------------------------------

def test_dc_motor_reproduces_printed_scb():
    """Sec. VIII-A: χ̇_a = −σ0/σ1 χ_a + …, χ̇_q2 = D_q χ_q + (σ0/J) χ_a + δ (up to χ_a scale).

    Normalisation: Γo = 1 (γ = y). The χ_a scale is free, so A_a, D_q and L_aq·D_a are
    compared; they do not depend on it.
    """
    _, _, _, res = _computed("dc_motor")
    assert (res.n_a, res.n_b, res.chain_lengths) == (1, 0, (2,))
    assert sp.simplify(res.A_a[0, 0] + s0 / s1) == 0
    paper_D_q = sp.Matrix([[-s0 * (-s1 * a2 + J * s0) / (J * s1 ** 2),
                            (J * s0 - s1 * a2 - s1 ** 2) / (s1 * J)]])
    assert _is_zero_matrix(res.D_q - paper_D_q)
    paper_L_aq, paper_D_a = s0 * (-s1 * a2 + J * s0) / s1 ** 3, s0 / J
    assert _is_zero_matrix(res.L_aq * res.D_a - sp.Matrix([[paper_L_aq * paper_D_a]]))
    assert res.output_transform == sp.Matrix([[1]])
    assert _is_zero_matrix(res.L_qq)                      # SISO: pure shift, (5)
    assert res.invariant_zeros == [-s0 / s1]
    assert sp.simplify(res.generic_condition - s1 / J) == 0   # σ1 ≠ 0 is assumed


def test_dc_motor_design_system_sigma1_zero():
    """Sec. VIII-A with σ1 = 0: χ̇_q3 = −σ0/J χ_q2 − α2/J χ_q3 + δ, no zero dynamics."""
    _, _, _, res = _computed("dc_motor_sigma1_0")
    assert (res.n_a, res.n_b, res.chain_lengths) == (0, 0, (3,))
    assert _is_zero_matrix(res.D_q - sp.Matrix([[0, -s0 / J, -a2 / J]]))
    assert res.invariant_zeros == []
    assert res.zero_polynomial.as_expr() == 1
    assert _is_zero_matrix(res.L_qq)


def test_dc_motor_agrees_with_numeric_scb(dc_motor):
    """Cross-check with the floating-point scb at the paper's parameter values."""
    from thetahat.structure.scb import scb

    _, _, _, res = _computed("dc_motor")
    vals = {J: dc_motor.J, s0: dc_motor.sigma0, s1: dc_motor.sigma1, a2: dc_motor.alpha2}
    num = scb(*dc_motor.extended())
    assert num.chain_lengths == res.chain_lengths and num.n_a == res.n_a
    for name in ("A_a", "D_q"):
        sym = np.array(getattr(res, name).subs(vals), dtype=float)
        np.testing.assert_allclose(getattr(num, name), sym, rtol=1e-7)
    prod = np.array((res.L_aq * res.D_a).subs(vals), dtype=float)
    np.testing.assert_allclose(num.L_aq @ num.D_a, prod, rtol=1e-7)


# ------------------------------------------------------------------------------------------
# invariants on every example
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(EXAMPLES))
def test_transforms_reproduce_system_exactly(name):
    A, B, C, res = _computed(name)
    Gs, Go, Gi = res.state_transform, res.output_transform, res.input_transform
    # a nonzero determinant at one exact rational point proves det ≢ 0 (cheaper than det)
    point = {x: sp.Rational(3 + 2 * i, 5 + i) for i, x in enumerate(
        sorted(Gs.free_symbols | Gi.free_symbols, key=str))}
    for G in (Gs, Go, Gi):
        assert G.subs(point).det() != 0
    # Γs⁻¹AΓs = Ã ⇔ AΓs = ΓsÃ for invertible Γs (no symbolic inverse needed)
    assert _is_zero_matrix(A * Gs - Gs * res.A_tilde)
    assert _is_zero_matrix(B * Gi - Gs * res.B_tilde)
    assert _is_zero_matrix(C * Gs - Go * res.C_tilde)


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_transformed_triple_has_exact_form_6(name):
    A, B, C, res = _computed(name)
    n = A.rows
    assert res.n_a + res.n_b + res.n_q == n
    At, Bt, Ct, lasts = _expected_pattern(res, C.rows)
    assert _is_zero_matrix(res.A_tilde - At)
    assert _is_zero_matrix(res.B_tilde - Bt)
    assert _is_zero_matrix(res.C_tilde - Ct)
    off = res.n_a + res.n_b
    assert all(res.L_qq[i - off, j] == 0 for i in lasts for j in range(len(lasts)))
    assert [sl.stop - sl.start for sl in res.chain_slices()] == list(res.chain_lengths)
    assert res.chain_slices()[-1].stop == n and res.r_b == C.rows - res.k


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_zeros_match_rosenbrock_pencil(name, rng):
    A, B, C, res = _computed(name)
    (An, Bn, Cn, Aa), vals = _numbers(rng, A, B, C, res.A_a)
    z_scb = np.sort_complex(np.linalg.eigvals(Aa)) if res.n_a else np.zeros(0, complex)
    if res.invariant_zeros is not None:
        z_closed = np.sort_complex(np.array([complex(z.subs(vals)) for z in res.invariant_zeros]))
        np.testing.assert_allclose(z_closed, z_scb, rtol=ZERO_RTOL, atol=ZERO_RTOL)
    if B.cols == C.rows:
        z_pencil = _pencil_zeros(An, Bn, Cn)
        assert z_pencil.shape == z_scb.shape
        np.testing.assert_allclose(z_pencil, z_scb, rtol=ZERO_RTOL)
    else:  # non-square: P(z) must lose rank exactly at eig(A_a), and not at a random point
        n, k = Bn.shape

        def smin(z):
            Pz = np.block([[z * np.eye(n) - An, -Bn], [Cn, np.zeros((Cn.shape[0], k))]])
            sv = np.linalg.svd(Pz, compute_uv=False)
            return sv[-1] / sv[0]

        assert all(smin(z) < RANK_DROP_RTOL for z in z_scb)
        assert smin(0.123 + 0.456j) > 1e3 * RANK_DROP_RTOL


# ------------------------------------------------------------------------------------------
# structure of the individual examples
# ------------------------------------------------------------------------------------------

def test_siso_relative_degree_one():
    _, _, _, res = _computed("siso_rd1")
    assert (res.n_a, res.chain_lengths) == (2, (1,))
    assert len(res.invariant_zeros) == 2           # roots of a quadratic, in closed form
    assert res.input_transform.shape == (1, 1)


def test_siso_relative_degree_three():
    _, _, _, res = _computed("siso_rd3")
    assert (res.n_a, res.n_b, res.chain_lengths) == (1, 0, (3,))
    assert res.invariant_zeros == [-a]
    assert _is_zero_matrix(res.L_qq)
    assert res.generic_condition != 0 and res.generic_condition.is_number


def test_relative_degree_decided_by_cancellation():
    """C B = p(p + 1) − p² − p is identically zero though not syntactically 0."""
    A = sp.Matrix([[0, 1], [-a, -b]])
    B = sp.Matrix([p * (p + 1) - p ** 2 - p, 1])
    res = scb_symbolic(A, B, sp.Matrix([[1, 0]]))
    assert res.chain_lengths == (2,) and res.n_a == 0


def test_mimo_chains_of_different_lengths():
    _, _, _, res = _computed("mimo_square")
    assert (res.n_a, res.n_b, res.chain_lengths) == (1, 0, (1, 3))
    assert res.invariant_zeros == [-c]
    # u2 enters ẋ2 = ÿ1 with gain h: the top row of the long chain (q-row 1) gets the
    # injection h γ_q1 from the short chain's top, so that its next row is free of u2
    assert sp.cancel(res.L_qq[1, 0] - h) == 0
    assert _is_zero_matrix(res.L_qq[2:, :]) and _is_zero_matrix(res.L_qq[0, :])
    assert res.generic_condition != 0


def test_nonsquare_b_subsystem(rng):
    _, _, _, res = _computed("mimo_nonsquare")
    assert (res.n_a, res.n_b, res.chain_lengths) == (1, 2, (2,))
    assert res.C_b.shape == (1, 2) and res.L_ab.shape == (1, 1)
    # the Sylvester step needs eig A_a = {−c} disjoint from eig A_b (roots of s² + b1 s + b0)
    assert sp.cancel(res.generic_condition / (c ** 2 - b1 * c + b0)).is_number
    (Ab, Cb), _ = _numbers(rng, res.A_b, res.C_b)
    assert np.linalg.matrix_rank(np.vstack([Cb, Cb @ Ab])) == 2     # (C_b, A_b) observable


def test_simplify_false_gives_the_same_blocks():
    A, B, C, res = _computed("dc_motor")
    raw = scb_symbolic(A, B, C, simplify=False)
    for name in ("A_a", "L_aq", "D_a", "D_q", "state_transform", "A_tilde"):
        assert _is_zero_matrix(getattr(raw, name) - getattr(res, name))


def test_zeros_without_closed_form_fall_back_to_polynomial():
    """Numerator s⁵ − s − 1 has no solution by radicals: the polynomial is reported instead."""
    den = [1, 2, 3, 4, 5, 6]                  # s⁶ + 1 s⁵ + … (any denominator)
    A = sp.zeros(6, 6)
    A[:5, 1:] = sp.eye(5)
    A[5, :] = sp.Matrix([[-x for x in reversed(den)]])
    C = sp.Matrix([[-1, -1, 0, 0, 0, 1]])     # numerator −1 − s + s⁵
    res = scb_symbolic(A, sp.Matrix([0, 0, 0, 0, 0, 1]), C)
    assert res.invariant_zeros is None
    s = res.zero_polynomial.gen
    assert sp.expand(res.zero_polynomial.as_expr() - (s ** 5 - s - 1)) == 0
    assert "s**5" in repr(res)


# ------------------------------------------------------------------------------------------
# error paths
# ------------------------------------------------------------------------------------------

def test_zero_transfer_function_is_not_left_invertible():
    A = sp.Matrix([[-a, 0], [0, -b]])
    with pytest.raises(NotLeftInvertibleError, match="not left-invertible") as info:
        scb_symbolic(A, sp.Matrix([1, 0]), sp.Matrix([[0, 1]]))
    assert info.value.rank_B == 1 and info.value.dim_intersection == 1
    assert info.value.normal_rank == 2          # < n + k = 3


def test_more_inputs_than_outputs_is_not_left_invertible():
    A = sp.Matrix([[-a, 1], [0, -b]])
    with pytest.raises(NotLeftInvertibleError, match="V\\* ∩ S\\*") as info:
        scb_symbolic(A, sp.eye(2), sp.Matrix([[1, p]]))
    assert info.value.dim_intersection == 1 and info.value.normal_rank == 3


def test_rank_deficient_input_matrix_is_rejected():
    A = sp.Matrix([[-a, 1, 0], [0, -b, 1], [0, 0, -c]])
    B = sp.Matrix([[0, 0], [1, p], [0, 0]])
    with pytest.raises(NotLeftInvertibleError, match="B has rank 1") as info:
        scb_symbolic(A, B, sp.Matrix([[1, 0, 0], [0, 0, 1]]))
    assert info.value.rank_B == 1


def test_shared_spectra_in_sylvester_step_is_not_supported():
    """A_a = 0 and A_b with an eigenvalue 0: the a–b decoupling is not unique."""
    A = sp.Matrix([[0, 1, 0, 0, 0], [0, 0, p, 0, q1], [1, 0, 0, 1, 0],
                   [1, 0, 0, -b1, 0], [1, 0, 0, e, 0]])
    B = sp.Matrix([0, 1, 0, 0, 0])
    C = sp.Matrix([[1, 0, 0, 0, 0], [0, 0, 1, 0, 0]])
    with pytest.raises(NotImplementedError, match="share eigenvalues"):
        scb_symbolic(A, B, C)


@pytest.mark.parametrize("A, B, C, match", [
    ([[0, 1], [0, 0]], [[0], [1], [0]], [[1, 0]], "B must have shape"),
    ([[0, 1, 0]], [[0], [1]], [[1, 0]], "A must be square"),
    ([[0, 1], [0, 0]], [[0], [1]], [[1, 0, 0]], "C must have shape"),
    ([[0, 1], [0, 0]], [[0], [1]], [[1, 0], [2, 0]], "full row rank"),
])
def test_bad_shapes_raise_dimension_error(A, B, C, match):
    with pytest.raises(DimensionError, match=match):
        scb_symbolic(sp.Matrix(A), sp.Matrix(B), sp.Matrix(C))


# ------------------------------------------------------------------------------------------
# presentation
# ------------------------------------------------------------------------------------------

def test_repr_and_pretty_name_structure_and_assumption():
    _, _, _, res = _computed("dc_motor")
    text = repr(res)
    assert "chain_lengths=(2,)" in text and "sigma1/J != 0" in text
    pretty = res.pretty()
    assert "D_q" in pretty and "valid where" in pretty
    with pytest.raises(AttributeError):
        res.n_a = 3  # frozen


def test_docstring_examples_run():
    failures, tried = doctest.testmod(scb_symbolic_module, verbose=False)
    assert tried > 0 and failures == 0
