"""The C printer of the formulas' subset (thetahat.codegen.c_printer), on its own."""

from __future__ import annotations

import ast
import ctypes
import subprocess
import textwrap

import numpy as np
import pytest

from thetahat.codegen.c_printer import CUnit
from thetahat.codegen.c_values import Arr, Const, Scal
from thetahat.codegen.harness import C_FLAGS
from thetahat.codegen.loader import find_compiler
from thetahat.errors import UnsupportedError
from thetahat.estimation.kernels import scalar_primitives
from thetahat.estimation.kernels.printer import Program
from thetahat.estimation.kernels.subset import definition
from thetahat.estimation.status import status_constants

#: A pivoted elimination printed as C against LAPACK's, relative to the solution's norm:
#: rounding only (different pivot arithmetic order), 1e-12 is ~1e4 ulps on these
#: well-conditioned 5 × 5 systems.
SOLVE_RTOL = 1e-12


def unit_of(source: str) -> CUnit:
    tree = ast.parse(textwrap.dedent(source))
    functions = {fn.name: fn for fn in tree.body if isinstance(fn, ast.FunctionDef)}
    return CUnit(functions, {"N": Const(3)}, lambda name, args: None, "double")


def test_constants_fold_and_unused_parameters_are_dropped():
    unit = unit_of("""
        def f(a, b, flag, n):
            if flag:
                for i in range(n):
                    a[i] = 2.0 * a[i]
            else:
                b[0] = 1.0
            return N + 1
    """)
    fn = unit.call("f", [Arr("x", (3,)), Arr("y", (1,)), Const(True), Const(3)])
    text = unit.source()
    assert fn.args == ["x"]                        # b is not used once flag is known
    assert "real_t b" not in text and "if" not in text
    assert "a[2] = (2.0 * a[2]);" in text          # the short loop is written out
    assert "return 4;" in text
    other = unit.call("f", [Arr("x", (3,)), Arr("y", (1,)), Scal("on", "int"), Const(3)])
    assert other.name == "f_f_2" and other.args == ["x", "y", "on"]   # a runtime flag


def test_constructs_outside_the_subset_are_refused():
    unit = unit_of("""
        def f(a):
            return [v for v in a]
    """)
    with pytest.raises(UnsupportedError, match="outside the formulas' subset"):
        unit.call("f", [Arr("x", (3,))])


def test_printed_solve_agrees_with_lapack(tmp_path):
    """scalar_primitives.solve, printed for the scalar target and as C for q = 5, compiled
    with the acceptance's flags, solves random systems as numpy.linalg.solve does."""
    if find_compiler() is None:
        pytest.skip("no C compiler (cc or $CC)")
    q = 5
    program = Program({"solve": definition(scalar_primitives.solve)})
    unit = CUnit({"solve": program.printed("solve", "scalar")},
                 {k: Const(v) for k, v in status_constants().items()},
                 lambda name, args: None, "double")
    fn = unit.call("solve", [Const(q), Arr("M", (q, q)), Arr("rhs", (q,))])
    src = tmp_path / "solve.c"
    src.write_text("#include <math.h>\ntypedef double real_t;\n" + unit.source()
                   + f"\nvoid run(real_t M[], real_t rhs[]);\n"
                   f"void run(real_t M[], real_t rhs[])\n{{\n    {fn.name}(M, rhs);\n}}\n")
    lib = tmp_path / "libsolve.so"
    out = subprocess.run([find_compiler(), *C_FLAGS, "-fPIC", "-shared", "-o", str(lib),
                          str(src)], capture_output=True, text=True)
    assert out.returncode == 0 and not out.stderr, out.stderr
    run = ctypes.CDLL(str(lib)).run
    ptr = ctypes.POINTER(ctypes.c_double)
    rng = np.random.default_rng(3)
    for _ in range(20):
        M = rng.standard_normal((q, q)) + q * np.eye(q)
        b = rng.standard_normal(q)
        Mc, bc = M.copy(), b.copy()                # the elimination overwrites M
        run(Mc.ctypes.data_as(ptr), bc.ctypes.data_as(ptr))
        x = np.linalg.solve(M, b)
        assert np.linalg.norm(bc - x) <= SOLVE_RTOL * np.linalg.norm(x)


#: Kernel source in numba's subset for the local-array test: allocations, block and row
#: copies, an array returned, a tuple with an array returned, a branch a constant ends.
LOCAL_ARRAYS = """
import numpy as np

def scaled(v, c):
    w = v.copy()
    for i in range(w.shape[0]):
        w[i] = c * w[i]
    return w

def parts(M, row):
    r = M[row].copy()
    B = M[1:, 1:].copy()
    t = 0.0
    for i in range(B.shape[0]):
        t += B[i, i]
    return r, t

def kernel(M, v, out, mode):
    if mode == 0:
        for i in range(v.shape[0]):
            out[i] = v[i]
        return
    I = np.eye(3)
    Z = np.zeros((3, 3))
    w = scaled(v, 2.0)
    r, t = parts(M, 2)
    for i in range(3):
        Z[i, i] = I[i, i] * t
        out[i] = w[i] + r[i] + Z[i, i] + max(i, 1)
"""


def test_local_arrays_and_returned_arrays_compile_and_agree(tmp_path):
    """The numba-subset constructs of stage 2's kernels, printed as C, compiled with the
    acceptance's flags (-Werror: no unused local) and run, give the Python kernel's result
    exactly (the same operations in the same order on small integers and halves)."""
    if find_compiler() is None:
        pytest.skip("no C compiler (cc or $CC)")
    namespace: dict = {}
    exec(compile(LOCAL_ARRAYS, "<kernels>", "exec"), namespace)   # the Python reference
    unit = unit_of(LOCAL_ARRAYS)
    fn = unit.call("kernel", [Arr("M", (3, 3)), Arr("v", (3,)), Arr("out", (3,)), Const(1)])
    assert "ret[]" in unit.source()                 # scaled writes its array through ret
    folded = unit_of(LOCAL_ARRAYS).call("kernel", [Arr("M", (3, 3)), Arr("v", (3,)),
                                                   Arr("out", (3,)), Const(0)])
    assert folded.args == ["v", "out"]              # the taken branch returned: no more
    src = tmp_path / "k.c"
    src.write_text("#include <math.h>\ntypedef double real_t;\n" + unit.source()
                   + "\nvoid run(real_t M[], real_t v[], real_t out[]);\n"
                   f"void run(real_t M[], real_t v[], real_t out[])\n{{\n"
                   f"    {fn.name}({', '.join(fn.args)});\n}}\n")
    lib = tmp_path / "libk.so"
    res = subprocess.run([find_compiler(), *C_FLAGS, "-fPIC", "-shared", "-o", str(lib),
                          str(src)], capture_output=True, text=True)
    assert res.returncode == 0 and not res.stderr, res.stderr
    ptr = ctypes.POINTER(ctypes.c_double)
    M = np.arange(9.0).reshape(3, 3) / 2.0
    v = np.array([1.0, -2.0, 0.5])
    out_c, out_py = np.zeros(3), np.zeros(3)
    ctypes.CDLL(str(lib)).run(M.ctypes.data_as(ptr), v.ctypes.data_as(ptr),
                              out_c.ctypes.data_as(ptr))
    namespace["kernel"](M, v, out_py, 1)
    assert out_c.tolist() == out_py.tolist()
