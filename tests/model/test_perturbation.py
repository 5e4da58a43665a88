"""Perturbations g(v, x, θ): symbolic and numeric Jacobians, batches, checks and parsing."""

from __future__ import annotations

import dataclasses
import pickle
import re

import numpy as np
import pytest
import sympy as sp

from thetahat.errors import DimensionError, ModelFileError, NonFiniteError
from thetahat.model.jacobian_check import CHECK_RTOL, JacobianCheck, check_jacobians
from thetahat.model.perturbation import CallablePerturbation, SymbolicPerturbation
from thetahat.model.parse import parse_perturbation

# Sec. VIII: the LuGre friction parameters that stay known (θ = α0 is the unknown one).
SIGMA0, ALPHA1, OMEGA0 = 260.0, 0.05, 0.01
LUGRE_TEXT = "sigma0*eta*Abs(y)/(alpha0 + alpha1*exp(-(omega/omega0)**2))"
LUGRE_CONSTANTS = {"sigma0": SIGMA0, "alpha1": ALPHA1, "omega0": OMEGA0}

#: Two evaluations of the same formula through different code paths (hand-built SymPy vs.
#: parsed text, or SymPy vs. numpy) differ only by rounding.
SAME_FORMULA_RTOL = 1e-12
#: Central differences with h ≈ 6e-6 max(|z|, 1) are accurate to ~1e-9 relative for the
#: smooth, well-scaled test functions used here (not LuGre, see CHECK_RTOL).
FD_RTOL = 1e-7


def _zeta(omega, theta):
    return theta + ALPHA1 * np.exp(-((omega / OMEGA0) ** 2))


@pytest.fixture(scope="module")
def lugre() -> SymbolicPerturbation:
    torque, y, omega, eta, alpha0 = sp.symbols("torque y omega eta alpha0")
    expr = SIGMA0 * eta * sp.Abs(y) / (alpha0 + ALPHA1 * sp.exp(-((omega / OMEGA0) ** 2)))
    return SymbolicPerturbation.from_sympy(expr, u=[torque], y=[y], x=[omega, eta],
                                           theta=[alpha0])


def lugre_points(rng: np.random.Generator, shape: tuple[int, ...] = (40,)):
    """Points in the Stribeck region (|ω| up to 5 ω0), away from the kink of |y| at 0."""
    omega = rng.uniform(-0.05, 0.05, shape)
    y = rng.choice([-1.0, 1.0], shape) * rng.uniform(1e-3, 0.1, shape)
    v = np.stack([rng.normal(size=shape), y], axis=-1)
    x = np.stack([omega, rng.uniform(-2e-3, 2e-3, shape)], axis=-1)
    theta = rng.uniform(0.05, 1.0, shape + (1,))
    return v, x, theta


@pytest.fixture(scope="module")
def mimo() -> SymbolicPerturbation:
    """u ∈ R¹, y ∈ R², x ∈ R², θ ∈ R², φ ∈ R²."""
    u1, y1, y2, x1, x2, t1, t2 = sp.symbols("u1 y1 y2 x1 x2 t1 t2")
    expr = sp.Matrix([t1 * sp.sin(x1) * y1 + t2**2 * x2,
                      sp.exp(-t1 * x2) * u1 + t2 * sp.Abs(y2) * x1 + 3])
    return SymbolicPerturbation.from_sympy(expr, u=[u1], y=[y1, y2], x=[x1, x2], theta=[t1, t2])


def mimo_numeric_g(v, x, th):
    return np.stack([th[..., 0] * np.sin(x[..., 0]) * v[..., 1] + th[..., 1] ** 2 * x[..., 1],
                     np.exp(-th[..., 0] * x[..., 1]) * v[..., 0]
                     + th[..., 1] * np.abs(v[..., 2]) * x[..., 0] + 3], axis=-1)


def mimo_points(rng: np.random.Generator, n: int = 30):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.where(np.abs(v[:, 2]) < 0.1, 0.5, v[:, 2])  # away from the kink of |y2|
    return v, rng.normal(size=(n, 2)), rng.normal(size=(n, 2))


# ----------------------------------------------------------------------------------------------
# Symbolic Jacobians
# ----------------------------------------------------------------------------------------------

def test_lugre_dims_and_symbols(lugre):
    assert lugre.dims == (2, 1, 1, 1, 1)
    assert [s.name for s in lugre.x] == ["omega", "eta"]
    assert [s.name for s in lugre.theta] == ["alpha0"]
    assert lugre.expr.shape == (1, 1)


def test_lugre_abs_derivative_is_sign_not_re_im(lugre):
    """Remark 4: g uses |y|; its derivative must be sign(y), free of re/im/Derivative."""
    J = lugre.jacobian("v")
    assert J.shape == (1, 2)
    assert J[0, 0] == 0  # g does not depend on the torque u
    y, = lugre.y
    assert J[0, 1].has(sp.sign(y))
    for atom in (sp.re, sp.im, sp.Derivative):
        assert not J.has(atom)


def test_lugre_jacobians_match_hand_derivation(lugre, rng):
    v, x, th = lugre_points(rng)
    zeta = _zeta(x[:, 0], th[:, 0])
    g = SIGMA0 * x[:, 1] * np.abs(v[:, 1]) / zeta
    np.testing.assert_allclose(lugre.g(v, x, th)[:, 0], g, rtol=SAME_FORMULA_RTOL)
    dv = lugre.dg_dv(v, x, th)
    np.testing.assert_array_equal(dv[:, 0, 0], 0.0)
    np.testing.assert_allclose(dv[:, 0, 1], SIGMA0 * x[:, 1] * np.sign(v[:, 1]) / zeta,
                               rtol=SAME_FORMULA_RTOL)
    dzeta_domega = -2 * x[:, 0] / OMEGA0**2 * ALPHA1 * np.exp(-((x[:, 0] / OMEGA0) ** 2))
    dx = lugre.dg_dx(v, x, th)
    np.testing.assert_allclose(dx[:, 0, 0], -g / zeta * dzeta_domega, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(dx[:, 0, 1], SIGMA0 * np.abs(v[:, 1]) / zeta,
                               rtol=SAME_FORMULA_RTOL)
    np.testing.assert_allclose(lugre.dg_dtheta(v, x, th)[:, 0, 0], -g / zeta,
                               rtol=SAME_FORMULA_RTOL)


def test_lugre_symbolic_matches_finite_differences(lugre, rng):
    report = check_jacobians(lugre, *lugre_points(rng))
    assert report.ok, report
    assert report.n_points == 40
    for comparison in (report.dg_dv, report.dg_dx, report.dg_dtheta):
        assert comparison is not None and comparison.max_rel_error < CHECK_RTOL


def test_mimo_symbolic_matches_finite_differences(mimo, rng):
    assert mimo.dims == (2, 1, 2, 2, 2)
    report = check_jacobians(mimo, *mimo_points(rng), rtol=FD_RTOL)
    assert report.ok, report


def test_mimo_symbolic_matches_numeric_function(mimo, rng):
    v, x, th = mimo_points(rng)
    np.testing.assert_allclose(mimo.g(v, x, th), mimo_numeric_g(v, x, th),
                               rtol=SAME_FORMULA_RTOL)
    fd = CallablePerturbation(g=mimo_numeric_g, n=2, m=1, r=2, p=2, k=2)
    for name in ("dg_dv", "dg_dx", "dg_dtheta"):
        np.testing.assert_allclose(getattr(fd, name)(v, x, th), getattr(mimo, name)(v, x, th),
                                   rtol=FD_RTOL, atol=FD_RTOL)


def test_jacobian_shapes_and_unknown_wrt(mimo):
    assert mimo.jacobian("v").shape == (2, 3)
    assert mimo.jacobian("x").shape == (2, 2)
    assert mimo.jacobian("theta").shape == (2, 2)
    with pytest.raises(DimensionError, match="wrt must be one of"):
        mimo.jacobian("u")


def test_sign_and_max_differentiate_almost_everywhere():
    y, x1, t = sp.symbols("y x1 t")
    pert = SymbolicPerturbation.from_sympy([x1 * sp.sign(y), sp.Max(x1, t)], u=[], y=[y],
                                           x=[x1], theta=[t])
    assert not pert.jacobian("v").has(sp.DiracDelta)
    x = np.array([[2.0], [0.5]])
    dv = pert.dg_dv([-3.0], x, [1.0])
    np.testing.assert_array_equal(dv[:, 0, 0], 0.0)  # d(x1 sign y)/dy = 0 for y != 0
    np.testing.assert_array_equal(pert.dg_dx([-3.0], x, [1.0])[:, 1, 0], [1.0, 0.0])
    np.testing.assert_array_equal(pert.dg_dtheta([-3.0], x, [1.0])[:, 1, 0], [0.0, 1.0])


# ----------------------------------------------------------------------------------------------
# Batches
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("method,width", [("g", None), ("dg_dv", 2), ("dg_dx", 2),
                                          ("dg_dtheta", 1)])
def test_lugre_batch_shapes(lugre, rng, method, width):
    """Scalar batch, (N,) and broadcast (N, 1) x (1, M) batches give pointwise results."""
    f = getattr(lugre, method)
    tail = (1,) if width is None else (1, width)
    v, x, th = lugre_points(rng, (4,))
    single = f(v[0], x[0], th[0])
    assert single.shape == tail
    stacked = f(v, x, th)
    assert stacked.shape == (4,) + tail
    for i in range(4):
        np.testing.assert_allclose(stacked[i], f(v[i], x[i], th[i]), rtol=SAME_FORMULA_RTOL)
    grid = f(v[:, None, :], x[None, :3, :], th[0])
    assert grid.shape == (4, 3) + tail
    np.testing.assert_allclose(grid[2, 1], f(v[2], x[1], th[0]), rtol=SAME_FORMULA_RTOL)


def test_constant_and_partial_entries_broadcast_to_full_batch():
    y, x1, x2, t = sp.symbols("y x1 x2 t")
    pert = SymbolicPerturbation.from_sympy([sp.Integer(3), t * y, x1], u=[], y=[y],
                                           x=[x1, x2], theta=[t])
    v = np.zeros((5, 1, 1))
    x = np.ones((1, 4, 2))
    theta = np.array([2.0])
    g = pert.g(v, x, theta)
    assert g.shape == (5, 4, 3)
    np.testing.assert_array_equal(g[..., 0], 3.0)
    np.testing.assert_array_equal(g[..., 2], 1.0)
    J = pert.dg_dx(v, x, theta)
    assert J.shape == (5, 4, 3, 2)
    np.testing.assert_array_equal(J[..., 2, :], np.broadcast_to([1.0, 0.0], (5, 4, 2)))
    np.testing.assert_array_equal(pert.dg_dtheta(v, x, theta)[..., 1, 0], 0.0)


def test_zero_width_arguments():
    y, x1 = sp.symbols("y x1")
    pert = SymbolicPerturbation.from_sympy(x1 * y, u=[], y=[y], x=[x1], theta=[])
    assert pert.dims == (1, 0, 1, 0, 1)
    assert pert.dg_dtheta(np.ones((3, 1)), np.ones((3, 1)), np.zeros((0,))).shape == (3, 1, 0)


def test_batches_that_do_not_broadcast_are_rejected(lugre):
    with pytest.raises(DimensionError, match="do not broadcast"):
        lugre.g(np.zeros((3, 2)), np.zeros((4, 2)), np.zeros(1))


@pytest.mark.parametrize("args,name,size", [
    ((np.zeros(3), np.zeros(2), np.zeros(1)), "v", 2),
    ((np.zeros(2), np.zeros((5, 3)), np.zeros(1)), "x", 2),
    ((np.zeros(2), np.zeros(2), 0.28), "theta", 1),
])
def test_wrong_last_axis_names_argument_and_shape(lugre, args, name, size):
    with pytest.raises(DimensionError, match=rf"^{name} must have shape \(\.\.\., {size}\)"):
        lugre.dg_dx(*args)


def test_complex_argument_rejected(lugre):
    with pytest.raises(DimensionError, match="x must be real"):
        lugre.g(np.zeros(2), np.zeros(2, dtype=complex), np.ones(1))


def test_nan_propagates_through_dependent_entries(lugre):
    """Documented policy: NaN is not an error here; it reaches every entry that depends on it."""
    v = np.array([[1.0, np.nan], [1.0, 0.5]])
    x, th = np.array([0.01, 1e-3]), np.array([0.28])
    g = lugre.g(v, x, th)
    assert np.isnan(g[0, 0]) and np.isfinite(g[1, 0])
    dv = lugre.dg_dv(v, x, th)
    assert np.isnan(dv[0, 0, 1])
    assert dv[0, 0, 0] == 0.0  # ∂g/∂u ≡ 0 does not depend on y


# ----------------------------------------------------------------------------------------------
# Construction errors and object behaviour
# ----------------------------------------------------------------------------------------------

def test_shared_symbol_between_y_and_x_is_rejected():
    omega, eta, a0 = sp.symbols("omega eta alpha0")
    with pytest.raises(DimensionError, match="in both y and x.*Remark 4"):
        SymbolicPerturbation.from_sympy(eta * sp.Abs(omega) / a0, u=[], y=[omega],
                                        x=[omega, eta], theta=[a0])


@pytest.mark.parametrize("expr,error,match", [
    (sp.Symbol("c") * sp.Symbol("x1"), DimensionError, "not among u, y, x, theta: c"),
    (sp.Function("f")(sp.Symbol("x1")), DimensionError, "undefined functions"),
    ("x1 + 1", DimensionError, "parse_perturbation"),
    (sp.I * sp.Symbol("x1"), DimensionError, "real-valued"),
    (sp.S.One / 0, NonFiniteError, "non-finite"),
    (sp.Float("1e400") * sp.Symbol("x1"), NonFiniteError, "float64 range"),
    (sp.Integer(10) ** 400 + sp.Symbol("x1"), NonFiniteError, "float64 range"),
    (sp.Matrix([[1, 2], [3, 4]]), DimensionError, "vector with k entries"),
    ([], DimensionError, "at least one entry"),
    (sp.Eq(sp.Symbol("x1"), 1), DimensionError, "scalar SymPy expression"),
])
def test_invalid_expressions_are_rejected(expr, error, match):
    x1, y = sp.symbols("x1 y")
    with pytest.raises(error, match=match):
        SymbolicPerturbation.from_sympy(expr, u=[], y=[y], x=[x1], theta=[])


@pytest.mark.parametrize("groups,match", [
    ({"u": [], "y": ["y"], "x": [sp.Symbol("x1")], "theta": []}, "y must hold SymPy symbols"),
    ({"u": [], "y": "y", "x": [sp.Symbol("x1")], "theta": []}, "sequence of SymPy symbols"),
    ({"u": [], "y": [sp.Symbol("y")], "x": [], "theta": []}, "at least one symbol"),
])
def test_invalid_symbol_groups_are_rejected(groups, match):
    with pytest.raises(DimensionError, match=match):
        SymbolicPerturbation.from_sympy(sp.Integer(1), **groups)


def test_symbolic_perturbation_is_frozen_hashable_and_pickles(mimo, rng):
    with pytest.raises(dataclasses.FrozenInstanceError):
        mimo.expr = sp.ImmutableMatrix([0, 0])
    clone = pickle.loads(pickle.dumps(mimo))
    assert clone == mimo and hash(clone) == hash(mimo)
    v, x, th = mimo_points(rng, 5)
    np.testing.assert_array_equal(clone.dg_dx(v, x, th), mimo.dg_dx(v, x, th))


# ----------------------------------------------------------------------------------------------
# CallablePerturbation and check_jacobians
# ----------------------------------------------------------------------------------------------

def lugre_numeric_g(v, x, th):
    return SIGMA0 * x[..., 1:2] * np.abs(v[..., 1:2]) / _zeta(x[..., 0:1], th)


def lugre_numeric_dg_dtheta(v, x, th):
    return (-lugre_numeric_g(v, x, th) / _zeta(x[..., 0:1], th))[..., np.newaxis]


def test_callable_finite_differences_match_symbolic_lugre(lugre, rng):
    pert = CallablePerturbation(g=lugre_numeric_g, n=2, m=1, r=1, p=1, k=1)
    assert pert.supplied_jacobians == ()
    v, x, th = lugre_points(rng)
    for name in ("dg_dv", "dg_dx", "dg_dtheta"):
        exact = getattr(lugre, name)(v, x, th)
        np.testing.assert_allclose(getattr(pert, name)(v, x, th), exact, rtol=CHECK_RTOL,
                                   atol=CHECK_RTOL * np.max(np.abs(exact)))


def test_callable_uses_supplied_jacobian_and_broadcasts_arguments(rng):
    calls = []

    def dg_dtheta(v, x, th):
        calls.append((v.shape, x.shape, th.shape))
        return lugre_numeric_dg_dtheta(v, x, th)

    pert = CallablePerturbation(g=lugre_numeric_g, dg_dtheta=dg_dtheta, n=2, m=1, r=1, p=1,
                                k=1)
    assert pert.supplied_jacobians == ("theta",)
    v, x, th = lugre_points(rng, (3,))
    out = pert.dg_dtheta(v, x, th[0])
    assert out.shape == (3, 1, 1)
    assert calls == [((3, 2), (3, 2), (3, 1))]  # the user sees one common batch shape


def test_check_jacobians_flags_a_wrong_user_jacobian(rng):
    def wrong_dg_dx(v, x, th):  # ∂g/∂η correct, ∂g/∂ω forgotten (set to 0)
        dx = np.zeros(x.shape[:-1] + (1, 2))
        dx[..., 0, 1] = SIGMA0 * np.abs(v[..., 1]) / _zeta(x[..., 0], th[..., 0])
        return dx

    pert = CallablePerturbation(g=lugre_numeric_g, dg_dx=wrong_dg_dx,
                                dg_dtheta=lugre_numeric_dg_dtheta, n=2, m=1, r=1, p=1, k=1)
    v, x, th = lugre_points(rng)
    report = check_jacobians(pert, v, x, th)
    assert isinstance(report, JacobianCheck)
    assert not report.ok
    assert report.dg_dv is None
    assert report.dg_dtheta is not None and report.dg_dtheta.ok
    bad = report.dg_dx
    assert bad is not None and not bad.ok
    batch, row, col = bad.max_abs_index
    assert (row, col) == (0, 0)  # the wrong entry is ∂g/∂ω
    assert bad.value == 0.0 and abs(bad.reference) > 0
    assert bad.max_rel_index[-1] == 0
    text = repr(report)
    assert "ok=False" in text and "dg_dx: MISMATCH" in text and "dg_dtheta: ok" in text


def test_check_jacobians_detects_small_relative_error(mimo, rng):
    """A 0.1 % error in one Jacobian entry is caught with the default tolerances."""
    def g(v, x, th):
        return mimo.g(v, x, th)

    def dg_dv(v, x, th):
        J = mimo.dg_dv(v, x, th)
        J[..., 1, 0] *= 1.001
        return J

    pert = CallablePerturbation(g=g, dg_dv=dg_dv, n=2, m=1, r=2, p=2, k=2)
    report = check_jacobians(pert, *mimo_points(rng))
    assert not report.ok
    assert report.dg_dv.max_rel_error == pytest.approx(1e-3, rel=0.05)


def test_check_jacobians_input_errors(lugre):
    with pytest.raises(NonFiniteError, match="x contains NaN"):
        check_jacobians(lugre, np.ones(2), np.array([np.nan, 0.0]), np.ones(1))
    with pytest.raises(DimensionError, match="rtol must be > 0"):
        check_jacobians(lugre, np.ones(2), np.ones(2), np.ones(1), rtol=0.0)


def test_callable_output_shape_is_checked():
    pert = CallablePerturbation(g=lambda v, x, th: x[0] * th, n=2, m=0, r=1, p=1, k=1)
    with pytest.raises(DimensionError, match=r"returned shape \(3, 2\); expected \(3, 1\)"
                       r".*x\[\.\.\., 0\]"):
        pert.g(np.ones((3, 1)), np.ones((3, 2)), np.ones((3, 1)))


@pytest.mark.parametrize("kwargs,match", [
    ({"n": 0}, "n must be >= 1"),
    ({"k": 1.5}, "k must be an integer"),
    ({"dg_dx": np.eye(2)}, "dg_dx must be callable"),
])
def test_callable_construction_errors(kwargs, match):
    base = {"g": lugre_numeric_g, "n": 2, "m": 1, "r": 1, "p": 1, "k": 1}
    with pytest.raises(DimensionError, match=match):
        CallablePerturbation(**{**base, **kwargs})


def test_finite_difference_step_is_exact_for_quadratics():
    """Central differences are exact for quadratics up to rounding, also for large |x|."""
    pert = CallablePerturbation(g=lambda v, x, th: th * x**2, n=1, m=0, r=1, p=1, k=1)
    x = np.array([[1e-8], [0.3], [-7.0], [1e5]])
    np.testing.assert_allclose(pert.dg_dx(np.zeros(1), x, np.array([2.0]))[:, 0, 0],
                               4 * x[:, 0], rtol=FD_RTOL, atol=FD_RTOL)


# ----------------------------------------------------------------------------------------------
# Parsing
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def parsed_lugre() -> SymbolicPerturbation:
    return parse_perturbation(LUGRE_TEXT, u=["torque"], y=["y"], x=["omega", "eta"],
                              theta=["alpha0"], constants=LUGRE_CONSTANTS)


def test_parser_reproduces_hand_built_lugre(parsed_lugre, lugre, rng):
    assert parsed_lugre.dims == lugre.dims
    assert [s.name for s in parsed_lugre.x] == ["omega", "eta"]
    assert all(s.is_real for s in parsed_lugre.x + parsed_lugre.y + parsed_lugre.theta)
    v, x, th = lugre_points(rng)
    for name in ("g", "dg_dv", "dg_dx", "dg_dtheta"):
        np.testing.assert_allclose(getattr(parsed_lugre, name)(v, x, th),
                                   getattr(lugre, name)(v, x, th), rtol=SAME_FORMULA_RTOL)


def test_parser_vector_and_builtin_functions(rng):
    pert = parse_perturbation(["theta1*tanh(x1) + abs(y1)", "Max(x1, 0) * sqrt(theta2) - pi"],
                              u=[], y="y1", x=["x1"], theta=["theta1", "theta2"])
    assert pert.dims == (1, 0, 1, 2, 2)
    v, x, th = rng.normal(size=(6, 1)), rng.normal(size=(6, 1)), rng.uniform(0.5, 2, (6, 2))
    expected = np.stack([th[:, 0] * np.tanh(x[:, 0]) + np.abs(v[:, 0]),
                         np.maximum(x[:, 0], 0) * np.sqrt(th[:, 1]) - np.pi], axis=-1)
    np.testing.assert_allclose(pert.g(v, x, th), expected, rtol=SAME_FORMULA_RTOL)


@pytest.mark.parametrize("text,token", [
    ("__import__('os')", "the function '__import__'"),
    ("__import__('os').system('ls')", "the function \"__import__('os').system\""),
    ("x.real", "the attribute construct 'x.real'"),
    ("x[0]", "the subscript construct 'x[0]'"),
    ("(lambda: 1)()", "the function 'lambda: 1'"),
    ("lambda: x", "the lambda construct 'lambda: x'"),
    ("foo + x", "the unknown name 'foo'"),
    ("exp", "the function name without a call 'exp'"),
    ("exp(x, 1)", "exp takes 1 argument"),
    ("exp(x=1)", "keyword or starred arguments"),
    ("x ^ 2", "use ** for powers"),
    ("x if y else 1", "'x if y else 1'"),
    ("[x]", "'[x]'"),
    ("x == 1", "'x == 1'"),
    ("'abc'", "the literal \"'abc'\""),
    ("True * x", "the literal 'True'"),
    ("2j * x", "the literal '2j'"),
    ("x % 2", "'x % 2'"),
])
def test_parser_rejects_everything_outside_the_whitelist(text, token):
    with pytest.raises(ModelFileError, match=re.escape(token)) as info:
        parse_perturbation(text, u=[], y=["y"], x=["x"], theta=["t"])
    assert "Allowed:" in str(info.value) or "takes" in str(info.value)


@pytest.mark.parametrize("text,kwargs,match", [
    ("x +", {}, "not a valid expression"),
    ("1/0 + x", {}, "non-finite"),
    ("9**9**9 * x", {}, "not a finite float64"),
    ([], {}, "non-empty list"),
    ("x", {"x": ["1x"]}, "not a valid name"),
    ("x", {"theta": ["exp"]}, "clashes"),
    ("x", {"y": ["x"]}, "declared twice"),
    ("x*c", {"constants": {"c": float("nan")}}, "constant c must be finite"),
    ("x*c", {"constants": {"x": 1.0}}, "clashes"),
])
def test_parser_error_paths(text, kwargs, match):
    names = {"u": [], "y": ["y"], "x": ["x"], "theta": ["t"], **kwargs}
    with pytest.raises(ModelFileError, match=match):
        parse_perturbation(text, **names)


@pytest.mark.parametrize("method", ["g", "dg_dv", "dg_dx", "dg_dtheta"])
def test_a_long_batch_is_evaluated_in_blocks_with_the_same_numbers(mimo, method, monkeypatch):
    """Beyond EVAL_BLOCK samples the printed expression runs a block at a time (its
    intermediates a block long): element-wise arithmetic, so the same numbers to the bit,
    with θ given per sample, as one row, or broadcast from (p,)."""
    import thetahat.model.perturbation as perturbation
    v, x, th = mimo_points(np.random.default_rng(5), 1_000)
    f = getattr(mimo, method)
    wants = [f(v, x, th), f(v, x, th[:1]), f(v, x, th[0])]
    monkeypatch.setattr(perturbation, "EVAL_BLOCK", 64)          # 16 blocks, the last short
    for want, theta in zip(wants, (th, th[:1], th[0])):
        got = f(v, x, theta)
        assert got.shape == want.shape and np.array_equal(got, want)
    assert not np.array_equal(wants[0], wants[2])                 # θ per sample mattered
