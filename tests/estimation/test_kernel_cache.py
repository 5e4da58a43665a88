"""Stage-2 kernels through printed, disk-cached modules: same results, compiled once."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from thetahat.estimation.kernels.kernel_cache import load_module
from thetahat.estimation.kernels.modules import KernelSourceError, ModuleText
from thetahat.estimation.statistical.plant_kernel import (Propagation, model_kernel,
                                                          printed_kernels)
from thetahat.models import lugre

numba = pytest.importorskip("numba")

#: A module-level kernel and the names it leaves free (bound when printed).
SCALE: float
TABLE: np.ndarray


def _inner(x):
    return SCALE * x - 7


def _outer(x, out):
    for i in range(out.shape[0]):
        out[i] = _inner(x) + TABLE[i]
    s = 0.0
    for v in out:
        s += v
    return s


def test_a_bound_kernel_with_numbers_and_arrays_equals_its_python():
    """The printed module binds each free name to what the caller provides (exact floats),
    prints the functions it calls beside it, and numba compiles the same operations."""
    table = np.array([0.1, -2.5e-300, np.pi])
    mod, (name,) = printed_kernels("thetahat_doc_test", "Test.", [_outer],
                                   {"SCALE": 1.0 / 3.0, "TABLE": table}, True)
    out_py, out_nb = np.empty(3), np.empty(3)
    expect = [1.0 / 3.0 * 0.7 - 7 + v for v in table]
    s_nb = getattr(mod, name)(0.7, out_nb)
    py = getattr(getattr(mod, name), "py_func")
    s_py = py(0.7, out_py)
    np.testing.assert_array_equal(out_nb, out_py)       # same operations, no reassociation
    np.testing.assert_array_equal(out_py, expect)
    assert s_nb == s_py


def test_an_inlined_kernel_is_marked_alone_and_computes_the_same():
    """``inline=[f]`` prints f alone with numba's inline='always' (its caller keeps the plain
    decorator), and the caller computes what the called version does, to the bit."""
    table = np.array([0.1, -2.5e-300, np.pi])
    given = {"SCALE": 1.0 / 3.0, "TABLE": table}
    called, (name_c,) = printed_kernels("thetahat_doc_test", "Test.", [_outer], given, True)
    inlined, (name_i,) = printed_kernels("thetahat_doc_test", "Test.", [_outer], given, True,
                                         inline=[_inner])
    src = open(inlined.__file__).read()
    marked = [block.split("\n")[1] for block in src.split("\n\n\n")
              if "inline='always'" in block]
    assert [line.split("(")[0] for line in marked] == ["def _inner_f1"], marked
    assert "inline=" not in open(called.__file__).read()
    a, b = np.empty(3), np.empty(3)
    assert getattr(called, name_c)(0.7, a) == getattr(inlined, name_i)(0.7, b)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ["silverbox", "two_inertia", "actuator"])
def test_the_plant_step_with_its_stage_inlined_is_the_called_one(name):
    """The plant module with ``stage_jac`` compiled into ``propagate_into`` (the default) and
    with it called: x⁺, Φ and Γ equal to the bit over the record's first samples at 1, 4 and
    16 sub-steps and every hold (the same operations in the same order; only the calls
    differ)."""
    from records import shipped_record
    spec, t, U, Y, theta = shipped_record(name, samples=64)
    th = np.asarray(spec.estimator.theta_hat0 if theta is None else theta, dtype=float)
    n, p = spec.system.n, spec.system.p
    kernels = [model_kernel(spec.system, compiled=True, inline=flag) for flag in (True, False)]
    U = np.ascontiguousarray(U, dtype=float)
    x = np.concatenate([Y[0, :1], np.zeros(n - 1)])
    for hold in ("zoh", "foh", "bandlimited"):
        for sub in (1, 4, 16):
            outs = []
            for k in kernels:
                pc, WT = Propagation(hold=hold, substeps=sub).arrays()
                Phi, Gam = np.empty((n, n)), np.empty((n, p))
                xs = [x]
                for j in range(8):
                    xs.append(k.propagate(xs[-1], th, U, j, t[j + 1] - t[j], pc, WT, True,
                                          Phi, Gam))
                outs.append((np.array(xs), Phi.copy(), Gam.copy()))
            for a, b in zip(*outs):
                np.testing.assert_array_equal(a, b)


def _closure(k):
    def times(x):
        return k * x
    return times


def test_closures_and_unknown_names_are_refused():
    """Kernels are module-level functions: a closure (the mechanism that read code objects and
    cells is gone) and a name that is neither provided nor global are refused."""
    with pytest.raises(KernelSourceError, match="closure"):
        ModuleText("Doc.").bound(_closure(2.0))
    with pytest.raises(KernelSourceError, match="unknown name 'SCALE'"):
        ModuleText("Doc.").bound(_inner)
    with pytest.raises(KernelSourceError, match="dict"):
        ModuleText("Doc.").bound(_inner, None, {"SCALE": {"k": 2.0}})
    assert load_module(ModuleText("Doc.").source(), "thetahat_doc_test").__doc__ == "Doc."


def test_stage2_propagation_matches_the_python_kernels():
    """LuGre's RK4 map and its Jacobians, compiled through the cache vs plain Python: the
    same arithmetic up to numba's contraction of a·b + c (1e-12 relative, margin 1e3 over
    the 1e-15 seen), for every hold."""
    sys_ = lugre.system()
    fast, slow = model_kernel(sys_, compiled=True), model_kernel(sys_, compiled=False)
    x, th = np.array([0.8, 2e-4]), np.array([0.28])
    U = np.array([[0.9], [1.0], [1.05], [1.2]])
    for hold in ("zoh", "foh", "bandlimited"):
        outs = []
        for k in (fast, slow):
            pc, WT = Propagation(hold=hold).arrays()
            Phi, Gam = np.empty((2, 2)), np.empty((2, 1))
            xn = k.propagate(x, th, U, 1, 1e-3, pc, WT, True, Phi, Gam)
            outs.append((xn, Phi, Gam))
        for a, b in zip(*outs):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)


SCRIPT = """
import json, numpy as np
from thetahat.estimation.statistical.plant_kernel import Propagation, model_kernel
from thetahat.models import lugre
k = model_kernel(lugre.system(), compiled=True)
Phi, Gam = np.empty((2, 2)), np.empty((2, 1))
pc, WT = Propagation(hold="foh").arrays()
k.propagate(np.array([0.8, 2e-4]), np.array([0.28]), np.array([[1.0], [1.0]]), 0, 1e-3, pc,
            WT, True, Phi, Gam)
st = k.propagate.stats
print(json.dumps({"hits": sum(st.cache_hits.values()), "misses": sum(st.cache_misses.values())}))
"""


def test_a_second_process_loads_the_machine_code(tmp_path):
    """The point of the cache: the first process compiles, the next one only loads."""
    env = {**os.environ, "THETAHAT_CACHE_DIR": str(tmp_path), "OPENBLAS_NUM_THREADS": "1"}
    runs = [json.loads(subprocess.run([sys.executable, "-c", SCRIPT], env=env, check=True,
                                      capture_output=True, text=True).stdout.splitlines()[-1])
            for _ in range(2)]
    assert runs[0]["misses"] >= 1
    assert runs[1] == {"hits": 1, "misses": 0}


@pytest.mark.parametrize("compiled", [False, True])
def test_the_plant_model_is_one_printed_module_from_the_cache(compiled):
    """rhs_jac (printed by SymPy) and the RK4 kernels live in one module file written to the
    cache directory under its content hash and imported from there (no exec of a string),
    compiled or as plain Python."""
    import inspect

    from thetahat.estimation.kernels.kernel_cache import cache_dir
    kern = model_kernel(lugre.system(), compiled=compiled)
    fns = [getattr(f, "py_func", f) for f in (kern.rhs_jac, kern.propagate)]
    files = {inspect.getsourcefile(f) for f in fns}
    assert len(files) == 1
    (path,) = files
    assert os.path.dirname(path) == str(cache_dir())
    assert os.path.basename(path).startswith("thetahat_plant_")
    assert kern.source in open(path, encoding="utf-8").read()
