"""The step written once: every target printed from the formulas computes the same thing.

The formulas' language (thetahat.estimation.kernels.subset) is printed for three targets —
scalar loops (numba, C), NumPy on one row, NumPy on rows along a leading axis — and each is
checked against an independent NumPy computation; the scalar functions of the vocabulary
against NumPy's and SciPy's; the whole kernel's text (run as plain Python, no numba) against
``run``.

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

from thetahat.errors import UnsupportedError
from thetahat.estimation.kernels import primitives
from thetahat.estimation.kernels import scalar_primitives as sc
from thetahat.estimation.kernels.kernel_cache import load_module
from thetahat.estimation.kernels.modules import ModuleText, numpy_binding
from thetahat.estimation.kernels.printer import Program
from thetahat.estimation.kernels.subset import AliasingError, definition
from thetahat.estimation.observer import formulas
from thetahat.estimation.observer.kernel_data import (kernel_arrays, kernel_parts, kernel_work,
                                                      phi_table)
from thetahat.estimation.observer.kernel_source import LAWS, kernel_program, kernel_source
from thetahat.estimation.observer.laws import (AlgebraicInversion, ConstantLaw, GradientInversion,
                                             IntermittentInversion, smooth_ramp)
from thetahat.estimation.observer.laws import formulas as law_formulas
from thetahat.estimation.observer.observer import ModifiedHighGainObserver
from thetahat.estimation.observer.redesign import SecondObserver
from thetahat.model.paramset import Box
from thetahat.models import lugre

RTOL = 1e-12
B = 5


def test_formulas_import_nothing_they_call() -> None:
    """The formula modules hold definitions only: no imports besides typing helpers and, for
    the type checker only, the named argument tuples (kernel_args) they read."""
    for module in (formulas, law_formulas):
        tree = ast.parse(inspect.getsource(module))
        imported = {alias.name for node in ast.walk(tree)
                    if isinstance(node, (ast.Import, ast.ImportFrom))
                    for alias in node.names}
        assert imported <= {"annotations", "Callable", "Any", "TYPE_CHECKING", "LawArrays",
                            "PlanArrays", "SecondArrays", "WorkArrays"}, (module.__name__, imported)


@pytest.mark.parametrize("law", sorted(set(LAWS.values())))
def test_every_formula_prints_for_every_target(law: str) -> None:
    """Each formula the kernel runs prints for every target; the scalar print has no block
    left (no slice, no product), the batch print no ``@`` (products are batched calls)."""
    prog = kernel_program(law)
    names = prog.closure(["kernel_run"])
    assert {"advance", "implicit_step", law, "kernel_run"} <= set(names)
    for name in names:
        tree = prog.printed(name, "scalar")
        assert not any(isinstance(n, (ast.Slice, ast.MatMult)) for n in ast.walk(tree)), name
    observer = Program({n: definition(f) for n, f in formulas.FORMULAS.items()})
    for name in formulas.FORMULAS:
        for target in ("row", "batch"):
            tree = observer.printed(name, target)
            if target == "batch":
                assert not any(isinstance(n, ast.MatMult) for n in ast.walk(tree)), name


# --------------------------------------------------------------- blocks on every target
BLOCKS = '''
def inner(A, x, out):
    """
    Parameters
    ----------
    A : array, shape (3, 4)
    x : array, shape (4,)
    out : array, shape (3,)
    """
    out[:] = A @ x


def blocks(P, s, y, c, M, N, out, w, K):
    """
    Parameters
    ----------
    P : array, shape (3, 4)
    s : array, shape (9,)
    y : array, shape (3,)
    c : float
    M, N : array, shape (3, 3)
    out : array, shape (9,)
    w : array, shape (3,)
    K : array, shape (3, 3)
    """
    head, mid, tail = s[0:4], s[4:7], s[6:9]
    out_a, out_b = out[0:3], out[3:6]
    out_a[:] = P @ head + c * y - mid
    out_b[:] = y
    out_b -= M @ tail
    inner(P, s[2:6], w)
    out[6:9] = w
    K[:] = eye(3) - c * (M @ N.T)
    K[0:2, 1:3] += N[0:2, 0:2] @ M[0:2, 1:3]
'''


def _reference(P, s, y, c, M, N):
    out = np.empty(9)
    out[0:3] = P @ s[0:4] + c * y - s[4:7]
    out[3:6] = y - M @ s[6:9]
    out[6:9] = P @ s[2:6]
    K = np.eye(3) - c * (M @ N.T)
    K[0:2, 1:3] += N[0:2, 0:2] @ M[0:2, 1:3]
    return out, K


@pytest.fixture(scope="module")
def block_program(tmp_path_factory) -> Program:
    path = tmp_path_factory.mktemp("formulas") / "block_formulas.py"
    path.write_text(BLOCKS, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)                      # a file: inspect reads its source
    return Program({"inner": definition(module.inner), "blocks": definition(module.blocks)})


def test_block_statements_agree_on_every_target(block_program: Program,
                                                 rng: np.random.Generator) -> None:
    """Views with offsets, products (with a transpose and an identity), updates of a block
    and a view passed to another formula: scalar loops, one NumPy row and a NumPy batch each
    equal the same computation written out in NumPy."""
    args = [(rng.normal(size=(3, 4)), rng.normal(size=9), rng.normal(size=3), 0.7,
             rng.normal(size=(3, 3)), rng.normal(size=(3, 3))) for _ in range(B)]
    text = ModuleText("test")
    for name in ("inner", "blocks"):
        text.function(block_program.printed(name, "scalar"))
    scalar = load_module(text.source(), "thetahat_blocks_test")
    row = numpy_binding(block_program, "row", block_program, ["blocks"], "row", dict)
    batch = numpy_binding(block_program, "batch", block_program, ["blocks"], "batch", dict)
    outs = {}
    for name, run in (("scalar", scalar.blocks), ("row", row["blocks"])):
        got = []
        for a in args:
            out, w, K = np.empty(9), np.empty(3), np.empty((3, 3))
            run(*a[:4], *a[4:], out, w, K)
            got.append((out, K))
        outs[name] = got
    stacked = [np.stack([a[i] for a in args]) for i in range(6)]
    out, w, K = np.empty((B, 9)), np.empty((B, 3)), np.empty((B, 3, 3))
    batch["blocks"](*stacked[:3], 0.7, *stacked[4:], out, w, K)
    outs["batch"] = list(zip(out, K))
    for name, got in outs.items():
        for a, (o, k) in zip(args, got):
            want_out, want_K = _reference(*a)
            np.testing.assert_allclose(o, want_out, rtol=RTOL, err_msg=name)
            np.testing.assert_allclose(k, want_K, rtol=RTOL, err_msg=name)


def test_views_are_resolved_at_print_time(block_program: Program) -> None:
    """In the scalar print a view is its array and an offset, and a parameter that receives
    views takes the offset as a further parameter."""
    text = ast.unparse(block_program.printed("blocks", "scalar"))
    assert "head" not in text and "tail" not in text
    assert "s[6 + l_" in text                       # tail = s[6:9] inside M @ tail
    assert "inner(P, s, 2, w)" in text               # the view s[2:6] as (s, 2)
    assert block_program.viewed["inner"] == {"x"}
    inner = block_program.printed("inner", "scalar")
    assert [a.arg for a in inner.args.args] == ["A", "x", "x_at", "out"]


def test_a_block_of_an_undeclared_shape_is_refused(tmp_path) -> None:
    path = tmp_path / "undeclared.py"
    path.write_text("def f(A, x, out):\n    out[:] = A @ x\n", encoding="utf-8")
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with pytest.raises(UnsupportedError, match="not a known array"):
        Program({"f": definition(module.f)}).printed("f", "scalar")


# --------------------------------------------------------------- aliasing
ALIASED = '''
def in_product(M, x):
    """
    Parameters
    ----------
    M : array, shape (2, 2)
    x : array, shape (2,)
    """
    x[:] = M @ x


def shifted(x):
    """
    Parameters
    ----------
    x : array, shape (4,)
    """
    x[0:2] = x[2:4] + x[1:3]


def fine(M, x, y):
    """
    Parameters
    ----------
    M : array, shape (2, 2)
    x, y : array, shape (2,)
    """
    y[:] = M @ x
    y[:] = 2.0 * y - x
'''


@pytest.fixture(scope="module")
def aliased(tmp_path_factory):
    path = tmp_path_factory.mktemp("aliased") / "aliased_formulas.py"
    path.write_text(ALIASED, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return Program({name: definition(getattr(module, name))
                    for name in ("in_product", "shifted", "fine")})


@pytest.mark.parametrize("target", ["scalar", "row", "batch"])
def test_aliased_blocks_are_refused_on_every_target(aliased: Program, target: str) -> None:
    """Why: x[:] = M @ x with the swap M = [[0, 1], [1, 0]] and x = [1, 2] is [2, 1] in NumPy
    (the product first) and [2, 2] in loops (x[0] written before row 1 reads it); and
    x[0:2] = x[2:4] + x[1:3] reads x[1] after the loop wrote it. Every target refuses both."""
    with pytest.raises(AliasingError, match="in a product"):
        aliased.printed("in_product", target)
    with pytest.raises(AliasingError, match="at another offset"):
        aliased.printed("shifted", target)
    aliased.printed("fine", target)                  # the same entry read and written: fine


def test_the_formulas_alias_nothing() -> None:
    """Every formula (the observer's, the laws', the hooks) prints on its targets: none reads
    the array a block statement writes."""
    numpy_side = {*formulas.FORMULAS, *law_formulas.LAW_FORMULAS}
    for law in set(LAWS.values()):
        prog = kernel_program(law)
        for name in prog.closure(["kernel_run"]):
            prog.printed(name, "scalar")
            if name in numpy_side:
                prog.printed(name, "row")
                prog.printed(name, "batch")


# --------------------------------------------------------------- the scalar vocabulary
def test_solve_agrees_with_lapack(rng: np.random.Generator) -> None:
    q = 4
    M = np.eye(q) - 0.5 * rng.normal(size=(B, q, q))
    rhs = rng.normal(size=(B, q))
    expected = np.linalg.solve(M, rhs[..., None])[..., 0]
    for b in range(B):
        Mb, r = M[b].copy(), rhs[b].copy()
        assert sc.solve(q, Mb, r) == 0              # pivoted elimination: a permutation
        np.testing.assert_allclose(r, expected[b], rtol=1e-10)
    x = rhs.copy()
    assert primitives.solve_rows(M.copy(), x).tolist() == [0] * B
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


def test_elementwise_vocabulary_agrees() -> None:
    values = [0.0, -0.0, 1.5, -2.0, 1e300, -1e300, math.inf, -math.inf, math.nan, -800.0,
              sc.EXP_TINY_ARG, math.nextafter(sc.EXP_TINY_ARG, -math.inf)]
    arr = np.array(values)
    np.testing.assert_array_equal(np.isnan(arr), [sc.isnan(v) for v in values])
    # exp: plain Python raises OverflowError where numba's math.exp returns inf, so the
    # overflowing arguments are left out; the underflow cut-off (exact 0 and 5e-324) and NaN
    # are in. NumPy's SIMD exp and libm's may differ by an ulp (numpy 1.26): rtol 1e-15.
    small = [v for v in values if not v > 709.0]
    np.testing.assert_allclose(np.exp(np.array(small)), [sc.exp(v) for v in small],
                               rtol=1e-15, atol=0)
    assert sc.exp(math.nextafter(sc.EXP_TINY_ARG, -math.inf)) == 0.0
    assert sc.exp(sc.EXP_TINY_ARG) == math.exp(sc.EXP_TINY_ARG) > 0.0
    np.testing.assert_array_equal(primitives.clip(arr, -1.0, 1.0),
                                  [min(max(v, -1.0), 1.0) for v in values])   # the scalar clip
    assert primitives.count_rows(np.isnan(arr)) == sum(math.isnan(v) for v in values)
    big = np.array([[3e300, 4e300], [0.0, 0.0], [1.0, -1.0]])
    np.testing.assert_allclose(primitives.norm(big), [sc.norm(2, r) for r in big], rtol=RTOL)
    np.testing.assert_allclose(primitives.sumsq_rows(big[1:]), [sc.sumsq(2, r) for r in big[1:]],
                               rtol=RTOL)


# ------------------------------------------------------------------ the printed kernel
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
def test_printed_kernel_runs_the_formulas_as_python(law: str, second: str) -> None:
    """The compiled path's module, without numba, equals the NumPy back end's run."""
    obs = _observer(law, second)
    data = lugre.simulate(seed=3, t_end=0.12)
    dt = float(data.t[1] - data.t[0])
    parts = kernel_parts(obs)
    ts = parts.theta_star
    source = kernel_source(parts.perturbation, None if ts is None else ts.expr,
                           None if ts is None else ts.arguments, LAWS[parts.code], numba=False)
    kernel = load_module(source, "thetahat_kernel_test")      # the printed text, no numba
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
        status, _ = kernel.kernel_run(s0, U, Y, dts, ok, plan_of, PH, P, P2, LP, *flags,
                                      False, W, rows, S, PHI)
    assert status == 0
    ref = obs.run(data.t, data.u, data.y, state0=s0)
    scale = np.abs(ref.x_hat).max(axis=0)
    np.testing.assert_allclose(S[:, plan.layout.x], ref.x_hat, rtol=0, atol=1e-10 * scale.max())
    np.testing.assert_allclose(S[:, plan.layout.theta], ref.theta_hat, rtol=1e-10)
    np.testing.assert_allclose(PHI, ref.phi_hat, rtol=0,
                               atol=1e-10 * np.abs(ref.phi_hat).max())
    assert np.all((S[:, plan.layout.theta] >= 0.05) & (S[:, plan.layout.theta] <= 1.0))


def test_the_numpy_formulas_are_a_printed_module_file() -> None:
    """The NumPy back end's formulas come from a printed module file of the cache directory
    (no code object rebuilt, nothing executed from a string)."""
    from thetahat.estimation.kernels.kernel_cache import cache_dir
    from thetahat.estimation.observer.step import program
    prog = program()
    env = numpy_binding(prog, "file test", prog, ["advance"], "row",
                        lambda: {name: None for name in prog.free_names(
                            prog.closure(["advance"]), "row")})
    path = inspect.getsourcefile(env["advance"])
    assert path is not None and path.startswith(str(cache_dir()))
    text = open(path, encoding="utf-8").read()
    assert "def advance(" in text and "F_x += P.E @ g" in text   # the formula as written
