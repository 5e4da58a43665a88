"""K(ε): the paper's numbers, Remark 2, the corrigendum, design systems, bad input."""

from __future__ import annotations


import numpy as np
import pytest
import scipy.linalg

from thetahat import (DesignError, ThetahatWarning, apply_design, extended_system, high_gain,
                      modified_high_gain)
from thetahat.design.gains import place_observer
from thetahat.testing import STRUCTURES, random_scb_system

#: The paper's numbers against our own closed-form derivation: pure floating point.
PAPER_RTOL = 1e-6
#: Zeros and b-poles must appear in eig(A − KC) "exactly": they are eigenvalues of blocks of a
#: block-triangular matrix, computed to ~cond·eps; 1e-6 relative leaves a wide margin.
EXACT_RTOL = 1e-6
EPS_SWEEP = (1e-1, 1e-2, 1e-3)
#: Remark 2's sweep: a half-decade grid down to where K(ε) ~ ε^−3 makes eig meaningless.
REMARK_2_EPS = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3)
#: A point of that sweep is used only where round-off can explain at most this fraction of the
#: error measured there (first-order bound ε·κ_max·u·‖A − KC‖ with the eigenvalue condition
#: numbers κ): the test is about Remark 2's O(ε), not LAPACK's last digits.
ROUNDOFF_SHARE = 0.1


def observability_gain(A, C, coefficients):
    """Independent derivation for SISO systems without zeros: with T = [C; CA; …; CA^{n−1}]
    the chain states are χ = T x, so K = T⁻¹ K_q with K_q the polynomial coefficients."""
    n = A.shape[0]
    T = np.vstack([C @ np.linalg.matrix_power(A, i) for i in range(n)])
    return np.linalg.solve(T, coefficients)


def test_paper_first_observer(dc_motor):
    """Sec. VIII: poles −1, −2, −3 on the σ1 = 0 design system, ε = 1 → K ≈ [6, 0, 6]ᵀ."""
    A, _, E, C = dc_motor.linear(sigma1=0.0)
    d = modified_high_gain(A, E, C, eps=1.0, chain_poles=[[-1, -2, -3]])
    A_e, _, C_e = extended_system(A, E, C)
    expected = observability_gain(A_e, C_e, np.array([6.0, 11.0, 6.0]))
    np.testing.assert_allclose(d.K.ravel(), expected, rtol=PAPER_RTOL)
    np.testing.assert_allclose(d.K.ravel(), [6.0, -0.0041588, 6.0075], rtol=1e-3, atol=1e-6)
    np.testing.assert_allclose(np.vstack([d.K_x, d.K_phi]), d.K)
    assert d.K_x.shape == (2, 1) and d.K_phi.shape == (1, 1)


def test_paper_second_observer(dc_motor):
    """Sec. VIII: second observer, poles −1, −2, ε = 1 → K ≈ [3, 0]ᵀ (not [3, 1]ᵀ: D_q kept)."""
    A, _, E, C = dc_motor.linear(sigma1=0.0)
    d = high_gain(A, E, C, eps=1.0, chain_poles=[[-1, -2]])
    expected = observability_gain(A, C, np.array([3.0, 2.0]))
    np.testing.assert_allclose(d.K.ravel(), expected, rtol=PAPER_RTOL)
    np.testing.assert_allclose(d.K.ravel(), [3.0, -0.00204846], rtol=1e-5)


def test_design_system_stabilises_true_motor(dc_motor):
    """Sec. VIII: the σ1 = 0 design stabilises the σ1 = 0.6 error dynamics at ε = 1."""
    A0, _, E0, C = dc_motor.linear(sigma1=0.0)
    A, _, E, _ = dc_motor.linear()
    d = modified_high_gain(A0, E0, C, eps=1.0)
    rep = apply_design(d, A, E, C)
    assert rep.stable
    A_e, _, C_e = extended_system(A, E, C)
    np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(A_e - d.K @ C_e)), rep.eig_true)


def _split_spectrum(d, zeros, b_poles):
    """Remove the zeros and b-poles from eig(A − KC) (nearest match); return the rest."""
    rest = list(d.eigenvalues)
    removed = []
    for z in list(zeros) + list(b_poles):
        i = int(np.argmin(np.abs(np.array(rest) - z)))
        removed.append((z, rest.pop(i)))
    return removed, np.array(rest)


def _chain_error(d, rest, eps):
    targets = np.concatenate([np.roots(np.r_[1.0, Kb]) for Kb in d.K_bar])
    return max(min(abs(eps * lam - t) for t in targets) for lam in rest)


def _roundoff_bound(M, eps):
    """First-order bound on the round-off error of ε·λ for the eigenvalues λ of M."""
    _, left, right = scipy.linalg.eig(M, left=True, right=True)
    kappa = 1.0 / np.abs(np.sum(left.conj() * right, axis=0))
    return eps * kappa.max() * np.finfo(float).eps * np.linalg.norm(M, 2)


def test_remark_2(known_system):
    """eig(A − K(ε)C) ⊃ zeros and b-poles exactly; ελ → eig(H_j) with an O(ε) error."""
    ks = known_system
    b_poles = [-2.0 - 0.5 * i for i in range(ks.n_b)]
    used, errors = [], []
    for eps in REMARK_2_EPS:
        d = high_gain(ks.A, ks.B, ks.C, eps, b_poles=b_poles)
        removed, rest = _split_spectrum(d, ks.zeros, b_poles)
        for want, got in removed:
            # eig is backward stable: its error is ~ machine eps·‖A − KC‖·κ, and ‖K‖ ~ ε^−n_q
            tol = max(EXACT_RTOL, 1e3 * np.finfo(float).eps * np.linalg.norm(d.K @ ks.C, 2))
            assert abs(got - want) <= tol * max(1.0, abs(want)), (want, got, tol)
        assert rest.size == sum(ks.chain_lengths)
        error = _chain_error(d, rest, eps)
        if _roundoff_bound(ks.A - d.K @ ks.C, eps) <= ROUNDOFF_SHARE * error:
            used.append(eps)
            errors.append(error)
    assert len(used) >= 3, f"only {used} are computable: too few points for a rate"
    errors = np.array(errors)
    assert np.all(np.diff(errors) < 0), errors
    slope = np.polyfit(np.log10(used), np.log10(errors), 1)[0]
    assert slope > 0.7, (used, errors, slope)    # O(ε): slope ≈ 1 on the log-log scale


def test_uncorrected_exponents_fail_on_chains_1_and_3():
    """The corrigendum: with the original exponents ε^(n̄_q − n_qj + i) the length-1 chain's
    pole scales like 1/ε³, so ελ does not converge to eig(H_1)."""
    ks = random_scb_system(np.random.default_rng(11), chain_lengths=(1, 3), n_a=1)
    errors_ok, errors_bad = [], []
    for eps in EPS_SWEEP:
        d = high_gain(ks.A, ks.B, ks.C, eps)
        K_bad = high_gain(ks.A, ks.B, ks.C, eps, scaling="original").K
        for K, out in ((d.K, errors_ok), (K_bad, errors_bad)):
            eig = np.linalg.eigvals(ks.A - K @ ks.C)
            # the eigenvalues at the zeros, to eig's round-off (~ machine eps·‖KC‖, as in
            # the test above: ‖K‖ ~ ε^−3 here; a fixed 1e-6 kept one of them on LAPACK builds
            # of the lowest supported NumPy at ε = 1e-3)
            tol = max(1e-6, 1e3 * np.finfo(float).eps * np.linalg.norm(K @ ks.C, 2))
            rest = [lam for lam in eig
                    if min(abs(lam - z) for z in ks.zeros) > tol * max(1.0, abs(lam))]
            out.append(_chain_error(d, rest, eps))
    assert errors_ok[-1] < 0.05
    assert errors_bad[-1] > 10 * errors_bad[0] or errors_bad[-1] > 1.0


def test_chain_pole_specifications(rng):
    ks = random_scb_system(rng, chain_lengths=(1, 2), n_a=1)
    d1 = high_gain(ks.A, ks.B, ks.C, 0.5, chain_poles=[[-3], [-1 + 1j, -1 - 1j]])
    np.testing.assert_allclose(d1.K_bar[1], [2.0, 2.0])
    d2 = high_gain(ks.A, ks.B, ks.C, 0.5, chain_poles=lambda n: [-2.0] * n)
    np.testing.assert_allclose(d2.K_bar[0], [2.0])
    np.testing.assert_allclose(d2.K_bar[1], [4.0, 4.0])


@pytest.mark.parametrize("name", [k for k, v in STRUCTURES.items() if v[2] > 0])
def test_repeated_b_poles(name):
    """Repeated b-poles: det(sI − (A_b − K_bb C_b)) = (s + 2)^n_b (checked on coefficients,
    which, unlike a multiple eigenvalue, are well-conditioned)."""
    lengths, n_a, n_b, r_b = STRUCTURES[name]
    ks = random_scb_system(np.random.default_rng(5), chain_lengths=lengths, n_a=n_a, n_b=n_b,
                           r_b=r_b)
    d = high_gain(ks.A, ks.B, ks.C, 0.1, b_poles=[-2.0] * ks.n_b)
    F = d.scb.A_b - d.K_bb @ d.scb.C_b
    np.testing.assert_allclose(np.poly(F), np.poly([-2.0] * ks.n_b), rtol=1e-6, atol=1e-6)


def test_place_observer_repeated_poles(rng):
    A = rng.standard_normal((4, 4))
    C = rng.standard_normal((1, 4))
    K = place_observer(A, C, [-1.0, -1.0, -2.0, -2.0])
    eig = np.sort(np.linalg.eigvals(A - K @ C).real)
    np.testing.assert_allclose(eig, [-2, -2, -1, -1], atol=1e-4)


@pytest.mark.parametrize("kwargs, match", [
    (dict(eps=0.0), "eps must be > 0"),
    (dict(eps=-1.0), "eps must be > 0"),
    (dict(eps=1.0, chain_poles=[[-1, 2, -3]]), "open left half-plane"),
    (dict(eps=1.0, chain_poles=[[-1, -2]]), "needs 3 poles"),
    (dict(eps=1.0, chain_poles=[[-1, -2], [-3]]), "one pole list per chain"),
    (dict(eps=1.0, chain_poles=[[-1 + 1j, -1 + 1j, -3]]), "conjugate pairs"),
])
def test_bad_design_input(dc_motor, kwargs, match):
    A, _, E, C = dc_motor.linear(sigma1=0.0)
    with pytest.raises(DesignError, match=match):
        modified_high_gain(A, E, C, **kwargs)


def test_eps_above_one_warns(dc_motor):
    A, _, E, C = dc_motor.linear(sigma1=0.0)
    with pytest.warns(ThetahatWarning, match="eps = 2 > 1"):
        modified_high_gain(A, E, C, eps=2.0)


def test_wrong_number_of_b_poles():
    ks = random_scb_system(np.random.default_rng(3), chain_lengths=(2,), n_b=2, r_b=1)
    with pytest.raises(DesignError, match="b_poles needs 2 poles"):
        high_gain(ks.A, ks.B, ks.C, 0.5, b_poles=[-1.0])


#: K(ε) from ``at`` and from a fresh design follow the same arithmetic on the same SCB and
#: pole placement; they may differ only by rounding in the last transform, amplified by
#: ‖K‖ ~ ε^−n_q: 1e-9 relative to ‖K‖ leaves orders of magnitude of margin.
AT_RTOL = 1e-9


@pytest.mark.parametrize("eps", [0.7, 0.2, 0.03])
def test_at_eps_equals_a_fresh_design(known_system, eps):
    """GainDesign.at(ε) reuses the SCB (corrigendum: only K'_qj depends on ε) and gives the
    design a fresh high_gain(ε) computes: K, the spectrum, the K_x/K_φ split."""
    ks = known_system
    b_poles = [-2.0 - 0.5 * i for i in range(ks.n_b)]
    base = high_gain(ks.A, ks.B, ks.C, 1.0, b_poles=b_poles)
    fresh = high_gain(ks.A, ks.B, ks.C, eps, b_poles=b_poles)
    moved = base.at(eps)
    assert moved.scb is base.scb and moved.eps == eps
    scale = np.linalg.norm(fresh.K)
    np.testing.assert_allclose(moved.K, fresh.K, rtol=0, atol=AT_RTOL * scale)
    np.testing.assert_allclose(moved.K_tilde, fresh.K_tilde, rtol=0, atol=AT_RTOL * scale)
    np.testing.assert_allclose(np.sort_complex(moved.eigenvalues), fresh.eigenvalues,
                               rtol=1e-6)
    assert base.at(1.0) is base


def test_at_eps_keeps_the_modified_split(dc_motor):
    A, _, E, C = dc_motor.linear(sigma1=0.0)
    d = modified_high_gain(A, E, C, eps=1.0, chain_poles=[[-1, -2, -3]]).at(0.25)
    fresh = modified_high_gain(A, E, C, eps=0.25, chain_poles=[[-1, -2, -3]])
    np.testing.assert_allclose(d.K_x, fresh.K_x, rtol=0, atol=AT_RTOL * np.linalg.norm(d.K))
    np.testing.assert_allclose(d.K_phi, fresh.K_phi, rtol=0,
                               atol=AT_RTOL * np.linalg.norm(d.K))
    with pytest.raises(DesignError, match="eps must be > 0"):
        d.at(0.0)
