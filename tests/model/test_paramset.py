"""Parameter sets Θ: validation, membership, and the projection ``nearest`` (Euclidean and
weighted) for Box, Ball, Ellipsoid and ConvexSet."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from thetahat.errors import DimensionError, NonFiniteError, ParameterSetError
from thetahat.model.paramset import Ball, Box, ConvexSet, Ellipsoid, ParameterSet

#: Projections are exact up to rounding (clip, radial scaling, secular equation) or up to the
#: Newton tolerance of ConvexSet (1e-12 relative); 1e-9 leaves room for ill-conditioning.
PROJ_ATOL = 1e-9
#: Variational-inequality check (z - x)ᵀW(θ - x) <= tol, scaled by the distances involved.
VI_RTOL = 1e-8

Q_ROT = np.array([[np.cos(0.6), -np.sin(0.6)], [np.sin(0.6), np.cos(0.6)]])
Q_ELL = Q_ROT @ np.diag([1.0, 25.0]) @ Q_ROT.T  # semi-axes 1 and 0.2, rotated
C_ELL = np.array([0.5, -0.3])


def _ellipsoid_as_convex() -> ConvexSet:
    return ConvexSet(P=lambda t: np.einsum("...i,ij,...j->...", t - C_ELL, Q_ELL, t - C_ELL) - 1,
                     grad_P=lambda t: 2.0 * (t - C_ELL) @ Q_ELL, interior_point=C_ELL)


def _superellipse() -> ConvexSet:
    """|θ₁|⁴ + (θ₂/2)⁴ <= 1: smooth, convex, not quadratic."""
    return ConvexSet(P=lambda t: t[..., 0] ** 4 + (t[..., 1] / 2) ** 4 - 1,
                     grad_P=lambda t: np.stack([4 * t[..., 0] ** 3, t[..., 1] ** 3 / 4], axis=-1),
                     interior_point=[0.1, 0.0])


SETS: dict[str, ParameterSet] = {
    "box": Box([-1.0, 0.0], [1.0, 3.0]),
    "ball": Ball([0.5, -0.5], 1.5),
    "ellipsoid": Ellipsoid(C_ELL, Q_ELL),
    "convex-ellipsoid": _ellipsoid_as_convex(),
    "superellipse": _superellipse(),
}
METRIC = np.array([[2.0, 0.7], [0.7, 0.5]])  # SPD, not diagonal

points = st.lists(st.floats(-50, 50, allow_nan=False), min_size=2, max_size=2).map(np.array)
metrics = st.sampled_from([None, METRIC])
set_names = st.sampled_from(sorted(SETS))


# --------------------------------------------------------------------------- validation

@pytest.mark.parametrize("lower, upper, match", [
    ([0.0, 1.0], [1.0, 1.0], "coordinate 1 has lower=1.0 >= upper=1.0"),
    ([0.0], [1.0, 2.0], "give one bound per parameter"),
    ([np.nan], [1.0], "lower must be finite"),
    ([0.0], [np.inf], "upper must be finite"),
    ([], [], "non-empty"),
])
def test_box_rejects_bad_bounds(lower, upper, match):
    with pytest.raises(ParameterSetError, match=match):
        Box(lower, upper)


@pytest.mark.parametrize("radius", [0.0, -1.0, np.inf, np.nan])
def test_ball_rejects_bad_radius(radius):
    with pytest.raises(ParameterSetError, match="radius must be finite and > 0"):
        Ball([0.0, 0.0], radius)


@pytest.mark.parametrize("Q, match", [
    ([[1.0, 0.5], [0.0, 1.0]], "symmetric"),
    ([[1.0, 0.0], [0.0, -1.0]], "positive definite"),
    ([[1.0, 0.0], [0.0, 0.0]], "positive definite"),
    ([[1.0, np.nan], [np.nan, 1.0]], "NaN"),
    ([[1.0]], r"\(2, 2\) matrix"),
])
def test_ellipsoid_rejects_bad_shape(Q, match):
    with pytest.raises(ParameterSetError, match=match):
        Ellipsoid([0.0, 0.0], Q)


def test_convex_set_sanity_checks():
    P = lambda t: np.sum(t**2, axis=-1) - 1.0  # noqa: E731
    with pytest.raises(ParameterSetError, match="P\\(interior_point\\) must be a finite scalar < 0"):
        ConvexSet(P=P, grad_P=lambda t: 2 * t, interior_point=[2.0, 0.0])
    with pytest.raises(ParameterSetError, match="grad_P disagrees with finite differences"):
        ConvexSet(P=P, grad_P=lambda t: 3 * t, interior_point=[0.0, 0.0])
    with pytest.raises(ParameterSetError, match="must be bounded"):
        ConvexSet(P=lambda t: t[..., 0] ** 2 - 1.0,
                  grad_P=lambda t: np.stack([2 * t[..., 0], 0 * t[..., 1]], axis=-1),
                  interior_point=[0.0, 0.0])
    with pytest.raises(ParameterSetError, match="must map shape"):
        ConvexSet(P=lambda t: np.sum(t**2) - 1.0, grad_P=lambda t: 2 * t,
                  interior_point=[0.0, 0.0])


def test_dimension_and_finiteness_errors():
    box = SETS["box"]
    with pytest.raises(DimensionError, match=r"shape \(\.\.\., 2\)"):
        box.contains([1.0, 2.0, 3.0])
    with pytest.raises(NonFiniteError, match="NaN or inf"):
        box.nearest([np.nan, 0.0])
    with pytest.raises(DimensionError, match="symmetric positive definite"):
        SETS["ball"].nearest([5.0, 5.0], metric=[[1.0, 2.0], [2.0, 1.0]])


# --------------------------------------------------------------------------- membership

@pytest.mark.parametrize("name", sorted(SETS))
def test_constraint_describes_the_set(name):
    """P_j <= 0 for all j exactly where contains() is True; ∇P matches finite differences."""
    ps = SETS[name]
    rng = np.random.default_rng(1)
    c = ps.interior_point
    pts = c + (ps.sample(rng, 400) - c) * rng.uniform(0.5, 2.0, size=(400, 1))
    inside = ps.contains(pts)
    assert np.array_equal(inside, np.all(ps.constraint(pts) <= 0, axis=-1))
    assert 20 < inside.sum() < 380  # the sample straddles the boundary
    h = 1e-6
    for pt in pts[:20]:
        fd = np.stack([(ps.constraint(pt + h * e) - ps.constraint(pt - h * e)) / (2 * h)
                       for e in np.eye(2)], axis=-1)
        assert np.allclose(ps.constraint_grad(pt), fd, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", sorted(SETS))
def test_sample_and_interior_point_are_inside(name):
    ps = SETS[name]
    pts = ps.sample(np.random.default_rng(2), 500)
    assert pts.shape == (500, 2) and np.all(ps.contains(pts))
    assert np.all(ps.constraint(ps.interior_point) < 0)
    # the samples fill the set: their spread is a sizeable part of its extent
    far = ps.nearest(ps.interior_point + 1e3 * np.array([[1, 0], [-1, 0], [0, 1], [0, -1]]))
    extent = far.max(axis=0) - far.min(axis=0)
    assert np.all(pts.max(axis=0) - pts.min(axis=0) > 0.5 * extent)


def test_contains_with_tolerance_is_a_distance():
    for ps, outward in ((SETS["box"], [1.0, 0.0]), (SETS["ball"], [1.0, 0.0]),
                        (SETS["ellipsoid"], Q_ROT[:, 0]), (SETS["superellipse"], [1.0, 0.0])):
        edge = ps.nearest(ps.interior_point + 100 * np.asarray(outward))
        d = np.asarray(outward) / np.linalg.norm(outward)
        assert ps.contains(edge)
        assert not ps.contains(edge + 1e-3 * d)
        assert ps.contains(edge + 1e-3 * d, tol=2e-3)
        assert not ps.contains(edge + 1e-2 * d, tol=2e-3)


# --------------------------------------------------------------------------- projection

def _check_projection(ps: ParameterSet, z: np.ndarray, metric, rng) -> None:
    x = ps.nearest(z, metric=metric)
    W = np.eye(2) if metric is None else metric
    assert x.shape == z.shape
    assert np.all(ps.contains(x)), (z, x)
    if ps.contains(z):
        assert np.allclose(x, z, atol=0)  # identity inside Θ
        return
    # optimality: (z - x)ᵀW(θ - x) <= 0 for every θ ∈ Θ (variational inequality)
    thetas = np.concatenate([ps.sample(rng, 200), ps.nearest(rng.uniform(-60, 60, (50, 2)))])
    vi = (z - x) @ W @ (thetas - x).T
    scale = np.linalg.norm(z - x) * (1 + np.linalg.norm(thetas - x, axis=-1)) * np.max(W)
    assert np.all(vi <= VI_RTOL * scale + PROJ_ATOL), vi.max()


@settings(max_examples=60, deadline=None)
@given(name=set_names, z=points, metric=metrics, seed=st.integers(0, 2**16))
# found by hypothesis: a KKT point with P = 0 in a batch and P = 2.2e-16 evaluated alone
@example(name="superellipse", z=np.array([21.0, 21.0]), metric=None, seed=0)
def test_nearest_is_the_projection(name, z, metric, seed):
    _check_projection(SETS[name], z, metric, np.random.default_rng(seed))


@settings(max_examples=60, deadline=None)
@given(name=set_names, z=points, metric=metrics, seed=st.integers(0, 2**16))
def test_nearest_never_increases_the_distance_to_theta(name, z, metric, seed):
    """‖Π(z) - θ*‖_W <= ‖z - θ*‖_W for every θ* ∈ Θ (the discrete Lemma E.1)."""
    ps = SETS[name]
    W = np.eye(2) if metric is None else metric
    thetas = ps.sample(np.random.default_rng(seed), 50)
    x = ps.nearest(z, metric=metric)
    d_after = np.einsum("ni,ij,nj->n", x - thetas, W, x - thetas)
    d_before = np.einsum("ni,ij,nj->n", z - thetas, W, z - thetas)
    assert np.all(d_after <= d_before * (1 + 1e-10) + PROJ_ATOL)


def test_ellipsoid_secular_solution_matches_general_method():
    """The secular-equation projection agrees with the Newton–KKT projection of ConvexSet."""
    rng = np.random.default_rng(3)
    z = C_ELL + rng.standard_normal((300, 2)) * np.repeat([0.3, 3.0, 300.0], 100)[:, None]
    for metric in (None, METRIC):
        a = SETS["ellipsoid"].nearest(z, metric=metric)
        b = SETS["convex-ellipsoid"].nearest(z, metric=metric)
        assert np.max(np.abs(a - b)) < PROJ_ATOL


@pytest.mark.parametrize("name", sorted(SETS))
def test_nearest_handles_far_points_and_batches(name):
    ps = SETS[name]
    z = np.array([[[1e300, -1e300], [3.0, 0.1]], [[-1e200, 5.0], [0.0, 1e-300]]])
    x = ps.nearest(z)
    assert x.shape == z.shape and np.all(np.isfinite(x)) and np.all(ps.contains(x))
    assert np.allclose(x[0, 1], ps.nearest(z[0, 1]), rtol=0, atol=PROJ_ATOL)
    # far along a direction, the projection is the boundary point with that outward normal
    far = ps.nearest(ps.interior_point + np.array([1e250, 0.0]))
    near = ps.nearest(ps.interior_point + np.array([1e6, 0.0]))
    assert np.allclose(far, near, atol=1e-5)


def test_box_projection_in_a_non_diagonal_metric_is_not_a_clip():
    box = Box([0.0, 0.0], [1.0, 1.0])
    z = np.array([2.0, 0.5])
    W = np.array([[1.0, 0.9], [0.9, 1.0]])
    x = box.nearest(z, metric=W)
    # the minimiser of (x - z)ᵀW(x - z) with x₁ = 1 is x₂ = 0.5 + 0.9, clipped to 1
    assert np.allclose(x, [1.0, 1.0])
    assert np.allclose(box.nearest(z), [1.0, 0.5])
    assert np.allclose(box.nearest(z, metric=np.diag([3.0, 1.0])), [1.0, 0.5])


def test_repr_is_readable():
    assert repr(Box([0, 1], [2, 3])) == "Box(lower=[0.0, 1.0], upper=[2.0, 3.0])"
    assert "radius=2.0" in repr(Ball([0, 0], 2))
    assert "Ellipsoid(center=" in repr(SETS["ellipsoid"])
