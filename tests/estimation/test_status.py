"""One status enum in every binding: a singular implicit step is Status.SINGULAR in NumPy,
numba and C, and the API turns it into the same documented error."""

from __future__ import annotations

import ast
import ctypes
import subprocess

import numpy as np
import pytest

from thetahat.codegen.c_api import STATUS
from thetahat.codegen.c_printer import CUnit
from thetahat.codegen.c_values import Arr, Const
from thetahat.codegen.harness import C_FLAGS
from thetahat.codegen.loader import find_compiler
from thetahat.errors import NonFiniteError, UpdateLawError
from thetahat.estimation.kernels import scalar_primitives
from thetahat.estimation.observer.kernel_data import kernel_parts
from thetahat.estimation.observer.discretize import IMPLICITNESS
from thetahat.estimation.kernels.modules import numpy_binding
from thetahat.estimation.observer.kernel_source import LAWS, kernel_program, kernel_source
from thetahat.estimation.status import MESSAGES, Status, status_constants
from thetahat.estimation.observer.record_run import failure
from thetahat.estimation.observer.step import program
from thetahat.models import lugre

Q = 2
#: Φ₁ = I and N = diag(2, 0): I − γΦ₁N = diag(0, 1) with γ = 1/2, exactly singular (a zero
#: pivot in LAPACK's LU and in the scalar elimination alike).
SINGULAR_N = np.diag([2.0, 0.0])
#: A regular N: I − γΦ₁N = diag(0.5, 1).
REGULAR_N = np.diag([1.0, 0.0])


#: Positions of the arrays in :func:`_args` (the implicit step's parameters).
OUT, M_AT = 8, 9


def _args(N: np.ndarray) -> tuple:
    """implicit_step(q, Φ₁, Φ₂, F, Ḟ, foh, N, s, out, M, rhs) for the NumPy targets."""
    F = np.array([1.0, 2.0])
    return (Q, np.eye(Q), np.zeros((Q, Q)), F, np.zeros(Q), False, N.copy(), np.zeros(Q),
            np.zeros(Q), np.zeros((Q, Q)), np.zeros(Q))


def _scalar_args(N: np.ndarray) -> tuple:
    """The same for the scalar target, where s and out (views) come with their offsets."""
    a = _args(N)
    return (*a[:8], 0, a[8], 0, *a[9:])


def _numpy_implicit_step(row: bool):
    prog = program()
    return numpy_binding(prog, ("status test", row), prog, ["implicit_step"],
                         "row" if row else "batch",
                         lambda: {"IMPLICITNESS": IMPLICITNESS})["implicit_step"]


def test_the_c_header_codes_are_the_enum():
    assert {k: v[0] for k, v in STATUS.items()} == {s.name.lower(): int(s) for s in Status}
    assert all(STATUS[s.name.lower()][1] == MESSAGES[s] for s in Status)
    # the codes the C interface used before the enum keep their values
    assert (STATUS["ok"][0], STATUS["theta_star"][0], STATUS["diverged"][0],
            STATUS["init"][0]) == (0, 3, 4, 5)


def test_numpy_row_and_batch_report_a_singular_step():
    step = _numpy_implicit_step(True)
    a = _args(SINGULAR_N)
    assert step(*a) == Status.SINGULAR
    b = _args(REGULAR_N)
    assert step(*b) == Status.OK
    np.testing.assert_allclose(b[OUT], [2.0, 2.0])          # (I − ½N)⁻¹ F = [1/0.5, 2]
    batch = _numpy_implicit_step(False)
    rows = [_args(SINGULAR_N), _args(REGULAR_N)]
    stacked = [np.stack([r[i] for r in rows]) if isinstance(rows[0][i], np.ndarray)
               else rows[0][i] for i in range(len(rows[0]))]
    status = batch(*stacked)
    assert status.tolist() == [Status.SINGULAR, Status.OK]  # per row, no LinAlgError
    np.testing.assert_allclose(stacked[OUT][1], [2.0, 2.0])


def test_python_scalar_primitives_report_a_singular_step():
    M = np.diag([0.0, 1.0])
    assert scalar_primitives.solve(Q, M, np.array([1.0, 2.0])) == Status.SINGULAR


def test_numba_reports_a_singular_step():
    pytest.importorskip("numba")
    from thetahat.estimation.kernels.kernel_cache import load_module
    parts = kernel_parts(lugre.observer(1.0))
    ts = parts.theta_star
    source = kernel_source(parts.perturbation, None if ts is None else ts.expr,
                           None if ts is None else ts.arguments, LAWS[parts.code], numba=True)
    mod = load_module(source, "thetahat_status_test")
    # implicit_step alone (compiled on this first call; its blocks are loops, it calls solve)
    assert mod.implicit_step(*_scalar_args(SINGULAR_N)) == Status.SINGULAR
    b = _scalar_args(REGULAR_N)
    assert mod.implicit_step(*b) == Status.OK
    np.testing.assert_allclose(b[OUT + 1], [2.0, 2.0])      # after s and its offset


def test_c_reports_a_singular_step(tmp_path):
    if find_compiler() is None:
        pytest.skip("no C compiler (cc or $CC)")
    prog = kernel_program("held_law")
    functions = {name: prog.printed(name, "scalar") for name in ("implicit_step", "solve")}
    for fn in functions.values():
        assert isinstance(fn, ast.FunctionDef)
    constants = {"IMPLICITNESS": Const(IMPLICITNESS),
                 **{k: Const(v) for k, v in status_constants().items()}}
    unit = CUnit(functions, constants, lambda name, args: None, "double")
    arrays = {"Phi1": (Q, Q), "Phi2": (Q, Q), "F": (Q,), "Fd": (Q,), "Nm": (Q, Q), "s": (Q,),
              "out": (Q,), "M": (Q, Q), "rhs": (Q,)}
    call = unit.call("implicit_step", [Const(Q), Arr("Phi1", arrays["Phi1"]),
                                       Arr("Phi2", arrays["Phi2"]), Arr("F", arrays["F"]),
                                       Arr("Fd", arrays["Fd"]), Const(False),
                                       Arr("Nm", arrays["Nm"]), Arr("s", arrays["s"]),
                                       Const(0), Arr("out", arrays["out"]), Const(0),
                                       Arr("M", arrays["M"]), Arr("rhs", arrays["rhs"])])
    params = ", ".join(f"real_t {a}[]" for a in call.args)
    src = tmp_path / "step.c"
    src.write_text("#include <math.h>\ntypedef double real_t;\n" + unit.source()
                   + f"\nint run({params});\nint run({params})\n{{\n"
                   f"    return {call.name}({', '.join(call.args)});\n}}\n")
    lib = tmp_path / "libstep.so"
    out = subprocess.run([find_compiler(), *C_FLAGS, "-fPIC", "-shared", "-o", str(lib),
                          str(src)], capture_output=True, text=True)
    assert out.returncode == 0 and not out.stderr, out.stderr
    run = ctypes.CDLL(str(lib)).run
    ptr = ctypes.POINTER(ctypes.c_double)
    for N, want in ((SINGULAR_N, Status.SINGULAR), (REGULAR_N, Status.OK)):
        a = _args(N)
        values = {"Phi1": a[1], "Phi2": a[2], "F": a[3], "Fd": a[4], "Nm": a[6], "s": a[7],
                  "out": a[OUT], "M": a[M_AT], "rhs": a[M_AT + 1]}
        bufs = {k: np.ascontiguousarray(v, dtype=np.float64) for k, v in values.items()}
        assert run(*(bufs[name].ctypes.data_as(ptr) for name in call.args)) == want
        if want == Status.OK:
            np.testing.assert_allclose(bufs["out"], [2.0, 2.0])


def test_every_binding_raises_the_same_error_for_a_failed_step():
    """The one description of a failed step that the NumPy, numba and C runs all build
    (record_run.failure) from the status code and the step: a singular step and a divergence
    read alike and name the step; an invalid θ* is the law's error."""
    t = np.arange(5) * 1e-3
    for status in (Status.SINGULAR, Status.DIVERGED):
        fail = failure(int(status), 3, t, "GradientInversion")
        assert fail.status == status and fail.failed_at == 4
        assert "singular" in fail.message and "t[3] = 0.003" in fail.message
        with pytest.raises(NonFiniteError) as err:
            raise fail.error()
        assert str(err.value) == fail.message
    with pytest.raises(UpdateLawError, match=r"theta_star.*t\[3\]"):
        raise failure(int(Status.THETA_STAR), 3, t, "IntermittentInversion").error()
