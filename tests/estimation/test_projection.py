"""The projection operator Proj (Krstić et al. 1995, App. E), the discrete projection, and the
saturation of Remark 3."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from thetahat.errors import DimensionError, NonFiniteError, UpdateLawError
from thetahat.estimation.observer.laws.projection import BOUNDARY_TOL, Projection, Saturation, saturate
from thetahat.model.paramset import Ball, Box, ConvexSet, Ellipsoid, ParameterSet

#: The Lemma E.1 inequalities are exact in real arithmetic; the computed sides differ by
#: rounding of products of τ, Γ and ∇P, so compare with a tolerance relative to their size.
LEMMA_RTOL = 1e-9

_Q = np.array([[2.0, 0.6, 0.0], [0.6, 1.0, 0.2], [0.0, 0.2, 4.0]])
SETS: dict[str, ParameterSet] = {
    "box": Box([-1.0, 0.0, 2.0], [1.0, 3.0, 2.5]),
    "ball": Ball([0.5, -0.5, 0.0], 1.5),
    "ellipsoid": Ellipsoid([0.0, 1.0, -1.0], _Q),
    "convex": ConvexSet(P=lambda t: np.sum(t**4, axis=-1) - 1.0, grad_P=lambda t: 4 * t**3,
                        interior_point=[0.0, 0.0, 0.0]),
}


def _spd(rng: np.random.Generator, p: int, spread: float) -> np.ndarray:
    R, _ = np.linalg.qr(rng.standard_normal((p, p)))
    return R @ np.diag(10.0 ** rng.uniform(-spread, spread, p)) @ R.T


def _theta_hat(ps: ParameterSet, rng: np.random.Generator, kind: str) -> np.ndarray:
    """An estimate in the interior, on a face, or (for the box) at a corner."""
    if kind == "interior":
        return ps.sample(rng, 1)[0]
    if kind == "corner" and isinstance(ps, Box):
        pick = rng.integers(0, 2, ps.dim).astype(bool)
        return np.where(pick, ps.upper, ps.lower)
    return ps.nearest(ps.interior_point + 50 * rng.standard_normal(ps.dim))


case = st.fixed_dictionaries({
    "name": st.sampled_from(sorted(SETS)),
    "kind": st.sampled_from(["interior", "boundary", "corner"]),
    "seed": st.integers(0, 2**32 - 1),
    "spread": st.sampled_from([0.0, 1.0, 3.0]),
    "layer": st.sampled_from([0.0, 0.0, 0.3]),
})


@settings(max_examples=150, deadline=None)
@given(c=case)
def test_proj_satisfies_lemma_E1(c):
    """−θ̃ᵀΓ⁻¹Proj(τ) <= −θ̃ᵀΓ⁻¹τ and Proj(τ)ᵀΓ⁻¹Proj(τ) <= τᵀΓ⁻¹τ (Krstić Lemma E.1)."""
    ps = SETS[c["name"]]
    rng = np.random.default_rng(c["seed"])
    G = _spd(rng, ps.dim, c["spread"])
    pr = Projection(ps, G, layer=c["layer"])
    th_hat = _theta_hat(ps, rng, c["kind"])
    tau = rng.standard_normal((40, ps.dim)) * 10.0 ** rng.uniform(-3, 3, (40, 1))
    theta = ps.sample(rng, 40)
    if c["layer"] > 0:  # the smooth variant assumes θ in the shrunken set {P <= -δ}
        theta = theta[np.all(ps.constraint(theta) <= -c["layer"], axis=-1)]
        tau = tau[: len(theta)]
    w = pr.proj(tau, th_hat)
    Gi = np.linalg.inv(G)
    tt = theta - th_hat
    lhs = -np.einsum("ni,ij,nj->n", tt, Gi, w)
    rhs = -np.einsum("ni,ij,nj->n", tt, Gi, tau)
    scale = np.linalg.norm(tt, axis=-1) * np.linalg.norm(tau, axis=-1) * np.linalg.norm(Gi, 2)
    assert np.all(lhs <= rhs + LEMMA_RTOL * (1 + scale))
    nw = np.einsum("ni,ij,nj->n", w, Gi, w)
    nt = np.einsum("ni,ij,nj->n", tau, Gi, tau)
    assert np.all(nw <= nt * (1 + LEMMA_RTOL) + 1e-300)


@settings(max_examples=100, deadline=None)
@given(c=case)
@example(c={"name": "box", "kind": "boundary", "seed": 299, "spread": 3.0, "layer": 0.0})
def test_proj_never_points_out_of_theta(c):
    """At active constraints a_jᵀProj(τ) <= 0 (θ̂ stays in Θ); inside, Proj(τ) = τ."""
    ps = SETS[c["name"]]
    rng = np.random.default_rng(c["seed"])
    pr = Projection(ps, _spd(rng, ps.dim, c["spread"]), layer=c["layer"])
    th_hat = _theta_hat(ps, rng, c["kind"])
    tau = rng.standard_normal((30, ps.dim)) * 10.0 ** rng.uniform(-3, 3, (30, 1))
    w = pr.proj(tau, th_hat)
    P = ps.constraint(th_hat)
    A = ps.constraint_grad(th_hat)
    active = P >= -BOUNDARY_TOL
    out = (w @ A[active].T) / (np.linalg.norm(A[active], axis=-1) * np.linalg.norm(tau, axis=-1,
                                                                                keepdims=True))
    # the correction solves the dual in Γ's metric (a Cholesky factor of AΓAᵀ): rounding of
    # order ε·cond(Γ) relative to |τ| remains where the exact answer is on the face (w ⟂ a_j,
    # or 0 at a corner); 100 covers p ≤ 3 and the sums (seed 299 at a box corner, cond(Γ) =
    # 5.5e5 from spread 3: 3.0e-9, where ε·cond(Γ) = 1.2e-10)
    assert np.all(out <= LEMMA_RTOL + 100 * np.finfo(float).eps * np.linalg.cond(pr.Gamma))
    inner = -c["layer"] if c["layer"] > 0 else -BOUNDARY_TOL
    if np.all(P < inner):
        assert np.array_equal(w, tau)


def test_single_constraint_matches_krstic_formula():
    """On the sphere, Proj(τ) = τ - Γ∇P∇Pᵀτ/(∇PᵀΓ∇P) when ∇Pᵀτ > 0 (App. E, (E.3))."""
    rng = np.random.default_rng(4)
    ball = SETS["ball"]
    G = _spd(rng, 3, 1.0)
    pr = Projection(ball, G)
    th = ball.nearest(ball.center + [3.0, 1.0, -2.0])
    a = ball.constraint_grad(th)[0]
    for tau in rng.standard_normal((20, 3)):
        expect = tau - G @ a * (a @ tau) / (a @ G @ a) if a @ tau > 0 else tau
        assert np.allclose(pr.proj(tau, th), expect, rtol=1e-12, atol=1e-14)


def test_smooth_variant_interpolates_in_the_layer():
    """With layer δ the correction is scaled by c = min(1, 1 + P/δ) (App. E, (E.4))."""
    ball = Ball([0.0, 0.0], 1.0)
    tau = np.array([1.0, 0.5])
    hard = Projection(ball).proj(tau, [1.0, 0.0])
    for r, c in ((0.9, 0.0), (np.sqrt(0.95), 0.5), (1.0, 1.0)):
        w = Projection(ball, layer=0.1).proj(tau, [r, 0.0])
        assert np.allclose(w, tau + c * (hard - tau), atol=1e-12)


def test_box_corner_with_coupled_gain_uses_both_faces():
    """At a corner with non-diagonal Γ, projecting on one face alone would leave the box."""
    box = Box([0.0, 0.0], [1.0, 1.0])
    G = np.array([[1.0, -0.9], [-0.9, 1.0]])
    tau = np.array([1.0, -0.5])  # out through θ₁ = 1, inward for θ₂
    w = Projection(box, G).proj(tau, [1.0, 1.0])
    single = tau - G @ [1.0, 0.0] * tau[0] / G[0, 0]  # Krstić formula on the face θ₁ = 1 only
    assert single[1] > 0  # ... which would push θ₂ out through the face θ₂ = 1
    assert np.all(w <= 1e-12)
    # KKT of the Γ⁻¹-weighted projection onto {w₁ <= 0, w₂ <= 0}: Γ⁻¹(τ - w) = μ >= 0, μ ⊥ w
    mu = np.linalg.solve(G, tau - w)
    assert np.all(mu >= -1e-12) and np.allclose(mu * w, 0.0, atol=1e-12)


def test_proj_batches_and_validates():
    ps = SETS["box"]
    pr = Projection(ps, np.diag([1.0, 2.0, 3.0]))
    rng = np.random.default_rng(5)
    th = np.stack([_theta_hat(ps, rng, k) for k in ("interior", "boundary", "corner")])
    tau = rng.standard_normal((3, 3))
    batch = pr.proj(tau, th)
    assert np.allclose(batch, [pr.proj(t, h) for t, h in zip(tau, th)], atol=0)
    assert pr.proj(tau[:, None, :], th[None, :, :]).shape == (3, 3, 3)
    with pytest.raises(DimensionError, match=r"tau must have shape \(\.\.\., 3\)"):
        pr.proj([1.0, 2.0], th[0])
    with pytest.raises(NonFiniteError, match="finite"):
        pr.proj([np.nan, 0.0, 0.0], th[0])


@pytest.mark.parametrize("Gamma, match", [
    ([[1.0, 0.5], [0.0, 1.0]], "symmetric"),
    ([[1.0, 0.0], [0.0, -2.0]], "positive definite"),
    (0.0, "positive definite"),
    ([[1.0, np.inf], [np.inf, 1.0]], "NaN or inf"),
    (np.eye(3), r"\(2, 2\) matrix"),
])
def test_gain_validation(Gamma, match):
    with pytest.raises(UpdateLawError, match=match):
        Projection(Box([0.0, 0.0], [1.0, 1.0]), Gamma)


def test_layer_validation():
    with pytest.raises(UpdateLawError, match="layer must be finite and >= 0"):
        Projection(Box([0.0], [1.0]), layer=-0.1)


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(sorted(SETS)), seed=st.integers(0, 2**32 - 1),
       spread=st.sampled_from([0.0, 1.0, 2.0]))
def test_discrete_projection_is_nonexpansive_in_the_gain_norm(name, seed, spread):
    """‖Π(z) - θ‖_Γ⁻¹ <= ‖z - θ‖_Γ⁻¹ for θ ∈ Θ: V = ½θ̃ᵀΓ⁻¹θ̃ never grows by projecting."""
    ps = SETS[name]
    rng = np.random.default_rng(seed)
    G = _spd(rng, ps.dim, spread)
    pr = Projection(ps, G)
    z = ps.interior_point + rng.standard_normal(ps.dim) * 10.0 ** rng.uniform(-1, 3)
    x = pr.project(z)
    assert ps.contains(x)
    Gi = np.linalg.inv(G)
    theta = ps.sample(rng, 30)
    before = np.einsum("ni,ij,nj->n", z - theta, Gi, z - theta)
    after = np.einsum("ni,ij,nj->n", x - theta, Gi, x - theta)
    assert np.all(after <= before * (1 + 1e-9))


# --------------------------------------------------------------------------- saturation

BOX2 = Box([-1.0, 0.0], [1.0, 2.0])
values = st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=2, max_size=2).map(np.array)


@settings(max_examples=80, deadline=None)
@given(a=values, b=values, margin=st.sampled_from([0.0, 0.1, 1.0]))
def test_saturation_is_identity_inside_bounded_and_1_lipschitz(a, b, margin):
    sa, sb = saturate(a, BOX2, margin=margin), saturate(b, BOX2, margin=margin)
    assert np.all(np.abs(sa - sb) <= np.abs(a - b) * (1 + 1e-12) + 1e-12)
    assert np.all(sa >= BOX2.lower - margin) and np.all(sa <= BOX2.upper + margin)
    inside = (a >= BOX2.lower) & (a <= BOX2.upper)
    assert np.array_equal(sa[inside], a[inside])


def test_smooth_saturation_is_continuously_differentiable():
    h = 1e-7
    for edge in (BOX2.upper[0], BOX2.lower[0]):
        for side in (-1.0, 1.0):
            x0 = edge + side * 1e-5
            d = (saturate([x0 + h, 1.0], BOX2, margin=0.5)[0]
                 - saturate([x0 - h, 1.0], BOX2, margin=0.5)[0]) / (2 * h)
            assert abs(d - 1.0) < 1e-4  # slope 1 on both sides of the box edge
    assert saturate([50.0, 1.0], BOX2, margin=0.5)[0] == pytest.approx(1.5)
    assert saturate([50.0, 1.0], BOX2)[0] == 1.0


def test_saturation_object_and_errors():
    sat = Saturation(x_box=BOX2, phi_box=Box([-3.0], [3.0]), margin=0.0)
    x, phi = sat.apply([[5.0, -5.0]], [[10.0]])
    assert x.tolist() == [[1.0, 0.0]] and phi.tolist() == [[3.0]]
    x, phi = Saturation().apply([5.0, -5.0], [10.0])
    assert x.tolist() == [5.0, -5.0] and phi.tolist() == [10.0]
    with pytest.raises(UpdateLawError, match="margin must be finite and >= 0"):
        Saturation(x_box=BOX2, margin=-1.0)
    with pytest.raises(DimensionError, match="x_box must be a thetahat Box"):
        Saturation(x_box=Ball([0.0], 1.0))
    with pytest.raises(DimensionError, match=r"value must have shape \(\.\.\., 2\)"):
        saturate([1.0, 2.0, 3.0], BOX2)
