"""The step written once: the primitives' two bindings agree, and the emitted scalar module
(the formulas after the syntax rewrite, run as plain Python, no numba) reproduces ``run``.

Tolerances: a product or a solve summed in another order differs by a few ulps of its largest
term; 1e-12 relative leaves a margin of ~100× on these well-scaled inputs. The scalar expm is
a degree-20 Taylor series with scaling and squaring, SciPy's a Padé approximant: both are
accurate to ~1e-15 relative for the norms used, so 1e-12 again.
"""

from __future__ import annotations

import ast
import importlib.util
import inspect
import math

import numpy as np
import pytest
import scipy.linalg

from thetahat.estimation.observer import formulas
from thetahat.estimation.observer.laws import formulas as law_formulas
from thetahat.estimation.kernels import scalar_primitives as sc
from thetahat.estimation.observer.compiled import kernel_arrays, kernel_parts, kernel_work, phi_table
from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.estimation.kernels.primitives import (ARRAYS, NUMPY, NUMPY_ROW, PRIMITIVES, AliasingError,
                                            bind, check_aliasing)
from thetahat.estimation.observer.redesign import SecondObserver
from thetahat.estimation.observer.kernel_source import LAWS, kernel_source
from thetahat.estimation.observer.laws import (AlgebraicInversion, ConstantLaw, GradientInversion,
                                             IntermittentInversion, smooth_ramp)
from thetahat.model.paramset import Box
from thetahat.models import lugre

RTOL = 1e-12
B = 5


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


def test_both_bindings_cover_the_vocabulary() -> None:
    assert set(NUMPY) == set(PRIMITIVES)
    assert set(sc.SCALAR_PRIMITIVES) == set(PRIMITIVES)


def test_formulas_import_nothing_they_call() -> None:
    """The formula modules hold definitions only: no imports besides typing helpers and, for
    the type checker only, the named argument tuples (kernel_args) they read."""
    for module in (formulas, law_formulas):
        tree = ast.parse(inspect.getsource(module))
        imported = {alias.name for node in ast.walk(tree)
                    if isinstance(node, (ast.Import, ast.ImportFrom))
                    for alias in node.names}
        assert imported <= {"annotations", "Callable", "Any", "TYPE_CHECKING", "LawArrays",
                            "PlanArrays", "SecondArrays"}, (module.__name__, imported)


@pytest.mark.parametrize("acc", [0, 1, -1])
def test_mv_rows_agree(rng: np.random.Generator, acc: int) -> None:
    M = rng.normal(size=(B, 3, 4))
    x = rng.normal(size=(B, 6))
    out_np = rng.normal(size=(B, 5))
    out_sc = out_np.copy()
    NUMPY["mv"](M, 3, 4, x, 2, out_np, 1, acc)
    for b in range(B):
        sc.mv(M[b], 3, 4, x[b], 2, out_sc[b], 1, acc)
    np.testing.assert_allclose(out_np, out_sc, rtol=RTOL)


@pytest.mark.parametrize("acc", [0, 1])
def test_mm_rows_agree(rng: np.random.Generator, acc: int) -> None:
    A, Bm = rng.normal(size=(1, 3, 2)), rng.normal(size=(B, 2, 4))
    out_np = rng.normal(size=(B, 5, 6))
    out_sc = out_np.copy()
    NUMPY["mm"](A, Bm, 3, 2, 4, out_np, 1, 2, acc)
    for b in range(B):
        sc.mm(A[0], Bm[b], 3, 2, 4, out_sc[b], 1, 2, acc)
    np.testing.assert_allclose(out_np, out_sc, rtol=RTOL)
    G, J = rng.normal(size=(B, 2, 2)), rng.normal(size=(B, 3, 2))
    t_np, t_sc = np.empty((B, 2, 3)), np.empty((B, 2, 3))
    NUMPY["mmt"](G, J, 2, 2, 3, t_np)
    for b in range(B):
        sc.mmt(G[b], J[b], 2, 2, 3, t_sc[b])
    np.testing.assert_allclose(t_np, t_sc, rtol=RTOL)


def test_solve_and_eye_minus_agree_with_lapack(rng: np.random.Generator) -> None:
    q = 4
    N = rng.normal(size=(B, q, q))
    M_np = N.copy()
    NUMPY["eye_minus"](M_np, q, 0.5)
    np.testing.assert_allclose(M_np, np.eye(q) - 0.5 * N, rtol=RTOL)
    rhs = rng.normal(size=(B, q))
    expected = np.linalg.solve(M_np, rhs[..., None])[..., 0]
    for b in range(B):
        M, r = M_np[b].copy(), rhs[b].copy()
        sc.solve(q, M, r)                      # pivoted elimination: a permutation is needed
        np.testing.assert_allclose(r, expected[b], rtol=1e-10)
    x = rhs.copy()
    NUMPY["solve"](q, M_np.copy(), x)
    np.testing.assert_allclose(x, expected, rtol=RTOL)


@pytest.mark.parametrize("scale", [0.1, 3.0, 40.0])
def test_scalar_expm_matches_scipy(rng: np.random.Generator, scale: float) -> None:
    """Scale 40 needs squarings (‖Z‖₁ ≫ 1/2); Z has the law's shape [[−K dt, f dt], [0, 0]]."""
    Z = np.zeros((3, 3))
    Z[:2, :2] = -scale * (np.eye(2) + 0.3 * rng.normal(size=(2, 2)))
    Z[:2, 2] = scale * rng.normal(size=2)
    E, T, U = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    sc.expm(3, Z, E, T, U)
    ref = scipy.linalg.expm(Z)
    np.testing.assert_allclose(E, ref, rtol=1e-11, atol=1e-13 * np.abs(ref).max())


def test_elementwise_primitives_agree() -> None:
    values = [0.0, -0.0, 1.5, -2.0, 1e300, -1e300, math.inf, -math.inf, math.nan, -800.0,
              sc.EXP_TINY_ARG, math.nextafter(sc.EXP_TINY_ARG, -math.inf)]
    arr = np.array(values)
    for name in ("isfinite", "isnan", "absolute"):
        got_np = NUMPY[name](arr)
        got_sc = [sc.SCALAR_PRIMITIVES[name](v) for v in values]
        np.testing.assert_array_equal(got_np, np.array(got_sc), err_msg=name)
    # exp: plain Python raises OverflowError where numba's math.exp returns inf, so the
    # overflowing arguments are left out; the underflow cut-off (exact 0 and 5e-324) and NaN
    # are in. NumPy's SIMD exp and libm's may differ by an ulp (numpy 1.26): rtol 1e-15.
    small = [v for v in values if not v > 709.0]
    np.testing.assert_allclose(NUMPY["exp"](np.array(small)), [sc.exp(v) for v in small],
                               rtol=1e-15, atol=0)
    assert sc.exp(math.nextafter(sc.EXP_TINY_ARG, -math.inf)) == 0.0
    assert sc.exp(sc.EXP_TINY_ARG) == math.exp(sc.EXP_TINY_ARG) > 0.0
    np.testing.assert_array_equal(NUMPY["clip"](arr, -1.0, 1.0),
                                  [sc.clip(v, -1.0, 1.0) for v in values])
    assert NUMPY["count_"](np.isnan(arr)) == sum(sc.count_(math.isnan(v)) for v in values)
    big = np.array([[3e300, 4e300], [0.0, 0.0], [1.0, -1.0]])
    np.testing.assert_allclose(NUMPY["norm"](big, 2), [sc.norm(r, 2) for r in big], rtol=RTOL)
    np.testing.assert_allclose(NUMPY["sumsq"](big[1:], 2), [sc.sumsq(r, 2) for r in big[1:]],
                               rtol=RTOL)


# ------------------------------------------------------------------ the emitted scalar module
def _observer(law: str, second: str) -> ModifiedHighGainObserver:
    system = lugre.system()
    d1, d2 = lugre.designs(1.0)
    box = Box([0.05], [1.0])
    ts = lugre.theta_star()
    laws = {"held": ConstantLaw([0.4], box),
            "algebraic": AlgebraicInversion(ts, 2.0, box, on_invalid="freeze"),
            "ramp": IntermittentInversion(ts, smooth_ramp(*lugre.EXCITATION), 2.0, box),
            "gradient": GradientInversion(lugre.perturbation(), 50.0, box)}
    obs2 = None if second == "none" else SecondObserver(
        system=system, K_x=d2.K, g_on_estimates=second == "estimates")
    return ModifiedHighGainObserver(system=system, K_x=d1.K_x, K_phi=d1.K_phi,
                                    update_law=laws[law], second=obs2)


@pytest.mark.parametrize("law, second", [("held", "none"), ("algebraic", "y"),
                                         ("ramp", "estimates"), ("gradient", "estimates")])
def test_emitted_module_runs_the_formulas_as_python(law: str, second: str) -> None:
    """The compiled path's source, without numba, equals the NumPy back end's run."""
    obs = _observer(law, second)
    data = lugre.simulate(seed=3, t_end=0.12)
    dt = float(data.t[1] - data.t[0])
    parts = kernel_parts(obs)
    ts = parts.theta_star
    source = kernel_source(parts.perturbation, None if ts is None else ts.expr,
                           None if ts is None else ts.arguments, LAWS[parts.code], numba=False)
    namespace: dict[str, object] = {"__name__": "thetahat_kernel_test"}
    exec(compile(source, "<kernel>", "exec"), namespace)   # our generated text, no numba
    plan = obs.plan(dt)
    P, P2, LP, flags = kernel_arrays(parts, plan)
    W, rows = kernel_work(plan.layout)
    N = data.t.size
    dts = np.diff(data.t)
    ok = np.ones(N, dtype=bool)
    plan_of, PH = phi_table(obs, dts, ok[:-1])
    S, PHI = np.empty((N, obs.state_size)), np.empty((N, plan.layout.k))
    s0 = obs.init(theta_hat0=[0.5])
    U, Y = data.u.reshape(N, -1), data.y.reshape(N, -1)
    with np.errstate(all="ignore"):     # numba's error_model='numpy': NaN, not a warning
        status, _ = namespace["kernel_run"](s0, U, Y, dts, ok, plan_of, PH, P, P2, LP, *flags,
                                            False, W, rows, S, PHI)
    assert status == 0
    ref = obs.run(data.t, data.u, data.y, state0=s0)
    scale = np.abs(ref.x_hat).max(axis=0)
    np.testing.assert_allclose(S[:, plan.layout.x], ref.x_hat, rtol=0, atol=1e-10 * scale.max())
    np.testing.assert_allclose(S[:, plan.layout.theta], ref.theta_hat, rtol=1e-10)
    np.testing.assert_allclose(PHI, ref.phi_hat, rtol=0,
                               atol=1e-10 * np.abs(ref.phi_hat).max())
    assert np.all((S[:, plan.layout.theta] >= 0.05) & (S[:, plan.layout.theta] <= 1.0))


def test_row_binding_agrees_with_the_batch_binding(rng: np.random.Generator) -> None:
    """NUMPY_ROW (one row, used by step/run) means what NUMPY means on a batch of one."""
    from thetahat.estimation.kernels.primitives import NUMPY_ROW
    M, x = rng.normal(size=(3, 4)), rng.normal(size=6)
    for acc in (0, 1, -1):
        a, b = rng.normal(size=5), None
        b = a.copy()
        NUMPY_ROW["mv"](M, 3, 4, x, 2, a, 1, acc)
        NUMPY["mv"](M, 3, 4, x[None], 2, b[None], 1, acc)
        np.testing.assert_allclose(a, b, rtol=RTOL)
    A, Bm = rng.normal(size=(2, 3)), rng.normal(size=(3, 2))
    o1, o2 = np.zeros((4, 4)), np.zeros((1, 4, 4))
    NUMPY_ROW["mm"](A, Bm, 2, 3, 2, o1, 1, 2, 0)
    NUMPY["mm"](A, Bm, 2, 3, 2, o2, 1, 2, 0)
    np.testing.assert_allclose(o1, o2[0], rtol=RTOL)
    N = rng.normal(size=(3, 3))
    r1, r2 = N.copy(), N[None].copy()
    NUMPY_ROW["eye_minus"](r1, 3, 0.5)
    NUMPY["eye_minus"](r2, 3, 0.5)
    np.testing.assert_array_equal(r1, r2[0])
    for v in (0.3, -2.0, 7.0, math.nan):
        assert np.array_equal(NUMPY_ROW["clip"](v, -1.0, 1.0), NUMPY["clip"](v, -1.0, 1.0),
                              equal_nan=True)
        assert NUMPY_ROW["where"](v > 0.0, 1.0, 2.0) == NUMPY["where"](v > 0.0, 1.0, 2.0)
        assert NUMPY_ROW["isfinite"](v) == NUMPY["isfinite"](v)


# --------------------------------------------------------------------------- aliasing
def test_aliased_output_makes_the_bindings_disagree() -> None:
    """Why aliasing is refused: mv(M, …, x, …, x, …) with the swap M = [[0, 1], [1, 0]] and
    x = [1, 2] gives [2, 1] in NumPy (the product first) and [2, 2] in the scalar loop (x[0]
    written before row 1 reads it)."""
    M = np.array([[0.0, 1.0], [1.0, 0.0]])
    a, b = np.array([1.0, 2.0]), np.array([1.0, 2.0])
    NUMPY["mv"](M, 2, 2, a, 0, a, 0, 0)
    sc.mv(M, 2, 2, b, 0, b, 0, 0)
    assert a.tolist() == [2.0, 1.0] and b.tolist() == [2.0, 2.0]


def _aliased_call(name: str, written: int, other: int) -> str:
    """Source of a call of primitive ``name`` whose array arguments are a0, a1, … except that
    the one at ``other`` repeats the written one (the others are integers)."""
    arrays, _ = ARRAYS[name]
    params = list(inspect.signature(sc.SCALAR_PRIMITIVES[name]).parameters)
    args = [f"a{i}" if i in arrays else "1" for i in range(len(params))]
    args[other] = args[written]
    return f"def formula(a0, a1, a2, a3, a4, a5):\n    {name}({', '.join(args)})\n"


CASES_ALIASED = [(name, w, o) for name, (arrays, written) in ARRAYS.items()
                 for w in written for o in arrays if o != w]


@pytest.mark.parametrize("name, written, other", CASES_ALIASED)
def test_every_primitive_refuses_an_aliased_output_where_bound(tmp_path, name, written, other):
    """Each block primitive, each written argument aliased with each other array argument:
    bind (NumPy, both row and batch) and the scalar emitter refuse the formula."""
    path = tmp_path / f"formula_{name}_{written}_{other}.py"
    path.write_text(_aliased_call(name, written, other), encoding="utf-8")
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)                      # a file: inspect reads its source
    for names in (NUMPY, NUMPY_ROW):
        with pytest.raises(AliasingError, match=f"argument {written + 1} \\(written\\)"):
            bind({"formula": module.formula}, names)
    with pytest.raises(AliasingError):
        check_aliasing(module.formula)


def test_the_formulas_alias_nothing_and_distinct_arguments_pass(tmp_path) -> None:
    for fn in (*formulas.FORMULAS.values(), *law_formulas.LAW_FORMULAS.values()):
        check_aliasing(fn)                               # what every back end binds
    path = tmp_path / "formula_ok.py"
    path.write_text("def formula(M, x, y):\n    mv(M, 2, 2, x, 0, y, 0, 0)\n", encoding="utf-8")
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    M, x, y = np.eye(2), np.array([1.0, 2.0]), np.zeros(2)
    bind({"formula": module.formula}, NUMPY_ROW)["formula"](M, x, y)
    assert y.tolist() == [1.0, 2.0]
